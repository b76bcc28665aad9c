"""Parameter sweeps: a loss and its residuals on a grid or a Latin hypercube of parameter values.

``sweep(objective, thetas)`` evaluates ``objective.residual_fn`` at every row of ``thetas``: one
member at a time ("loop"), in vmapped chunks of one shape ("vmap"), or in chunks sharded over the
local devices ("shard"). A failed member gets loss NaN without touching the others. How far the
modes and chunk sizes agree: docs/fitting.md, "Sweeps".
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import numpy as np

from jaxmpm import describe_status

from ..problem.options import check_int
from ..problem.protocol import ResidualModel
from .compiled import compile_batch

__all__ = [
    "MODES", "DEFAULT_CHUNK", "grid_points", "latin_hypercube", "sweep_points", "SweepResult", "sweep",
    "write_sweep",
]


MODES = ("auto", "vmap", "shard", "loop")


#: Members per device in a trial chunk (the chunk used when the memory analysis is unavailable).
DEFAULT_CHUNK = 64


# ---- parameter sets ---------------------------------------------------------------------------
def _check_ranges(ranges: Mapping[str, Sequence[float]], keys) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    if not isinstance(ranges, Mapping) or not ranges:
        raise ValueError(f"ranges must be a non-empty mapping key -> (lo, hi), got {ranges!r}")
    if keys is None:
        keys = tuple(ranges)
    else:
        keys = tuple(keys)
        if set(keys) != set(ranges) or len(keys) != len(ranges):
            raise ValueError(f"keys must order the keys of ranges {list(ranges)} once each, got {list(keys)}")
    lo, hi = [], []
    for k in keys:
        try:
            a, b = (float(v) for v in ranges[k])
        except (TypeError, ValueError):
            raise ValueError(f"ranges[{k!r}] must be a pair (lo, hi), got {ranges[k]!r}") from None
        if not (math.isfinite(a) and math.isfinite(b) and a < b):
            raise ValueError(f"ranges[{k!r}] must be finite with lo < hi, got ({a}, {b})")
        lo.append(a)
        hi.append(b)
    return keys, np.asarray(lo), np.asarray(hi)


def grid_points(ranges: Mapping[str, tuple[float, float]], num: int | Mapping[str, int],
                keys: Sequence[str] | None = None) -> tuple[tuple[str, ...], np.ndarray]:
    """The cartesian product of ``np.linspace(lo, hi, num)`` over the keys of ``ranges``.

    ``num`` is one count for every key or a mapping key -> count. Returns ``(keys, thetas)``
    with ``thetas`` of shape (Π num, n_keys); the last key varies fastest.
    """
    keys, lo, hi = _check_ranges(ranges, keys)
    if isinstance(num, Mapping):
        if set(num) != set(keys):
            raise ValueError(f"num must give a count for each of {list(keys)}, got {dict(num)}")
        counts = [check_int(f"num[{k!r}]", num[k]) for k in keys]
    else:
        counts = [check_int("num", num)] * len(keys)
    axes = [np.linspace(a, b, c) for a, b, c in zip(lo, hi, counts)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return keys, np.stack([m.reshape(-1) for m in mesh], axis=-1)


def latin_hypercube(ranges: Mapping[str, tuple[float, float]], n: int, seed: int = 0,
                    keys: Sequence[str] | None = None) -> tuple[tuple[str, ...], np.ndarray]:
    """``n`` points in the box ``ranges``: along every axis each of the n equal strata holds
    exactly one point, at a uniform random place inside it; strata are paired across axes by
    independent random permutations. Returns ``(keys, thetas)`` with ``thetas`` (n, n_keys)."""
    keys, lo, hi = _check_ranges(ranges, keys)
    n = check_int("n", n)
    rng = np.random.default_rng(check_int("seed", seed, least=0))
    u = np.stack([(rng.permutation(n) + rng.random(n)) / n for _ in keys], axis=-1)
    return keys, lo + (hi - lo) * u


def sweep_points(over: Mapping[str, tuple[float, float, int]], lhs: int | None = None,
                 seed: int = 0) -> tuple[tuple[str, ...], np.ndarray]:
    """The members of a sweep over ``over`` ({key: (lo, hi, n)}): the grid of n values per key
    (``grid_points``), or with ``lhs`` that many Latin-hypercube samples over the ranges
    (``latin_hypercube``, ``seed``; the counts unused). Returns (keys, thetas)."""
    ranges = {k: (lo, hi) for k, (lo, hi, _) in over.items()}
    if lhs:
        return latin_hypercube(ranges, lhs, seed=seed)
    return grid_points(ranges, {k: n for k, (_, _, n) in over.items()})


# ---- the result -------------------------------------------------------------------------------
def _failure_text(status: int) -> str:
    """Why a member failed, in words: the engine's status reasons, or a non-finite loss."""
    return "; ".join(describe_status(status)) if status else "non-finite loss (no status bit set)"


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    return value


