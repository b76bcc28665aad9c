"""Whether a fit's end point is the lowest loss near it (``probe_loss``).

Every test of the verdict is made at the end point: the optimiser's stop, the bounds, the misfit
against the noise. None of them sees a loss that is rough below the interval's scale, where a
Gauss–Newton step follows the local slope and the stop comes wherever that slope is flat (the
aluminium bars of docs/real_data.md: fits "of the data" from 0.300 and from 0.360 whose intervals
do not overlap). The probe runs the model where the interval says the loss has risen: along each
principal direction u_k of the interval's covariance, at the 95 % edge (s = ±1) and 2, 4 and 8
times as far, 8 runs a key, and compares the fit's own loss there with the end point's, in χ²
units (the rise a restart could descend: the loss weighs the blocks as the optimiser does). (The far
probes find the valley a fit on a ripple of its wall does not see: the bars' fit from 0.300 is a
minimum within ±2 half-widths, and its χ² is 20 units lower 8 half-widths away.)

- A probe whose χ² is below the end point's by more than ``PROBE_DROP`` (and than three times the
  jitter the run's round-off puts into χ²) means the end point is not the lowest loss within its
  interval.
- So does the parabola through a direction's points within two half-widths when its lowest point
  lies beyond the edge (1 < |s*| ≤ 2) and below the end point's χ² by as much.

Either makes the verdict "not a fit of the data" (``judge_point``), and the report's advice names
the lowest point found. The χ² rise at the edges is reported against the quadratic model's
δᵀFδ (F the data's Fisher matrix), a check of the interval's width: where the data's χ² has not
risen by 1.96² at an edge (a loss flatter there than its curvature at the point says), that side
of the interval is widened to where it has, between the probes (``LossProbe.widened``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..problem.protocol import ObjectiveLike, is_valid
from .noise import NOISE_FLOOR, Z95
from .scatter import _ran_cleanly, _runs

__all__ = ["PROBE_DROP", "PROBE_STEPS", "LossProbe", "probe_loss"]

#: Where the probe runs, in units of the 95 % interval's half-width along each direction.
PROBE_STEPS = (-8.0, -4.0, -2.0, -1.0, 1.0, 2.0, 4.0, 8.0)

#: The parabola is fitted to the probes this close (beyond, the quadratic model is not expected to hold).
PARABOLA_REACH = 2.0

#: A side of the interval is stretched only by more than this factor (the probes' interpolation is no finer).
STRETCH_MIN = 1.05

#: ... or this many standard deviations of the jitter the run's round-off puts into χ², where that
#: is more (a noise-free twin, whose residuals are the round-off itself).
JITTER_SIGMAS = 3.0

#: A probe this far below the end point's χ² (one unit: a likelihood e^0.5 times higher) counts.
PROBE_DROP = 1.0


@dataclasses.dataclass(frozen=True)
class LossProbe:
    """The χ² about a fit's end point along the interval's principal directions (``probe_loss``)."""

    directions: np.ndarray  # (d, n): θ moves by s · directions[k] (the 95 % half-width along u_k)
    steps: tuple[float, ...]
    rise: np.ndarray  # (d, len(steps)): χ²(θ + s δ_k) − χ²(θ); NaN: not run (outside the bounds, or a failed run)
    predicted: np.ndarray  # (d,): the quadratic model's rise at s = 1, δ_kᵀ F δ_k
    vertex: np.ndarray  # (d,): the parabola's lowest point s* (NaN: no upward curvature or too few points)
    vertex_rise: np.ndarray  # (d,): the parabola's value there
    threshold: float  # the drop that counts (``PROBE_DROP``, or three times the round-off's jitter)
    lowest: np.ndarray  # (n,): θ with the lowest χ² the probe saw (a probe, or the end point itself)
    lowest_rise: float  # its χ² − the end point's (0 when the end point is the lowest)
    lowest_step: float  # its distance in half-widths (|s|; 0 for the end point)
    wall_s: float = 0.0

    def edge_steps(self) -> np.ndarray:
        """(d, 2): on the − and + side of each direction, the step s ≥ 1 at which the data's χ²
        has risen by 1.96² (a 95 % likelihood-ratio edge with one degree of freedom), linear
        between the probes; the farthest probe run where it never has (a lower bound); 1 where
        that is within ``STRETCH_MIN``."""
        out = np.ones((len(self.directions), 2))
        steps = np.asarray(self.steps)
        for k, row in enumerate(self.rise):
            for side, sign in enumerate((-1.0, 1.0)):
                keep = (np.sign(steps) == sign) & np.isfinite(row)
                s, y = np.abs(steps[keep]), row[keep]
                order = np.argsort(s)
                s, y = np.concatenate([[0.0], s[order]]), np.concatenate([[0.0], y[order]])
                above = np.flatnonzero(y >= Z95**2)
                if above.size == 0:
                    out[k, side] = s[-1] if s[-1] > STRETCH_MIN else 1.0
                    continue
                j = above[0]
                edge = s[j - 1] + (s[j] - s[j - 1]) * (Z95**2 - y[j - 1]) / (y[j] - y[j - 1])
                out[k, side] = edge if edge > STRETCH_MIN else 1.0
        return out

    def widened(self, theta, ci95) -> np.ndarray:
        """The interval ``ci95`` (n, 2) about θ with each side of each direction stretched to
        ``edge_steps``: key i's lower and upper half-widths become sqrt(Σ_k (f_k δ_ki)²), f_k the
        stretch on the side of direction k that lowers (raises) key i. Never narrower than ``ci95``."""
        theta, ci95 = np.asarray(theta, float), np.asarray(ci95, float)
        f = self.edge_steps()
        lower, upper = np.empty_like(theta), np.empty_like(theta)
        for i in range(theta.size):
            d = self.directions[:, i]
            up = np.where(d >= 0, f[:, 1], f[:, 0])  # moving along +δ_k raises key i where δ_ki > 0
            down = np.where(d >= 0, f[:, 0], f[:, 1])
            upper[i] = math.sqrt(float(np.sum((up * d) ** 2)))
            lower[i] = math.sqrt(float(np.sum((down * d) ** 2)))
        return np.stack([np.minimum(ci95[:, 0], theta - lower), np.maximum(ci95[:, 1], theta + upper)], axis=1)

    @property
    def passed(self) -> bool:
        """No probe, and no parabola's lowest point beyond the edge, below the end point's χ² by
        more than ``threshold``."""
        return not (self.lowest_rise < -self.threshold or np.any(self._beyond & (self.vertex_rise < -self.threshold)))

    @property
    def _beyond(self) -> np.ndarray:
        """(d,): the directions whose parabola has its lowest point beyond the edge, within reach."""
        return (np.abs(self.vertex) > 1.0) & (np.abs(self.vertex) <= PARABOLA_REACH)

    def reason(self, keys: Sequence[str]) -> str:
        """Why the end point is not the lowest loss within its interval (empty when it is)."""
        if self.passed:
            return ""
        where = ", ".join(f"{k} = {v:.4g}" for k, v in zip(keys, self.lowest))
        text = "not the lowest loss near the point"
        if self.lowest_rise < -self.threshold:
            text += (f": χ² is {-self.lowest_rise:.3g} lower at {where}, {self.lowest_step:g} times its 95 % "
                     "interval's half-width away")
        beyond = self._beyond
        k = int(np.argmin(np.where(beyond, self.vertex_rise, np.inf)))
        if beyond[k] and self.vertex_rise[k] < -self.threshold:
            text += (f"; along {_direction(self.directions[k], keys)} the parabola through the probes has its "
                     f"lowest point {self.vertex[k]:+.2g} half-widths from the end point")
        return text + " (the loss is rough, or the fit stopped on a slope: the probe of docs/verdict.md)"

    def to_dict(self, keys: Sequence[str]) -> dict[str, Any]:
        rows = []
        finite = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        for k, delta in enumerate(self.directions):
            rows.append({"direction": {key: float(v) for key, v in zip(keys, delta)},
                         "rise": {f"{s:+g}": finite(v) for s, v in zip(self.steps, self.rise[k])},
                         "predicted_at_edge": float(self.predicted[k]), "parabola_lowest": finite(self.vertex[k]),
                         "parabola_lowest_rise": finite(self.vertex_rise[k])})
        return {"passed": self.passed, "threshold": self.threshold, "directions": rows,
                "lowest": {key: float(v) for key, v in zip(keys, self.lowest)}, "lowest_rise": self.lowest_rise,
                "lowest_step": self.lowest_step,
                "wall_s": round(self.wall_s, 3)}


def _direction(delta, keys) -> str:
    big = np.max(np.abs(delta))
    return " ".join(f"{'+' if v >= 0 else '−'}{abs(v):.3g}·{k}" for k, v in zip(keys, delta) if abs(v) >= 0.1 * big)


def _parabola(steps, rise):
    """The lowest point s* of the least-squares parabola through (0, 0) and the finite (s, rise)
    with |s| ≤ ``PARABOLA_REACH``, and its value; NaN where it curves down or fewer than two
    probes ran."""
    keep = np.isfinite(rise) & (np.abs(np.asarray(steps)) <= PARABOLA_REACH)
    s = np.concatenate([[0.0], np.asarray(steps)[keep]])
    y = np.concatenate([[0.0], rise[keep]])
    if keep.sum() < 2 or np.unique(s).size < 3:
        return math.nan, math.nan
    a, b, c = np.linalg.lstsq(np.stack([np.ones_like(s), s, s * s], axis=1), y, rcond=None)[0]
    if c <= 0:
        return math.nan, math.nan
    return float(-b / (2 * c)), float(a - b * b / (4 * c))


def _jitter(objective: ObjectiveLike, r, sigma, scatter) -> float:
    """The standard deviation the run's round-off (``scatter``'s σ_num by block) puts into χ²:
    sqrt(Σ_b 4 χ²_b σ_num,b² / σ_b²), to first order in the perturbation."""
    if scatter is None:
        return 0.0
    e = np.asarray(r, float) / np.asarray(objective.row_scale, float)
    var = 0.0
    for name, sl in objective.blocks.items():
        if sigma.get(name) is None:
            continue
        s2 = max(sigma[name], NOISE_FLOOR) ** 2
        var += 4.0 * float(np.sum(e[sl] ** 2)) / s2 * scatter.noise.get(name, 0.0) ** 2 / s2
    return math.sqrt(var)


def probe_loss(objective: ObjectiveLike, theta, r, J, cov, sigma, *, scatter=None, steps=PROBE_STEPS,
               workers=None) -> LossProbe:
    """Run the model about the end point θ (residuals ``r`` and Jacobian ``J`` there, the
    objective's weighted ones) at ``steps`` × the 95 % half-width of the interval's covariance
    ``cov`` along each of its principal directions, and compare χ² (with the verdict's noise
    ``sigma`` by block) with θ's. Probes outside the bounds, or outside the model's rules, are
    not run. ``scatter``: the run's round-off (``model_scatter``), which sets the drop that counts."""
    clock = time.perf_counter()
    theta, r, J = np.asarray(theta, float), np.asarray(r, float), np.asarray(J, float)
    evals, evecs = np.linalg.eigh(0.5 * (np.asarray(cov, float) + np.asarray(cov, float).T))
    directions = (Z95 * np.sqrt(np.maximum(evals, 0.0)) * evecs).T  # (d, n), rows δ_k
    lower, upper = np.asarray(objective.bounds.lower), np.asarray(objective.bounds.upper)
    points = [(k, j, theta + s * delta) for k, delta in enumerate(directions) for j, s in enumerate(steps)]
    points = [(k, j, t) for k, j, t in points if np.all((t > lower) & (t < upper)) and is_valid(objective, t)]
    runs = _runs(objective, [t for _, _, t in points], workers) if points else []
    Je = J / np.asarray(objective.row_scale, float)[:, None]
    fisher = sum(Je[sl].T @ Je[sl] / max(sigma[name], NOISE_FLOOR) ** 2
                 for name, sl in objective.blocks.items() if sigma.get(name) is not None)
    predicted = np.array([float(d @ fisher @ d) for d in directions]) if np.ndim(fisher) else np.zeros(len(directions))
    # The rise is the fit's own loss Σ r² (its blocks weighted as the optimiser weighs them, so that
    # a lower probe is one a restart descends to), in χ² units along each direction: scaled by the
    # quadratic models' ratio δᵀFδ / δᵀJᵀJδ (1/σ² for one block of equal weights).
    loss_0 = float(np.sum(r * r))
    curvature = np.array([float(np.sum((J @ d) ** 2)) for d in directions])
    scale = np.where(curvature > 0, predicted / np.where(curvature > 0, curvature, 1.0), 0.0)
    rise = np.full((len(directions), len(steps)), np.nan)
    lowest, lowest_rise, lowest_step = theta, 0.0, 0.0
    for (k, j, t), (r_p, pred) in zip(points, runs):
        if _ran_cleanly(r_p, pred):
            rise[k, j] = scale[k] * (float(np.sum(np.asarray(r_p, float) ** 2)) - loss_0)
            if rise[k, j] < lowest_rise:
                lowest, lowest_rise, lowest_step = t, float(rise[k, j]), abs(steps[j])
    vertex, vertex_rise = np.array([_parabola(steps, row) for row in rise]).reshape(-1, 2).T
    threshold = max(PROBE_DROP, JITTER_SIGMAS * _jitter(objective, r, sigma, scatter))
    return LossProbe(directions, tuple(steps), rise, predicted, vertex, vertex_rise, threshold, np.asarray(lowest),
                     lowest_rise, lowest_step, time.perf_counter() - clock)
