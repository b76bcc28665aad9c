"""Every core busy: independent model runs on one single-threaded XLA process per core.

A calibration's cost is model runs that do not depend on each other: the columns of a
forward-mode Jacobian, the starts of a search, the perturbed runs of the round-off check, the
members of a sampling-seed ensemble. On the CPU one XLA process using two threads does about a
third of the work of two single-threaded processes side by side (docs/performance.md): the
step is a chain of small kernels, and XLA splits each one between its threads. ``Workers(n)``
holds ``n`` such processes (the standard library's ``ProcessPoolExecutor``, started with
``spawn``; each pins itself to one core where the system allows and runs XLA on one thread)
and maps picklable tasks over them.

A task is a module-level function and its arguments: the static description of the run
(``jaxmpm.Config``, ``calibration.observe.Observations``, the fitted keys) and numpy arrays.
Each worker builds and compiles the model functions of a description once and keeps them
(``calibration.observe.model_functions``'s cache), so a fit compiles once per worker. A task
computes exactly what the same function computes in the calling process: the results do not
depend on the number of workers or on which worker ran which task (tested bit for bit).

``Workers(1)`` runs the tasks in the calling process, one after the other: the same numbers.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from jaxmpm.threads import SINGLE_THREAD_FLAGS, use_one_thread

__all__ = ["Workers", "available_cores", "as_workers", "using", "SINGLE_THREAD_FLAGS"]

def available_cores() -> int:
    """The cores this process may run on (its affinity mask where the system has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def _init_worker(x64: bool, counter, cores: Sequence[int]) -> None:
    use_one_thread()
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    if cores:
        try:
            os.sched_setaffinity(0, {cores[index % len(cores)]})
        except (AttributeError, OSError):  # pragma: no cover (no affinity on this system)
            pass
    from jaxmpm.precision import enable_x64

    enable_x64(x64)  # a fresh process: its parent's precision, once, before anything is traced


class Workers:
    """``n`` worker processes (started on first use), or the calling process when ``n`` is 1.

    ``map(fn, tasks)`` returns ``[fn(*task) for task in tasks]``, computed in parallel; an
    exception in a task is raised in the caller. Use as a context manager, or ``close()``."""

    def __init__(self, n: int):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"workers must be an integer >= 1, got {n!r}")
        self.n = int(n)
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    @property
    def parallel(self) -> bool:
        return self.n > 1

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            from jaxmpm.precision import x64_enabled

            context = multiprocessing.get_context("spawn")
            try:
                cores = sorted(os.sched_getaffinity(0))
            except AttributeError:  # pragma: no cover
                cores = []
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=self.n, mp_context=context, initializer=_init_worker,
                initargs=(x64_enabled(), context.Value("i", 0), cores))
        return self._pool

    def map(self, fn: Callable, tasks: Iterable[tuple]) -> list[Any]:
        tasks = list(tasks)
        if not self.parallel:
            return [fn(*task) for task in tasks]
        futures = [self._executor().submit(fn, *task) for task in tasks]
        return [f.result() for f in futures]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Workers({self.n})"


def as_workers(workers) -> Workers:
    """``workers`` as a ``Workers``: None or 1 the calling process, an integer that many
    processes, a ``Workers`` itself."""
    if workers is None:
        return Workers(1)
    if isinstance(workers, Workers):
        return workers
    return Workers(workers)


@contextlib.contextmanager
def using(workers):
    """``as_workers(workers)`` for a block, closed at its end if it was made here (a ``Workers``
    passed in stays open for its owner)."""
    pool = as_workers(workers)
    try:
        yield pool
    finally:
        if pool is not workers:
            pool.close()
