"""An incline experiment as a candidate of ``calibration.design.design``: the flow-rule table's
plan (its slopes, thicknesses and quantity) at θ, with the closed form of the steady flow
(``calibration.problem.flow_rule.FlowRuleObjective``, docs/incline_fits.md).

At θ the model's own velocities are the data, so the residuals (u_model / u_data − 1) are zero
and only their Jacobian matters: its columns of the keys the flow rule does not depend on (β, ξ,
p_c0, ...) are exactly zero. A closed form draws no particles and has no grid: its shares of
those are zero, and ``expected_halfwidths`` counts them so (``Experiment.closed_form``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from jaxmpm import SideWalls
from jaxmpm.scenes.incline import steady_velocity

from ..data.flow_rule import FLOW_RULE_KEYS, FlowRuleTable
from ..problem.flow_rule import FlowRuleObjective, flow_rule_material

__all__ = ["INCLINE_KINDS", "INCLINE_MATERIAL", "incline_experiment", "incline_plans", "incline_sigma"]

#: The observation an incline gives: its flow-rule table (the velocities of the steady layers).
INCLINE_KINDS = ("flow_rule",)
#: The parameters of the closed form besides the flow rule's keys.
INCLINE_MATERIAL = ("rho", "rho_s", "d")


def incline_plans(inclines, taken: Sequence[str]) -> dict[str, tuple[FlowRuleTable, dict[str, float], Any]]:
    """``design``'s ``inclines`` checked: {label: (table, the incline's own material, its chute's
    side walls or None)}. A value is a ``FlowRuleTable`` (the scene's material, no walls), a pair
    (table, {key: value}) whose values replace the scene's for this incline (its measured ρ, ρ_s,
    d; μ_w for walls whose friction is "mu_w"), or a triple (table, {key: value},
    ``jaxmpm.SideWalls``). Refuses a label among ``taken``."""
    plans = {}
    for label, value in dict(inclines or {}).items():
        label = str(label)
        if label in taken:
            raise ValueError(f"inclines: the label {label!r} is already an experiment's ({list(taken)}); "
                             "choose another")
        table, material, walls = (value, {}, None) if isinstance(value, FlowRuleTable) else _pair(label, value)
        plans[label] = (table, {str(k): float(v) for k, v in dict(material).items()}, walls)
    return plans


def _pair(label, value):
    if (isinstance(value, Sequence) and len(value) in (2, 3) and isinstance(value[0], FlowRuleTable)
            and isinstance(value[1], Mapping) and (len(value) == 2 or value[2] is None
                                                    or isinstance(value[2], SideWalls))):
        return (*value, None) if len(value) == 2 else tuple(value)
    raise ValueError(f"inclines[{label!r}] must be a FlowRuleTable, a pair (FlowRuleTable, {{key: value}}) or a "
                     "triple (FlowRuleTable, {key: value}, jaxmpm.SideWalls), "
                     f"got {type(value).__name__}")


def incline_sigma(table: FlowRuleTable, noise: Mapping[str, float], given: bool) -> float:
    """The relative noise of one velocity: ``noise["velocity"]`` where the caller gave it (one number
    for all, or the entry), else the table's stated ``noise``, else ``noise["velocity"]``'s default."""
    return float(noise["velocity"]) if given or table.noise is None else float(table.noise)


def incline_experiment(label: str, table: FlowRuleTable, material: Mapping[str, float], scene_params,
                       keys: Sequence[str], values: Mapping[str, float], sigma: float, experiment_type,
                       side_walls=None):
    """The ``experiment_type`` (``design.Experiment``) of an incline: its rows ("flow_rule"), σ, the
    Jacobian of the relative residuals with respect to ``keys`` at ``values`` (zero columns for
    the keys the flow rule does not depend on), unit weights, no draws and no coarse grid; the
    walled steady flow between ``side_walls`` (μ_w a key where their friction is "mu_w")."""
    keys = tuple(keys)
    base = {k: float(np.asarray(getattr(scene_params, k))) for k in (*INCLINE_MATERIAL, *FLOW_RULE_KEYS, "mu_w")}
    at = {**base, **{k: v for k, v in material.items() if k not in keys}, **{k: values[k] for k in keys}}
    try:
        at = flow_rule_material(at)
    except ValueError as err:
        raise ValueError(f"inclines[{label!r}]: the material at theta is not valid: {err}") from None
    reads_mu_w = side_walls is not None and side_walls.friction == "mu_w"
    own = tuple(k for k in keys if k in FLOW_RULE_KEYS or (k == "mu_w" and reads_mu_w))
    probe = FlowRuleObjective(table, FLOW_RULE_KEYS, values=at, side_walls=side_walls)
    why = probe.no_steady_flow({k: at[k] for k in FLOW_RULE_KEYS})
    if why is not None:
        raise ValueError(f"inclines[{label!r}]: at theta the table's slopes give no steady flow: {why}")
    m = table.n
    J = np.zeros((m, len(keys)))
    objective = None
    if own:
        u = np.asarray(steady_velocity(table.h, table.slope_deg, *(at[k] for k in (*FLOW_RULE_KEYS, *INCLINE_MATERIAL)),
                                       table.quantity, side_walls, at["mu_w"] if reads_mu_w else None,
                                       height=table.z), float)
        twin = FlowRuleTable(table.slope_deg, table.h, u, table.quantity, table.source, table.secondary,
                             table.experiment, table.noise, dict(table.meta), table.path, table.z)
        objective = FlowRuleObjective(twin, own, values=at, side_walls=side_walls)
        r, J_own, _ = objective.residuals_and_jacobian([at[k] for k in own])
        if not (np.all(np.isfinite(np.asarray(J_own))) and np.max(np.abs(np.asarray(r))) < 1e-4):
            raise ValueError(f"inclines[{label!r}]: the closed form is not finite at theta (residuals {np.asarray(r)})")
        J[:, [keys.index(k) for k in own]] = np.asarray(J_own, float)
    if not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"noise: the velocity noise of incline {label!r} must be a positive fraction, got {sigma!r}")
    return experiment_type(label, objective, {"flow_rule": np.arange(m)}, np.full(m, float(sigma)), J, np.ones(m),
                           None, None, None, closed_form=True)
