"""A flow-rule table as an objective: the closed form of the steady incline flow against the
table's velocities, with the members a fit, a search and a composite call
(``calibration.problem.protocol.ObjectiveLike``), so that an incline and a collapse can be fitted
together with shared keys (``CompositeObjective.sharing``).

The model is ``jaxmpm.scenes.incline.steady_velocity`` (docs/incline_fits.md), between the chute's
side walls where it has them (``side_walls``: their friction "mu_w" makes μ_w a key); a profile's
table is its velocity at each row's height z (``quantity="profile"``). The residuals are relative,
u_model / u_data − 1, one block ("velocity"), NaN at a row whose slope would not flow
steadily (a run that failed: a fit rejects the step). A closed form has no grid and no particles:
``coarsened`` raises ``NotImplementedError`` (the grid term says so; in a composite the member
stays as it is), and a resampled run is the same run.
"""

from __future__ import annotations

import dataclasses
import math
import types
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import SideWalls
from jaxmpm.params import DEFAULTS, validate_params
from jaxmpm.scenes.incline import steady_velocity

from ..data.flow_rule import FLOW_RULE_KEYS, flow_rule_keys_problem
from .bounds import Bounds, physical
from .objective import _digest
from .protocol import as_theta

__all__ = ["FLOW_RULE_KEYS", "FlowRuleObjective", "flow_rule_residuals", "flow_rule_material", "measured_keys"]



def flow_rule_material(values: Mapping[str, float] | None) -> dict[str, float]:
    """The model's defaults (docs/model.md §4) overridden by ``values``, validated, as floats."""
    material = {**DEFAULTS, **dict(values or {})}
    validate_params(material)
    return {k: float(v) for k, v in material.items()}


def flow_rule_residuals(table, keys: Sequence[str], material: Mapping[str, float], dtype=None, side_walls=None):
    """The pure, traceable θ -> r of ``table`` (θ: the values of ``keys``; the other parameters
    from ``material``): r = u_model / u_data − 1 at every row (a profile's at its height z), NaN
    where the row's slope allows no steady flow; computed in ``dtype`` (default: θ's), between
    ``side_walls`` (a ``jaxmpm.SideWalls``; None: none)."""
    keys = tuple(keys)

    def residuals(theta):
        kind = theta.dtype if dtype is None else dtype
        slope, h, u = (jnp.asarray(a, kind) for a in (table.slope_deg, table.h, table.u))
        z = None if table.z is None else jnp.asarray(table.z, kind)
        p = {**{k: jnp.asarray(v, kind) for k, v in material.items()}, **dict(zip(keys, theta))}
        model = steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"], table.quantity,
                                side_walls, p["mu_w"], height=z)
        return model / u - 1.0

    return residuals


def measured_keys(keys: Sequence[str], side_walls=None) -> tuple[str, ...]:
    """The measured parameters a flow rule's model reads and does not fit: ρ, ρ_s, d, and μ_w
    between ``side_walls`` whose friction is "mu_w" where it is not among ``keys``."""
    reads = side_walls is not None and side_walls.friction == "mu_w" and "mu_w" not in keys
    return ("rho", "rho_s", "d") + (("mu_w",) if reads else ())


def _check_keys(keys, side_walls) -> tuple[str, ...]:
    keys = tuple(keys)
    problem = flow_rule_keys_problem(keys, side_walls)
    if problem:
        raise ValueError(f"keys: {problem}")
    return keys


