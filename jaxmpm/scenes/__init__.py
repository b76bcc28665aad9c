"""Scene builders: each returns ``(config, state0, params)`` ready for ``simulate``."""

from .elastic import falling_block

__all__ = ["falling_block"]
