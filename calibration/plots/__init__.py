"""Figures (matplotlib, the ``plot`` extra)."""
