"""The grid term of a sampled posterior: how far the same posterior moves on a coarser grid.

Along a flat, curved valley the Gauss–Newton shift of a fit (``gridcheck.grid_shift``) misses
where the posterior's mass moves, so the posterior is sampled again on the objective rebuilt at
``ratio`` × dx (and ``ratio``² × dx), and the shift of its mean gives Roache's index, added in
quadrature to each side of the 95 % interval (docs/grid_term.md). ``GridTerm`` gives a
posterior's dataclass the reading of it; ``coarse_objectives`` refuses a bad option before any
run; ``with_grid_term`` samples the coarser posteriors and attaches the result.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .gridcheck import GRID_ORDER, GridCheck, check_grid_options, three_grid_index, two_grid_index

__all__ = ["widened", "GridTerm", "coarse_objectives", "with_grid_term"]


def widened(lo, hi, centre: float, halfwidth: float, lower: float, upper: float) -> tuple[float | None, float | None]:
    """The 95 % interval (``lo``, ``hi``) with a grid term of 95 % half-width ``halfwidth`` added
    in quadrature to each side, measured from ``centre`` and kept inside [``lower``, ``upper``];
    an end the interval does not reach (None) stays None."""
    return (None if lo is None else float(max(centre - math.hypot(centre - lo, halfwidth), lower)),
            None if hi is None else float(min(centre + math.hypot(hi - centre, halfwidth), upper)))


@dataclasses.dataclass(frozen=True, kw_only=True)
class GridTerm:
    """The grid term of a posterior dataclass with ``keys``, ``mean``, ``sd`` and ``ci95`` (by
    key): its fields ``grid`` (a ``GridCheck`` or None), ``ci95_with_grid``, ``grid_posteriors``
    (the coarser posteriors' summaries) and ``grid_note`` (why it is missing), keyword-only, and
    their reading."""

    grid: GridCheck | None = None
    ci95_with_grid: dict[str, tuple[float, float]] | None = None
    grid_posteriors: tuple[dict[str, Any], ...] = ()
    grid_note: str = ""

    def _half(self, k: str) -> float:
        return 0.5 * (self.ci95[k][1] - self.ci95[k][0])

    @property
    def grid_converged(self) -> dict[str, bool] | None:
        """By key, whether the grid term's 95 % half-width stays within the half-width of the
        data's 95 % interval (None: the grid term was not measured)."""
        if self.grid is None:
            return None
        return {k: bool(h <= self._half(k)) for k, h in zip(self.keys, self.grid.halfwidth)}

    @property
    def adequate_dx(self) -> dict[str, float] | None:
        """By key, the grid spacing at which the grid term would shrink to the data's 95 %
        half-width, the index scaled as dx^p (p the order the grids showed, else 1): where the
        answer would become that key's property of the material (None: not measured)."""
        if self.grid is None:
            return None
        p = self.grid.order or GRID_ORDER
        return {k: float(self.grid.dx * min((self._half(k) / h) ** (1.0 / p), 1.0)) if h > 0 else float(self.grid.dx)
                for k, h in zip(self.keys, self.grid.halfwidth)}

    @property
    def grid_statement(self) -> str:
        """The grid term in words: which keys the grid moves by more than the data's interval,
        and how much finer a grid would bring them within it."""
        if self.grid is None:
            return f"The grid's share was not measured: {self.grid_note}." if self.grid_note else ""
        g, fine = self.grid, self.grid_converged
        moved = [f"{k} (±{h:.2g} against ±{self._half(k):.2g})" for k, h in zip(self.keys, g.halfwidth) if not fine[k]]
        levels = f"{g.ratio:.3g} × dx" + ("" if g.shift2 is None else f" and {g.ratio ** 2:.3g} × dx")
        rough = [f"{p['dx'] / g.dx:.3g} × dx" for p in self.grid_posteriors if not p["converged"]]
        caveat = (f" The posterior at {' and '.join(rough)} did not converge: its mean, and so the grid term, is "
                  "rough." if rough else "")
        if not moved:
            return (f"Converged in the grid as far as the posterior at {levels} can show: its share stays within "
                    "the data's interval for every key." + caveat)
        return (f"Not converged in the grid: the posterior at {g.ratio:.3g} × dx moves its mean by " + ", ".join(
            f"{k} {d:+.2g}" for k, d in zip(self.keys, g.shift)) + "; the grid's share of the interval of "
            + ", ".join(moved) + " exceeds the data's. At this dx that part of the answer is a property of the "
            f"grid, not of the material ({g.method}); ci95_with_grid carries it. The grid term would fall within "
            "the data's interval on a grid about " + ", ".join(
                f"{g.dx / self.adequate_dx[k]:.3g}× finer for {k}" for k in self.keys if not fine[k]) + "." + caveat)

    def grid_json(self) -> dict[str, Any]:
        """The JSON fields of the grid term (none where it was not asked for)."""
        if self.grid is None:
            return {"grid": {"measured": False, "why": self.grid_note}} if self.grid_note else {}
        return {"grid": {**self.grid.to_dict(self.keys), "posteriors": list(self.grid_posteriors)},
                "ci95_with_grid": {k: list(v) for k, v in self.ci95_with_grid.items()},
                "grid_converged": self.grid_converged, "adequate_dx": self.adequate_dx,
                "grid_statement": self.grid_statement}


def coarse_objectives(objective, ratio: float | None, levels: int) -> tuple[list, str]:
    """The objective rebuilt at ``ratio``^l × dx, l = 1 .. ``levels`` (before any run: a bad
    option or a scene that cannot be rebuilt is refused there), or ([], why not) where the
    objective has no coarser grid (its ``coarsened`` raises ``NotImplementedError``: a closed-form
    one, an emulator's)."""
    check_grid_options(ratio, 1, levels)
    if ratio is None:
        return [], ""
    try:
        return [objective.coarsened(ratio**level) for level in range(1, levels + 1)], ""
    except NotImplementedError as err:
        return [], f"{type(objective).__name__} has no coarser grid ({err})"


def with_grid_term(found, objective, coarse: list, ratio: float, sample: Callable, summary: Callable | None = None,
                   say: Callable[[str], None] = lambda text: None):
    """``found`` (a posterior dataclass with ``GridTerm``'s fields) with its grid term:
    ``sample(obj)`` the same posterior on each of the ``coarse`` objectives (``ratio``^l × dx);
    ``summary(other)``, extra fields of a coarser posterior's record (its diagnostics)."""
    clock = time.perf_counter()
    keys = found.keys
    fine = np.array([found.mean[k] for k in keys])
    shifts, summaries = [], []
    for level, obj in enumerate(coarse, start=1):
        say(f"the grid term: the same posterior at {ratio ** level:.3g} × dx")
        try:
            other = sample(obj)
        except RuntimeError as err:  # the coarse model's run fails where the chains start
            return dataclasses.replace(found, grid_note=f"the posterior at {ratio ** level:.3g} × dx failed: {err}")
        shifts.append(np.array([other.mean[k] for k in keys]) - fine)
        summaries.append({"dx": float(obj.dx), "mean": dict(other.mean), "sd": dict(other.sd),
                          "ci95": {k: list(v) for k, v in other.ci95.items()}, "converged": bool(other.converged),
                          **(summary(other) if summary else {}), "wall_s": round(other.wall_s, 1)})
    if len(shifts) == 1:
        halfwidth = two_grid_index(shifts[0], ratio)
        grid = GridCheck(float(objective.dx), float(coarse[0].dx), 1, shifts[0], halfwidth,
                         time.perf_counter() - clock, method="two posteriors' means: Roache's GCI with the order "
                                                                 "assumed 1 and safety factor 3")
    else:
        scale = [max(found.sd[k], 1e-300) for k in keys]
        halfwidth, order, method = three_grid_index(shifts[0], shifts[1], ratio, scale, what="posteriors' means")
        grid = GridCheck(float(objective.dx), float(coarse[0].dx), 1, shifts[0], halfwidth,
                         time.perf_counter() - clock, shift2=shifts[1], order=order, method=method)
    lower, upper = np.asarray(objective.bounds.lower, float), np.asarray(objective.bounds.upper, float)
    wide = {k: widened(*found.ci95[k], found.mean[k], halfwidth[j], lower[j], upper[j]) for j, k in enumerate(keys)}
    return dataclasses.replace(found, grid=grid, ci95_with_grid=wide, grid_posteriors=tuple(summaries))
