"""Fitting μ1, μ2 and I0 to steady flows down a rough incline (a flow-rule table).

In the local μ(I) model a layer of thickness h flowing steadily down a rough incline at θ is the
Bagnold profile of docs/model.md §6: every depth carries the friction tan θ, so the inertial
number is I_θ = I0 (tan θ − μ1) / (μ2 − tan θ) throughout, and the surface velocity is
(2/3) I_θ sqrt(φ g cos θ) h^{3/2} / d (φ = ρ/ρ_s; the depth average is 3/5 of it:
``jaxmpm.scenes.incline.steady_velocity``). At each slope the velocities of several thicknesses
fix one I_θ; slopes spread between atan μ1 and atan μ2 fix the three constants, which is how the
glass-bead constants every scene here uses were obtained (docs/incline_fits.md).

The model is that closed form, not an MPM run (``calibration.problem.flow_rule.FlowRuleObjective``):
the periodic strip the engine runs for S1 reaches it within 1.2-1.6 % in float64 (docs/validation.md
§2), and a closed form costs microseconds. It holds where the flow is uniform, wall-free and thick
(h ≫ h_stop, which the local model does not predict); between a chute's side walls the model is
their closed form (``steady_velocity(side_walls=)``: the walls' friction μ_w K p / W at each
depth, docs/incline_fits.md "A chute with side walls"). The residuals are relative
(u_model / u_data − 1), so a table's ``noise`` is a relative standard deviation. A velocity
profile v(z) is fitted the same way (v(z) = U_s(h) − U_s(h − z), U_s(D) the surface velocity of a
layer of depth D). An h_stop table is not fitted: the local model has a steady flow at every
thickness where tan θ > μ1 and none where tan θ <= μ1, so it has no h_stop (a non-local model would
be needed); ``h_stop_report`` sets the table beside the fitted threshold atan(μ1). The fit is
``calibration.fit`` in float64 (its verdict and Gauss–Newton intervals; no grid term: a closed form
has no grid). Fitted together with a collapse, the objective is a member of a
``CompositeObjective`` sharing μ1, μ2 and I0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from jaxmpm.precision import x64

from ..data.flow_rule import FlowRuleTable, HStopTable
from ..optim.fit import FitResult, fit
from ..problem.flow_rule import FLOW_RULE_KEYS, FlowRuleObjective, measured_keys

__all__ = ["FLOW_RULE_KEYS", "FlowRuleResult", "fit_flow_rule", "h_stop_report"]

#: Why an h_stop table is reported, never fitted.
NO_H_STOP = ("the local mu(I) model does not predict h_stop: it has a steady flow at every thickness where "
             "tan(theta) > mu1 and none where tan(theta) <= mu1 (a non-local model would be needed), so h_stop is "
             "not fitted; each row says whether the fitted model flows at its slope")


def h_stop_report(table: HStopTable, mu1: float, fitted: bool = True) -> dict[str, Any]:
    """The ``h_stop`` block of a flow-rule fit's JSON: ``table``'s rows, why they are not fitted
    (``NO_H_STOP``), whether the model flows at each row's slope (tan θ > ``mu1``, the fitted
    value, or the held one where not ``fitted``), and its threshold atan(μ1) against the range of
    the table's slopes."""
    threshold = math.degrees(math.atan(mu1))
    flows = [bool(math.tan(math.radians(s)) > mu1) for s in table.slope_deg.tolist()]
    low, high = float(table.slope_deg.min()), float(table.slope_deg.max())
    where = f"atan(mu1) = {threshold:.4g} deg"
    if all(flows):
        reading = (f"{where} is below every h_stop slope ({low:g}-{high:g} deg): the model flows at all of them "
                   "at any thickness, where the data's layers thinner than h_stop stop")
    elif not any(flows):
        reading = (f"{where} is at or above every h_stop slope ({low:g}-{high:g} deg): the model flows at none of "
                   "them at any thickness, where the data's layers thicker than h_stop flow")
    else:
        reading = (f"{where} lies among the h_stop slopes ({low:g}-{high:g} deg): the model flows at any thickness "
                   f"at {sum(flows)} of the {len(flows)} rows' slopes and at none at the others; the data flow above "
                   "h_stop at every one")
    return {"fitted": False, "why": NO_H_STOP, "path": table.path, "experiment": table.experiment,
            "source": table.source, "secondary": table.secondary, "mu1": float(mu1), "mu1_fitted": bool(fitted),
            "threshold_deg": threshold, "slopes_deg": [low, high], "reading": reading,
            "rows": [{"slope_deg": float(s), "h_stop_m": float(h), "model_flows": f}
                     for s, h, f in zip(table.slope_deg.tolist(), table.h_stop.tolist(), flows)]}


