"""Fitting the runout against aspect ratio (SCENES.md S5) to a scaling law.

One S5 collapse per aspect ratio a (a column L0 × a L0 released against a back wall); the datum
of each is its final front, x_f = L0 (1 + ΔL/L0 (a)) from the law, and the residual is the
normalised runout error (ΔL/L0)_model − (ΔL/L0)_law. The members are fitted together
(``CompositeObjective``) and then run at aspect ratios the fit did not use, to see whether the
fitted parameters predict them. The glass-bead law (Lajeunesse et al. 2005, quoted by K. Kumar)
is a secondary source: the comparison tests the model against a quoted trend, not a
measurement.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from jaxmpm.scenes import aspect_ratio_collapse, runout_law

from .fit import fit
from .objective import CompositeObjective, FrontTarget, Objective

__all__ = ["runout_objective", "fit_runout_law", "law_from_table"]


def law_from_table(table) -> Callable:
    """A law a -> ΔL/L0 from a loaded scaling-law file (``calibration.data.load_scaling_law``):
    it answers only at the tabulated aspect ratios (no interpolation between quoted values)."""
    values = {float(a): float(r) for a, r in zip(table.a, table.runout)}

    def law(a):
        a_arr = np.atleast_1d(np.asarray(a, float))
        missing = [float(v) for v in a_arr if float(v) not in values]
        if missing:
            raise ValueError(f"aspect ratios {missing} are not in {table.path or 'the law table'}; "
                             f"tabulated: {sorted(values)}")
        out = np.array([values[float(v)] for v in a_arr])
        return out if np.ndim(a) else out[0]

    law.__name__ = f"table:{table.experiment}"
    return law


def runout_objective(a: float, keys: Sequence[str], law: Callable = runout_law, L0: float = 0.05,
                     dx: float | None = None, ppc: float | None = None, values: Mapping[str, float] | None = None, dtype=None,
                     jacobian: str = "fd", fd_step: float = 0.05):
    """The S5 objective at aspect ratio ``a``: the final front against ``law(a)``. The Jacobian
    defaults to central differences over ±5 %: in the tall, violent columns (a ≥ 4) the final
    front scatters by ~0.1 L0 between neighbouring parameter values, and the autodiff
    derivative of the discrete run measures that scatter, not the trend (docs/calibration.md)."""
    scene = aspect_ratio_collapse(a, L0=L0, dx=dx, ppc=ppc, dtype=dtype, **dict(values or {}))
    t_end = scene.config.t_end
    target = FrontTarget(np.array([t_end]), np.array([L0 * (1.0 + float(law(a)))]))
    return Objective(scene, keys, front=target, jacobian=jacobian, fd_step=fd_step)


def _runouts(objective, theta) -> tuple[float, int]:
    _, pred = objective.residuals(theta)
    L0 = objective.length
    return (float(np.asarray(pred["front"])[-1]) - L0) / L0, int(np.asarray(pred["status"]))


def fit_runout_law(a_fit: Sequence[float] = (0.5, 1.0, 4.0), a_test: Sequence[float] = (2.0, 8.0),
                   keys: Sequence[str] = ("mu1", "mu2"), *, law: Callable = runout_law, L0: float = 0.05,
                   dx: float | None = None, ppc: float | None = None, values: Mapping[str, float] | None = None,
                   init: Mapping[str, float] | None = None, steps: int = 15, out=None, overwrite: bool = False,
                   progress: bool = False,
                   dtype=None, jacobian: str = "fd", fd_step: float = 0.05) -> dict[str, Any]:
    """Fit ``keys`` to the runout law at ``a_fit`` and predict it at ``a_test``. Returns a JSON-able
    dict (fitted values, standard errors, runouts before and after the fit at every a) plus the
    fit result under ``"_fit"``."""
    a_fit, a_test = [float(a) for a in a_fit], [float(a) for a in a_test]
    if not a_fit:
        raise ValueError("a_fit: at least one aspect ratio is needed")
    t0 = time.perf_counter()
    members = [runout_objective(a, keys, law, L0, dx, ppc, values, dtype, jacobian, fd_step) for a in a_fit]
    composite = CompositeObjective(members)
    theta0 = np.array([float(getattr(members[0].scene.params, k)) for k in keys])
    start = {**dict(zip(keys, theta0.tolist())), **dict(init or {})}
    result = fit(composite, start, method="lm", steps=steps, out=out, overwrite=overwrite, progress=progress,
                 meta={"runout_law": True, "a_fit": a_fit, "a_test": a_test})
    theta = np.array([result.theta[k] for k in keys])
    theta_start = np.array([start[k] for k in keys])
    rows = []
    for a in sorted(set(a_fit) | set(a_test)):
        obj = (members[a_fit.index(a)] if a in a_fit
               else runout_objective(a, keys, law, L0, dx, ppc, values, dtype, jacobian, fd_step))
        before, st0 = _runouts(obj, theta_start)
        after, st1 = _runouts(obj, theta)
        target = float(law(a))
        rows.append({"a": a, "used_in_fit": a in a_fit, "law": target, "model_start": before, "model_fit": after,
                     "rel_error_start": before / target - 1.0, "rel_error_fit": after / target - 1.0,
                     "status": st0 | st1, "n_particles": int(obj.scene.state.x.shape[0])})
    out_json = result.to_json()
    at_bound = composite.bounds.near_bound(theta)
    if at_bound:
        out_json["warning"] = (f"{at_bound} ended at a bound of {dict(zip(keys, zip(composite.bounds.lower, composite.bounds.upper)))}:"
                               " the law asks for values outside the physical range (a sign of missing physics or "
                               "resolution, not a measurement of them)")
    out_json.update({"start": start, "cases": rows, "wall_s": round(time.perf_counter() - t0, 3),
                     "law": getattr(law, "__name__", str(law)), "L0": L0, "dx": members[0].config.grid.dx,
                     "_fit": result})
    return out_json
