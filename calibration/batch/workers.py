"""Every core busy: independent model runs on one single-threaded XLA process per core.

``Workers(n)`` holds ``n`` processes (``spawn``ed, each pinned to one core where the system
allows and running XLA on one thread; docs/performance.md says why) and maps picklable tasks over
them: a module-level function and its arguments, such as ``calibration.problem.residuals.column_pass``.
Each worker compiles a problem's functions once; the results do not depend on the number of
workers (tested bit for bit). ``Workers(1)`` runs the tasks in the calling process.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import jax
import numpy as np

from jaxmpm.threads import allowed_cores, use_one_thread

from ..problem.options import check_int

__all__ = [
    "available_cores", "Workers", "as_workers", "using", "run_tasks", "jacobians_z", "residuals_at", "progress_bar",
]


def available_cores() -> int:
    """The cores this process may run on (its affinity mask where the system has one, as it was
    before the command line pinned the process to one core: ``jaxmpm.threads.allowed_cores``)."""
    return len(allowed_cores())


def _init_worker(x64: bool, counter, cores: Sequence[int]) -> None:
    # Worker k on the k-th of the cores its parent was allowed (the parent itself may be pinned to
    # one of them, and its children would inherit that one core).
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    if cores:
        try:
            os.sched_setaffinity(0, {cores[index % len(cores)]})
        except (AttributeError, OSError):  # pragma: no cover (no affinity on this system)
            pass
    use_one_thread()
    from jaxmpm.precision import enable_x64

    enable_x64(x64)  # a fresh process: its parent's precision, once, before anything is traced


class Workers:
    """``n`` worker processes (started on first use), or the calling process when ``n`` is 1.

    ``map(fn, tasks)`` returns ``[fn(*task) for task in tasks]``, computed in parallel; an
    exception in a task is raised in the caller. Use as a context manager, or ``close()``."""

    def __init__(self, n: int):
        self.n = check_int("workers", n)
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    @property
    def parallel(self) -> bool:
        return self.n > 1

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            from jaxmpm.precision import x64_enabled

            context = multiprocessing.get_context("spawn")
            cores = list(allowed_cores())
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


def progress_bar(show: bool, **options):
    """A tqdm bar made with ``options``, or None without ``show`` or without tqdm (the ``progress`` extra)."""
    if not show:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(**options)


def run_tasks(workers, tasks) -> list:
    """The results of ``(fn, args)`` tasks, computed by ``workers``."""
    return as_workers(workers).map(_call, tasks)


def _call(fn, args):
    return fn(*args)


def combine_columns(objective, results) -> tuple:
    """(r, dr/dz, dr/dθ, prediction) of ``objective`` from the results of its column tasks, one per
    key of each part in turn (each part's residuals and prediction from its first pass: every pass
    computes the same primal)."""
    outs, start = [], 0
    for part, _, _ in objective.parts:
        cols = results[start:start + len(part.keys)]
        start += len(part.keys)
        outs.append((cols[0][0], np.stack([c[1] for c in cols], axis=-1), np.stack([c[2] for c in cols], axis=-1),
                     cols[0][3]))
    return objective.join(outs)


def jacobians_z(objective, Z, workers, jacobian=None) -> tuple:
    """(r (k, m), dr/dz (k, m, n), dr/dθ (k, m, n), predictions stacked over k) at the rows of
    ``Z`` (k, n) and the objective's bounds: every forward-mode pass of every row (one per key of
    each of the objective's parts, made by the part), spread over ``workers``. ``jacobian`` (k,)
    bool: the rows that need their Jacobian (default all); the others are one run of each part's
    residuals, their Jacobians NaN, in the same spread of tasks."""
    Z = np.atleast_2d(np.asarray(Z))
    jacobian = np.ones(len(Z), bool) if jacobian is None else np.asarray(jacobian, bool)
    # θ for the rows run without their Jacobian (a column pass maps its z itself)
    thetas = np.asarray(objective.bounds.to_physical(Z), float) if not jacobian.all() else [None] * len(Z)
    tasks, spans = [], []
    for z, theta, with_jacobian in zip(Z, thetas, jacobian):
        first = len(tasks)
        if with_jacobian:
            tasks += [part.column_task(z[..., index], tangent, bounds) for part, index, bounds in objective.parts
                      for tangent in np.eye(len(part.keys), dtype=part.dtype)]
        else:
            tasks += [part.residual_task(theta[index]) for part, index, _ in objective.parts]
        spans.append((first, len(tasks), with_jacobian))
    results = run_tasks(workers, tasks)
    rows = [combine_columns(objective, results[a:b]) if with_jacobian else _without_jacobian(objective, results[a:b])
            for a, b, with_jacobian in spans]
    r, Jz, J, preds = zip(*rows)
    return np.stack(r), np.stack(Jz), np.stack(J), jax.tree.map(lambda *a: np.stack(a), *preds)


def _without_jacobian(objective, results) -> tuple:
    """(r, NaN, NaN, prediction) of ``objective`` from one residual run of each part."""
    outs = []
    for (part, _, _), (r, pred) in zip(objective.parts, results):
        nan = np.full((np.size(r), len(part.keys)), np.nan)
        outs.append((r, nan, nan, pred))
    return objective.join(outs)


def residuals_at(objective, thetas, workers, seeds=None) -> list[tuple]:
    """[(r, prediction)] at the rows of ``thetas`` (with the particles drawn with ``seeds``,
    row by row, if given), the runs spread over ``workers``: each part's runs, part after part."""
    thetas = np.atleast_2d(np.asarray(thetas, float))
    tasks = [part.residual_task(theta, None if seeds is None else seeds[i]) for part, index, _ in objective.parts
             for i, theta in enumerate(thetas[:, index])]
    results = run_tasks(workers, tasks)
    rows = thetas.shape[0]
    return [objective.join([results[j * rows + i] for j in range(len(objective.parts))]) for i in range(rows)]
