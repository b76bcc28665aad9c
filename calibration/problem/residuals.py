"""The pure core of a fit: a ``Problem`` and its residuals.

A ``Problem`` is what a fit solves, apart from the measured numbers: a run (its static
``config``, its initial particles ``state``, the scene's parameters ``base``), where and when that
run is looked at (``observations``), the fitted ``keys`` and their ``bounds``. The measured numbers
are a pytree of arrays beside it (``ResidualLayout.data``). ``make_residuals(problem)`` returns the
one pure map ``residuals(z, data) -> (r, prediction)``, as ``jaxmpm.make_step(config)`` returns the
engine's step. Its compiled calls (``ModelFunctions``) are built once per distinct (run
configuration, observations, fitted keys) and kept in ``calibration.problem.cache.MODEL_FUNCTIONS``:
the data, state, base parameters and bounds are arguments, not constants of the trace.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import Params, make_rollout
from jaxmpm.config import Config

from .bounds import Bounds, dphysical_dz, physical
from .cache import MODEL_FUNCTIONS
from .observe import Observations, whiten_front

__all__ = ["ModelFunctions", "Problem", "column_pass", "jacobian_by_columns", "make_residuals", "model_functions",
           "run_pass"]


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """What a fit solves, apart from the measured numbers (see the module's text). ``config``
    is the scene's; the compiled calls run it with the observation times as its frame times."""

    config: Config
    state: Any
    base: Params
    observations: Observations
    keys: tuple[str, ...]
    bounds: Bounds

    @property
    def dtype(self):
        return jnp.result_type(self.base.E)

    @property
    def functions(self) -> ModelFunctions:
        """The compiled calls of this problem (shared by every problem of equal config,
        observations and keys)."""
        return model_functions(self.config, self.observations, self.keys)

    @property
    def static(self) -> tuple[Config, Observations, tuple[str, ...]]:
        """What a worker process rebuilds the compiled calls from: (config, observations, keys)."""
        return self.config, self.observations, self.keys

    def lower_upper(self):
        """The bounds as arrays of the run's dtype (the ``lower, upper`` of the z-calls)."""
        return jnp.asarray(self.bounds.lower, self.dtype), jnp.asarray(self.bounds.upper, self.dtype)


def make_residuals(problem: Problem) -> Callable:
    """The pure, unjitted ``residuals(z, data) -> (r, prediction)`` of ``problem``: θ = the
    bounds' map of the unconstrained ``z`` inside the trace, r the weighted misfit against
    ``data`` (``ResidualLayout.data``)."""
    residual = problem.functions.residual
    lower, upper = problem.lower_upper()

    def residuals(z, data):
        return residual(physical(z, lower, upper), problem.state, problem.base, data)

    return residuals


def jacobian_by_columns(fn, x):
    """Forward-mode Jacobian of ``fn(x) -> (y, aux)`` (x a vector): ``(dy/dx, (y, aux))``.

    The columns are ``jax.jvp`` passes in a ``lax.map``, one after the other, not ``jax.jacfwd``'s
    vmapped batch, which costs more on the CPU (docs/cost.md). Each pass recomputes the
    primal, so the residuals come from the first."""
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
    values of ``keys``; z: unconstrained, with θ = ``calibration.problem.bounds.physical(z, lower, upper)``.

    - ``predict(theta, state, base)``: {"status", "h", "front"} (unjitted); ``predictions``: jit(predict);
    - ``residual(theta, state, base, data)``: (r, prediction) (unjitted, for vmap and grad);
    - ``residuals``: jit(residual); ``jacobian``: jit, (dr/dθ, (r, prediction));
    - ``jacobian_z(z, lower, upper, state, base, data)``: jit, (dr/dz, dr/dθ, (r, prediction)),
      both Jacobians from one trace (dr/dθ = dr/dz / dθ/dz, infinite where z saturates a bound);
    - ``value_and_grad``: jit, ((Σ r², prediction), dΣr²/dθ);
    - ``batched``: jit(vmap(residual)) over rows of θ; ``batched_jacobian_z``: over rows of z;
    - ``column_z(z, tangent, lower, upper, state, base, data)``: jit, (r, dr/dz · tangent,
      dr/dθ · tangent, prediction) for a unit ``tangent``: one forward-mode pass, the unit of
      work that ``calibration.batch.workers`` spreads over processes."""

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


def column_pass(config, observations, keys, z, tangent, lower, upper, state, base, data) -> tuple:
    """One forward-mode pass of the problem (config, observations, keys) at z along ``tangent``:
    (r, dr/dz · tangent, dr/dθ · tangent, prediction) as numpy. A module-level function of
    picklable arguments: the unit of work ``calibration.batch.workers`` sends to its processes."""
    r, dr_z, dr, pred = model_functions(config, observations, keys).column_z(z, tangent, lower, upper, state, base,
                                                                              data)
    return np.asarray(r), np.asarray(dr_z), np.asarray(dr), jax.tree.map(np.asarray, pred)


def run_pass(config, observations, keys, theta, state, base, data) -> tuple:
    """One run of the problem at θ: (r, prediction) as numpy (a task, as ``column_pass``)."""
    r, pred = model_functions(config, observations, keys).residuals(theta, state, base, data)
    return np.asarray(r), jax.tree.map(np.asarray, pred)
