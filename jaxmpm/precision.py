"""Double precision, switched in one place.

JAX holds 64-bit types behind a global flag. A command that runs in float64 turns it on once,
before anything is traced (``use_dtype``); a study that runs one case in float64 among float32
ones turns it on for that case only and restores it whatever happens (``x64``); a fresh worker
process takes its parent's setting once, before it traces anything (``enable_x64`` of the
parent's ``x64_enabled``). Nothing else in jaxmpm or calibration sets the flag.
"""

from __future__ import annotations

import contextlib

import jax

__all__ = ["DTYPES", "enable_x64", "use_dtype", "x64", "x64_enabled"]

#: The floating-point types a run may use (experiment files' ``dtype``, the command lines' ``--dtype``).
DTYPES = ("float32", "float64")


def use_dtype(dtype: str | None) -> None:
    """Make ``dtype`` ("float32" or "float64") available: float64 turns JAX's 64-bit mode on
    (for the rest of the process); float32 or None (the default type) leaves the mode as it is."""
    if dtype is None:
        return
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    if dtype == "float64":
        enable_x64(True)


def x64_enabled() -> bool:
    """Whether JAX's 64-bit mode is on."""
    return bool(jax.config.jax_enable_x64)


def enable_x64(enabled: bool) -> None:
    """Set JAX's 64-bit mode for the rest of the process, unscoped: for a process that sets it
    once before tracing anything (a fresh worker taking its parent's setting). A switch for one
    part of a run is ``x64``, which restores the mode."""
    jax.config.update("jax_enable_x64", bool(enabled))


@contextlib.contextmanager
def x64(enabled: bool = True):
    """JAX's 64-bit mode set to ``enabled`` inside the block, and restored on leaving it (also
    on an error)."""
    before = x64_enabled()
    enable_x64(enabled)
    try:
        yield
    finally:
        enable_x64(before)