@dataclasses.dataclass(frozen=True)
class SweepResult:
    """What a sweep produced, member by member (B members, m residuals, n keys).

    ``loss`` is Σ r² (NaN for failed members), ``status`` the engine's status bits, ``residuals``
    the residual vectors (B, m), ``predictions`` the objective's prediction pytree with a
    leading member axis, ``failed`` the indices of failed members. ``chunk`` is the number of
    members per compiled call (1 for "loop"), ``n_devices`` the devices a chunk was split over;
    ``compile_s`` is the compilation time (0 when every executable came from the cache) and
    ``wall_s`` the whole sweep including it.
    """

    keys: tuple[str, ...]
    thetas: np.ndarray
    loss: np.ndarray
    status: np.ndarray
    residuals: np.ndarray
    predictions: Any
    failed: np.ndarray
    mode: str
    chunk: int
    n_devices: int
    wall_s: float
    compile_s: float

    @property
    def n(self) -> int:
        return int(self.thetas.shape[0])

    @property
    def ok(self) -> np.ndarray:
        """Mask of successful members."""
        mask = np.ones(self.n, bool)
        mask[self.failed] = False
        return mask

    def params(self, index: int) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.keys, self.thetas[index])}

    @property
    def failures(self) -> list[dict[str, Any]]:
        """One dict per failed member: index, params, status and its plain-language reasons."""
        return [{"index": int(i), "params": self.params(int(i)), "status": int(self.status[i]),
                 "status_text": _failure_text(int(self.status[i]))} for i in self.failed]

    def best(self) -> dict[str, Any]:
        """The successful member with the lowest loss: its parameter values by key, and
        ``index``, ``loss`` and ``params`` (the same values as a dict of their own)."""
        if not self.ok.any():
            raise ValueError(f"best: all {self.n} members failed, e.g. {self.failures[:1]}")
        i = int(np.nanargmin(np.where(self.ok, self.loss, np.nan)))
        params = self.params(i)
        return {**params, "index": i, "loss": float(self.loss[i]), "params": params}

    def landscape(self, key_x: str, key_y: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xs, ys, L) for a grid sweep over ``key_x`` and ``key_y``: the sorted distinct values
        of each key and the loss L[j, i] at (xs[i], ys[j]) (the layout ``pcolormesh(xs, ys, L)``
        expects; NaN where a member failed). Other keys must be constant."""
        for name, key in (("key_x", key_x), ("key_y", key_y)):
            if key not in self.keys:
                raise ValueError(f"{name} must be one of {list(self.keys)}, got {key!r}")
        if key_x == key_y:
            raise ValueError(f"key_x and key_y must differ, both are {key_x!r}")
        ix, iy = self.keys.index(key_x), self.keys.index(key_y)
        varying = [k for j, k in enumerate(self.keys)
                   if j not in (ix, iy) and np.unique(self.thetas[:, j]).size > 1]
        if varying:
            raise ValueError(f"landscape: {varying} vary too; sweep a grid over {key_x!r} and {key_y!r} only")
        xs, col = np.unique(self.thetas[:, ix], return_inverse=True)
        ys, row = np.unique(self.thetas[:, iy], return_inverse=True)
        cells = row.reshape(-1) * xs.size + col.reshape(-1)
        if self.n != xs.size * ys.size or np.unique(cells).size != self.n:
            raise ValueError(f"landscape: the {self.n} members are not a full {xs.size} x {ys.size} grid "
                             f"over {key_x!r} and {key_y!r}")
        grid = np.full(xs.size * ys.size, np.nan)
        grid[cells] = self.loss
        return xs, ys, grid.reshape(ys.size, xs.size)

    def to_json(self, predictions: bool = False) -> dict[str, Any]:
        """A JSON-able dict (NaN as None); floats keep every bit through ``json.dumps``."""
        out = {"keys": list(self.keys), "thetas": self.thetas, "loss": self.loss, "status": self.status,
               "residuals": self.residuals, "failed": self.failed, "failures": self.failures,
               "mode": self.mode, "chunk": self.chunk, "n_devices": self.n_devices,
               "wall_s": self.wall_s, "compile_s": self.compile_s}
        if self.ok.any():
            out["best"] = self.best()
        if predictions:
            out["predictions"] = jax.tree.map(np.asarray, self.predictions)
        return _jsonable(out)


# ---- evaluation -------------------------------------------------------------------------------
def _default_budget(device) -> int:
    """A quarter of the device's memory limit if it reports one (GPUs), else of physical RAM."""
    try:
        stats = device.memory_stats() or {}
    except Exception:  # noqa: BLE001 (backends without memory statistics)
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]) // 4
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 4
    except (AttributeError, ValueError, OSError):
        return 4 << 30


