"""Fits on a ladder of grids (``grid_ladder``): the grid's share of a calibrated parameter read from
where fits on coarser grids land, and the point extrapolated to dx → 0 where the grids converge.

The one-step grid term (``calibration.inference.gridcheck.grid_shift``) linearises: it takes one
Gauss–Newton step from the fit's point on a coarser grid. Along a curved valley that step can miss
where a fit on that grid lands, and one coarser grid cannot show an order of convergence. The
ladder fits every rung, the coarsest from the caller's starts (a global search, or one fit from
``init``) and each finer one from the coarser one's point (moved off a bound it ended on), so
that the cheap coarse fits pay for the fine one's start. With three rungs (dx, ρ dx, ρ² dx) the
order the fitted points show decides what is reported (docs/grid_term.md):

- where they converge with an observed order p inside ``ORDER_RANGE``, the point is Richardson's
  extrapolation θ(dx) − e21 / (ρ^p − 1), e21 = θ(ρ dx) − θ(dx), and the grid's 95 % half-width is
  Roache's three-grid index 1.25 |e21| / (ρ^p − 1);
- where they do not (they oscillate, the finer change is the larger, or p lies outside the range),
  the point is the finest rung's, with the wider index of ``three_grid_index``, and the statement
  says so. Two rungs show no order: the finest point with the two-grid index 3 |e21| / (ρ − 1).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..batch.workers import using
from ..inference.gauss_newton import _inverse
from ..inference.gridcheck import (
    GRID_RATIO,
    ORDER_RANGE,
    GridCheck,
    check_grid_options,
    observed_order,
    three_grid_index,
    two_grid_index,
)
from ..inference.noise import Z95
from ..inference.options import JudgeOptions
from ..inference.verdict import judge_point
from ..problem.options import check_int
from ..problem.protocol import ObjectiveLike
from .fit import FitResult, fit
from .options import FitOptions
from .search import SearchResult, fit_from_starts

__all__ = ["LADDER_RUNGS", "Rung", "LadderResult", "grid_ladder"]


#: The rungs a ladder may have: two grids (an index, no order) or three (the order, and the
#: extrapolated point where it is consistent).
LADDER_RUNGS = (2, 3)


@dataclasses.dataclass(frozen=True)
class Rung:
    """One rung's fit: its grid spacing, end point and how it ended (``at_bound``: the keys that
    ended at a bound, where the fit is not a minimum of that grid's misfit)."""

    dx: float
    theta: dict[str, float]
    loss: float
    converged: bool
    iterations: int
    wall_s: float
    at_bound: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "wall_s": round(self.wall_s, 3)}


@dataclasses.dataclass(frozen=True)
class LadderResult:
    """A ladder of fits (``grid_ladder``). ``fit``: the finest rung's, judged, its interval
    carrying the ladder's grid term; ``rungs``: every rung's fit, coarsest first; ``point``: the
    answer (``extrapolated`` True: Richardson's extrapolation, else the finest fit's) and ``ci95``
    its 95 % interval (the finest fit's half-widths, the grid's share included, about the point;
    None where the verdict withholds it); ``search``: the coarsest rung's global search, if one ran."""

    keys: tuple[str, ...]
    fit: FitResult
    rungs: tuple[Rung, ...]
    ratio: float
    grid: GridCheck
    extrapolated: bool
    point: dict[str, float]
    ci95: dict[str, tuple[float, float]] | None
    statement: str
    wall_s: float
    search: SearchResult | None = None

    def to_json(self) -> dict[str, Any]:
        out = {"rungs": [r.to_json() for r in self.rungs], "ratio": self.ratio, "grid": self.grid.to_dict(self.keys),
               "extrapolated": self.extrapolated, "point": self.point,
               "ci95": None if self.ci95 is None else {k: list(v) for k, v in self.ci95.items()},
               "statement": self.statement, "wall_s": round(self.wall_s, 3)}
        if self.search is not None:
            out["coarsest_search"] = {"starts": len(self.search.starts), "minima": len(self.search.minima),
                                      "wall_s": round(self.search.wall_s, 3)}
        return out


def _rung(objective: ObjectiveLike, result: FitResult) -> Rung:
    near = objective.bounds.near_bound([result.theta[k] for k in objective.keys])
    return Rung(float(objective.dx), dict(result.theta), float(result.loss), bool(result.converged),
                int(result.iterations), float(result.wall_s), tuple(near))


def _ladder_term(rungs: tuple[Rung, ...], keys, ratio: float, scale) -> tuple[GridCheck, np.ndarray | None, str]:
    """The grid term of the rungs' fits (finest last) and, where three rungs converge with an
    order inside ``ORDER_RANGE``, the extrapolated point; the sentence that says which."""
    theta = np.array([[r.theta[k] for k in keys] for r in rungs])
    fine, wall = theta[-1], sum(r.wall_s for r in rungs[:-1])
    shift = theta[-2] - fine
    dx, dx_coarse = rungs[-1].dx, rungs[-2].dx
    if len(rungs) == 2:
        grid = GridCheck(dx, dx_coarse, 1, shift, two_grid_index(shift, ratio), wall,
                         method="fits at two grids: Roache's GCI with the order assumed 1 and safety factor 3")
        return grid, None, "Two grids show no order of convergence: the point is the finest grid's fit."
    shift2 = theta[0] - fine
    halfwidth, order, method = three_grid_index(shift, shift2, ratio, scale, what="grids' fits")
    grid = GridCheck(dx, dx_coarse, 1, shift, halfwidth, wall, shift2=shift2, order=order, method=method)
    observed = observed_order(shift, shift2, ratio, scale)
    if observed is None:
        return grid, None, f"The {method}; the point is the finest grid's fit."
    if not ORDER_RANGE[0] <= observed <= ORDER_RANGE[1]:
        return grid, None, (f"The grids' fits converge with observed order {observed:.2g}, outside "
                            f"{ORDER_RANGE[0]:g}–{ORDER_RANGE[1]:g}: not extrapolated; the point is the finest "
                            f"grid's fit, its grid term Roache's index at order {order:.2g}.")
    return grid, fine - shift / (ratio**observed - 1.0), (
        f"The grids' fits converge with observed order {observed:.2g}: the point is Richardson's extrapolation "
        "to dx -> 0, the grid's share Roache's three-grid index (safety factor 1.25).")


