"""XLA's CPU threads, chosen before JAX starts.

A step of this engine is a chain of small kernels. XLA's CPU runtime spreads them over its thread
pool, and below about 10⁵ particles that costs more than the second core gives: on two cores a
whole S4 run at dx = 4 mm (4,489 particles, 6,438 steps) takes 5.8 s on one core and 13.6 s with
XLA's pool on both (docs/performance.md). The command lines therefore run each process on one
core unless told otherwise (``--threads all``), and independent runs use one such process per
core (``calibration.Workers``).

One core means the process's CPU affinity. JAX sizes its thread pools from the affinity mask when
its backend starts, and that is the only control that works on the JAX this project uses: the
XLA flags once documented for it (``--xla_cpu_multi_thread_eigen=false
intra_op_parallelism_threads=1``, kept in ``SINGLE_THREAD_FLAGS`` for older JAX) no longer change
the run time (13.6 s with or without them). ``use_one_thread`` pins the process to one core (the
one it runs on, or a given one) and sets the flags; both must happen before the first computation,
and it raises if it comes too late rather than being silently ignored. Where the system has no
affinity call (macOS, Windows) only the flags are set. ``allowed_cores`` keeps the cores the
process was allowed before it pinned itself, for the worker processes it starts.

JAX has no public call that tells whether its backend has started without starting it (the
``backends_are_initialized`` of ``jax._src.xla_bridge`` is private). The check asks JAX through
its public configuration instead: the option ``jax_num_cpu_devices`` refuses a new value once
the backend has started (its documented contract, "must be set before JAX is initialized"), so
``_backend_started`` offers it another value and puts the old one back. Before the backend
starts the change is a plain setting, undone at once; after, JAX raises and nothing changes. A
JAX without that refusal (0.4.36 has no such option; 0.5.0 has it unchecked) cannot tell: there
a late call is not detected and the choice silently has no effect. A process that has not
imported JAX has not started it, and is not made to import it.
"""

from __future__ import annotations

import os
import sys

__all__ = ["SINGLE_THREAD_FLAGS", "THREAD_CHOICES", "allowed_cores", "apply_threads", "cores_in_use",
           "use_one_thread", "single_threaded"]

#: XLA's CPU runtime on one thread, as older JAX read it (module docstring: this JAX ignores them).
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


def _affinity() -> tuple[int, ...] | None:
    """The cores this process may run on now, or None where the system has no affinity call."""
    try:
        return tuple(sorted(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (macOS, Windows)
        return None


def cores_in_use() -> int:
    """How many cores this process runs on now (one once ``use_one_thread`` has pinned it)."""
    return len(_affinity() or range(os.cpu_count() or 1))


#: The affinity mask before ``use_one_thread`` narrowed it (None until then).
_allowed_before_pinning: tuple[int, ...] | None = None


def allowed_cores() -> tuple[int, ...]:
    """The cores this process may use: its affinity mask as it was before ``use_one_thread``
    pinned it to one (all of ``os.cpu_count()`` where the system has no affinity call)."""
    if _allowed_before_pinning is not None:
        return _allowed_before_pinning
    return _affinity() or tuple(range(os.cpu_count() or 1))


def _current_core(allowed: tuple[int, ...]) -> int:
    """The core this process last ran on (``/proc/self/stat``'s field 39), if it is allowed;
    the scheduler put it there because that core was free."""
    try:
        with open("/proc/self/stat") as f:
            core = int(f.read().rsplit(")", 1)[1].split()[36])
    except (OSError, ValueError, IndexError):
        return allowed[0]
    return core if core in allowed else allowed[0]


def single_threaded() -> bool:
    """Whether this process already runs on one core (where the system has affinity), or XLA_FLAGS
    asks for one thread (where it does not)."""
    cores = _affinity()
    if cores is not None:
        return len(cores) == 1
    return "--xla_cpu_multi_thread_eigen=false" in os.environ.get("XLA_FLAGS", "")


def use_one_thread(core: int | None = None) -> None:
    """Run this process, and the JAX backend it will start, on one core; the processes it starts
    inherit it (module docstring: how, and why).

    ``core`` picks one of ``allowed_cores()`` by its index (taken modulo their number: worker k of a
    pool passes k); None takes the core the process is running on. Call before JAX's first
    computation; raises ``RuntimeError`` after it, when the choice could no longer take effect.
    Flags already in XLA_FLAGS are kept."""
    global _allowed_before_pinning
    flags = os.environ.get("XLA_FLAGS", "")
    if single_threaded() and core is None:
        return
    if _backend_started():
        raise RuntimeError("XLA's threads are chosen when JAX starts its backend; call use_one_thread() "
                           "before the first computation (or start Python with taskset -c N)")
    if "--xla_cpu_multi_thread_eigen=false" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {SINGLE_THREAD_FLAGS}".strip()
    allowed = allowed_cores()
    if _affinity() is None:  # pragma: no cover (no affinity call: the flags are all there is)
        return
    chosen = allowed[core % len(allowed)] if core is not None else _current_core(allowed)
    try:
        os.sched_setaffinity(0, {chosen})
    except OSError:  # pragma: no cover (a sandbox that refuses it: the flags are all there is)
        return
    _allowed_before_pinning = allowed


THREAD_CHOICES = ("1", "all")


def apply_threads(choice: str | None) -> None:
    """Apply the command lines' ``--threads`` (``jaxmpm.cli.add_threads_argument``) before the
    first computation: "1" (or None, the default) runs the process on one core; "all" leaves XLA
    its own choice."""
    if choice not in (None, *THREAD_CHOICES):
        raise ValueError(f"--threads must be one of {THREAD_CHOICES}, got {choice!r}")
    if choice in (None, "1"):
        use_one_thread()