class FlowRuleObjective:
    """``table`` (a ``calibration.data.FlowRuleTable``) fitted for ``keys`` (some of μ1, μ2, I0;
    and μ_w between ``side_walls`` whose friction is "mu_w"), the other parameters from ``values``
    over the model's defaults; the chute's ``side_walls`` (a ``jaxmpm.SideWalls``; None: a
    wall-free chute); runs in ``dtype`` (default: JAX's default float)."""

    def __init__(self, table, keys: Sequence[str] = FLOW_RULE_KEYS, *, values: Mapping[str, float] | None = None,
                 bounds: Mapping[str, tuple[float, float]] | None = None, dtype=None, side_walls=None):
        if side_walls is not None and not isinstance(side_walls, SideWalls):
            raise ValueError(f"side_walls must be a jaxmpm.SideWalls or None, got {type(side_walls).__name__}")
        self.table, self.side_walls, self.keys = table, side_walls, _check_keys(keys, side_walls)
        if side_walls is not None and side_walls.friction == "mu_w" and "mu_w" not in {**(values or {})}:
            if "mu_w" not in self.keys:
                raise ValueError("values: the side walls' friction is the parameter mu_w (SideWalls(width, \"mu_w\")); "
                                 "give its value, values={'mu_w': ...}, or fit it (keys with mu_w)")
        self.material = flow_rule_material(values)
        self.bounds = Bounds.create(self.keys, bounds)
        self.bound_notes: tuple[str, ...] = ()
        self.dtype = jnp.dtype(dtype) if dtype is not None else jnp.zeros(()).dtype
        self.n_residuals = table.n
        self.blocks = {"velocity": slice(0, table.n)}
        self.row_scale = np.ones(table.n)
        self.jacobian = "ad"
        self._r = flow_rule_residuals(table, self.keys, self.material, self.dtype, side_walls)
        self._residuals = jax.jit(self.residual_fn)

        def with_aux(theta):
            r, pred = self.residual_fn(theta)
            return r, (r, pred)

        def in_z(z, lower, upper):
            return with_aux(physical(z, lower, upper))

        self._jac = jax.jit(jax.jacfwd(with_aux, has_aux=True))

        self._jac_z = jax.jit(jax.jacfwd(in_z, has_aux=True))

    def no_steady_flow(self, theta) -> str | None:
        """Why θ (by key, or an array in ``keys`` order) gives some row no steady flow; None if every row flows."""
        values = theta if isinstance(theta, Mapping) else dict(zip(self.keys, np.asarray(theta, float).tolist()))
        p = {**self.material, **values}
        low, high = float(self.table.slopes[0]), float(self.table.slopes[-1])
        if not p["mu1"] < math.tan(math.radians(low)):
            return f"mu1 = {p['mu1']:.4g} is not below tan {low:g}° = {math.tan(math.radians(low)):.4g} (no flow there)"
        if not math.tan(math.radians(high)) < p["mu2"]:
            return (f"mu2 = {p['mu2']:.4g} is not above tan {high:g}° = {math.tan(math.radians(high)):.4g} "
                    "(no steady flow there: the layer accelerates)")
        return None

    # ---- the model ---------------------------------------------------------------------------------
    def residual_fn(self, theta):
        """Pure, unjitted θ -> (r, {"status": 0}) (for ``jax.vmap``)."""
        return self._r(jnp.asarray(theta, self.dtype)), {"status": jnp.zeros((), jnp.int32)}

    def residuals(self, theta):
        return self._residuals(self.as_theta(theta))

    def residuals_resampled(self, theta, seed: int):
        """The same run: a closed form draws no particles."""
        return self.residuals(theta)

    def residuals_and_jacobian(self, theta, jacobian: str | None = None):
        J, (r, pred) = self._jac(self.as_theta(theta))
        return r, J, pred

    def residuals_and_jacobian_z(self, z, bounds: Bounds | None = None):
        bounds = self.bounds if bounds is None else bounds
        lower, upper = (jnp.asarray(b, self.dtype) for b in (bounds.lower, bounds.upper))
        Jz, (r, pred) = self._jac_z(self.as_theta(z, "z"), lower, upper)
        return r, Jz, Jz / bounds.jacobian_diag(jnp.asarray(z, self.dtype))[None, :], pred

    def batched_jacobian_z(self):
        def batched(Z):
            outs = [self.residuals_and_jacobian_z(z) for z in np.asarray(Z)]
            return tuple(jnp.stack(a) for a in zip(*[o[:3] for o in outs])) + (
                {"status": jnp.stack([o[3]["status"] for o in outs])},)

        return batched

    def value_and_grad(self, theta):
        theta = self.as_theta(theta)
        r, J, pred = self.residuals_and_jacobian(theta)
        return (jnp.sum(r * r), pred), 2.0 * J.T @ r

    def loss(self, theta) -> float:
        return float(jnp.sum(self.residuals(theta)[0] ** 2))

    # ---- the fit's bookkeeping -------------------------------------------------------------------
    @property
    def parts(self):
        return ((self, np.arange(len(self.keys)), self.bounds),)

    @staticmethod
    def join(outs) -> tuple:
        return outs[0]

    def column_task(self, z, tangent, bounds: Bounds) -> tuple:
        """One forward-mode pass as a task ``(fn, args)``: here in the calling process (microseconds)."""
        r, Jz, J, pred = self.residuals_and_jacobian_z(z, bounds)
        outs = (np.asarray(r), np.asarray(Jz) @ np.asarray(tangent), np.asarray(J) @ np.asarray(tangent),
                jax.tree.map(np.asarray, pred))
        return _constant, (outs,)

    def residual_task(self, theta, seed: int | None = None) -> tuple:
        r, pred = self.residuals(theta)
        return _constant, ((np.asarray(r), jax.tree.map(np.asarray, pred)),)

    @property
    def dx(self) -> float:
        return math.nan  # no grid

    @property
    def seeded(self) -> bool:
        return True  # every draw is the same: the particle draw's share is zero

    @property
    def sampling_seed(self) -> None:
        return None

    def coarsened(self, ratio: float):
        raise NotImplementedError("a closed form (the steady incline flow) has no grid to coarsen")

    def as_theta(self, theta, name: str = "theta"):
        """``theta`` as an array of the run's dtype, its shape checked against ``keys``."""
        return as_theta(theta, self.keys, self.dtype, name)

    def initial(self) -> dict[str, float]:
        return {k: self.material[k] for k in self.keys}

    def params_of(self, theta):
        """The material's values by name, the fitted keys set from θ (physical values; traceable),
        as ``Objective.params_of`` gives a scene's (the posteriors' support check reads μ1, μ2)."""
        return types.SimpleNamespace(**{**self.material, **{k: theta[i] for i, k in enumerate(self.keys)}})

    def expand(self, values: Mapping[str, float]) -> dict[str, float]:
        stray = [k for k in values if k not in self.keys]
        if stray:
            raise ValueError(f"{stray[0]!r} is not fitted (keys: {list(self.keys)})")
        return {k: float(v) for k, v in values.items()}

    def in_metres(self, r) -> dict[str, np.ndarray]:
        """The residuals by block: here relative velocities (model / data − 1), not metres."""
        return {"velocity": np.asarray(r, float)}

    def check_thetas(self, thetas, name: str = "thetas") -> None:
        thetas = np.atleast_2d(np.asarray(thetas, float))
        for i, row in enumerate(thetas):
            values = {**self.material, **dict(zip(self.keys, row.tolist()))}
            try:
                validate_params(values)
            except ValueError as err:
                raise ValueError(f"{name}: member {i} is not a valid parameter set: {err}") from None

    def fingerprint(self) -> dict[str, Any]:
        t = self.table
        walls = {} if self.side_walls is None else {"side_walls": self._walls()}  # a wall-free record as before
        return {"model": "steady incline flow (closed form)", "quantity": t.quantity, **walls,
                "data": _digest(t.slope_deg, t.h, t.u, *(() if t.z is None else (t.z,))), "keys": list(self.keys),
                "fixed": {k: v for k, v in self.material.items() if k not in self.keys},
                "bounds": {k: [lo, hi] for k, lo, hi in zip(self.keys, self.bounds.lower, self.bounds.upper)},
                "dtype": np.dtype(self.dtype).name}

    def describe(self) -> dict[str, Any]:
        t = self.table
        return {"model": "steady incline flow (closed form, docs/incline_fits.md)", "keys": list(self.keys),
                "data": {"path": t.path, "experiment": t.experiment, "quantity": t.quantity, "rows": t.n,
                         "slopes_deg": t.slopes.tolist()},
                "fixed": {k: v for k, v in self.material.items() if k in self.fixed_keys}, "side_walls": self._walls()}

    @property
    def fixed_keys(self) -> tuple[str, ...]:
        return measured_keys(self.keys, self.side_walls)

    def _walls(self) -> dict[str, Any] | None:
        return None if self.side_walls is None else dataclasses.asdict(self.side_walls)


def _constant(outs):
    """A task's function that returns what was computed when the task was made."""
    return outs
