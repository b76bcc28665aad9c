"""Fitting the runout against aspect ratio (docs/scenes.md S5) to a scaling law.

One S5 collapse per aspect ratio a, whose datum is its final front from the law; the members are
fitted together (``CompositeObjective``) and then run at aspect ratios the fit did not use, to see
whether the fitted parameters predict them. The quoted laws are secondary sources: the comparison
tests the model against a quoted trend, not a measurement. ``fit_runout_law(...)`` returns a
``LawResult``; its ``to_json()`` is what ``python -m calibration law --json`` prints.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from jaxmpm.scenes import aspect_ratio_collapse, runout_law

from ..optim.fit import FitResult, fit
from ..problem.composite import CompositeObjective
from ..problem.objective import Objective
from ..problem.targets import FrontTarget

__all__ = ["law_from_table", "named_law", "runout_objective", "LawCase", "LawResult", "fit_runout_law"]


def law_from_table(table) -> Callable:
    """A law a -> ΔL/L0 from a loaded scaling-law file (``calibration.data.loaders.load_scaling_law``):
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


def named_law(path=None, *, sand: bool = False) -> tuple[Callable, str]:
    """(law, label): the scaling-law table at ``path`` (``calibration.data.loaders.load_scaling_law``,
    ``law_from_table``) labelled by its experiment and source, else the glass-bead law of
    Lajeunesse et al. 2005 or with ``sand`` the sand law of Lube et al. 2005 (both secondary)."""
    if path:
        from ..data.loaders import load_scaling_law

        table = load_scaling_law(path)
        return law_from_table(table), (f"{table.experiment} ({'secondary' if table.secondary else 'primary'}: "
                                       f"{table.source})")
    law = functools.partial(runout_law, sand=True) if sand else runout_law
    return law, ("sand (Lube et al. 2005" if sand else "glass beads (Lajeunesse et al. 2005") + ", secondary)"


def runout_objective(a: float, keys: Sequence[str], law: Callable = runout_law, L0: float = 0.05,
                     dx: float | None = None, ppc: float | None = None, values: Mapping[str, float] | None = None,
                     dtype=None, jacobian: str = "fd", fd_step: float = 0.05, side_walls=None):
    """The S5 objective at aspect ratio ``a``: the final front against ``law(a)``, in a channel
    whose walls are ``side_walls`` (a ``jaxmpm.SideWalls``; default None, plane strain). The Jacobian
    defaults to central differences over ±5 %: in tall columns the final front scatters between
    neighbouring parameter values, and autodiff would measure that scatter, not the trend
    (docs/calibration.md)."""
    scene = aspect_ratio_collapse(a, L0=L0, dx=dx, ppc=ppc, dtype=dtype, side_walls=side_walls, **dict(values or {}))
    t_end = scene.config.t_end
    target = FrontTarget(np.array([t_end]), np.array([L0 * (1.0 + float(law(a)))]))
    return Objective(scene, keys, front=target, jacobian=jacobian, fd_step=fd_step)


def _runouts(objective, theta) -> tuple[float, int]:
    _, pred = objective.residuals(theta)
    L0 = objective.length
    return (float(np.asarray(pred["front"])[-1]) - L0) / L0, int(np.asarray(pred["status"]))


@dataclasses.dataclass(frozen=True)
class LawCase:
    """One aspect ratio: the law's ΔL/L0 and the model's before (at the start) and after the fit."""

    a: float
    used_in_fit: bool
    law: float
    model_start: float
    model_fit: float
    rel_error_start: float
    rel_error_fit: float
    status: int  # the engine's status bits of both runs, or-ed
    n_particles: int


