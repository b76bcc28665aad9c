"""What a calibration run observes, kept apart from what was measured.

``Observations`` says where and when a run is looked at: the x points of each deposit profile
and its time, the times of the front, and how both are read (the kernel width σ, the mirror at
the back wall, the front's threshold and reference point). It holds no measured value.

``model_functions(config, observations, keys)`` builds the pure functions a fit needs, jitted
once per distinct (run configuration, observations, fitted keys) in the process: the data (what
was measured, and the scales of the residuals) are arguments, not constants of the trace.
This module owns every compile cache of the calibration, keyed by content, never by an
object's identity: ``MODEL_FUNCTIONS`` (by configuration, observations and keys) and
``BATCHES`` (the batched, sharded calls of ``calibration.sweep`` and ``calibration.search``, by
an objective's fingerprint, ``content_key``, and the batch's shape, mode and devices). A
twin's generator and its fit, the seeds of a coverage study or two objectives of the same
experiment against different files share one compiled run. Functions of the unconstrained z
take the bounds as arguments and map z -> θ inside the traced function, so autodiff supplies
the chain rule of the bounds transform.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable, Hashable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import make_rollout
from jaxmpm.config import Config
from jaxmpm.observables import deposit_profile, front_from_profile, particle_volumes

from .bounds import dphysical_dz, physical

__all__ = ["BATCHES", "MODEL_FUNCTIONS", "MODES", "CompileCache", "CompiledBatch", "ModelFunctions", "Observations",
           "compile_batch", "content_key", "jacobian_by_columns", "model_functions"]

#: Compiled (configuration, observations, keys) kept at once; each holds a compiled rollout.
CACHE_SIZE = 4
#: Compiled batches (a sweep's chunk shape in a mode, a search's vmapped Jacobians) kept at once.
BATCH_CACHE_SIZE = 16
#: How a batch runs: one member per call, a vmapped chunk, or a vmapped chunk sharded over devices.
MODES = ("loop", "vmap", "shard")


class CompileCache:
    """Compiled functions by a hashable content key, the least recently used dropped beyond
    ``size`` (each entry may hold a compiled rollout: they are large). ``get(key, build)``
    returns the entry of ``key``, built by ``build()`` on a miss; a key of None (a model with no
    content description) builds every time and keeps nothing."""

    def __init__(self, size: int):
        self.size = int(size)
        self._entries: collections.OrderedDict = collections.OrderedDict()

    def get(self, key: Hashable | None, build: Callable[[], Any]) -> Any:
        if key is None:
            return build()
        if key in self._entries:
            self._entries.move_to_end(key)
            return self._entries[key]
        value = build()
        self._entries[key] = value
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)
        return value

    def __contains__(self, key) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()


#: The ``ModelFunctions`` of each (configuration, observations, keys).
MODEL_FUNCTIONS = CompileCache(CACHE_SIZE)
#: The compiled batches of sweeps and searches, by ``content_key`` and the batch's description.
BATCHES = CompileCache(BATCH_CACHE_SIZE)


def content_key(model) -> str | None:
    """The content key of a model (``calibration.protocol.ResidualModel``): its fingerprint as
    canonical JSON (equal fingerprints: equal residuals, so one compilation serves both); None
    where it gives none."""
    fingerprint = model.fingerprint()
    return None if fingerprint is None else json.dumps(fingerprint, sort_keys=True, default=str)


def _frozen(a) -> np.ndarray:
    a = np.array(a, float)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class Observations:
    """Where and when a run is observed.

    profile_x: the x points (m) of each profile; profile_times: the time (s) of each.
    front_times: the times (s) of the front (None: no front). front_points: the uniform x (m)
    on which the front's profile is read (``jaxmpm.observables.front_from_profile``).
    sigma: the profile kernel's width (m); front_threshold: the height (m) below which the
    deposit has ended; x_ref: where the front is measured from (m); mirror: the x (m) where
    the kernel is mirrored (None: nowhere); width: the channel width (m) of a 3D run (None in
    2D). Equal observations (by content) compile to the same functions."""

    profile_x: tuple[np.ndarray, ...]
    profile_times: tuple[float, ...]
    front_times: np.ndarray | None
    front_points: np.ndarray
    sigma: float
    front_threshold: float
    x_ref: float = 0.0
    mirror: float | None = None
    width: float | None = None

    def __post_init__(self):
        set_ = functools.partial(object.__setattr__, self)
        set_("profile_x", tuple(_frozen(x) for x in self.profile_x))
        set_("profile_times", tuple(float(t) for t in self.profile_times))
        set_("front_times", None if self.front_times is None else _frozen(self.front_times))
        set_("front_points", _frozen(self.front_points))
        if len(self.profile_x) != len(self.profile_times):
            raise ValueError(f"profile_times: {len(self.profile_times)} times for {len(self.profile_x)} profiles")
        if not self.profile_x and self.front_times is None:
            raise ValueError("observations: no profile and no front: nothing is observed")

    @property
    def times(self) -> tuple[float, ...]:
        """Every observation time, sorted, each once: the run's frame times."""
        front = () if self.front_times is None else tuple(float(t) for t in self.front_times)
        return tuple(sorted(set(self.profile_times) | set(front)))

    @property
    def n_profile(self) -> int:
        return int(sum(x.size for x in self.profile_x))

    @property
    def n_front(self) -> int:
        return 0 if self.front_times is None else int(self.front_times.size)

    def _key(self):
        arrays = self.profile_x + ((self.front_times,) if self.front_times is not None else ()) + (self.front_points,)
        return (tuple((a.shape, a.tobytes()) for a in arrays), self.profile_times, self.front_times is None,
                self.sigma, self.front_threshold, self.x_ref, self.mirror, self.width)

    def __eq__(self, other):
        return isinstance(other, Observations) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    def observer(self) -> Callable:
        """``(state, params) -> {"h": heights at every profile's points, "front": front x}``."""
        x_all = np.concatenate(self.profile_x) if self.profile_x else np.zeros(1)
        sigma, thr, x_ref, mirror, width, xs_front = (self.sigma, self.front_threshold, self.x_ref, self.mirror,
                                                      self.width, self.front_points)

        def observe(state, params):
            vol = particle_volumes(state)
            dtype = state.x.dtype
            h = deposit_profile(state.x, vol, jnp.asarray(x_all, dtype), sigma, width=width, mirror=mirror)
            h_front = deposit_profile(state.x, vol, jnp.asarray(xs_front, dtype), sigma, width=width, mirror=mirror)
            return {"h": h, "front": front_from_profile(jnp.asarray(xs_front, dtype), h_front, thr, x_ref)}

        return observe


