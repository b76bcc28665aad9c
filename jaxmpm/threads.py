"""XLA's CPU threads, chosen before JAX starts.

A step of this engine is a chain of small kernels. XLA's CPU runtime splits each kernel between
its threads, and below about 10⁵ particles the splitting costs more than the second core gives:
on two cores the S4 collapse at dx = 4 mm (4,489 particles) steps in 1.3 ms on one thread and in
4.1 ms on two (docs/performance.md). The command lines therefore run XLA on one thread unless
told otherwise (``--threads all``), and independent runs use one such process per core
(``calibration.Workers``).

XLA reads its flags once, when the backend starts; ``use_one_thread`` must run before the first
computation, and raises if it comes too late rather than being silently ignored.

JAX has no public call that tells whether its backend has started without starting it (the
``backends_are_initialized`` of ``jax._src.xla_bridge`` is private). The check asks JAX through
its public configuration instead: the option ``jax_num_cpu_devices`` refuses a new value once
the backend has started (its documented contract, "must be set before JAX is initialized"), so
``_backend_started`` offers it another value and puts the old one back. Before the backend
starts the change is a plain setting, undone at once; after, JAX raises and nothing changes. A
JAX without that refusal (0.4.36 has no such option; 0.5.0 has it unchecked) cannot tell: there
a late call is not detected and the flag silently has no effect. A process that has not
imported JAX has not started it, and is not made to import it.
"""

from __future__ import annotations

import os
import sys

__all__ = ["SINGLE_THREAD_FLAGS", "THREAD_CHOICES", "apply_threads", "use_one_thread", "single_threaded"]

#: XLA's CPU runtime on one thread.
SINGLE_THREAD_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def _backend_started() -> bool:
    """Whether JAX's backend has started (module docstring: how, and where it cannot tell)."""
    if "jax" not in sys.modules:
        return False
    import jax

    try:
        before = jax.config.jax_num_cpu_devices
    except AttributeError:  # pragma: no cover (a JAX without the option: it cannot tell)
        return False
    try:
        jax.config.update("jax_num_cpu_devices", before + 1)
    except RuntimeError:  # "... should be updated before backends are initialized"
        return True
    jax.config.update("jax_num_cpu_devices", before)
    return False


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