def _compiled_bytes(compiled) -> int | None:
    """Bytes one call of ``compiled`` needs on one device, from XLA's memory analysis (None if
    the backend gives none)."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 (not implemented on every backend)
        return None
    if m is None:
        return None
    if isinstance(m, (list, tuple)):
        m = m[0] if m else None
    try:
        return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
                   - m.alias_size_in_bytes + m.generated_code_size_in_bytes)
    except AttributeError:
        return None


def _check_thetas(objective, thetas) -> tuple[tuple[str, ...], np.ndarray]:
    keys = tuple(objective.keys)
    if isinstance(thetas, tuple) and len(thetas) == 2 and not np.isscalar(thetas[0]) and \
            all(isinstance(k, str) for k in thetas[0]):
        given, values = tuple(thetas[0]), np.asarray(thetas[1], float)
        if sorted(given) != sorted(keys) or len(set(given)) != len(given):
            raise ValueError(f"thetas: the points are over {list(given)}, the objective fits {list(keys)}")
        if values.ndim != 2 or values.shape[1] != len(given):
            raise ValueError(f"thetas: values must have shape (B, {len(given)}), got {values.shape}")
        thetas = values[:, [given.index(k) for k in keys]]
    else:
        thetas = np.asarray(thetas, float)
    if thetas.ndim != 2 or thetas.shape[0] < 1 or thetas.shape[1] != len(keys):
        raise ValueError(f"thetas must have shape (B >= 1, {len(keys)}) for keys {keys}, got {thetas.shape}")
    if not np.all(np.isfinite(thetas)):
        bad = np.argwhere(~np.isfinite(thetas))[0]
        raise ValueError(f"thetas must be finite; row {bad[0]} has {keys[bad[1]]} = {thetas[tuple(bad)]!r}")
    return keys, thetas


def member_losses(residuals: np.ndarray, status: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(loss, failed): Σ r² per member, summed on the host, NaN where a member failed (a status
    bit or a non-finite loss), and the indices of the failed members."""
    loss = np.sum(residuals * residuals, axis=-1)
    failed = (status != 0) | ~np.isfinite(loss)
    return np.where(failed, np.nan, loss), np.flatnonzero(failed)


