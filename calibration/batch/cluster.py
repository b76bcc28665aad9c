"""Sweeps beyond one machine, through Dask distributed (the optional ``cluster`` extra).

The chunks of a ``calibration.batch.sweep`` become Dask tasks, run by the workers of a cluster
(``cluster="local:N"``, a scheduler's ``"tcp://HOST:PORT"`` or a ``distributed.Client``) and
merged into one ``SweepResult``. The objective travels as a recipe, ``make_objective``: a
picklable callable of no arguments that each worker calls once per sweep. A task that raises, or
whose worker dies, is resubmitted up to ``retries`` times, every attempt's error kept; a chunk that
fails every attempt leaves its members in ``failed``, loss NaN. On a local cluster the scheduler's
own silent retries are off, so a lost worker is seen here. The numbers equal
``sweep(objective, thetas, mode="vmap", chunk=chunk)``'s (tested). How to run one: docs/cluster.md.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
import uuid
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..problem.protocol import ResidualModel
from .sweep import SweepResult, _check_thetas, _chunk_rows, _failure_text, _jsonable, member_losses, sweep, write_sweep
from .workers import progress_bar

__all__ = ["parse_cluster", "ClusterSweepResult", "write_cluster_sweep", "cluster_sweep"]


#: Tasks per worker when no chunk is given: enough that a lost worker costs a fraction of the sweep.
TASKS_PER_WORKER = 4


def parse_cluster(spec) -> tuple[str, Any]:
    """``("local", N)``, ``("address", "tcp://...")`` or ``("client", client)``; a ValueError naming
    ``cluster`` for anything else (checked before any worker starts)."""
    if spec is not None and type(spec).__name__ == "Client" and hasattr(spec, "submit"):
        return "client", spec
    if not isinstance(spec, str):
        raise ValueError(f"cluster must be 'local:N', a scheduler address 'tcp://HOST:PORT' or a "
                         f"distributed.Client, got {spec!r}")
    if spec.startswith("local:"):
        count = spec[len("local:"):]
        if not count.isdigit() or int(count) < 1:
            raise ValueError(f"cluster {spec!r}: N in 'local:N' must be an integer >= 1")
        return "local", int(count)
    if "://" in spec and spec.split("://", 1)[1]:
        return "address", spec
    raise ValueError(f"cluster must be 'local:N' or a scheduler address such as 'tcp://HOST:PORT', got {spec!r}")


# ---- the worker side ----------------------------------------------------------------------------
#: Objectives built on this worker process, by sweep token (one sweep at a time holds one entry).
_WORKER_OBJECTIVES: dict[str, Any] = {}


def _run_task(token: str, make_objective: Callable[[], Any], rows: np.ndarray, x64: bool) -> dict[str, Any]:
    """One chunk on a worker: build the objective once for this sweep, evaluate ``rows``."""
    import jax

    from jaxmpm.precision import enable_x64

    if x64:
        enable_x64(True)  # a worker process: its parent's precision, once, before anything is traced
    objective = _WORKER_OBJECTIVES.get(token)
    if objective is None:
        _WORKER_OBJECTIVES.clear()  # an earlier sweep's objective and its executables
        objective = _WORKER_OBJECTIVES[token] = make_objective()
    result = sweep(objective, rows, mode="vmap", chunk=rows.shape[0], validate=False)
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):  # called outside a worker (tests of this function)
        worker = "local"
    return {"residuals": result.residuals, "status": result.status,
            "predictions": jax.tree.map(np.asarray, result.predictions), "worker": worker, "pid": os.getpid(),
            "wall_s": result.wall_s, "compile_s": result.compile_s}


# ---- the result ---------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ClusterSweepResult:
    """A sweep run as Dask tasks. ``sweep`` holds the merged members in input order (mode
    "cluster", ``n_devices`` the workers); ``task[i]`` is the task that made member i; ``tasks``
    one dict per task: ``index``, ``members`` [start, stop), ``attempts``, ``worker``, ``pid``,
    ``wall_s``, ``errors`` (one line per failed attempt) and ``lost`` (every attempt failed)."""

    sweep: SweepResult
    task: np.ndarray
    tasks: tuple[dict[str, Any], ...]
    cluster: str

    @property
    def n_members(self) -> int:
        return self.sweep.n

    @property
    def failed(self) -> list[dict[str, Any]]:
        """Every member without a result: index, params, task and why (the engine's status
        reasons, a non-finite loss, or the errors of a chunk that failed every attempt)."""
        out = []
        for i in self.sweep.failed:
            t = self.tasks[int(self.task[i])]
            s = int(self.sweep.status[i])
            why = (f"task {t['index']} failed {t['attempts']} attempts: " + " | ".join(t["errors"]) if t["lost"]
                   else _failure_text(s))
            out.append({"index": int(i), "params": self.sweep.params(int(i)), "task": t["index"], "status": s,
                        "why": why})
        return out

    @property
    def retried(self) -> list[dict[str, Any]]:
        """The tasks that needed more than one attempt (a lost worker, an exception)."""
        return [t for t in self.tasks if t["attempts"] > 1]

    def to_json(self) -> dict[str, Any]:
        out = self.sweep.to_json()
        out.pop("failures", None)
        out.update({"n_members": self.n_members, "failed": self.failed, "cluster": self.cluster,
                    "n_tasks": len(self.tasks), "retried": self.retried, "task": self.task})
        return _jsonable(out)


def write_cluster_sweep(path, result: ClusterSweepResult, objective=None) -> None:
    """The sweep's HDF5 file (``write_sweep``) plus ``task`` (the task of each member) and the
    attributes ``tasks_json`` and ``cluster``; written atomically."""
    import json

    def extra(f):
        f.create_dataset("task", data=np.asarray(result.task))
        f.attrs["tasks_json"] = json.dumps(_jsonable(list(result.tasks)))
        f.attrs["cluster"] = result.cluster

    write_sweep(path, result.sweep, objective, extra=extra)


# ---- the client side ----------------------------------------------------------------------------
def _connect(kind: str, value):
    """(client, close) for a parsed cluster spec."""
    import dask
    from distributed import Client, LocalCluster

    if kind == "client":
        return value, lambda: None
    if kind == "local":
        # The scheduler runs in this process: with no silent retries a lost worker surfaces here.
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
            cluster = LocalCluster(n_workers=value, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)

        def close():
            client.close()
            cluster.close()

        return client, close
    client = Client(value)
    return client, client.close


def cluster_sweep(make_objective: Callable[[], ResidualModel], thetas, *, cluster="local:2", chunk: int | None = None,
                  retries: int = 2, x64: bool | None = None, progress: bool = False,
                  objective: ResidualModel | None = None) -> ClusterSweepResult:
    """Evaluate the objective that ``make_objective()`` builds at every row of ``thetas`` as Dask
    tasks of ``chunk`` members each (default: about ``TASKS_PER_WORKER`` tasks per worker).

    ``make_objective`` must be picklable (a module-level function or a ``functools.partial`` of
    one); it is also called here once, to check ``thetas`` with the objective's parameter rules
    before anything runs (pass the already built ``objective`` to skip that). ``retries``: extra
    attempts of a failed task. ``x64``: run the workers in float64 (default: as this process).
    ``progress``: a tqdm bar counting members (the ``progress`` extra)."""
    kind, value = _check_cluster_args(make_objective, cluster, retries, chunk)
    from jaxmpm.precision import x64_enabled

    objective = make_objective() if objective is None else objective
    keys, thetas = _check_thetas(objective, thetas)
    objective.check_thetas(thetas, "thetas")
    x64 = x64_enabled() if x64 is None else bool(x64)
    dtype = np.float64 if x64 else np.float32
    n_members = thetas.shape[0]

    clock = time.perf_counter()
    client, close = _connect(kind, value)
    try:
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        size = chunk or max(1, math.ceil(n_members / (TASKS_PER_WORKER * n_workers)))
        starts = list(range(0, n_members, size))
        token = uuid.uuid4().hex

        def submit(t, attempt):
            return client.submit(_run_task, token, make_objective, _chunk_rows(thetas, starts[t], size, dtype), x64,
                                 pure=False, key=f"jaxmpm-sweep-{token[:8]}-task{t}-attempt{attempt}")

        tasks = [{"index": t, "members": [s, min(s + size, n_members)], "attempts": 0, "worker": None,
                  "pid": None, "wall_s": None, "errors": [], "lost": False} for t, s in enumerate(starts)]
        outputs = _run_tasks(submit, tasks, retries, n_members, progress)
    finally:
        close()
    return ClusterSweepResult(sweep=_merge(keys, thetas, starts, size, outputs, n_workers, clock),
                              task=np.repeat(np.arange(len(starts)), [t["members"][1] - t["members"][0]
                                                                      for t in tasks]),
                              tasks=tuple(tasks), cluster=cluster if isinstance(cluster, str) else kind)


def _check_cluster_args(make_objective, cluster, retries, chunk) -> tuple[str, Any]:
    """``cluster_sweep``'s arguments checked before any worker starts (and Dask distributed there):
    the parsed ``cluster`` (``parse_cluster``)."""
    if not callable(make_objective):
        raise ValueError(f"make_objective must be a callable that builds the objective, got {make_objective!r}")
    kind, value = parse_cluster(cluster)
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be an integer >= 1, got {chunk!r}")
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise ImportError("cluster sweeps need Dask distributed: pip install 'jaxmpm[cluster]'") from None
    return kind, value


def _run_tasks(submit: Callable, tasks: list[dict[str, Any]], retries: int, n_members: int,
               progress: bool) -> dict[int, dict]:
    """Every task submitted (``submit(t, attempt)``) and gathered as it completes, a failed one
    submitted again while it has ``retries`` left; ``tasks`` records in place each one's attempts,
    errors, worker and whether it was lost, and a bar (``progress``) counts the members done.
    Returns the outputs by task."""
    from distributed import as_completed

    outputs: dict[int, dict] = {}
    pending = {submit(t, 0): t for t in range(len(tasks))}
    bar = progress_bar(progress, total=n_members, unit="member", desc="sweep", file=sys.stderr)
    completed = as_completed(list(pending))
    try:
        for future in completed:
            t = pending.pop(future)
            tasks[t]["attempts"] += 1
            try:
                out = future.result()
            except Exception as error:  # noqa: BLE001 (a task's exception or a lost worker: reported)
                tasks[t]["errors"].append(_short(f"{type(error).__name__}: {error}"))
                if tasks[t]["attempts"] <= retries:
                    again = submit(t, tasks[t]["attempts"])
                    pending[again] = t
                    completed.add(again)
                    continue
                tasks[t]["lost"] = True
            else:
                outputs[t] = out
                tasks[t].update(worker=out["worker"], pid=out["pid"], wall_s=out["wall_s"])
            finally:
                future.release()
            if bar is not None:  # the task's members are done, with a result or lost
                bar.update(tasks[t]["members"][1] - tasks[t]["members"][0])
    finally:
        if bar is not None:
            bar.close()
    return outputs


def _short(text: str, head: int = 200, tail: int = 300) -> str:
    """An error line for the report: its start and its end (where a traceback names the cause)."""
    text = text.replace("\\n", "\n")
    return text if len(text) <= head + tail else f"{text[:head]} … {text[-tail:]}"


def _merge(keys, thetas, starts, size, outputs: Mapping[int, dict], n_workers: int, clock: float) -> SweepResult:
    """One SweepResult in input order; a lost task's members get NaN residuals and predictions."""
    import jax

    n_members = thetas.shape[0]
    fields = ("residuals", "status", "predictions")
    template = next(iter(outputs.values()), None)
    if template is None:  # every task lost
        residuals, status, predictions = np.full((n_members, 0), np.nan), np.zeros(n_members, np.int64), None
    else:
        lost = jax.tree.map(_missing, {k: template[k] for k in fields})
        chunks = [{k: outputs[t][k] for k in fields} if t in outputs else lost for t in range(len(starts))]
        # Every task has ``size`` rows, the last one's padding at the end: concatenated, then cut.
        merged = jax.tree.map(lambda *a: np.concatenate(a)[:n_members], *chunks)
        residuals, status, predictions = (merged[k] for k in fields)
    residuals, status = np.asarray(residuals, float), status.astype(np.int64)
    loss, failed = member_losses(residuals, status)
    compile_s = max((o["compile_s"] for o in outputs.values()), default=0.0)
    return SweepResult(keys=keys, thetas=thetas, loss=loss, status=status, residuals=residuals,
                       predictions=predictions, failed=failed, mode="cluster", chunk=size,
                       n_devices=n_workers, wall_s=time.perf_counter() - clock, compile_s=compile_s)


def _missing(a: np.ndarray) -> np.ndarray:
    """A lost task's stand-in for ``a``: NaN (0 for integers) of its shape and dtype."""
    return np.full(a.shape, np.nan if np.issubdtype(a.dtype, np.floating) else 0, a.dtype)