def grid_ladder(objective: ObjectiveLike, init: Mapping[str, float] | None = None, *, rungs: int = 3,
                ratio: float = GRID_RATIO, starts: int = 1, seed: int = 0, options: FitOptions | None = None,
                judge: JudgeOptions | None = None, out=None, overwrite: bool = False, progress: bool = False,
                workers=None) -> LadderResult:
    """Fit ``objective`` on ``rungs`` grids, dx × ``ratio``^(rungs−1) … dx (the module's
    docstring): the coarsest from ``starts`` starts (``fit_from_starts``; ``init`` one more, or the
    only one, and ``seed`` the design's), every finer rung from the coarser one's point. The finest
    fit is judged with ``judge`` (its ``grid_ratio`` and ``grid_levels`` are replaced by the
    ladder's own term) and writes its history to ``out``. ``options``: every rung's ``FitOptions``.
    Raises ``ValueError`` for a bad option or an objective with no coarser grid, before any run."""
    rungs, starts = check_int("rungs", rungs, 2), check_int("starts", starts, 1)
    if rungs not in LADDER_RUNGS:
        raise ValueError(f"rungs must be one of {LADDER_RUNGS} (grids, the fit's included), got {rungs}")
    check_grid_options(ratio, 1, 1)
    options = options or FitOptions()
    judge = dataclasses.replace(judge or JudgeOptions(), grid_ratio=None, grid_levels=1)
    try:
        ladder = [objective.coarsened(ratio**level) for level in range(rungs - 1, 0, -1)] + [objective]
    except NotImplementedError as err:
        raise ValueError(f"grid_ladder: {type(objective).__name__} has no coarser grid ({err})") from None
    quick = JudgeOptions(noise=judge.noise, uncertainty=False, roundoff_samples=0)
    clock = time.perf_counter()
    with using(workers) as workers:
        first, search = fit_from_starts(ladder[0], init, starts=starts, options=options, judge=quick, seed=seed,
                                        progress=progress, workers=workers)
        results = [first]
        for level, obj in enumerate(ladder[1:], start=1):
            finest = level == len(ladder) - 1
            start = obj.bounds.move_inside([results[-1].theta[k] for k in obj.keys])[0]  # off a bound it ended on
            results.append(fit(obj, dict(zip(obj.keys, map(float, start))), options=options,
                               judge=dataclasses.replace(judge, uncertainty=False) if finest else quick,
                               out=out if finest else None, overwrite=overwrite, progress=progress,
                               workers=workers))
        final = results[-1]
        steps = tuple(_rung(obj, r) for obj, r in zip(ladder, results))
        J = np.asarray(final.jacobian, float)
        scale = np.sqrt(np.diag(_inverse(J.T @ J))) if np.all(np.isfinite(J)) else None
        grid, point, said = _ladder_term(steps, objective.keys, ratio, scale)
        lower, upper = np.asarray(objective.bounds.lower, float), np.asarray(objective.bounds.upper, float)
        unconverged = [f"{r.dx:.4g} m" for r in steps if not r.converged or r.at_bound]
        if point is not None and unconverged:
            point, said = None, (f"The fits at dx = {', '.join(unconverged)} did not converge or ended at a bound: "
                                 "not extrapolated; the point is the finest grid's fit.")
        elif point is not None and not np.all((lower <= point) & (point <= upper)):
            outside = [k for k, v, lo, hi in zip(objective.keys, point, lower, upper) if not lo <= v <= hi]
            point, said = None, (f"Richardson's extrapolation leaves the bounds ({', '.join(outside)}): not "
                                 "extrapolated; the point is the finest grid's fit.")
        theta = np.array([final.theta[k] for k in objective.keys])
        verdict, unc = judge_point(objective, final.residuals, J, theta, converged=final.converged,
                                   message=final.message, scatter=final.verdict.scatter, grid=grid, workers=workers,
                                   **judge.kwargs())
    final = dataclasses.replace(final, verdict=verdict, uncertainty=unc)
    centre = theta if point is None else point
    interval = None
    if unc is not None and not unc.withheld:
        half = Z95 * np.asarray(unc.stderr, float)
        interval = {k: (float(max(c - h, lo)), float(min(c + h, hi)))
                    for k, c, h, lo, hi in zip(objective.keys, centre, half, lower, upper)}
    return LadderResult(tuple(objective.keys), final, steps, float(ratio), grid, point is not None,
                        dict(zip(objective.keys, map(float, centre))), interval, said,
                        time.perf_counter() - clock, search)