def sweep(objective: ResidualModel, thetas, *, chunk: int | None = None, mode: str = "auto",
          memory_budget_bytes: int | None = None, progress: bool = False, validate: bool = True) -> SweepResult:
    """Evaluate ``objective.residual_fn`` at every row of ``thetas``.

    Parameters
    ----------
    objective: any ``calibration.problem.protocol.ResidualModel`` (a ``calibration.Objective``);
        its compiled chunks are kept by content (``calibration.batch.compiled.compile_batch``).
    thetas: (B, n) physical values ordered as ``objective.keys``, or the ``(keys, thetas)`` pair
        that ``grid_points`` / ``latin_hypercube`` return (its columns are reordered to match).
    chunk: members per compiled call ("vmap", "shard"); in "shard" mode a multiple of the device
        count. None: chosen from XLA's memory analysis so a chunk fits ``memory_budget_bytes``.
    mode: "loop", "vmap", "shard" or "auto" (shard over ``jax.devices()`` when there are several).
    memory_budget_bytes: the memory one chunk may use on one device (on the CPU the devices
        share the host's RAM, so it is split among them). Default: a quarter of the device's
        memory limit, or of physical RAM.
    progress: print progress lines to stderr (one per chunk, at most about twenty).
    validate: check every member with ``objective.check_thetas`` before anything compiles and
        raise ``ValueError`` naming the invalid ones (a member with μ2 < μ1 would run, get a finite
        loss and could be reported as the best); ``False`` runs them anyway.
    """
    keys, thetas, chunk = _check_sweep(objective, thetas, mode, chunk, memory_budget_bytes, validate)
    devices = jax.devices()
    if mode == "auto":
        mode = "shard" if len(devices) > 1 else "vmap"
    n_dev = len(devices) if mode == "shard" else 1
    if mode == "shard" and chunk is not None and chunk % n_dev:
        raise ValueError(f"chunk must be a multiple of the {n_dev} devices in shard mode, got {chunk}")
    dtype = np.dtype(objective.dtype)
    n_members = thetas.shape[0]
    clock = time.perf_counter()
    evaluator = _chunk_evaluator(objective, mode, chunk, memory_budget_bytes, n_members, dtype, devices, n_dev)
    residuals, status, predictions = _run_chunks(evaluator, thetas, mode, dtype, progress, clock)
    residuals = np.asarray(residuals, float).reshape(n_members, -1)
    status = np.asarray(status).astype(np.int64).reshape(n_members)
    loss, failed = member_losses(residuals, status)
    return SweepResult(keys=keys, thetas=thetas, loss=loss, status=status, residuals=residuals,
                       predictions=predictions, failed=failed, mode=mode, chunk=evaluator.chunk,
                       n_devices=n_dev, wall_s=time.perf_counter() - clock, compile_s=evaluator.compile_s)


