"""Do the intervals contain the truth as often as they claim? Twins over many noise seeds.

``coverage(seeds, noise, keys)`` runs the twin experiment (``calibration.studies.twin``) once per
noise seed and counts how often each 95 % interval holds the true value, under the noise the fit
estimates (what a user gets) and under the true noise given. A seed whose verdict is "not a fit of
the data" gives no interval and is counted apart, never as a hit. The rates carry Clopper–Pearson
95 % intervals (docs/twin.md, "Coverage, measured").
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..inference.gauss_newton import gauss_newton_uncertainty
from .twin import TwinResult, twin

__all__ = ["clopper_pearson", "CoverageRow", "CoverageResult", "coverage"]


def clopper_pearson(hits: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper–Pearson) ``level`` interval of a binomial rate from ``hits`` of ``n``."""
    from scipy.stats import beta

    if n == 0:
        return (0.0, 1.0)
    a = 1.0 - level
    lo = 0.0 if hits == 0 else float(beta.ppf(a / 2, hits, n - hits + 1))
    hi = 1.0 if hits == n else float(beta.ppf(1 - a / 2, hits + 1, n - hits))
    return lo, hi


def _rate(hits: int, n: int) -> dict[str, Any]:
    lo, hi = clopper_pearson(hits, n)
    return {"hits": hits, "of": n, "rate": hits / n if n else None, "rate_ci95": [lo, hi]}


@dataclasses.dataclass(frozen=True)
class CoverageRow:
    """One noise seed's fit."""

    seed: int
    theta: dict[str, float]
    is_fit: bool
    in_ci95: dict[str, bool] | None  # intervals with the estimated noise (None: withheld)
    in_ci95_given: dict[str, bool] | None  # with the true noise given
    ci95: dict[str, list[float]] | None
    ci95_given: dict[str, list[float]] | None
    delta_chi2_truth: float
    truth_in_joint_95: bool
    noise_estimated: dict[str, float]
    iterations: int
    wall_s: float


@dataclasses.dataclass(frozen=True)
class CoverageResult:
    keys: tuple[str, ...]
    truth: dict[str, float]
    noise: float
    quick: bool
    rows: tuple[CoverageRow, ...]
    wall_s: float

    @classmethod
    def from_json(cls, out: dict[str, Any]) -> CoverageResult:
        """The result again from ``to_json``'s dict (to redraw a saved study)."""
        rows = tuple(CoverageRow(**row) for row in out["rows"])
        return cls(tuple(out["keys"]), dict(out["truth"]), float(out["noise"]), bool(out["quick"]), rows,
                   float(out["wall_s"]))

    def rate(self, key: str, given: bool = False) -> dict[str, Any]:
        """Hits of ``key``'s 95 % interval over the seeds that gave one, with its 95 % interval."""
        field = "in_ci95_given" if given else "in_ci95"
        judged = [getattr(r, field)[key] for r in self.rows if getattr(r, field) is not None]
        return _rate(int(sum(judged)), len(judged))

    def joint_rate(self) -> dict[str, Any]:
        return _rate(int(sum(r.truth_in_joint_95 for r in self.rows)), len(self.rows))

    def to_json(self) -> dict[str, Any]:
        withheld = [r.seed for r in self.rows if r.in_ci95 is None]
        return {
            "keys": list(self.keys), "truth": self.truth, "noise": self.noise, "quick": self.quick,
            "seeds": len(self.rows), "not_a_fit": withheld, "wall_s": round(self.wall_s, 1),
            "coverage_estimated_noise": {k: self.rate(k) for k in self.keys},
            "coverage_given_noise": {k: self.rate(k, given=True) for k in self.keys},
            "joint_95_likelihood_ratio": self.joint_rate(),
            "rows": [dataclasses.asdict(r) for r in self.rows],
        }


def coverage(seeds: int | Sequence[int] = 20, *, noise: float = 0.02, keys: Sequence[str] = ("beta", "mu1"),
             quick: bool = True, progress: bool = False, run: Callable[..., TwinResult] = twin, **twin_options
             ) -> CoverageResult:
    """The twin at ``noise`` for each seed (an int k: seeds 0..k−1); ``twin_options`` go to
    ``calibration.studies.twin`` (dx, values, steps, ...); ``run`` replaces it (for tests: it must return
    a ``TwinResult``)."""
    if not (np.isfinite(noise) and 0 < noise < 1):
        raise ValueError(f"noise must be in (0, 1): coverage needs noisy data, got {noise!r}")
    seed_list = list(range(seeds)) if isinstance(seeds, (int, np.integer)) else [int(s) for s in seeds]
    if len(seed_list) < 2 or len(set(seed_list)) != len(seed_list):
        raise ValueError(f"seeds must be at least two distinct noise seeds, got {seeds!r}")
    keys = tuple(keys)
    clock = time.perf_counter()
    rows, truth = [], None
    for i, seed in enumerate(seed_list):
        tw = run(quick=quick, noise=noise, keys=keys, seed=seed, **twin_options)
        result, objective, truth = tw.fit, tw.objective, tw.truth
        given = ci_given = None
        if result.verdict is None or result.verdict.is_fit:
            unc = gauss_newton_uncertainty(result.jacobian, result.residuals, keys, [result.theta[k] for k in keys],
                                           objective.blocks, objective.row_scale, noise=noise,
                                           bounds=objective.bounds, verdict=result.verdict)
            given = {k: bool(lo <= truth[k] <= hi) for k, (lo, hi) in zip(keys, unc.ci95)}
            ci_given = {k: [float(lo), float(hi)] for k, (lo, hi) in zip(keys, unc.ci95)}
        rows.append(CoverageRow(seed=seed, theta=dict(result.theta), is_fit=bool(result.verdict.is_fit),
                                in_ci95=tw.in_ci95, in_ci95_given=given, ci95=tw.ci95, ci95_given=ci_given,
                                delta_chi2_truth=float(tw.delta_chi2_truth),
                                truth_in_joint_95=bool(tw.truth_in_joint_95),
                                noise_estimated=dict(result.uncertainty.noise_estimated),
                                iterations=int(result.iterations), wall_s=round(float(tw.wall_s), 3)))
        if progress:
            print(f"coverage: seed {seed} ({i + 1}/{len(seed_list)}): in 95 % {tw.in_ci95}, "
                  f"Δχ² of truth {tw.delta_chi2_truth:.2f}, {tw.wall_s:.0f} s", flush=True)
    return CoverageResult(keys, truth, float(noise), bool(quick), tuple(rows), time.perf_counter() - clock)
