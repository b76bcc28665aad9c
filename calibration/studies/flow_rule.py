"""Fitting μ1, μ2 and I0 to steady flows down a rough incline (a flow-rule table).

In the local μ(I) model a layer of thickness h flowing steadily down a rough incline at θ is the
Bagnold profile of docs/model.md §6: every depth carries the friction tan θ, so the inertial
number is I_θ = I0 (tan θ − μ1) / (μ2 − tan θ) throughout, and the surface velocity is
(2/3) I_θ sqrt(φ g cos θ) h^{3/2} / d (φ = ρ/ρ_s; the depth average is 3/5 of it:
``jaxmpm.scenes.incline.steady_velocity``). At each slope the velocities of several thicknesses
fix one I_θ; slopes spread between atan μ1 and atan μ2 fix the three constants, which is how the
glass-bead constants every scene here uses were obtained (docs/incline_fits.md).

The model is that closed form, not an MPM run: the periodic strip that the engine runs for S1
reaches it within 2.5 % (docs/validation.md §1), and a closed form costs microseconds. It holds
where the flow is uniform, wall-free and thick (h ≫ h_stop, which the local model does not
predict). The residuals are relative (u_model / u_data − 1), so a table's ``noise`` is a relative
standard deviation. The fit is the package's Levenberg–Marquardt (``calibration.optim.lm``) in
float64, with Gauss–Newton intervals from the table's noise (or the residuals' when it states none).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.params import DEFAULTS, validate_params
from jaxmpm.precision import x64
from jaxmpm.scenes.incline import steady_velocity

from ..data.flow_rule import FlowRuleTable
from ..inference.gauss_newton import Uncertainty, gauss_newton_uncertainty
from ..optim.evaluate import Evaluation
from ..optim.history import History
from ..optim.lm import LMOptions, levenberg_marquardt
from ..optim.loop import run
from ..problem.bounds import Bounds

__all__ = ["FLOW_RULE_KEYS", "FlowRuleResult", "fit_flow_rule", "flow_rule_residuals"]

#: The parameters a flow rule fixes (the grain size and φ = ρ/ρ_s are measured, not fitted).
FLOW_RULE_KEYS = ("mu1", "mu2", "I0")


def _material(values: Mapping[str, float] | None) -> dict[str, float]:
    material = {**DEFAULTS, **dict(values or {})}
    validate_params(material)
    return {k: float(v) for k, v in material.items()}


def flow_rule_residuals(table: FlowRuleTable, keys: Sequence[str], material: Mapping[str, float]):
    """The pure, traceable θ -> r of ``table`` (θ: the values of ``keys``; the other parameters
    from ``material``): r = u_model / u_data − 1 at every row, NaN where the row's slope allows
    no steady flow."""
    keys = tuple(keys)
    slope, h, u = (jnp.asarray(a) for a in (table.slope_deg, table.h, table.u))

    def residuals(theta):
        p = {**material, **dict(zip(keys, theta))}
        model = steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"], table.quantity)
        return model / u - 1.0

    return residuals


def _no_steady_flow(table: FlowRuleTable, p: Mapping[str, float]) -> str | None:
    """Why ``p`` gives some row of ``table`` no steady flow (None: every row flows steadily)."""
    low, high = float(table.slopes[0]), float(table.slopes[-1])
    if not p["mu1"] < math.tan(math.radians(low)):
        return f"mu1 = {p['mu1']:.4g} is not below tan {low:g}° = {math.tan(math.radians(low)):.4g} (no flow there)"
    if not math.tan(math.radians(high)) < p["mu2"]:
        return (f"mu2 = {p['mu2']:.4g} is not above tan {high:g}° = {math.tan(math.radians(high)):.4g} "
                "(no steady flow there: the layer accelerates)")
    return None


@dataclasses.dataclass(frozen=True, eq=False)
class FlowRuleResult:
    """The fit of ``keys`` to a flow-rule table: ``theta`` by key, the start, LM's ``message``,
    ``iterations``, the relative ``residuals`` at the end point, and its Gauss–Newton
    ``uncertainty`` (intervals from the table's noise, or the residuals' scatter)."""

    keys: tuple[str, ...]
    theta: dict[str, float]
    start: dict[str, float]
    material: dict[str, float]
    loss: float
    message: str
    iterations: int
    residuals: np.ndarray
    uncertainty: Uncertainty
    table: FlowRuleTable

    @property
    def converged(self) -> bool:
        return self.message.startswith("converged")

    def to_json(self) -> dict[str, Any]:
        """What ``python -m calibration flow-rule --json`` prints."""
        t = self.table
        return {"keys": list(self.keys), "theta": dict(self.theta), "start": dict(self.start),
                "fixed": {k: self.material[k] for k in ("rho", "rho_s", "d")}, "loss": self.loss,
                "message": self.message, "converged": self.converged, "iterations": self.iterations,
                "rms_relative_residual": float(np.sqrt(np.mean(self.residuals ** 2))),
                "uncertainty": self.uncertainty.to_dict(),
                "data": {"path": t.path, "experiment": t.experiment, "source": t.source, "secondary": t.secondary,
                         "quantity": t.quantity, "rows": t.n, "slopes_deg": t.slopes.tolist(), "noise": t.noise}}


def fit_flow_rule(table: FlowRuleTable, keys: Sequence[str] = FLOW_RULE_KEYS, *,
                  init: Mapping[str, float] | None = None, values: Mapping[str, float] | None = None,
                  bounds: Mapping[str, tuple[float, float]] | None = None, steps: int = 100) -> FlowRuleResult:
    """Fit ``keys`` (some of μ1, μ2, I0) to ``table`` from ``init`` (default: the material's own
    values), the other parameters (ρ, ρ_s, d and the keys not fitted) from ``values`` over the
    defaults of docs/model.md §4. A start at which some slope of the table has no steady flow is
    refused, naming the key."""
    keys = tuple(keys)
    if not keys or set(keys) - set(FLOW_RULE_KEYS) or len(set(keys)) != len(keys):
        raise ValueError(f"keys: a flow rule fits distinct keys among {FLOW_RULE_KEYS}, got {keys}")
    unknown = set(init or {}) - set(keys)
    if unknown:
        raise ValueError(f"init: {sorted(unknown)} are not among the fitted keys {keys}")
    material = _material(values)
    box = Bounds.create(keys, bounds)
    start = {k: float((init or {}).get(k, material[k])) for k in keys}
    box.check(np.array([start[k] for k in keys]), "init")
    problem = _no_steady_flow(table, {**material, **start})
    if problem:
        raise ValueError(f"init: {problem}; start where every slope of {table.path or 'the table'} flows steadily")
    if table.n <= len(keys):
        raise ValueError(f"{table.path or 'table'}: {table.n} rows cannot fix {len(keys)} keys")
    with x64():
        state, history = _run_lm(table, keys, material, box, start, steps)
        current = state.current
        theta = current.theta[0]
        r, J = current.residuals[0], current.jacobian[0]
    uncertainty = gauss_newton_uncertainty(J, r, keys, theta, {"velocity": slice(0, table.n)}, np.ones(table.n),
                                           noise=table.noise, bounds=box)
    return FlowRuleResult(keys=keys, theta=dict(zip(keys, theta.tolist())), start=start, material=material,
                          loss=float(current.loss[0]), message=str(state.message[0]), iterations=history.iterations,
                          residuals=np.asarray(r), uncertainty=uncertainty, table=table)


def _run_lm(table, keys, material, box: Bounds, start, steps: int):
    """LM from ``start`` in float64 (inside ``x64``): (its final state, history, evaluator)."""
    residuals = flow_rule_residuals(table, keys, material)
    jacobian = jax.jit(jax.jacfwd(lambda theta: (residuals(theta),) * 2, has_aux=True))

    def evaluate(z_rows) -> Evaluation:
        z_rows = np.asarray(z_rows, float)
        theta = np.asarray(box.to_physical(jnp.asarray(z_rows)))
        J, r = (np.stack(a) for a in zip(*[[np.asarray(o) for o in jacobian(jnp.asarray(t))] for t in theta]))
        Jz = J * np.asarray(box.jacobian_diag(jnp.asarray(z_rows)))[:, None, :]
        loss = np.where(np.all(np.isfinite(r), axis=1), np.sum(r ** 2, axis=1), np.inf)
        grad = 2 * np.einsum("kmi,km->ki", J, r)
        ok = np.zeros(len(r), int)
        return Evaluation(theta=theta, loss=loss, status=ok, grad=grad, residuals=r, jacobian=J, jacobian_z=Jz,
                          grad_z=None, prediction={"status": ok})

    optimiser = levenberg_marquardt(LMOptions())
    history = History()
    z0 = box.to_unconstrained(np.array([start[k] for k in keys]))[None]
    state = run(optimiser, optimiser.init(z0), evaluate, history, steps=steps)
    return state, history
