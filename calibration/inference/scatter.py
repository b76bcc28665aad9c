"""The run's own scatter at a point: its round-off (``model_scatter``) and its particle draw
(``sampling_scatter``), and the extra runs both need (``redrawn_residuals``, ``coarse_residuals``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..batch.workers import residuals_at
from ..problem.protocol import ObjectiveLike
from .gauss_newton import _inverse
from .noise import chi2_quantile

__all__ = ["ROUNDOFF_SAMPLES", "roundoff_limit", "ModelScatter", "model_scatter", "sampling_scatter"]


#: Perturbed runs behind ``model_scatter`` by default (each costs one forward run).
ROUNDOFF_SAMPLES = 8


#: Their relative size: far below any interval, far above the rounding of θ itself (float32: 8e-8).
ROUNDOFF_STEP = 1e-6


#: Other draws of the particles behind ``sampling_scatter`` when asked for (one forward run each).
SAMPLING_SEEDS = 4


#: A stopped optimiser's remaining Gauss–Newton step within this quantile (``roundoff_limit``, in
#: the metric of the run's scatter) counts as converged.
ROUNDOFF_P = 0.99


def roundoff_limit(n: int, samples: int, p: float = ROUNDOFF_P) -> float:
    """The largest remaining Gauss–Newton step, in standard deviations of a round-off scatter whose
    covariance was estimated from ``samples`` degrees of freedom, that counts as converged.

    A step δ ~ N(0, Σ) independent of the estimate S has δᵀS⁻¹δ · (ν − n + 1)/(n ν) ~ F(n, ν − n + 1)
    for ν = ``samples`` (Hotelling's T²); χ²_n's quantile would refuse true minima, as a handful of
    runs often understates Σ. Returns the square root of the ``p`` quantile; χ²_n's where ν < n."""
    if samples < n:
        return math.sqrt(chi2_quantile(p, n))
    from scipy.stats import f

    return math.sqrt(n * samples / (samples - n + 1) * float(f.ppf(p, n, samples - n + 1)))


@dataclasses.dataclass(frozen=True)
class ModelScatter:
    """The run's own scatter at a point, its round-off or its particle draw (docs/verdict.md)."""

    samples: int  # perturbed runs used (failed runs left out)
    step: float  # their relative size (0 for the sampling's scatter: same θ, other particles)
    noise: dict[str, float]  # σ_num by block, in the block's relative units
    cov: np.ndarray  # (n, n): the covariance of θ the scatter alone produces
    wall_s: float
    kind: str = "round-off"  # or "sampling" (``sampling_scatter``)

    @property
    def stderr(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def gauss_newton_distance(self, J, r) -> float:
        """The remaining Gauss–Newton step −J⁺r in the metric of ``cov``: sqrt(δᵀ cov⁻¹ δ)."""
        delta = np.linalg.lstsq(np.asarray(J, float), -np.asarray(r, float), rcond=None)[0]
        return float(math.sqrt(max(float(delta @ _inverse(self.cov) @ delta), 0.0)))

    def to_dict(self, keys: Sequence[str]) -> dict[str, Any]:
        out = {"samples": self.samples, "noise": self.noise,
               "stderr": {k: float(v) for k, v in zip(keys, self.stderr)}, "wall_s": round(self.wall_s, 3)}
        if self.kind == "round-off":
            out["relative_step"] = self.step
        return out


def _scatter_of(S, J, blocks, row_scale, kind, step, clock) -> ModelScatter:
    """σ by block and the covariance of θ = J⁺ s from the spread of the residual rows S."""
    dev = S - S.mean(axis=0)
    e = dev / np.asarray(row_scale, float)[None, :]
    noise = {name: float(math.sqrt(np.sum(e[:, sl] ** 2) / ((len(S) - 1) * max(sl.stop - sl.start, 1))))
             for name, sl in blocks.items()}
    P = np.linalg.lstsq(J, S.T, rcond=None)[0].T
    cov = np.atleast_2d(np.cov(P, rowvar=False, ddof=1))
    return ModelScatter(len(S) - 1, float(step), noise, cov, time.perf_counter() - clock, kind)


def _runs(objective: ObjectiveLike, thetas, workers, seeds=None) -> list:
    """[(r, prediction)] at ``thetas`` (particles drawn with ``seeds``, if given): in ``workers``
    when they are parallel and the objective can make tasks, else one after the other here."""
    if workers is not None and workers.parallel:
        return residuals_at(objective, thetas, workers, seeds)
    if seeds is None:
        return [objective.residuals(t) for t in thetas]
    return [objective.residuals_resampled(t, int(sd)) for t, sd in zip(thetas, seeds)]


def _ran_cleanly(r, pred) -> bool:
    """The run set no status bit and its residuals are finite."""
    return int(np.asarray(pred["status"])) == 0 and bool(np.all(np.isfinite(np.asarray(r, float))))


def clean_runs(runs) -> list[np.ndarray]:
    """The residuals of the runs (``_runs``' (r, prediction) pairs) that ran cleanly."""
    return [np.asarray(r, float) for r, pred in runs if _ran_cleanly(r, pred)]


def redrawn_residuals(objective: ObjectiveLike, theta, seeds: int, workers=None) -> list[np.ndarray]:
    """The residuals at θ with the scene's body drawn with ``seeds`` seeds other than its own
    (``Objective.residuals_resampled``), those that ran cleanly (``clean_runs``)."""
    own = objective.sampling_seed
    draws = [s for s in range(seeds + 1) if s != own][:seeds]
    return clean_runs(_runs(objective, [theta] * len(draws), workers, draws))


def coarse_residuals(objective: ObjectiveLike, theta, ratio: float, draws: int,
                     workers=None) -> tuple[Any, list[np.ndarray]]:
    """The objective rebuilt at ``ratio`` × its dx (``Objective.at_dx``) and its residuals at θ
    over ``draws`` particle draws (the scene's own only, for a sampling with no seed), those that
    ran cleanly (``clean_runs``)."""
    coarse = objective.coarsened(ratio)
    seeded = coarse.seeded
    seeds = list(range(draws)) if seeded else None
    return coarse, clean_runs(_runs(coarse, [np.asarray(theta, float)] * (draws if seeded else 1), workers, seeds))


def model_scatter(objective: ObjectiveLike, theta, r, J, *, samples: int = ROUNDOFF_SAMPLES,
                  step: float = ROUNDOFF_STEP, seed: int = 0, workers=None) -> ModelScatter | None:
    """The run's round-off scatter at θ (residuals ``r``, Jacobian ``J`` there, the objective's
    weighted ones): ``samples`` runs at θ + d_k, d_k of relative size ``step`` in random
    directions (reflected to stay inside the bounds), give s_k = r(θ + d_k) − J d_k, which differ
    from r only by the round-off (the curvature term is ~step² smaller). Their sample spread gives
    σ_num by block and, through p_k = J⁺ s_k, the covariance of θ due to the scatter. Returns None
    when fewer than two runs succeeded (then nothing is known about the scatter)."""
    samples = int(samples)
    if samples < 2:
        raise ValueError(f"samples must be >= 2 (a spread needs two runs besides the point), got {samples!r}")
    clock = time.perf_counter()
    theta, r, J = np.asarray(theta, float), np.asarray(r, float), np.asarray(J, float)
    lower, upper = np.asarray(objective.bounds.lower), np.asarray(objective.bounds.upper)
    scale = np.maximum(np.abs(theta), 0.01 * (upper - lower))
    rng = np.random.default_rng(seed)
    steps = []
    for _ in range(samples):
        u = rng.standard_normal(theta.size)
        d = step * scale * u / np.linalg.norm(u)
        steps.append(np.where((theta + d <= lower) | (theta + d >= upper), -d, d))
    runs = _runs(objective, [theta + d for d in steps], workers)
    kept = [r] + [np.asarray(r_k, float) - J @ d for d, (r_k, pred) in zip(steps, runs) if _ran_cleanly(r_k, pred)]
    if len(kept) < 3:
        return None
    return _scatter_of(np.stack(kept), J, objective.blocks, objective.row_scale, "round-off", step, clock)


def sampling_scatter(objective: ObjectiveLike, theta, r, J, *, seeds: int = SAMPLING_SEEDS,
                     workers=None) -> ModelScatter | None:
    """The scatter that the particle sampling puts into the prediction at θ: the residuals with
    the scene's body drawn with ``seeds`` other seeds (``Objective.residuals_resampled``), beside
    its own ``r``. Their spread gives σ by block and, through J⁺, the covariance of θ that the
    choice of one draw of the particles produces. None when the objective cannot redraw its
    particles (a lattice, a composite) or fewer than two redrawn runs succeed."""
    seeds = int(seeds)
    if seeds < 2:
        raise ValueError(f"seeds must be >= 2, got {seeds!r}")
    if objective.sampling_seed is None:
        return None
    clock = time.perf_counter()
    kept = [np.asarray(r, float)] + redrawn_residuals(objective, theta, seeds, workers)
    if len(kept) < 3:
        return None
    return _scatter_of(np.stack(kept), np.asarray(J, float), objective.blocks, objective.row_scale, "sampling", 0.0,
                       clock)