@dataclasses.dataclass(frozen=True, eq=False)
class FlowRuleResult:
    """The fit of a flow-rule table: the package's ``FitResult`` (``fit``: the point, its
    verdict and intervals), the table, the start, the material the other parameters came from,
    the chute's side walls (None: none) and the h_stop table reported beside it (None: none)."""

    fit: FitResult
    table: FlowRuleTable
    start: dict[str, float]
    material: dict[str, float]
    side_walls: Any = None
    h_stop: HStopTable | None = None

    keys = property(lambda self: self.fit.keys)
    theta = property(lambda self: self.fit.theta)
    message = property(lambda self: self.fit.message)
    iterations = property(lambda self: self.fit.iterations)
    uncertainty = property(lambda self: self.fit.uncertainty)
    residuals = property(lambda self: np.asarray(self.fit.residuals, float))

    @property
    def converged(self) -> bool:
        return bool(self.fit.converged)

    def to_json(self) -> dict[str, Any]:
        """What ``python -m calibration flow-rule --json`` prints: the fit's JSON, the material held
        fixed, the chute's side walls (null: none), the relative residuals' RMS, the table's
        description and, with an h_stop table, its ``h_stop`` block (``h_stop_report``)."""
        t = self.table
        out = self.fit.to_json()
        fixed = measured_keys(self.keys, self.side_walls)
        out.update({"start": dict(self.start), "fixed": {k: self.material[k] for k in fixed},
                    "side_walls": None if self.side_walls is None else dataclasses.asdict(self.side_walls),
                    "rms_relative_residual": float(np.sqrt(np.mean(self.residuals ** 2))),
                    "data": {"path": t.path, "experiment": t.experiment, "source": t.source,
                             "secondary": t.secondary, "quantity": t.quantity, "rows": t.n,
                             "slopes_deg": t.slopes.tolist(), "noise": t.noise}})
        if self.h_stop is not None:
            out["h_stop"] = h_stop_report(self.h_stop, self.theta.get("mu1", self.material["mu1"]),
                                          "mu1" in self.keys)
        return out


def fit_flow_rule(table: FlowRuleTable, keys: Sequence[str] = FLOW_RULE_KEYS, *,
                  init: Mapping[str, float] | None = None, values: Mapping[str, float] | None = None,
                  bounds: Mapping[str, tuple[float, float]] | None = None, steps: int = 100,
                  side_walls=None, h_stop: HStopTable | None = None) -> FlowRuleResult:
    """Fit ``keys`` (some of μ1, μ2, I0; and μ_w between ``side_walls`` whose friction is "mu_w")
    to ``table`` from ``init`` (default: the material's own values), the other parameters (ρ, ρ_s,
    d, μ_w and the keys not fitted) from ``values`` over the defaults of docs/model.md §4, the
    chute's ``side_walls`` (a ``jaxmpm.SideWalls``; None: none): ``calibration.fit`` of a
    ``FlowRuleObjective`` in float64, the table's noise (if it states one) for the intervals. A
    start at which some slope of the table has no steady flow is refused, naming the key.
    ``h_stop`` (an ``HStopTable``): reported beside the fit (``h_stop_report``), never fitted."""
    keys = tuple(keys)
    if h_stop is not None and not isinstance(h_stop, HStopTable):
        raise ValueError(f"h_stop must be an HStopTable (calibration.data.load_h_stop) or None, got "
                         f"{type(h_stop).__name__}")
    unknown = set(init or {}) - set(keys)
    if unknown:
        raise ValueError(f"init: {sorted(unknown)} are not among the fitted keys {keys}")
    with x64():
        objective = FlowRuleObjective(table, keys, values=values, bounds=bounds, dtype="float64",
                                      side_walls=side_walls)
        start = {k: float((init or {}).get(k, objective.material[k])) for k in objective.keys}
        objective.bounds.check(np.array([start[k] for k in objective.keys]), "init")
        problem = objective.no_steady_flow(start)
        if problem:
            raise ValueError(f"init: {problem}; start where every slope of {table.path or 'the table'} flows steadily")
        if table.n <= len(keys):
            raise ValueError(f"{table.path or 'table'}: {table.n} rows cannot fix {len(keys)} keys")
        result = fit(objective, start, steps=steps, noise=table.noise, workers=1)
    return FlowRuleResult(fit=result, table=table, start=start, material=objective.material, side_walls=side_walls,
                          h_stop=h_stop)
