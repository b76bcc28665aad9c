"""Uncertainty and identifiability from the residual Jacobian at the optimum (Gauss–Newton).

For residual blocks e_b (relative misfits of the profile, of the front, ...) with independent
noise of standard deviation σ_b, fitted by minimising Σ_b w_b Σ_i e_bi² (each block's weight
w_b shared by its m_b rows: w_b = weight / m_b), the linearised covariance of the fitted
parameters is the sandwich

    Cov = A⁻¹ B A⁻¹,  A = Σ_b w_b J_bᵀ J_b,  B = Σ_b w_b² σ_b² J_bᵀ J_b,

with J_b = de_b/dθ. When w_b ∝ 1/σ_b² (one block; or blocks of equal length and noise) it is the
familiar (Σ_b J_bᵀ J_b / σ_b²)⁻¹; otherwise it is wider, and the fit is not the most efficient
use of the data (a block of few rows weighs as much as a long one: design.py's validation).
σ_b is either given (a known measurement precision) or estimated from the
residuals at the optimum, s_b² = Σ e_b² / (m_b − n m_b / m) (each block takes its share of the
n degrees of freedom). Standard errors are sqrt(diag Cov), 95 % intervals θ ± 1.96 se (a normal
quantile: the data have many more points than parameters), and correlations Cov_ij / (se_i se_j).

**Identifiability** must not depend on how small the residual happens to be (a noise-free
twin has s_b ≈ 0 and would call everything constrained). So a parameter is called
*constrained* when, at a reference noise of ``reference_noise`` (1 % of the block's scale, or
the estimated noise if larger), its 95 % half-width is at most ``threshold`` (10 %) of its
scale (|θ|, or 1 % of its bound range when θ ≈ 0). The eigenvectors of the Fisher matrix in
these relative units name the combinations the data fix well and the one they fix worst.

**Not every minimum is a fit of the data** (``assess_fit``). A Gauss–Newton interval describes
the curvature at a minimum of the data's misfit; it is withheld (``stderr``, ``ci95`` and ``cov``
are None, the statement says why) when the point

- is not a verified minimum: the optimiser stopped on its rejection or step budget without
  meeting one of its convergence tests (``calibration.lm``);
- sits at a bound (``Bounds.near_bound``): the minimum lies outside the physical range, or the
  reparametrisation's flat tail stopped the optimiser;
- leaves a misfit well above the noise: in some block, χ² = Σ e²/σ² exceeds the 99.9 % quantile
  of χ² with that block's degrees of freedom. σ is the given noise, or is estimated from the
  residuals' *structure*, not from their size: ``structural_noise`` takes the robust spread of
  second differences of neighbouring residuals (the high-frequency part; a smooth misfit has
  almost none). An estimated σ is itself uncertain, so the limit is then raised by three of the
  estimate's standard deviations (``~4/sqrt(c)`` relative in σ², c second differences).

**The run's own scatter** (``model_scatter``). A float32 rollout of thousands of steps is not a
smooth function of θ below some level: a change of θ by a few ulps changes the rounding of every
step, and the deposit moves by what that rounding adds up to (coherently, not as white noise).
``model_scatter`` measures it where a fit ends: the residuals at ``samples`` points θ + d_k with
|d_k| ≈ 1e-6 of θ (far below any interval, far above θ's own rounding), with the exact linear
change J d_k taken off, scatter only by the run's round-off; their spread gives the noise σ_num of
each block and, mapped through the least-squares solution, the covariance of θ that the round-off
alone produces. It enters twice: a stopped optimiser whose remaining Gauss–Newton step is within
that scatter (Mahalanobis distance below the 99 % quantile of Hotelling's T² for a covariance
estimated from that many runs, ``roundoff_limit``; χ²_n as the runs grow) has converged as far as the
run can tell, and is a verified minimum; and the reported covariance is the statistical one plus
the numerical one (``stderr`` the total; ``stderr_statistical`` and ``stderr_numerical`` apart).
For noise-free twins made by the same program that numerical part is what is left, and it is
what keeps their interval from claiming a precision the run does not have.

**The grid** (``grid_shift``). A fitted value is a property of the material only if it does not
move with the grid. ``grid_shift`` rebuilds the objective at a coarser spacing ρ·dx
(``Objective.at_dx``; ρ = 1.5 by default), averages its residuals at the fitted θ over a few
particle draws, and takes one Gauss–Newton step with the fit's Jacobian: the shift
δ = −J⁺ r̄_coarse is, to first order, where a fit at ρ·dx would land (at the fit's minimum J⁺r = 0,
so the fine run's own draw does not enter; that is the sampling term). The grid term is Roache's
grid convergence index for two grids, a 95 % half-width of 3 |δ| / (ρ^p − 1) with the order p = 1
that the S4 deposit shows (docs/grid_convergence.md); its covariance, rank one along δ, is added to the
interval. Two grids cannot show the order, and the S4 study shows fits at two neighbouring grids
that agree while both are off: the term is a floor on the grid's share, not a bound. Where it
exceeds the data's interval for some key, the statement says the fit is not converged in the grid.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .objective import residuals_at
from .protocol import ObjectiveLike

__all__ = [
    "GRID_RATIO", "GridCheck", "GRID_DRAWS", "NOISE_FLOOR", "ROUNDOFF_SAMPLES", "ModelScatter", "Uncertainty",
    "Verdict", "assess_fit", "block_noise", "check_grid_options", "chi2_of", "chi2_quantile", "roundoff_limit",
    "gauss_newton_uncertainty", "grid_shift", "judge_point", "model_scatter", "sampling_scatter",
    "structural_noise",
]

Z95 = 1.959963984540054
#: Noise (relative units) below which no misfit is told apart from the run's own round-off.
NOISE_FLOOR = 1e-6
#: A block's misfit is "well above the noise" beyond this quantile of χ².
ABOVE_NOISE_P = 0.999
#: Blocks with fewer residuals than this get no structural noise estimate.
MIN_NOISE_POINTS = 5
#: Perturbed runs behind ``model_scatter`` by default (each costs one forward run).
ROUNDOFF_SAMPLES = 8
#: Their relative size: far below any interval, far above the rounding of θ itself (float32: 8e-8).
ROUNDOFF_STEP = 1e-6
#: Other draws of the particles behind ``sampling_scatter`` when asked for (one forward run each).
SAMPLING_SEEDS = 4
#: The grid check's coarser spacing, as a multiple of the fit's dx.
GRID_RATIO = 1.5
#: Particle draws averaged at the coarser spacing (one forward run each, cheaper than the fit's).
GRID_DRAWS = 2
#: Roache's safety factor for a two-grid study, and the order of convergence assumed.
GCI_SAFETY, GRID_ORDER = 3.0, 1.0
#: A stopped optimiser's remaining Gauss–Newton step within this quantile (``roundoff_limit``, in
#: the metric of the run's scatter) counts as converged.
ROUNDOFF_P = 0.99


def roundoff_limit(n: int, samples: int, p: float = ROUNDOFF_P) -> float:
    """The largest remaining Gauss–Newton step, in standard deviations of a round-off scatter whose
    covariance was estimated from ``samples`` degrees of freedom, that counts as converged.

    A step δ independent of the estimate S, with δ ~ N(0, Σ) in n dimensions, has
    δᵀS⁻¹δ · (ν − n + 1)/(n ν) ~ F(n, ν − n + 1) for ν = ``samples`` (Hotelling's T²): a handful of
    runs understates Σ often enough that χ²_n's quantile would refuse true minima (with six runs,
    five of eight points one standard deviation from a float32 twin's truth). Returns the square
    root of the ``p`` quantile; χ²_n's where ν < n (S singular: nothing better is known)."""
    if samples < n:
        return math.sqrt(chi2_quantile(p, n))
    from scipy.stats import f

    return math.sqrt(n * samples / (samples - n + 1) * float(f.ppf(p, n, samples - n + 1)))


def chi2_quantile(p: float, dof: float) -> float:
    """The ``p`` quantile of χ² with ``dof`` degrees of freedom (scipy ships with jax)."""
    try:
        from scipy.stats import chi2
    except ImportError as err:  # pragma: no cover (jax depends on scipy)
        raise ImportError("the χ² quantiles need scipy: pip install 'jaxmpm[sampling]'") from err
    return float(chi2.ppf(p, dof))


def structural_noise(e) -> tuple[float | None, int]:
    """The noise σ of residuals ``e`` (in data order, e.g. along x) from their high-frequency
    part: 1.4826 · median |e[i−1] − 2 e[i] + e[i+1]| / sqrt(6), a robust spread of second
    differences (which remove any linear trend and nearly all of a smooth misfit). Triples that
    are exactly zero (no material in model and data, beyond the front) carry no information and
    are left out. Returns ``(σ, c)`` with c the number of second differences used; σ is None
    when fewer than ``MIN_NOISE_POINTS`` remain."""
    e = np.asarray(e, float)
    if e.size < 3:
        return None, 0
    d2 = e[:-2] - 2.0 * e[1:-1] + e[2:]
    informative = (e[:-2] != 0) | (e[1:-1] != 0) | (e[2:] != 0)
    d2 = d2[informative]
    if d2.size < MIN_NOISE_POINTS:
        return None, int(d2.size)
    return float(1.482602218505602 * np.median(np.abs(d2)) / math.sqrt(6.0)), int(d2.size)


def front_correlation(t, e) -> dict[str, float | None]:
    """The serial correlation of front residuals ``e`` (m, model − data, at times ``t``): the
    lag-1 autocorrelation ρ = Σ e_i e_{i−1} / Σ e_i² (about zero, not the mean: an offset that
    persists over frames is correlated error too), the correlation time τ = −mean(Δt) / ln ρ of
    the exponential model ``FrontTarget.correlation_time`` assumes (None where ρ ≤ 0.05: no
    measurable correlation), and the effective number of independent points
    n (1 − ρ) / (1 + ρ) (AR(1)). Feed τ back as the target's ``correlation_time`` and refit."""
    t, e = np.asarray(t, float), np.asarray(e, float)
    if t.shape != e.shape or e.ndim != 1 or e.size < 3:
        raise ValueError(f"t and e must be 1-D of one length >= 3, got {t.shape} and {e.shape}")
    denom = float(np.sum(e * e))
    rho = float(np.sum(e[1:] * e[:-1]) / denom) if denom > 0 else 0.0
    rho = min(rho, 0.999)
    tau = float(-np.mean(np.diff(t)) / math.log(rho)) if rho > 0.05 else None
    return {"lag1": rho, "correlation_time_s": tau, "n": int(e.size),
            "n_effective": float(e.size * (1 - max(rho, 0.0)) / (1 + max(rho, 0.0)))}


def block_noise(r, row_scale, blocks: Mapping[str, slice], noise: Mapping[str, float] | float | None = None
                ) -> tuple[dict[str, float | None], dict[str, int], str]:
    """σ of each block (relative units): the given ``noise`` (a float applies to every block),
    or ``structural_noise`` of the block's residuals. Returns ``(sigma, counts, source)``, counts
    the number of second differences behind each estimate (0 for given noise)."""
    e = np.asarray(r, float) / np.asarray(row_scale, float)
    if noise is not None:
        if not isinstance(noise, Mapping):
            noise = {name: float(noise) for name in blocks}
        return {name: float(noise[name]) for name in blocks}, {name: 0 for name in blocks}, "given"
    sigma, counts = {}, {}
    for name, sl in blocks.items():
        sigma[name], counts[name] = structural_noise(e[sl])
    return sigma, counts, "estimated from the residuals' second differences"


def chi2_of(r, row_scale, blocks: Mapping[str, slice], sigma: Mapping[str, float | None]) -> float:
    """Σ_b Σ e_b² / σ_b² over the blocks with a noise level (σ floored at ``NOISE_FLOOR``)."""
    e = np.asarray(r, float) / np.asarray(row_scale, float)
    return sum(float(np.sum(e[sl] ** 2)) / max(sigma[name], NOISE_FLOOR) ** 2
               for name, sl in blocks.items() if sigma.get(name) is not None)


@dataclasses.dataclass(frozen=True)
class ModelScatter:
    """The run's own (round-off) scatter at a point; see the module docstring."""

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


def clean_runs(runs) -> list[np.ndarray]:
    """The residuals of the runs (``_runs``' (r, prediction) pairs) that ran without status bits
    and are finite."""
    kept = []
    for r, pred in runs:
        r = np.asarray(r, float)
        if int(np.asarray(pred["status"])) == 0 and np.all(np.isfinite(r)):
            kept.append(r)
    return kept


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
    kept = [r]
    steps = []
    for _ in range(samples):
        u = rng.standard_normal(theta.size)
        d = step * scale * u / np.linalg.norm(u)
        steps.append(np.where((theta + d <= lower) | (theta + d >= upper), -d, d))
    for d, (r_k, pred) in zip(steps, _runs(objective, [theta + d for d in steps], workers)):
        r_k = np.asarray(r_k, float)
        if int(np.asarray(pred["status"])) != 0 or not np.all(np.isfinite(r_k)):
            continue
        kept.append(r_k - J @ d)
    if len(kept) < 3:
        return None
    return _scatter_of(np.stack(kept), J, objective.blocks, objective.row_scale, "round-off", step, clock)


def sampling_scatter(objective: ObjectiveLike, theta, r, J, *, seeds: int = SAMPLING_SEEDS,
                     workers=None) -> ModelScatter | None:
    """The scatter that the particle sampling puts into the prediction at θ: the residuals with
    the scene's body drawn with ``seeds`` other seeds (``Objective.residuals_resampled``), beside
    its own ``r``. Their spread gives σ by block and, through J⁺, the covariance of θ that the
    choice of one draw of the particles produces: a fitted value that moves by more than its
    statistical interval from one draw to the next is a property of the discretisation, not of
    the material. None when the objective cannot redraw its particles (a lattice, a composite)
    or fewer than two redrawn runs succeed."""

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


@dataclasses.dataclass(frozen=True)
class GridCheck:
    """The grid's share of a fit's uncertainty (``grid_shift``; the module docstring)."""

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


def three_grid_index(shift1, shift2, ratio: float, scale=None,
                     what: str = "grids") -> tuple[np.ndarray, float | None, str]:
    """The grid convergence index from three grids (dx, ρ dx, ρ² dx) by the shifts of θ to the
    two coarser ones: (95 % half-width per key, the observed order or None, how it was made).

    With e21 = shift1 and e32 = shift2 − shift1, each key divided by its ``scale`` (the data's
    standard error or the posterior's sd: without it a key in large units, ξ ~ 50 beside μ ~ 0.4,
    decides the order alone), their ratio along e21, q = e32·e21 / |e21|², is ρ^p on a grid
    converging with order p. When q > 1 (the changes shrink as the grid is
    refined) p = ln q / ln ρ, limited to [0.5, 2], and the index is Roache's three-grid one,
    1.25 |e21| / (ρ^p − 1). Otherwise the grids oscillate or are not yet in the range where the
    error shrinks (what the S4 study shows, docs/grid_convergence.md): the index is 3 max(|e21|,
    |e32|) / (ρ − 1), the two-grid one on the larger change. ``what``: the three things compared,
    in the method's words (grids, or posteriors' means)."""
    e21 = np.asarray(shift1, float)
    e32 = np.asarray(shift2, float) - e21
    scale = np.ones_like(e21) if scale is None else np.asarray(scale, float)
    if not np.all(np.isfinite(scale) & (scale > 0)):
        raise ValueError(f"scale must be positive and finite for every key, got {scale!r}")
    w = 1.0 / scale**2
    norm2 = float(e21 @ (w * e21))
    q = float(e32 @ (w * e21)) / norm2 if norm2 > 0 else math.inf
    if norm2 > 0 and q > 1.0:
        order = min(max(math.log(q) / math.log(ratio), 0.5), 2.0)
        return (1.25 * np.abs(e21) / (ratio ** order - 1.0), order,
                f"three {what} converging with observed order {order:.2g}: Roache's GCI, safety factor 1.25")
    kind = "oscillate" if q <= 0 else "do not yet converge (the finer change is the larger)"
    return (two_grid_index(np.maximum(np.abs(e21), np.abs(e32)), ratio), None,
            f"three {what} {kind}: the larger change with the order assumed 1 and safety factor 3")


def check_grid_options(ratio, draws, levels: int = 1) -> None:
    """Refuse a grid check that cannot be made (before anything runs): ``ratio`` None (no
    check) or a number > 1, ``draws`` an integer >= 1, ``levels`` 1 or 2 coarser grids. The one
    check of these options (``JudgeOptions`` calls it); an ``OptionError`` names the field."""
    from .options import OptionError  # options imports this module's constants

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if ratio is not None and not (number(ratio) and ratio > 1.0):
        raise OptionError("grid_ratio", "must be off (None; 0 on the command line) or a finite factor > 1 of the "
                                        f"grid spacing, got {ratio!r}")
    if not (isinstance(draws, int) and not isinstance(draws, bool) and draws >= 1):
        raise OptionError("grid_draws", f"must be an integer >= 1, got {draws!r}")
    if isinstance(levels, bool) or levels not in (1, 2):
        raise OptionError("grid_levels", f"must be 1 or 2 (coarser grids), got {levels!r}")


def grid_shift(objective: ObjectiveLike, theta, J, *, ratio: float = GRID_RATIO, draws: int = GRID_DRAWS,
               levels: int = 1, workers=None) -> GridCheck | None:
    """The grid term at the fit's θ (``J`` the objective's weighted Jacobian there): the
    objective rebuilt at ``ratio`` × its dx (``Objective.at_dx``), its residuals at θ averaged over
    ``draws`` particle draws (one, the scene's own, for a sampling with no seed), and the
    Gauss–Newton shift −J⁺ r̄ (see the module docstring). ``levels=2`` adds a second coarser grid,
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


@dataclasses.dataclass(frozen=True)
class Verdict:
    """Whether a point is a fit of the data, and if not, why (see the module docstring)."""

    is_fit: bool
    reasons: tuple[str, ...]
    verified: bool  # the optimiser met one of its convergence tests
    at_bound: tuple[str, ...]
    noise: dict[str, float | None]  # σ by block (None: not estimable)
    noise_source: str
    chi2: dict[str, float]  # by block with a noise level
    chi2_limit: dict[str, float]
    statement: str
    convergence: str = ""  # how the minimum was verified (the optimiser's test, or the run's round-off)
    scatter: ModelScatter | None = None

    def to_dict(self) -> dict[str, Any]:
        out = {"is_fit": self.is_fit, "verdict": "a fit of the data" if self.is_fit else "not a fit of the data",
               "reasons": list(self.reasons), "verified_minimum": self.verified, "at_bound": list(self.at_bound),
               "noise": self.noise, "noise_source": self.noise_source, "chi2": self.chi2,
               "chi2_limit": self.chi2_limit, "statement": self.statement}
        if self.convergence:
            out["convergence"] = self.convergence
        return out


def assess_fit(r, row_scale, blocks: Mapping[str, slice], theta, *, converged: bool, message: str = "",
               bounds=None, noise: Mapping[str, float] | float | None = None, J=None,
               scatter: ModelScatter | None = None) -> Verdict:
    """Judge the point θ with residuals ``r`` (the objective's weighted ones): a verified
    minimum (``converged``, ``message`` the optimiser's), off the bounds, with a misfit within
    the noise in every block (the given ``noise``, or the residuals' structural noise).

    With the run's ``scatter`` (``model_scatter``) and the Jacobian ``J``: a point where the
    optimiser stopped without converging still counts as a verified minimum when its remaining
    Gauss–Newton step lies within the scatter (the run cannot resolve a better point), and each
    block's noise for the χ² test is sqrt(σ² + σ_num²)."""
    theta = np.asarray(theta, float)
    e = np.asarray(r, float) / np.asarray(row_scale, float)
    m, n = e.size, theta.size
    reasons = []
    convergence = message if converged else ""
    if not converged and scatter is not None and J is not None:
        distance = scatter.gauss_newton_distance(J, r)
        limit_d = roundoff_limit(n, scatter.samples)
        if distance <= limit_d:
            converged = True
            convergence = (f"converged within the run's round-off: the remaining Gauss–Newton step is {distance:.2g} "
                           f"standard deviations of the scatter {scatter.samples} perturbed runs show (limit "
                           f"{limit_d:.2g}); the optimiser had {message or 'stopped'}")
        else:
            message = (f"{message or 'the optimiser did not converge'}; the remaining Gauss–Newton step is "
                       f"{distance:.2g} standard deviations of the run's round-off scatter, beyond {limit_d:.2g}")
    if not converged:
        reasons.append(f"not a verified minimum ({message or 'the optimiser did not converge'})")
    at_bound = tuple(bounds.near_bound(theta)) if bounds is not None else ()
    if at_bound:
        reasons.append(f"{', '.join(at_bound)} at a bound (the misfit falls towards or beyond the physical range)")
    sigma, counts, source = block_noise(r, row_scale, blocks, noise)
    if scatter is not None:
        sigma = {name: None if v is None else math.hypot(v, scatter.noise.get(name, 0.0)) for name, v in sigma.items()}
        source += ", with the run's round-off scatter added in quadrature"
    chi2, limit, unknown = {}, {}, []
    for name, sl in blocks.items():
        if sigma[name] is None:
            unknown.append(f"{name} ({sl.stop - sl.start} residuals: too few to estimate its noise)")
            continue
        mb = sl.stop - sl.start
        chi2[name] = float(np.sum(e[sl] ** 2)) / max(sigma[name], NOISE_FLOOR) ** 2
        inflate = 1.0 if counts[name] == 0 else 1.0 + 3.0 * 4.0 / math.sqrt(counts[name])
        limit[name] = chi2_quantile(ABOVE_NOISE_P, max(mb - n * mb / m, 1.0)) * inflate
        if chi2[name] > limit[name]:
            rms = math.sqrt(float(np.mean(e[sl] ** 2)))
            reasons.append(f"{name} misfit well above the noise (rms {rms:.3g} against σ {sigma[name]:.3g} "
                           f"{'given' if source == 'given' else 'estimated'}; χ² {chi2[name]:.3g} > {limit[name]:.3g})")
    is_fit = not reasons
    if is_fit:
        statement = "A fit of the data: a verified minimum, off the bounds, with a misfit within the noise."
    else:
        statement = ("Not a fit of the data: " + "; ".join(reasons) + ". No Gauss–Newton interval is given: it "
                     "describes the curvature at a minimum of the data's misfit, which this point is not.")
    if unknown:
        statement += " The noise test left out " + ", ".join(unknown) + "."
    return Verdict(is_fit, tuple(reasons), bool(converged), at_bound, sigma, source, chi2, limit, statement,
                   convergence, scatter)


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    keys: tuple[str, ...]
    theta: np.ndarray
    stderr: np.ndarray | None  # None (with cov, ci95, ...): withheld, the point is not a fit of the data
    cov: np.ndarray | None
    corr: np.ndarray
    ci95: np.ndarray | None  # (n, 2)
    noise: dict[str, float]  # the σ_b used, by block
    noise_estimated: dict[str, float]
    reference_stderr: np.ndarray | None  # se at the reference noise (for identifiability)
    relative_halfwidth: np.ndarray | None  # 1.96 se_ref / scale
    constrained: tuple[str, ...]
    eigenvalues: np.ndarray  # of the relative Fisher matrix, descending
    eigenvectors: np.ndarray  # columns
    statement: str
    verdict: Verdict | None = None
    stderr_statistical: np.ndarray | None = None  # from the data's noise alone
    stderr_numerical: np.ndarray | None = None  # from the run's round-off scatter alone (None: not measured)
    sampling: ModelScatter | None = None  # the particle sampling's scatter (None: not measured)
    grid: GridCheck | None = None  # the grid's share (None: not measured)
    grid_note: str = ""  # why the grid term is missing, when it was asked for

    @property
    def grid_converged(self) -> bool | None:
        """Whether the grid term stays within the data's interval for every key (None: not
        measured, or no interval)."""
        if self.grid is None or self.stderr_statistical is None:
            return None
        return bool(np.all(self.grid.stderr <= self.stderr_statistical))

    @property
    def withheld(self) -> bool:
        """True when no interval is given (the verdict: not a fit of the data)."""
        return self.stderr is None

    def to_dict(self) -> dict[str, Any]:
        by_key = lambda a: {k: float(v) for k, v in zip(self.keys, a)}  # noqa: E731
        out = {"corr": {a: by_key(row) for a, row in zip(self.keys, self.corr)},
               "noise": self.noise, "noise_estimated": self.noise_estimated,
               "constrained": list(self.constrained), "statement": self.statement}
        if not self.withheld:
            out["stderr"] = by_key(self.stderr)
            if self.stderr_numerical is not None or self.sampling is not None or self.grid is not None:
                out["stderr_statistical"] = by_key(self.stderr_statistical)
            if self.stderr_numerical is not None:
                out["stderr_numerical"] = by_key(self.stderr_numerical)
            if self.sampling is not None:
                out["stderr_sampling"] = by_key(self.sampling.stderr)
            out["ci95"] = {k: [float(lo), float(hi)] for k, (lo, hi) in zip(self.keys, self.ci95)}
            out["relative_halfwidth_at_reference_noise"] = by_key(self.relative_halfwidth)
            if self.grid is not None:
                out["stderr_grid"] = by_key(self.grid.stderr)
                out["grid_converged"] = self.grid_converged
        if self.sampling is not None:
            out["sampling"] = self.sampling.to_dict(self.keys)
        if self.grid is not None:
            out["grid"] = self.grid.to_dict(self.keys)
        elif self.grid_note:
            out["grid"] = {"measured": False, "why": self.grid_note}
        return out


def _combination(vec, keys, tol=0.2) -> str:
    vec = vec / np.max(np.abs(vec))
    vec = vec if vec[np.argmax(np.abs(vec))] > 0 else -vec
    terms = [f"{'+' if c > 0 else '−'} {abs(c):.2f}·{k}" for c, k in zip(vec, keys) if abs(c) >= tol]
    text = " ".join(terms)
    return text[2:] if text.startswith("+ ") else text


def _inverse(fisher, rcond: float = 1e-14):
    """The inverse of a symmetric positive semi-definite matrix, with eigenvalues below
    ``rcond`` × the largest raised to that floor: a direction the data do not see gets a huge,
    finite variance (a pseudo-inverse would give it zero, i.e. claim it is perfectly known)."""
    evals, evecs = np.linalg.eigh(fisher)
    floor = rcond * max(float(np.max(evals)), 1e-300)
    return (evecs / np.maximum(evals, floor)) @ evecs.T


def _sandwich_fisher(A, B):
    """The inverse of the sandwich covariance A⁻¹ B A⁻¹ of a weighted least-squares estimate
    (A = Jᵀ W J, B = Jᵀ W Σ W J), A B⁻¹ A: with weights W = Σ⁻¹ it is Jᵀ Σ⁻¹ J."""
    F = A @ _inverse(B) @ A
    return 0.5 * (F + F.T)


def gauss_newton_uncertainty(
    J, r, keys: Sequence[str], theta, blocks: Mapping[str, slice], row_scale,
    *, noise: Mapping[str, float] | float | None = None, reference_noise: float = 0.01,
    threshold: float = 0.1, bounds=None, verdict: Verdict | None = None, scatter: ModelScatter | None = None,
    sampling: ModelScatter | None = None, grid: GridCheck | None = None, grid_note: str = "",
) -> Uncertainty:
    """Covariance, standard errors and identifiability at the optimum.

    ``J`` (m × n) and ``r`` (m) are the objective's weighted residuals and Jacobian in physical
    units; ``blocks`` and ``row_scale`` (the objective's) undo the weights. ``noise``: the known
    σ of each block in the block's relative units (a float applies to every block); None:
    estimate it from the residuals. ``verdict`` (from ``assess_fit``): when it says the point
    is not a fit of the data, every interval (stderr, ci95, cov, the half-widths and the
    constrained keys) is withheld and the statement says why; only the local geometry
    (correlations, Fisher eigen-directions) is kept. ``scatter`` (``model_scatter``; default:
    the verdict's): its covariance of θ, the run's round-off, is added to the statistical one;
    so is ``sampling``'s (``sampling_scatter``), the particle draw's, and ``grid``'s
    (``grid_shift``), the grid's; ``grid_note`` says why the grid term is missing, if it is.
    """
    keys = tuple(keys)
    J = np.asarray(J, float)
    r = np.asarray(r, float)
    theta = np.asarray(theta, float)
    row_scale = np.asarray(row_scale, float)
    m, n = J.shape
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        raise ValueError("J and r must be finite (the run at the optimum failed?)")
    e = r / row_scale  # raw relative misfits
    Je = J / row_scale[:, None]
    if noise is not None and not isinstance(noise, Mapping):
        noise = {name: float(noise) for name in blocks}
    estimated, used, reference = {}, {}, {}
    # The fit minimises Σ (row_scale e)²: its weights are row_scale², which need not be 1/σ² (a block's
    # weight is shared by its rows, so a short block's rows weigh more). The covariance of that
    # estimator is the sandwich A⁻¹ B A⁻¹; its inverse, A B⁻¹ A, is the Fisher matrix used below.
    weight = row_scale ** 2
    A = np.zeros((n, n))
    B = np.zeros((n, n))
    B_ref = np.zeros((n, n))
    for name, sl in blocks.items():
        mb = sl.stop - sl.start
        dof = max(mb - n * mb / m, 1.0)
        s = math.sqrt(float(np.sum(e[sl] ** 2)) / dof)
        estimated[name] = s
        sigma = float(noise[name]) if noise is not None else s
        used[name] = sigma
        reference[name] = max(s, reference_noise)
        Jb, wb = Je[sl], weight[sl]
        A += Jb.T @ (wb[:, None] * Jb)
        B += Jb.T @ ((wb * wb)[:, None] * Jb) * max(sigma, 1e-12) ** 2  # σ = 0 only for an exact fit
        B_ref += Jb.T @ ((wb * wb)[:, None] * Jb) * reference[name] ** 2
    fisher, fisher_ref = _sandwich_fisher(A, B), _sandwich_fisher(A, B_ref)
    cov_stat = _inverse(fisher)
    if scatter is None and verdict is not None:
        scatter = verdict.scatter
    cov = cov_stat + sum(sc.cov for sc in (scatter, sampling, grid) if sc is not None)
    stderr = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(stderr, stderr)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    ci95 = np.stack([theta - Z95 * stderr, theta + Z95 * stderr], axis=1)

    if bounds is not None:
        span = np.asarray(bounds.upper) - np.asarray(bounds.lower)
    else:
        span = np.ones(n)
    scale = np.maximum(np.abs(theta), 0.01 * span)
    cov_ref = _inverse(fisher_ref)
    se_ref = np.sqrt(np.maximum(np.diag(cov_ref), 0.0))
    rel = Z95 * se_ref / scale
    constrained = tuple(k for k, v in zip(keys, rel) if v <= threshold)

    fisher_rel = fisher_ref * np.outer(scale, scale)
    evals, evecs = np.linalg.eigh(fisher_rel)
    order = np.argsort(evals)[::-1]
    evals, evecs = evals[order], evecs[:, order]

    lines = []
    if constrained:
        lines.append("The data constrain " + ", ".join(
            f"{k} (±{100 * v:.2g} % at {100 * reference_noise:.2g} % noise)" for k, v in zip(keys, rel)
            if k in constrained) + ".")
    weak = [k for k in keys if k not in constrained]
    if weak:
        lines.append("They do not constrain " + ", ".join(
            f"{k} (±{100 * v:.3g} %)" if math.isfinite(v) else f"{k} (no sensitivity)"
            for k, v in zip(keys, rel) if k in weak)
            + f" to within {100 * threshold:.0f} %.")
    if n > 1:
        lines.append(f"Best-fixed combination: {_combination(evecs[:, 0], keys)}; worst: "
                     f"{_combination(evecs[:, -1], keys)} (Fisher eigenvalue ratio "
                     f"{evals[0] / max(evals[-1], 1e-300):.3g}).")
    strong = [(keys[i], keys[j], corr[i, j]) for i in range(n) for j in range(i + 1, n) if abs(corr[i, j]) > 0.9]
    for a, b, c in strong:
        lines.append(f"{a} and {b} are strongly correlated ({c:+.2f}): the data fix a combination, not each.")
    if verdict is not None and not verdict.is_fit:
        geometry = [line for line in lines if not line.startswith(("The data constrain", "They do not"))]
        statement = " ".join([verdict.statement] + (["Local geometry only:"] + geometry if geometry else []))
        if grid is not None:
            statement += (f" At {grid.ratio:.3g} × the grid spacing the same θ would move " + ", ".join(
                f"{k} by {d:+.2g}" for k, d in zip(keys, grid.shift)) + ".")
        return Uncertainty(keys, theta, None, None, corr, None, used, estimated, None, None, (), evals, evecs,
                           statement, verdict, sampling=sampling, grid=grid, grid_note=grid_note)
    se_stat = np.sqrt(np.maximum(np.diag(cov_stat), 0.0))
    if scatter is not None:
        dominated = [k for k, a, b in zip(keys, se_stat, scatter.stderr) if b > a]
        if dominated:
            lines.append(f"The run's own round-off ({scatter.samples} perturbed runs) dominates the interval of "
                         f"{', '.join(dominated)}: the data resolve more than the simulator can reproduce.")
    if sampling is not None:
        moved = [f"{k} (±{Z95 * b:.2g} against ±{Z95 * a:.2g})" for k, a, b in zip(keys, se_stat, sampling.stderr)
                 if b > a]
        if moved:
            lines.append(f"Another draw of the particles ({sampling.samples} seeds) moves " + ", ".join(moved)
                         + " by more than the data's interval: at this resolution that part of the answer is a "
                         "property of the discretisation, not of the material.")
    if grid is not None:
        moved = [f"{k} (±{h:.2g} against ±{Z95 * a:.2g})" for k, a, h in zip(keys, se_stat, grid.halfwidth)
                 if h > Z95 * a]
        if moved:
            lines.append(f"Not converged in the grid: a fit at {grid.ratio:.3g} × dx would move " + ", ".join(
                f"{k} by {d:+.2g}" for k, d in zip(keys, grid.shift)) + "; the grid's share of the interval of "
                + ", ".join(moved) + " exceeds the data's. At this dx that part of the answer is a property of "
                "the grid, not of the material: refit at a finer dx."
                + ("" if grid.shift2 is None else f" Grid term from {grid.method}."))
        else:
            seen = (f"one coarser grid ({grid.ratio:.3g} × dx) can show" if grid.shift2 is None
                    else f"two coarser grids ({grid.ratio:.3g} and {grid.ratio ** 2:.3g} × dx) show")
            lines.append(f"Converged in the grid as far as {seen}: its share stays within the data's interval "
                         "for every key.")
    elif grid_note:
        lines.append(f"The grid's share was not measured: {grid_note}.")
    return Uncertainty(keys, theta, stderr, cov, corr, ci95, used, estimated, se_ref, rel, constrained,
                       evals, evecs, " ".join(lines), verdict, se_stat,
                       scatter.stderr if scatter is not None else None, sampling, grid, grid_note)


def judge_point(objective: ObjectiveLike, r, J, theta, *, converged: bool, message: str,
                noise: Mapping[str, float] | float | None = None, uncertainty: bool = True,
                roundoff_samples: int = ROUNDOFF_SAMPLES, sampling_seeds: int = 0, reference_noise: float = 0.01,
                threshold: float = 0.1, grid_ratio: float | None = None, grid_draws: int = GRID_DRAWS,
                grid_levels: int = 1, workers=None):
    """The verdict on a fit's end point and, when ``uncertainty``, its Gauss–Newton uncertainty
    (intervals withheld unless the verdict is a fit): what ``fit`` and ``search`` report for
    their best point. ``roundoff_samples`` perturbed runs measure the run's own scatter there
    (``model_scatter``; 0: not measured, the verdict and interval then assume a smooth run);
    ``sampling_seeds`` other draws of the particles measure the sampling's share of the interval
    (``sampling_scatter``; 0, the default: not measured); ``grid_ratio`` rebuilds the objective at
    that multiple of its dx for the grid's share (``grid_shift``, ``grid_draws`` draws there; None,
    the default: not measured). All go to ``workers`` (a ``calibration.workers.Workers``) when
    given. Returns ``(verdict, uncertainty or None)``."""
    check_grid_options(grid_ratio, grid_draws, grid_levels)
    J = np.asarray(J, float)
    scatter = None
    if roundoff_samples and np.all(np.isfinite(J)):
        scatter = model_scatter(objective, theta, r, J, samples=roundoff_samples, workers=workers)
    verdict = assess_fit(r, objective.row_scale, objective.blocks, theta, converged=converged, message=message,
                         bounds=objective.bounds, noise=noise, J=J if scatter is not None else None,
                         scatter=scatter)
    unc = None
    if uncertainty:
        sampling = None
        if sampling_seeds and np.all(np.isfinite(J)):
            sampling = sampling_scatter(objective, theta, r, J, seeds=sampling_seeds, workers=workers)
        grid, grid_note = None, ""
        if grid_ratio is not None and np.all(np.isfinite(J)):
            try:
                grid = grid_shift(objective, theta, J, ratio=grid_ratio, draws=grid_draws, levels=grid_levels,
                                  workers=workers)
            except ValueError as error:
                grid_note = str(error)
            else:
                if grid is None:
                    grid_note = f"no run at {grid_ratio:g} × dx ran without status bits"
        unc = gauss_newton_uncertainty(J, r, objective.keys, theta, objective.blocks, objective.row_scale,
                                       noise=noise, bounds=objective.bounds, verdict=verdict, scatter=scatter,
                                       sampling=sampling, grid=grid, grid_note=grid_note,
                                       reference_noise=reference_noise, threshold=threshold)
    return verdict, unc

