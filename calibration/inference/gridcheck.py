"""The grid's share of a fit's uncertainty (``grid_shift``): the fit's objective rebuilt on a coarser
grid, the Gauss–Newton shift of its point there, and Roache's grid convergence index.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..problem.options import OptionError, _is_int, _is_number
from ..problem.protocol import ObjectiveLike
from .gauss_newton import _inverse
from .noise import Z95
from .scatter import coarse_residuals

__all__ = ["GRID_RATIO", "GRID_DRAWS", "GridCheck", "check_grid_options", "grid_shift"]


#: The grid check's coarser spacing, as a multiple of the fit's dx.
GRID_RATIO = 1.5


#: Particle draws averaged at the coarser spacing (one forward run each, cheaper than the fit's).
GRID_DRAWS = 2


#: Roache's safety factor for a two-grid study, and the order of convergence assumed.
GCI_SAFETY, GRID_ORDER = 3.0, 1.0


@dataclasses.dataclass(frozen=True)
class GridCheck:
    """The grid's share of a fit's uncertainty (``grid_shift``; docs/grid_term.md)."""

    dx: float  # the fit's grid spacing (m)
    dx_coarse: float
    draws: int  # coarse runs averaged (particle draws that ran without status bits)
    shift: np.ndarray  # θ(ρ dx) − θ(dx), to first order
    halfwidth: np.ndarray  # the grid convergence index: the 95 % half-width of θ's grid error
    wall_s: float
    #: With a second coarser grid (``levels=2``): θ(ρ² dx) − θ(dx), the order the three grids
    #: show along the shift (None: they do not converge monotonically) and how the index was made.
    shift2: np.ndarray | None = None
    order: float | None = None
    method: str = "two grids: Roache's GCI with the order assumed 1 and safety factor 3"

    @property
    def ratio(self) -> float:
        return self.dx_coarse / self.dx

    @property
    def stderr(self) -> np.ndarray:
        return self.halfwidth / Z95

    @property
    def cov(self) -> np.ndarray:
        """Rank one along the shift: the grid moves the keys together, as the fits move along a valley."""
        norm = np.linalg.norm(self.shift)
        if norm == 0.0:
            return np.zeros((self.shift.size, self.shift.size))
        v = self.shift / norm * np.linalg.norm(self.stderr)
        return np.outer(v, v)

    def to_dict(self, keys: Sequence[str]) -> dict[str, Any]:
        by_key = lambda a: {k: float(v) for k, v in zip(keys, a)}  # noqa: E731
        out = {"dx": self.dx, "dx_coarse": self.dx_coarse, "ratio": round(self.ratio, 6), "draws": self.draws,
               "shift": by_key(self.shift), "halfwidth95": by_key(self.halfwidth), "stderr": by_key(self.stderr),
               "method": self.method, "wall_s": round(self.wall_s, 3)}
        if self.shift2 is None:
            out.update(order_assumed=GRID_ORDER, safety_factor=GCI_SAFETY)
        else:
            out.update(levels=2, dx_coarse2=self.dx * self.ratio ** 2, shift2=by_key(self.shift2),
                       order_observed=self.order)
        return out


def two_grid_index(shift, ratio: float) -> np.ndarray:
    """Roache's grid convergence index from two grids: the 95 % half-width 3 |shift| / (ρ^p − 1)
    with the order p assumed 1 (``GCI_SAFETY``, ``GRID_ORDER``)."""
    return GCI_SAFETY * np.abs(np.asarray(shift, float)) / (ratio**GRID_ORDER - 1.0)


#: The orders of convergence a three-grid index believes: an observed one outside is clamped to it.
ORDER_RANGE = (0.5, 2.0)


def convergence_ratio(shift1, shift2, scale=None) -> float:
    """q = e32·e21 / |e21|² of three grids (dx, ρ dx, ρ² dx) by θ's shifts to the two coarser ones
    (e21 = ``shift1``, e32 = ``shift2`` − ``shift1``), each key measured in its ``scale``: ρ^p on a
    grid converging with order p, ≤ 0 where the grids oscillate, inf where e21 is nil."""
    e21 = np.asarray(shift1, float)
    e32 = np.asarray(shift2, float) - e21
    scale = np.ones_like(e21) if scale is None else np.asarray(scale, float)
    if not np.all(np.isfinite(scale) & (scale > 0)):
        raise ValueError(f"scale must be positive and finite for every key, got {scale!r}")
    w = 1.0 / scale**2
    norm2 = float(e21 @ (w * e21))
    return float(e32 @ (w * e21)) / norm2 if norm2 > 0 else math.inf


def observed_order(shift1, shift2, ratio: float, scale=None) -> float | None:
    """The order p the three grids show (ρ^p = ``convergence_ratio``), unclamped; None where they
    do not converge monotonically (q <= 1, or e21 nil)."""
    q = convergence_ratio(shift1, shift2, scale)
    return math.log(q) / math.log(ratio) if 1.0 < q < math.inf else None


def three_grid_index(shift1, shift2, ratio: float, scale=None,
                     what: str = "grids") -> tuple[np.ndarray, float | None, str]:
    """The grid convergence index from three grids (dx, ρ dx, ρ² dx) by the shifts of θ to the
    two coarser ones: (95 % half-width per key, the observed order or None, how it was made).
    With e21 = shift1 and e32 = shift2 − shift1, q = e32·e21 / |e21|² is ρ^p on a grid converging
    with order p (``convergence_ratio``): where q > 1, Roache's three-grid index
    1.25 |e21| / (ρ^p − 1), p limited to ``ORDER_RANGE``; else the two-grid one on the larger
    change (docs/grid_term.md). Each key is
    measured in its ``scale`` (the data's standard error or the posterior's sd), lest a key in
    large units decide the order alone. ``what``: the three things compared (grids, or
    posteriors' means)."""
    e21 = np.asarray(shift1, float)
    e32 = np.asarray(shift2, float) - e21
    observed = observed_order(shift1, shift2, ratio, scale)
    if observed is not None:
        order = min(max(observed, ORDER_RANGE[0]), ORDER_RANGE[1])
        return (1.25 * np.abs(e21) / (ratio ** order - 1.0), order,
                f"three {what} converging with observed order {order:.2g}: Roache's GCI, safety factor 1.25")
    oscillate = convergence_ratio(shift1, shift2, scale) <= 0
    kind = "oscillate" if oscillate else "do not yet converge (the finer change is the larger)"
    return (two_grid_index(np.maximum(np.abs(e21), np.abs(e32)), ratio), None,
            f"three {what} {kind}: the larger change with the order assumed 1 and safety factor 3")


def check_grid_options(ratio, draws, levels: int = 1) -> None:
    """Refuse a grid check that cannot be made (before anything runs): ``ratio`` None (no
    check) or a number > 1, ``draws`` an integer >= 1, ``levels`` 1 or 2 coarser grids. The one
    check of these options (``JudgeOptions`` calls it); an ``OptionError`` names the field."""
    if ratio is not None and not (_is_number(ratio) and ratio > 1.0):
        raise OptionError("grid_ratio", "must be off (None; 0 on the command line) or a finite factor > 1 of the "
                                        f"grid spacing, got {ratio!r}")
    if not (_is_int(draws) and draws >= 1):
        raise OptionError("grid_draws", f"must be an integer >= 1, got {draws!r}")
    if isinstance(levels, bool) or levels not in (1, 2):
        raise OptionError("grid_levels", f"must be 1 or 2 (coarser grids), got {levels!r}")


def grid_shift(objective: ObjectiveLike, theta, J, *, ratio: float = GRID_RATIO, draws: int = GRID_DRAWS,
               levels: int = 1, workers=None) -> GridCheck | None:
    """The grid term at the fit's θ (``J`` the objective's weighted Jacobian there): the
    objective rebuilt at ``ratio`` × its dx (``Objective.at_dx``), its residuals at θ averaged over
    ``draws`` particle draws (one, the scene's own, for a sampling with no seed), and the
    Gauss–Newton shift −J⁺ r̄ (docs/grid_term.md). ``levels=2`` adds a second coarser grid,
    ρ² dx, and the index from the three (``three_grid_index``): the order the grids show, or a
    wider index where they oscillate. Raises ``ValueError`` when the objective cannot be rebuilt
    (a scene with no recipe, data outside the coarser grid); returns None when no coarse run ran
    without status bits."""
    check_grid_options(ratio, draws, levels)
    clock = time.perf_counter()
    dx = objective.dx
    coarse, kept = coarse_residuals(objective, theta, ratio, draws, workers)
    if not kept:
        return None
    J = np.asarray(J, float)
    shift = -np.linalg.lstsq(J, np.mean(kept, axis=0), rcond=None)[0]
    if levels == 1:
        return GridCheck(dx, coarse.dx, len(kept), shift, two_grid_index(shift, ratio), time.perf_counter() - clock)
    _, kept2 = coarse_residuals(objective, theta, ratio * ratio, draws, workers)
    if not kept2:
        return None
    shift2 = -np.linalg.lstsq(J, np.mean(kept2, axis=0), rcond=None)[0]
    halfwidth, order, method = three_grid_index(shift, shift2, ratio, scale=np.sqrt(np.diag(_inverse(J.T @ J))))
    return GridCheck(dx, coarse.dx, min(len(kept), len(kept2)), shift, halfwidth, time.perf_counter() - clock,
                     shift2=shift2, order=order, method=method)
