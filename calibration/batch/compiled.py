"""A model's residuals compiled for a batch of parameter sets: one member per call, a vmapped chunk,
or a vmapped chunk sharded over devices (``compile_batch``), kept in ``calibration.problem.cache.BATCHES``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.cache import BATCHES, content_key

__all__ = ["MODES", "CompiledBatch", "compile_batch"]


#: How a batch runs: one member per call, a vmapped chunk, or a vmapped chunk sharded over devices.
MODES = ("loop", "vmap", "shard")


class CompiledBatch(NamedTuple):
    """A compiled call of a model's residuals on a batch of exactly ``chunk`` rows of θ (one row
    in "loop" mode): ``compiled(thetas) -> (r, status, prediction)`` (``status`` 0 where the
    prediction has none); ``sharding`` the rows' sharding in "shard" mode (else None);
    ``compile_s`` the seconds its compilation took (0 when it came from ``BATCHES``)."""

    mode: str
    chunk: int
    compiled: Any
    sharding: Any
    compile_s: float

    def __call__(self, thetas: np.ndarray):
        """Dispatch (asynchronously) one chunk of exactly ``chunk`` rows."""
        if self.mode == "loop":
            return self.compiled(thetas[0])
        if self.sharding is not None:
            return self.compiled(jax.device_put(thetas, self.sharding))
        return self.compiled(thetas)


def _member_fn(model):
    def member(theta):
        r, pred = model.residual_fn(theta)
        status = pred.get("status") if isinstance(pred, Mapping) else None
        status = jnp.zeros((), jnp.int32) if status is None else jnp.asarray(status)
        return r, status, pred

    return member


def compile_batch(model, mode: str, chunk: int, n_keys: int, dtype, devices) -> CompiledBatch:
    """``model.residual_fn`` compiled for a batch of ``chunk`` rows of ``n_keys`` values in
    ``dtype``: in ``mode`` "loop" one row per call, "vmap" a vmapped chunk, "shard" a vmapped
    chunk split over ``devices``. Kept in ``BATCHES`` by the model's ``content_key`` and the
    batch's description, so a second sweep of equal content does not compile again."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    content = content_key(model)
    key = None if content is None else ("sweep", content, mode, int(chunk), int(n_keys), np.dtype(dtype).str,
                                        tuple(d.id for d in devices))

    def build():
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        member = _member_fn(model)
        clock = time.perf_counter()
        sharding = None
        if mode == "loop":
            compiled = jax.jit(member).lower(jax.ShapeDtypeStruct((n_keys,), dtype)).compile()
        elif mode == "vmap":
            compiled = jax.jit(jax.vmap(member)).lower(jax.ShapeDtypeStruct((chunk, n_keys), dtype)).compile()
        else:
            sharding = NamedSharding(Mesh(np.asarray(devices), ("members",)), PartitionSpec("members"))
            arg = jax.ShapeDtypeStruct((chunk, n_keys), dtype, sharding=sharding)
            fn = jax.jit(jax.vmap(member), in_shardings=sharding, out_shardings=sharding)
            compiled = fn.lower(arg).compile()
        return CompiledBatch(mode, chunk, compiled, sharding, time.perf_counter() - clock)

    cached = key is not None and key in BATCHES
    batch = BATCHES.get(key, build)
    return batch._replace(compile_s=0.0) if cached else batch
