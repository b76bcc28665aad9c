"""Double precision, switched in one place.

JAX holds 64-bit types behind a global flag. A command that runs in float64 turns it on once,
before anything is traced (``use_dtype``); a study that runs one case in float64 among float32
ones turns it on for that case only and restores it whatever happens (``x64``).
"""

from __future__ import annotations

import contextlib

import jax

__all__ = ["use_dtype", "x64"]


def use_dtype(dtype: str | None) -> None:
    """Make ``dtype`` ("float32" or "float64") available: float64 turns JAX's 64-bit mode on
    (for the rest of the process); float32 or None (the default type) leaves the mode as it is."""
    if dtype is None:
        return
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    if dtype == "float64":
        jax.config.update("jax_enable_x64", True)


@contextlib.contextmanager
def x64(enabled: bool = True):
    """JAX's 64-bit mode set to ``enabled`` inside the block, and restored on leaving it (also
    on an error)."""
    before = bool(jax.config.jax_enable_x64)
    jax.config.update("jax_enable_x64", bool(enabled))
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", before)