def _check_sweep(objective, thetas, mode, chunk, memory_budget_bytes, validate):
    """``sweep``'s arguments checked before anything compiles: the keys, the members (B, n) in the
    objective's key order, and the chunk."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if not isinstance(objective, ResidualModel):
        raise ValueError("objective must be a calibration.problem.protocol.ResidualModel (keys, dtype, residual_fn, "
                         "check_thetas, fingerprint, describe; a calibration.Objective), got "
                         f"{type(objective).__name__}")
    keys, thetas = _check_thetas(objective, thetas)
    if validate:
        objective.check_thetas(thetas, "thetas")
    if chunk is not None:
        chunk = check_int("chunk", chunk)
    if memory_budget_bytes is not None and not (
            isinstance(memory_budget_bytes, (int, np.integer)) and memory_budget_bytes > 0):
        raise ValueError(f"memory_budget_bytes must be a positive integer, got {memory_budget_bytes!r}")
    return keys, thetas, chunk


def _chunk_evaluator(objective, mode, chunk, memory_budget_bytes, n_members, dtype, devices, n_dev):
    """The compiled chunk (``compile_batch``): one member in "loop" mode, else ``chunk`` members or,
    without one, the whole (padded) batch capped at ``DEFAULT_CHUNK`` per device and shrunk to the
    memory budget if XLA's memory analysis says it needs more."""
    n_keys = len(objective.keys)
    whole = -(-n_members // n_dev) * n_dev
    if mode == "loop":
        return compile_batch(objective, mode, 1, n_keys, dtype, devices[:1])
    if chunk is not None:
        return compile_batch(objective, mode, min(chunk, whole), n_keys, dtype, devices)
    budget = memory_budget_bytes or _default_budget(devices[0])
    if mode == "shard" and devices[0].platform == "cpu":
        budget //= n_dev  # host "devices" share one RAM
    evaluator = compile_batch(objective, mode, min(DEFAULT_CHUNK * n_dev, whole), n_keys, dtype, devices)
    need = _compiled_bytes(evaluator.compiled)
    if need is not None and need > budget and evaluator.chunk > n_dev:
        per_member = need / (evaluator.chunk // n_dev)
        fit = max(1, int(budget // per_member)) * n_dev
        if fit < evaluator.chunk:
            spent = evaluator.compile_s
            evaluator = compile_batch(objective, mode, fit, n_keys, dtype, devices)
            evaluator = evaluator._replace(compile_s=evaluator.compile_s + spent)
    return evaluator


def _run_chunks(evaluator, thetas, mode, dtype, progress, clock):
    """Every member through ``evaluator`` chunk by chunk, dispatching the next chunk before fetching
    the last (jax dispatch is async); the last chunk's padding (``_chunk_rows``) is dropped here.
    Returns (residuals, status, predictions) with a leading member axis."""
    size, n_members = evaluator.chunk, thetas.shape[0]
    starts = list(range(0, n_members, size))

    def dispatch(start):
        return evaluator(_chunk_rows(thetas, start, size, dtype))

    outputs, pending = [], dispatch(starts[0])
    for k, start in enumerate(starts):
        out = pending
        if k + 1 < len(starts):
            pending = dispatch(starts[k + 1])
        outputs.append(jax.tree.map(lambda a: np.asarray(a)[None] if mode == "loop" else np.asarray(a), out))
        if progress and (k + 1 == len(starts) or k % max(1, len(starts) // 20) == 0):
            print(f"sweep ({mode}, chunk {size}): {min(start + size, n_members)}/{n_members} members, "
                  f"{time.perf_counter() - clock:.1f} s", file=sys.stderr, flush=True)
    return jax.tree.map(lambda *a: np.concatenate(a)[:n_members], *outputs)  # the padding dropped


def _chunk_rows(thetas: np.ndarray, start: int, size: int, dtype) -> np.ndarray:
    """The ``size`` members from ``start``, in ``dtype``; a last, short chunk is padded with copies
    of its first member, so that every chunk has one shape (one compilation)."""
    rows = thetas[start:start + size]
    if rows.shape[0] < size:
        rows = np.concatenate([rows, np.repeat(rows[:1], size - rows.shape[0], axis=0)])
    return np.asarray(rows, dtype)


def write_sweep(path, result: SweepResult, objective: ResidualModel | None = None, extra=None) -> None:
    """Write a sweep to the HDF5 file ``path``: attributes ``keys_json`` (and ``objective_json``,
    the objective's ``describe()``), datasets ``thetas``, ``loss``, ``status`` and ``residuals``;
    ``extra(f)``, if given, adds to the open file (the cluster sweep's task of each member).
    Written atomically (``jaxmpm.io.atomic_h5``): a reader never sees a partial file."""
    import json
    import pathlib

    from jaxmpm.io import atomic_h5

    def write(f):
        f.attrs["keys_json"] = json.dumps(list(result.keys))
        if objective is not None:
            f.attrs["objective_json"] = json.dumps(objective.describe())
        f.create_dataset("thetas", data=np.asarray(result.thetas))
        f.create_dataset("loss", data=np.asarray(result.loss))
        f.create_dataset("status", data=np.asarray(result.status))
        f.create_dataset("residuals", data=np.asarray(result.residuals))
        if extra is not None:
            extra(f)

    atomic_h5(pathlib.Path(path), write)
