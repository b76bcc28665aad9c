"""XLA's CPU threads, chosen before JAX starts.

A step of this engine is a chain of small kernels. XLA's CPU runtime splits each kernel between
its threads, and below about 10⁵ particles the splitting costs more than the second core gives:
on two cores the S4 collapse at dx = 4 mm (4,489 particles) steps in 1.3 ms on one thread and in
4.1 ms on two (docs/performance.md). The command lines therefore run XLA on one thread unless
told otherwise (``--threads all``), and independent runs use one such process per core
(``calibration.Workers``).

XLA reads its flags once, when the backend starts; ``use_one_thread`` must run before the first
computation, and raises if it comes too late rather than being silently ignored.
"""

from __future__ import annotations

import os

__all__ = ["SINGLE_THREAD_FLAGS", "THREAD_CHOICES", "apply_threads", "use_one_thread", "single_threaded"]

#: XLA's CPU runtime on one thread.
SINGLE_THREAD_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover (a JAX without the private module: assume not started)
        return False
    return bool(xla_bridge.backends_are_initialized())


def single_threaded() -> bool:
    """Whether XLA_FLAGS (as this process sees it) asks for one thread."""
    return "--xla_cpu_multi_thread_eigen=false" in os.environ.get("XLA_FLAGS", "")


def use_one_thread() -> None:
    """Run XLA's CPU runtime on one thread in this process (and in processes it starts).

    Call before JAX's first computation; raises ``RuntimeError`` after it, when the flag could no
    longer take effect. Flags already in XLA_FLAGS are kept."""
    if single_threaded():
        return
    if _backend_started():
        raise RuntimeError("XLA's threads are chosen when JAX starts its backend; call use_one_thread() "
                           "before the first computation (or set XLA_FLAGS before starting Python)")
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} {SINGLE_THREAD_FLAGS}".strip()


THREAD_CHOICES = ("1", "all")


def apply_threads(choice: str | None) -> None:
    """Apply the command lines' ``--threads`` (``jaxmpm.cli.add_threads_argument``) before the
    first computation: "1" (or None, the default, when the user has not set XLA_FLAGS) runs XLA
    on one thread; "all" leaves XLA its own choice."""
    if choice not in (None, *THREAD_CHOICES):
        raise ValueError(f"--threads must be one of {THREAD_CHOICES}, got {choice!r}")
    if choice == "1" or (choice is None and "XLA_FLAGS" not in os.environ):
        use_one_thread()