@dataclasses.dataclass(frozen=True, eq=False)
class LawResult:
    """The runout-law fit: the ``FitResult`` of the members fitted together, every aspect ratio's
    runout before and after it (``cases``, in increasing a), and ``warning`` when a fitted value
    ended at a bound (None otherwise)."""

    fit: FitResult
    start: dict[str, float]
    cases: tuple[LawCase, ...]
    law: str  # how the law is named in the JSON
    L0: float
    dx: float
    warning: str | None
    wall_s: float
    side_walls: Any = None  # the channel's jaxmpm.SideWalls, or None (plane strain)

    def to_json(self) -> dict[str, Any]:
        """The fit's JSON and every case: what ``python -m calibration law --json`` prints."""
        out = self.fit.to_json()
        if self.warning:
            out["warning"] = self.warning
        out.update({"start": dict(self.start), "cases": [dataclasses.asdict(c) for c in self.cases],
                    "wall_s": round(self.wall_s, 3), "law": self.law, "L0": self.L0, "dx": self.dx,
                    "side_walls": None if self.side_walls is None else dataclasses.asdict(self.side_walls)})
        return out


def fit_runout_law(a_fit: Sequence[float] = (0.5, 1.0, 4.0), a_test: Sequence[float] = (2.0, 8.0),
                   keys: Sequence[str] = ("mu1", "mu2"), *, law: Callable = runout_law, label: str | None = None,
                   L0: float = 0.05, dx: float | None = None, ppc: float | None = None,
                   values: Mapping[str, float] | None = None, init: Mapping[str, float] | None = None,
                   steps: int = 15, out=None, overwrite: bool = False, progress: bool = False,
                   dtype=None, jacobian: str = "fd", fd_step: float = 0.05, side_walls=None) -> LawResult:
    """Fit ``keys`` to the runout law at ``a_fit`` and predict it at ``a_test``. ``law(a)`` must
    answer at every aspect ratio (checked before any run); ``label`` names it in the result
    (default: the function's name). ``side_walls`` (a ``jaxmpm.SideWalls``) puts every column in
    that channel: its width is in metres, so the walls weigh more on the taller columns."""
    a_fit, a_test = [float(a) for a in a_fit], [float(a) for a in a_test]
    if not a_fit:
        raise ValueError("a_fit: at least one aspect ratio is needed")
    for a in a_fit + a_test:
        law(a)  # an aspect ratio the law does not give (e.g. a table's missing row) fails here, before any run
    t0 = time.perf_counter()
    members = [runout_objective(a, keys, law, L0, dx, ppc, values, dtype, jacobian, fd_step, side_walls) for a in a_fit]
    composite = CompositeObjective(members)
    theta0 = np.array([float(getattr(members[0].scene.params, k)) for k in keys])
    start = {**dict(zip(keys, theta0.tolist())), **dict(init or {})}
    result = fit(composite, start, method="lm", steps=steps, out=out, overwrite=overwrite, progress=progress,
                 meta={"runout_law": True, "a_fit": a_fit, "a_test": a_test,
                       **({"side_walls": dataclasses.asdict(side_walls)} if side_walls is not None else {})})
    theta = np.array([result.theta[k] for k in keys])
    theta_start = np.array([start[k] for k in keys])
    cases = []
    for a in sorted(set(a_fit) | set(a_test)):
        obj = (members[a_fit.index(a)] if a in a_fit
               else runout_objective(a, keys, law, L0, dx, ppc, values, dtype, jacobian, fd_step, side_walls))
        before, st0 = _runouts(obj, theta_start)
        after, st1 = _runouts(obj, theta)
        target = float(law(a))
        cases.append(LawCase(a=a, used_in_fit=a in a_fit, law=target, model_start=before, model_fit=after,
                             rel_error_start=before / target - 1.0, rel_error_fit=after / target - 1.0,
                             status=st0 | st1, n_particles=int(obj.scene.state.x.shape[0])))
    warning = None
    at_bound = composite.bounds.near_bound(theta)
    if at_bound:
        box = dict(zip(keys, zip(composite.bounds.lower, composite.bounds.upper)))
        warning = (f"{at_bound} ended at a bound of {box}: the law asks for values outside the physical range "
                   "(a sign of missing physics or resolution, not a measurement of them)")
    return LawResult(fit=result, start=start, cases=tuple(cases),
                     law=label if label is not None else getattr(law, "__name__", str(law)), L0=L0,
                     dx=members[0].config.grid.dx, warning=warning, wall_s=time.perf_counter() - t0,
                     side_walls=side_walls)