def whiten_front(e, phi):
    """The front residuals whitened for an exponentially correlated error (``FrontTarget``):
    w_0 = e_0, w_i = (e_i − φ_i e_{i−1}) / sqrt(1 − φ_i²); φ = 0 leaves e as it is. For
    corr(e_i, e_j) = Π φ between them (the Ornstein–Uhlenbeck covariance at any spacing),
    Σ w² = eᵀ C⁻¹ e exactly: C's inverse is tridiagonal, this is its Cholesky factor."""
    prev = jnp.concatenate([jnp.zeros_like(e[:1]), e[:-1]])
    return (e - phi * prev) / jnp.sqrt(1 - phi * phi)


def unwhiten_front(w, phi) -> np.ndarray:
    """``whiten_front``'s inverse (numpy): e_i = w_i sqrt(1 − φ_i²) + φ_i e_{i−1}."""
    w, phi = np.asarray(w, float), np.asarray(phi, float)
    e = np.empty_like(w)
    prev = 0.0
    for i in range(w.size):
        prev = e[i] = w[i] * math.sqrt(1.0 - phi[i] ** 2) + phi[i] * prev
    return e


def jacobian_by_columns(fn, x):
    """Forward-mode Jacobian of ``fn(x) -> (y, aux)`` (x a vector): ``(dy/dx, (y, aux))``.

    The columns are ``jax.jvp`` passes in a ``lax.map``, one after the other, not ``jax.jacfwd``'s
    vmapped batch: on the CPU the batch carries every tangent through each scatter and gather of
    the step together and costs more than the passes one at a time (at the S4 fit of docs/performance.md,
    dx = 4 mm, two parameters: jacfwd 7.2 forward runs, two passes 3.7). Each pass recomputes
    the primal, so the residuals come from the first."""
    def column(tangent):
        y, dy, aux = jax.jvp(fn, (x,), (tangent,), has_aux=True)
        return dy, y, aux

    dy, y, aux = jax.lax.map(column, jnp.eye(x.shape[0], dtype=x.dtype))
    first = lambda a: a[0]  # noqa: E731
    return jnp.moveaxis(dy, 0, -1), (first(y), jax.tree.map(first, aux))


class ModelFunctions(NamedTuple):
    """The pure functions of one (configuration, observations, keys). ``data`` is the dict of
    measured values and scales (``Objective.data``): ``h``, ``h_scale`` (profile points),
    ``front``, ``front_scale`` (front times), ``row_scale`` (every residual). θ: physical
    values of ``keys``; z: unconstrained, with θ = ``calibration.bounds.physical(z, lower, upper)``.

    - ``predict(theta, state, base)``: {"status", "h", "front"} (unjitted); ``predictions``: jit(predict);
    - ``residual(theta, state, base, data)``: (r, prediction) (unjitted, for vmap and grad);
    - ``residuals``: jit(residual); ``jacobian``: jit, (dr/dθ, (r, prediction));
    - ``jacobian_z(z, lower, upper, state, base, data)``: jit, (dr/dz, dr/dθ, (r, prediction)),
      both Jacobians from one trace (dr/dθ = dr/dz / dθ/dz, infinite where z saturates a bound);
    - ``value_and_grad``: jit, ((Σ r², prediction), dΣr²/dθ);
    - ``batched``: jit(vmap(residual)) over rows of θ; ``batched_jacobian_z``: over rows of z;
    - ``column_z(z, tangent, lower, upper, state, base, data)``: jit, (r, dr/dz · tangent,
      dr/dθ · tangent, prediction) for a unit ``tangent`` (a key's column): one forward-mode
      pass, the unit of work that ``calibration.workers`` spreads over processes (a Jacobian
      column, a start's column in a search)."""

    config: Config
    predict: Callable
    predictions: Callable
    residual: Callable
    residuals: Callable
    jacobian: Callable
    jacobian_z: Callable
    value_and_grad: Callable
    batched: Callable
    batched_jacobian_z: Callable
    column_z: Callable


def model_functions(config: Config, observations: Observations, keys: tuple[str, ...]) -> ModelFunctions:
    """The ``ModelFunctions`` of ``keys`` observed by ``observations`` in runs of ``config``
    (its frame times are replaced by the observation times), from ``MODEL_FUNCTIONS``."""
    keys = tuple(keys)
    return MODEL_FUNCTIONS.get((config, observations, keys), lambda: _build_model_functions(config, observations, keys))


def _build_model_functions(config: Config, observations: Observations, keys: tuple[str, ...]) -> ModelFunctions:
    times = observations.times
    config = dataclasses.replace(config, frame_times=times, max_steps=config.max_steps + len(times))
    rollout = make_rollout(config, observations.observer())
    offsets = np.cumsum([0] + [x.size for x in observations.profile_x])
    slices = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:])]
    prof_index = [times.index(t) for t in observations.profile_times]
    front_index = (None if observations.front_times is None
                   else np.array([times.index(float(t)) for t in observations.front_times]))

    def predict(theta, state, base):
        theta = jnp.asarray(theta, jnp.result_type(base.E))
        final, frames = rollout(state, base.replace(**{k: theta[i] for i, k in enumerate(keys)}))
        out = {"status": final.status}
        if slices:
            out["h"] = jnp.concatenate([frames["h"][i, sl] for i, sl in zip(prof_index, slices)])
        if front_index is not None:
            out["front"] = frames["front"][jnp.asarray(front_index)]
        return out

    def residual(theta, state, base, data):
        pred = predict(theta, state, base)
        parts = []
        if slices:
            parts.append((pred["h"] - data["h"]) / data["h_scale"])
        if front_index is not None:
            parts.append(whiten_front((pred["front"] - data["front"]) / data["front_scale"], data["front_phi"]))
        return jnp.concatenate(parts) * data["row_scale"], pred

    def residual_z(z, lower, upper, state, base, data):
        return residual(physical(z, lower, upper), state, base, data)

    def loss(theta, state, base, data):
        r, pred = residual(theta, state, base, data)
        return jnp.sum(r * r), pred

    def jac(theta, state, base, data):
        return jacobian_by_columns(lambda t: residual(t, state, base, data), theta)

    def jac_z(z, lower, upper, state, base, data):
        Jz, out = jacobian_by_columns(lambda z_: residual_z(z_, lower, upper, state, base, data), z)
        return Jz, Jz / dphysical_dz(z, lower, upper)[None, :], out  # dθ/dz = 0 at a bound: J inf there

    def column_z(z, tangent, lower, upper, state, base, data):
        r, dr, pred = jax.jvp(lambda z_: residual_z(z_, lower, upper, state, base, data), (z,), (tangent,),
                              has_aux=True)
        return r, dr, dr / jnp.vdot(dphysical_dz(z, lower, upper), tangent), pred

    return ModelFunctions(
        config=config, predict=predict, predictions=jax.jit(predict), residual=residual, residuals=jax.jit(residual),
        jacobian=jax.jit(jac),
        jacobian_z=jax.jit(jac_z), value_and_grad=jax.jit(jax.value_and_grad(loss, has_aux=True)),
        batched=jax.jit(jax.vmap(residual, in_axes=(0, None, None, None))),
        batched_jacobian_z=jax.jit(jax.vmap(jac_z, in_axes=(0, None, None, None, None, None))),
        column_z=jax.jit(column_z))


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
    built = []

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
        built.append(time.perf_counter() - clock)
        return CompiledBatch(mode, chunk, compiled, sharding, 0.0)

    batch = BATCHES.get(key, build)
    return batch._replace(compile_s=built[0]) if built else batch
