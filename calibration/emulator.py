"""A posterior for many keys at a few dozen runs: NUTS on a quadratic emulator of the residuals,
corrected to the model's own posterior by Pareto-smoothed importance sampling.

NUTS on the model itself (``calibration.mcmc.nuts_posterior``) spends one Jacobian per leapfrog
step: a converged five-key posterior is tens of thousands of runs, weeks on two cores. Here the
model runs only where they inform:

1. **Design.** Residuals and their Jacobians at 3k + 1 points in whitened logit coordinates w
   (z = m + L w, ``calibration.mcmc``'s, from a fit's Gauss–Newton covariance or the Laplace
   covariance at a given point): the centre, ±``axial`` along every axis (a star) and k points
   drawn from N(0, ``axial``²/4 I).
2. **Emulator.** Every residual is fitted as a quadratic in w, r(w) ≈ a + b·w + ½ wᵀ C w, by
   least squares on the values and the Jacobians together (each point gives 1 + k equations per
   residual, the quadratic has (k + 1)(k + 2)/2 coefficients), each point weighed by a Gaussian
   kernel exp(−|w|²/(2 ``reach``²)) of its distance from the posterior of the round. χ² = Σ W r²
   from it is a quartic: the curvature of a valley that Gauss–Newton misses is kept. By default
   (``emulator="corrected"``, ``CorrectedQuadratic``) a Gaussian process through the quadratic's
   errors in the design points' values and slopes is added, so that the emulator follows the
   model wherever it was run: on five keys the quadratic alone bent one flat valley into two wells.
3. **Rounds: the design follows the posterior.** NUTS on the emulator (``EmulatedObjective``:
   the objective with its residuals replaced; cheap, so the chains can be long); then the
   coordinates are re-centred and re-whitened on the draws' mean and covariance, the model's
   Jacobians are taken at the new centre and star (2k + 1 points), and the emulator is fitted
   again in them, ``rounds`` times. A quadratic fitted over a wide first design is smoothly
   wrong in a posterior much narrower than that design (measured on five keys: 99 % of the
   emulator's χ² error at the checked draws was a quadratic in θ); the kernel and the new star
   make it right where the mass is. Each round records the previous emulator's χ² error at the
   new points and how far the posterior's mean moved (in its own standard deviations).
4. **Correction.** The model's χ² at ``checks`` draws taken at random from the final chains;
   importance weights exp(−(χ²_model − χ²_emulator)/2), Pareto-smoothed (``psis``, Vehtari et al.
   2024). The reported mean, sd and 95 % interval are the weighted ones: the model's posterior, not
   the emulator's. Pareto k̂ < 0.7 says the weights are reliable; above it the emulator is too far
   from the model where the posterior lies, and the answer is refused (``converged`` False), as
   it is when the weights leave fewer than 100 effective draws.

The chains' R̂ and ESS are those of the emulator's posterior (which NUTS samples exactly); the
correction's accuracy is the importance sample's (its ESS, ``ess_importance``). A draw where the
model's run fails has weight zero, and is counted. Like every importance sampler, the correction
cannot see mass the emulator puts nowhere near: the rounds place the design where the emulated
posterior is, and k̂ catches an emulator that is wrong where its draws are.
"""

from __future__ import annotations

import dataclasses
import math
import time
import types
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .bounds import dphysical_dz, physical, unconstrained
from .gridterm import GridTerm, coarse_objectives, with_grid_term
from .likelihood import checked_point, noise_levels, weighted_quantile
from .objective import jacobians_z, residuals_at
from .protocol import ObjectiveLike
from .uncertainty import GridCheck

__all__ = ["EMULATORS", "CorrectedQuadratic", "EmulatedObjective", "EmulatedPosterior", "QuadraticEmulator",
           "emulated_posterior", "log_uniform", "prior_sensitivity", "psis", "scale_keys"]

#: The least effective sample size of a reported posterior (``calibration.mcmc``'s, Vehtari et al. 2021).
ESS_MIN = 100.0

#: Pareto k̂ above which importance weights are unreliable (Vehtari et al. 2024, for S ≥ 2,000 draws).
PARETO_K_MAX = 0.7


def _features(w):
    """[1, w_i, w_i w_j (i ≤ j)] of w (k,): the quadratic's basis."""
    k = w.shape[-1]
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    quad = [w[..., i] * w[..., j] for i, j in pairs]
    return jnp.concatenate([jnp.ones(w.shape[:-1] + (1,), w.dtype), w, jnp.stack(quad, axis=-1)], axis=-1)


def _feature_rows(W):
    """The design matrix of values and derivatives at the rows of W (P, k): (P (1 + k), F)."""
    W = np.asarray(W, float)
    P, k = W.shape
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    F = 1 + k + len(pairs)
    rows = np.zeros((P, 1 + k, F))
    rows[:, 0, :] = np.asarray(_features(jnp.asarray(W)))
    for m in range(k):  # d/dw_m of every feature
        rows[:, 1 + m, 1 + m] = 1.0
        for f, (i, j) in enumerate(pairs):
            rows[:, 1 + m, 1 + k + f] = (W[:, j] if i == m else 0.0) + (W[:, i] if j == m else 0.0)
    return rows.reshape(P * (1 + k), F)


@dataclasses.dataclass(frozen=True)
class QuadraticEmulator:
    """Every residual as a quadratic in the whitened coordinates w: r(w) = features(w) @ ``coef``
    (``coef`` (F, m)), fitted at the design points ``W`` (P, k); ``rms``: the fit's root-mean-square
    misfit of values and derivatives, relative to their own RMS (0: the residuals are quadratic)."""

    coef: np.ndarray
    W: np.ndarray
    rms: float

    @classmethod
    def fit(cls, W, R, JW, weights=None) -> QuadraticEmulator:
        """From residuals ``R`` (P, m) and their Jacobians ``JW`` (P, m, k) in w at the points
        ``W`` (P, k): the least-squares quadratic of values and derivatives together, each
        point's equations weighed by ``weights`` (P,; default 1). ``rms`` is the weighted misfit."""
        W, R, JW = np.asarray(W, float), np.asarray(R, float), np.asarray(JW, float)
        P, k = W.shape
        F = (k + 1) * (k + 2) // 2
        if P * (1 + k) < F:
            raise ValueError(f"W: {P} points give {P * (1 + k)} equations, a quadratic in {k} keys needs {F}")
        omega = np.ones(P) if weights is None else np.asarray(weights, float)
        if omega.shape != (P,) or not np.all(np.isfinite(omega) & (omega >= 0)) or not omega.any():
            raise ValueError(f"weights must be {P} finite non-negative numbers, not all zero")
        root = np.repeat(np.sqrt(omega), 1 + k)[:, None]
        A = _feature_rows(W)
        Y = np.concatenate([R[:, None, :], np.transpose(JW, (0, 2, 1))], axis=1).reshape(P * (1 + k), -1)
        coef, *_ = np.linalg.lstsq(root * A, root * Y, rcond=None)
        misfit = root * (A @ coef - Y)
        rms = float(np.sqrt(np.mean(misfit**2)) / max(np.sqrt(np.mean((root * Y) ** 2)), 1e-300))
        return cls(coef, W, rms)

    def __call__(self, w):
        return _features(w) @ jnp.asarray(self.coef, w.dtype)


def _gradient_kernel(X, Y, length: float) -> np.ndarray:
    """The covariance of a Gaussian process with the squared-exponential kernel of ``length``
    (unit variance) between its values and gradients at the rows of X (P, k) and at those of Y
    (Q, k): (P (1 + k), Q (1 + k)), each point's value first, then its k derivatives."""
    d = X[:, None, :] - Y[None, :, :]
    K0 = np.exp(-0.5 * np.sum(d**2, axis=-1) / length**2)
    P, Q, k = d.shape
    out = np.zeros((P, 1 + k, Q, 1 + k))
    out[:, 0, :, 0] = K0
    out[:, 0, :, 1:] = K0[..., None] * d / length**2  # cov(f(x), ∂_b f(y))
    out[:, 1:, :, 0] = np.moveaxis(-K0[..., None] * d / length**2, -1, 1)  # cov(∂_a f(x), f(y))
    cross = K0[..., None, None] * (np.eye(k) / length**2 - d[..., :, None] * d[..., None, :] / length**4)
    out[:, 1:, :, 1:] = np.transpose(cross, (0, 2, 1, 3))
    return out.reshape(P * (1 + k), Q * (1 + k))


@dataclasses.dataclass(frozen=True)
class CorrectedQuadratic:
    """A ``QuadraticEmulator`` plus the mean of a Gaussian process on what it misses: the
    quadratic's errors in the values and the Jacobians at the design points are interpolated
    (squared-exponential kernel of length ``length``, the median distance from a point to its
    nearest neighbour, at least 0.5; a relative nugget ``NUGGET``), so that the emulator follows
    every design point's value and slope, and returns to the quadratic away from the design. The
    quadratic's global shape where the design is sparse, the model's own where it is dense;
    ``rms`` is the quadratic's."""

    quadratic: QuadraticEmulator
    W: np.ndarray
    alpha: np.ndarray  # (P (1 + k), m): the process's weights for every residual
    length: float

    @property
    def rms(self) -> float:
        return self.quadratic.rms

    @classmethod
    def fit(cls, W, R, JW, weights=None) -> CorrectedQuadratic:
        W, R, JW = np.asarray(W, float), np.asarray(R, float), np.asarray(JW, float)
        quadratic = QuadraticEmulator.fit(W, R, JW, weights)
        P, k = W.shape
        Y = np.concatenate([R[:, None, :], np.transpose(JW, (0, 2, 1))], axis=1).reshape(P * (1 + k), -1)
        E = Y - _feature_rows(W) @ quadratic.coef
        D = np.sqrt(np.sum((W[:, None, :] - W[None, :, :]) ** 2, axis=-1))
        np.fill_diagonal(D, np.inf)
        length = max(float(np.median(D.min(axis=1))), 0.5)
        K = _gradient_kernel(W, W, length)
        K[np.diag_indices_from(K)] += NUGGET * np.diag(K)
        alpha = np.linalg.solve(K, E)
        return cls(quadratic, W, alpha, length)

    def __call__(self, w):
        W = jnp.asarray(self.W, w.dtype)
        d = w[None, :] - W
        K0 = jnp.exp(-0.5 * jnp.sum(d**2, axis=-1) / self.length**2)
        k_star = jnp.concatenate([K0[:, None], K0[:, None] * d / self.length**2], axis=1).reshape(-1)
        return self.quadratic(w) + k_star @ jnp.asarray(self.alpha, w.dtype)


#: The Gaussian process's nugget, relative to the kernel's variance (values and derivatives).
NUGGET = 1e-6

#: The emulators ``emulated_posterior`` can use, by name.
EMULATORS = {"quadratic": QuadraticEmulator, "corrected": CorrectedQuadratic}


class EmulatedObjective:
    """``objective`` with its residuals replaced by ``emulator``'s (in the whitening ``z_hat``,
    ``L`` of the chains): what ``nuts_posterior`` samples cheaply. Everything else (keys, bounds,
    blocks, weights, members) is the objective's. Its runs never fail (status 0)."""

    def __init__(self, objective: ObjectiveLike, emulator, z_hat, L):
        self._objective, self.emulator = objective, emulator
        self._z_hat, self._L = np.asarray(z_hat, float), np.asarray(L, float)
        self._Linv = np.linalg.inv(self._L)
        self.keys = tuple(objective.keys)

    def __getattr__(self, name):  # the objective's data, bounds and weights
        return getattr(self._objective, name)

    def whiten(self, theta):
        """θ (physical) -> w."""
        lower = jnp.asarray(self._objective.bounds.lower, theta.dtype)
        upper = jnp.asarray(self._objective.bounds.upper, theta.dtype)
        u = (theta - lower) / (upper - lower)
        z = jnp.log(u) - jnp.log1p(-u)
        return jnp.asarray(self._Linv, theta.dtype) @ (z - jnp.asarray(self._z_hat, theta.dtype))

    def residual_fn(self, theta):
        theta = jnp.asarray(theta)
        return self.emulator(self.whiten(theta)), {"status": jnp.zeros((), jnp.int32)}

    def residuals(self, theta):
        return self.residual_fn(jnp.asarray(theta, jnp.result_type(float)))

    def fingerprint(self):
        return None  # nothing compiled for it is cached by content

    def describe(self) -> dict[str, Any]:
        return {"emulator": "quadratic in the whitened coordinates", "design_points": int(self.emulator.W.shape[0]),
                "objective": self._objective.describe()}


def psis(log_weights) -> tuple[np.ndarray, float]:
    """Pareto-smoothed importance sampling (Vehtari, Simpson, Gelman, Yao and Gabry 2024): the
    normalised log weights with their largest M = min(S/5, 3√S) replaced by the quantiles of a
    generalised Pareto fitted to them (Zhang and Stephens 2009, with the weakly informative prior
    on k of the paper), and the shape k̂ (0 where the tail is flat: equal weights; NaN below 25
    weights, whose tail is too short to fit). −∞ entries (a
    failed run) stay −∞."""
    lw = np.asarray(log_weights, float).copy()
    finite = np.isfinite(lw)
    if finite.sum() < 2:
        raise ValueError(f"log_weights: {int(finite.sum())} finite weights; at least 2 are needed")
    x = lw[finite] - lw[finite].max()
    S = x.size
    order = np.argsort(x)
    xs = x[order]
    tail = int(math.ceil(min(0.2 * S, 3.0 * math.sqrt(S))))
    k_hat = math.nan  # too few weights for a tail of five
    if tail > 4 and S - tail - 1 >= 0:
        cutoff = xs[S - tail - 1]
        exceed = np.exp(xs[S - tail:]) - np.exp(cutoff)
        k_hat, sigma = _gpd_fit(exceed)
        if math.isfinite(k_hat) and sigma > 0:
            p = (np.arange(tail) + 0.5) / tail
            q = sigma * np.expm1(-k_hat * np.log1p(-p)) / k_hat if abs(k_hat) > 1e-12 else -sigma * np.log1p(-p)
            xs[S - tail:] = np.minimum(np.log(q + np.exp(cutoff)), 0.0)
    x[order] = xs
    x -= np.log(np.sum(np.exp(x - x.max()))) + x.max()
    lw[finite] = x
    return lw, float(k_hat)


def _gpd_fit(x) -> tuple[float, float]:
    """(k, σ) of a generalised Pareto fitted to the exceedances ``x`` (sorted ascending, > 0) by
    Zhang and Stephens' (2009) empirical Bayes estimate, with k shrunk towards 0.5 as in PSIS."""
    n = x.size
    if not x[-1] > 0:  # a flat tail (equal weights): nothing heavier than the bulk
        return 0.0, 0.0
    m = 30 + int(math.sqrt(n))
    b = 1.0 - np.sqrt(m / (np.arange(1, m + 1) - 0.5))
    quartile = x[int(n / 4 + 0.5) - 1]
    quartile = quartile if quartile > 0 else np.min(x[x > 0])
    b = b / (3.0 * quartile) + 1.0 / x[-1]
    k = np.mean(np.log1p(-b[:, None] * x), axis=1)
    log_lik = n * (np.log(-b / k) - k - 1.0)
    weights = 1.0 / np.sum(np.exp(log_lik[None, :] - log_lik[:, None]), axis=1)
    keep = weights >= 10 * np.finfo(float).eps
    b, weights = b[keep], weights[keep] / weights[keep].sum()
    b_post = float(np.sum(b * weights))
    k_post = float(np.mean(np.log1p(-b_post * x)))
    sigma = -k_post / b_post
    k_post = (n * k_post + 10 * 0.5) / (n + 10)
    return k_post, sigma


@dataclasses.dataclass(frozen=True)
class EmulatedPosterior(GridTerm):
    """The model's posterior from NUTS on an emulator and the importance correction (module
    docstring). ``mean``, ``sd``, ``ci95`` by key: the corrected ones; ``emulated``: the
    emulator's NUTS posterior (its chains, R̂ and ESS); ``pareto_k`` and ``ess_importance``: the
    correction's reliability; ``checks``: (θ (n, k), raw log importance weight (n,)) at the
    checked draws (−∞: the model's run failed there, ``failed_checks`` of them); ``rounds``: per
    emulator its design points, the kernel's weight (``kernel_points``, points' worth near the
    posterior), the fit's ``emulator_rms``, how far its posterior's mean lay from the centre of
    its design (``posterior_mean_from_centre_sd``, in the posterior's sd: the rounds stop below
    ``settle``) and, from the second on, the previous emulator's χ² error at the new star
    (``new_points_dchi2``); ``settled``: whether the last did; ``jacobians`` and ``runs``: the
    model's Jacobians (design) and forward runs (checks) spent; ``check_chi2``: the model's χ² at
    the checked draws (∞ where the run failed) with ``noise``, the likelihood's σ by block
    (``credible_level`` places a point inside or outside the joint credible regions); ``prior``: the
    normal priors of keys measured elsewhere it was sampled with (None: flat in the bounds)."""

    keys: tuple[str, ...]
    mean: dict[str, float]
    sd: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    emulated: Any
    pareto_k: float
    ess_importance: float
    checks: tuple[np.ndarray, np.ndarray]
    failed_checks: int
    rounds: tuple[dict[str, Any], ...]
    jacobians: int
    runs: int
    wall_s: float
    emulator: str = "corrected"
    check_chi2: np.ndarray | None = None
    noise: dict[str, float] | None = None
    prior: dict[str, tuple[float, float]] | None = None
    grid: GridCheck | None = None
    ci95_with_grid: dict[str, tuple[float, float]] | None = None
    grid_posteriors: tuple[dict[str, Any], ...] = ()
    grid_note: str = ""

    @property
    def settled(self) -> bool:
        """The last emulator's posterior lay where its design was centred (the rounds stopped
        there, not at their limit)."""
        return bool(self.rounds[-1].get("settled", False))

    @property
    def converged(self) -> bool:
        """The emulator's chains converged (R̂ < 1.01, bulk ESS ≥ 100, no divergence) and the
        correction is reliable: Pareto k̂ < 0.7 and an importance ESS of at least 100 (the
        chains' own threshold)."""
        return bool(self.emulated.converged and self.pareto_k < PARETO_K_MAX and self.ess_importance >= ESS_MIN)

    def _weights(self, log_prior=None) -> tuple[np.ndarray, float]:
        """The checks' Pareto-smoothed weights (and k̂), under the flat prior or ``log_prior``."""
        log_w = self.checks[1]
        if log_prior is not None:
            extra = np.asarray(log_prior(self.checks[0]), float)
            if extra.shape != log_w.shape or np.any(np.isnan(extra)):
                raise ValueError(f"log_prior must give one log density per check ({log_w.shape}), got {extra.shape}")
            log_w = log_w + extra
        smoothed, k_hat = psis(log_w)
        return np.exp(smoothed), k_hat

    def credible_level(self, chi2: float, log_prior=None) -> float:
        """The posterior's mass where the model's χ² is below ``chi2`` (the importance-weighted
        checks): the smallest joint credible region, ordered by the likelihood, that holds a point
        of χ² ``chi2``; a point is inside the joint 95 % region when the level is at most 0.95.
        Under the flat prior in θ the posterior's density is exp(−χ²/2), so this is its
        highest-density region, and it does not change with the keys' parametrisation. Unlike
        the marginal intervals, it is not moved by how much room a ridge the data leave open has
        in the box. ``log_prior``: the same region's mass under another prior (``reweighted``)."""
        if self.check_chi2 is None:
            raise ValueError("this posterior carries no χ² at its checks (made before they were kept)")
        if not (isinstance(chi2, (int, float, np.floating)) and not math.isnan(chi2)):
            raise ValueError(f"chi2 must be a number, got {chi2!r}")
        w, _ = self._weights(log_prior)
        return float(np.sum(w[self.check_chi2 < chi2]))

    def reweighted(self, log_prior) -> dict[str, Any]:
        """The posterior under another prior, from the same checks: ``log_prior`` maps θ (n, k),
        keys in order, to the new prior's log density (n,) up to a constant (``log_uniform`` for
        scale keys); the checks' weights are multiplied by it and Pareto-smoothed again. The
        mean, sd and 95 % interval by key, with ``pareto_k`` and ``ess_importance`` (a prior
        that puts its mass where the checks are few leaves few effective draws: then sample it
        instead). Beside the flat prior's, this says how much of an interval is the prior's: a
        key the data fix does not move."""
        w, k_hat = self._weights(log_prior)
        thetas = self.checks[0]
        mean = {k: float(np.sum(w * thetas[:, j])) for j, k in enumerate(self.keys)}
        return {"mean": mean,
                "sd": {k: float(np.sqrt(np.sum(w * (thetas[:, j] - mean[k]) ** 2))) for j, k in enumerate(self.keys)},
                "ci95": {k: [float(v) for v in weighted_quantile(thetas[:, j], w, [0.025, 0.975])]
                         for j, k in enumerate(self.keys)},
                "pareto_k": k_hat if math.isfinite(k_hat) else None, "ess_importance": float(1.0 / np.sum(w**2))}

    def chi2_at(self, objective: ObjectiveLike, theta) -> float:
        """The model's χ² at ``theta`` (a mapping by key, or values in key order) with this
        posterior's noise: one forward run. ∞ where the run fails."""
        from .mcmc import _row_weights

        if self.noise is None:
            raise ValueError("this posterior carries no noise level (made before it was kept)")
        if tuple(objective.keys) != self.keys:
            raise ValueError(f"objective: its keys {tuple(objective.keys)} are not this posterior's {self.keys}")
        r, pred = objective.residuals(checked_point(objective, theta))
        if int(np.max(np.asarray(pred["status"]))) != 0:
            return math.inf
        return float(np.sum(_row_weights(objective, self.noise) * np.asarray(r, float) ** 2))

    def to_json(self) -> dict[str, Any]:
        emulated = {k: v for k, v in self.emulated.to_json().items() if k not in ("draws", "log_density")}
        kind = {"quadratic": "a quadratic emulator of the residuals",
                "corrected": "a quadratic emulator of the residuals corrected by a Gaussian process through the "
                             "design points"}[self.emulator]
        return {"keys": list(self.keys), "method": f"NUTS on {kind}, corrected by Pareto-smoothed importance sampling "
                "with the model's runs", "emulator": self.emulator, "mean": self.mean, "sd": self.sd,
                "ci95": {k: list(v) for k, v in self.ci95.items()}, "converged": self.converged,
                "settled": self.settled, "pareto_k": self.pareto_k if math.isfinite(self.pareto_k) else None,
                "pareto_k_max": PARETO_K_MAX, "ess_importance": self.ess_importance,
                "ess_min": ESS_MIN,
                "checks": int(self.checks[1].size), "failed_checks": self.failed_checks,
                "rounds": list(self.rounds), "model_jacobians": self.jacobians, "model_runs": self.runs,
                "wall_s": round(self.wall_s, 1), "emulated": emulated,
                "check_draws": {k: self.checks[0][:, j].tolist() for j, k in enumerate(self.keys)},
                "check_log_weights": [v if math.isfinite(v) else None for v in self.checks[1].tolist()],
                "check_chi2": None if self.check_chi2 is None else [v if math.isfinite(v) else None
                                                                    for v in self.check_chi2.tolist()],
                "noise": self.noise,
                "prior": None if self.prior is None else {k: list(v) for k, v in self.prior.items()},
                **self.grid_json()}


def log_uniform(keys, *names: str):
    """The log density, up to a constant, of a prior uniform in log θ for the keys ``names``
    (flat in the others) relative to the flat one: −Σ log θ_j, for ``EmulatedPosterior.reweighted``.
    The scale-free prior of a positive key whose box spans decades (I0)."""
    keys = tuple(keys)
    unknown = [n for n in names if n not in keys]
    if unknown or not names:
        raise ValueError(f"names must be keys of {keys}, got {list(names)}")
    columns = [keys.index(n) for n in names]

    def log_prior(thetas):
        thetas = np.asarray(thetas, float)[:, columns]
        if np.any(thetas <= 0):
            raise ValueError(f"a log-uniform prior needs {list(names)} > 0")
        return -np.sum(np.log(thetas), axis=1)

    return log_prior


def scale_keys(bounds, decades: float = 2.0) -> tuple[str, ...]:
    """The keys of ``bounds`` whose box is positive and spans at least ``decades`` decades (I0's
    0.001-3): for them a prior flat in θ and one flat in log θ are both defensible and differ."""
    return tuple(k for k, lo, hi in zip(bounds.keys, np.asarray(bounds.lower, float), np.asarray(bounds.upper, float))
                 if lo > 0 and math.log10(hi / lo) >= decades)


def prior_sensitivity(posterior: EmulatedPosterior, keys: tuple[str, ...]) -> dict[str, Any]:
    """``posterior`` again under a prior uniform in log θ for ``keys`` (``reweighted``), with
    each key's mean shift in the flat prior's sd: a key the data fix does not move; one whose
    interval is the prior's (a ridge the data leave open) does."""
    other = posterior.reweighted(log_uniform(posterior.keys, *keys))
    shift = {k: (other["mean"][k] - posterior.mean[k]) / posterior.sd[k] if posterior.sd[k] > 0 else 0.0
             for k in posterior.keys}
    return {"log_uniform_keys": list(keys), **other, "mean_shift_sd": shift}


def _laplace_cov_z(objective, weights, z, Jz, prior=None) -> np.ndarray:
    """The Laplace covariance in z at ``z``: the inverse of Gauss–Newton's JᵀWJ plus the
    curvature of the flat prior's log-Jacobian, 2 s(1 − s) per key (s = sigmoid z), and of a
    ``prior`` (``gaussian_prior``'s terms), (dθ/dz / sd)². The flat prior's term keeps a key the
    data do not fix at the scale of its box (a logistic's), not at infinity."""
    z = np.asarray(z, float)
    s = 1.0 / (1.0 + np.exp(-z))
    curvature = 2.0 * s * (1.0 - s)
    if prior is not None:
        idx, _, sd = prior
        span = np.asarray(objective.bounds.upper, float) - np.asarray(objective.bounds.lower, float)
        dtheta_dz = span * s * (1.0 - s)
        curvature[idx] += (dtheta_dz[idx] / sd) ** 2
    precision = Jz.T @ (weights[:, None] * Jz) + np.diag(curvature)
    return np.linalg.inv(precision)


def emulated_posterior(objective: ObjectiveLike, centre, *, noise: Mapping[str, float] | float | None = None,
                       rounds: int = 6, settle: float = 1.0, axial: float = 2.0, reach: float = 3.0,
                       checks: int = 200, chains: int = 4,
                       warmup: int = 200, draws: int = 1000, seed: int = 0, emulator: str = "corrected",
                       target_accept: float = 0.8, prior: Mapping[str, tuple[float, float]] | None = None,
                       grid_ratio: float | None = None, grid_levels: int = 1,
                       workers=None, progress: bool = False) -> EmulatedPosterior:
    """The posterior of ``objective``'s keys from NUTS on a quadratic emulator whose design follows
    the posterior (at most ``rounds`` re-centrings, until the emulated posterior's mean lies within
    ``settle`` of its standard deviations of the centre it was designed around), corrected with
    the model's runs at ``checks`` draws (module docstring).

    ``centre``: a fit (its point, Gauss–Newton covariance and noise whiten the first round, as
    ``nuts_posterior``'s), or parameter values by key: then the first whitening is the Laplace
    covariance at that point (the Jacobian there, with the flat prior's curvature in the logit
    coordinates, so that keys the data leave free span their box), and ``noise`` is needed. A
    point need not be a fit: where the fit's verdict refuses one (a valley, a key at its bound),
    the posterior is still defined, and this samples it. ``noise``: σ by block (default: the fit's).
    ``axial``: the star's reach and ``reach`` the kernel's, in whitened units; ``chains``,
    ``warmup``, ``draws``, ``target_accept``: the emulator's NUTS (cheap: long chains cost seconds;
    a higher acceptance target takes smaller steps where its chains diverge); ``workers``:
    processes for the model's runs (``calibration.workers``). The model is run 3k + 1 + (2k + 1) per
    re-centring with its Jacobian and ``checks`` times without. ``emulator``: "corrected" (a
    quadratic per residual and a Gaussian process through the design points' values and slopes,
    ``CorrectedQuadratic``; the default) or "quadratic" (the quadratic alone, ``QuadraticEmulator``).
    ``prior``: {key: (mean, sd)}, a normal in θ for keys measured by another experiment
    (``calibration.mcmc.gaussian_prior``), beside the flat prior in the bounds; the emulator's
    chains and the model's posterior both carry it, so the importance weights do not.

    ``grid_ratio``, ``grid_levels``: the grid term (``calibration.gridterm``; None: not measured):
    the same posterior, with the same noise, prior and settings, on the objective rebuilt at
    ``grid_ratio`` × dx (and its square with ``grid_levels=2``), centred on this one's mean; the
    shift of its mean gives ``grid`` and ``ci95_with_grid``. About ``grid_ratio``⁻³ of the cost per
    level in 2D."""
    from .mcmc import _row_weights, gauss_newton_point, gaussian_prior, nuts_posterior

    keys = tuple(objective.keys)
    k = len(keys)
    for name, value, least in (("rounds", rounds, 0), ("checks", checks, 30), ("chains", chains, 2),
                               ("warmup", warmup, 1), ("draws", draws, 4)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    for name, value in (("axial", axial), ("reach", reach), ("settle", settle)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number (whitened units), got {value!r}")
    if emulator not in EMULATORS:
        raise ValueError(f"emulator must be one of {sorted(EMULATORS)}, got {emulator!r}")
    if not (isinstance(target_accept, float) and 0.0 < target_accept < 1.0):
        raise ValueError(f"target_accept must be a float strictly between 0 and 1, got {target_accept!r}")
    if checks > chains * draws:
        raise ValueError(f"checks: {checks} draws to check, the chains keep only {chains * draws}")
    prior_terms = gaussian_prior(keys, prior)
    coarse, grid_note = coarse_objectives(objective, grid_ratio, grid_levels)
    lower, upper = np.asarray(objective.bounds.lower, float), np.asarray(objective.bounds.upper, float)
    if isinstance(centre, Mapping):
        if set(centre) != set(keys):
            raise ValueError(f"centre must give every key of the objective {keys}, got {sorted(centre)}")
        theta_hat = np.array([float(centre[key]) for key in keys])
        if noise is None:
            raise ValueError("noise: a centre without a fit needs the data's noise (a float or σ by block)")
        sigma = noise_levels(objective, None, noise)
        gn_cov = None
    else:
        theta_hat, sigma, gn_cov = gauss_newton_point(objective, centre, noise, name="centre", hint=(
            "; pass its point as a mapping of values and the noise, for the Laplace whitening there"))
    if not np.all((theta_hat > lower) & (theta_hat < upper)):
        raise ValueError(f"centre: {dict(zip(keys, theta_hat.tolist()))} is not strictly inside the bounds")
    clock = time.perf_counter()
    weights = _row_weights(objective, sigma)
    rng = np.random.default_rng(seed)
    jl, ju = jnp.asarray(lower), jnp.asarray(upper)

    def say(text):
        if progress:
            import sys

            print(f"emulated posterior: {text} ({time.perf_counter() - clock:.0f} s)", file=sys.stderr, flush=True)

    Z, R, Jz = np.zeros((0, k)), None, None  # the design: points in z, residuals, dr/dz

    def run(points):  # the model's residuals and Jacobians at the rows of ``points`` (z); keeps the good ones
        nonlocal Z, R, Jz
        r, jz, _, pred = jacobians_z(objective, points, workers)
        ok = (np.asarray(pred["status"]).reshape(len(points), -1) == 0).all(axis=1) & np.all(np.isfinite(jz), (1, 2))
        r, jz = np.asarray(r, float)[ok], np.asarray(jz, float)[ok]
        Z = np.concatenate([Z, points[ok]])
        R = r if R is None else np.concatenate([R, r])
        Jz = jz if Jz is None else np.concatenate([Jz, jz])
        return r, ok

    m = np.asarray(unconstrained(theta_hat, lower, upper), float)
    star = np.concatenate([axial * np.eye(k), -axial * np.eye(k)])
    if gn_cov is None:  # the Laplace whitening from the model's Jacobian at the centre (the first design point)
        say("the model's Jacobian at the centre")
        _, ok = run(m[None, :])
        if not ok.all():
            raise RuntimeError(f"centre: the model's run fails at {dict(zip(keys, theta_hat.tolist()))}")
        L = np.linalg.cholesky(_laplace_cov_z(objective, weights, m, Jz[0], prior_terms))
        W = np.concatenate([star, rng.normal(0.0, axial / 2, size=(k, k))])
    else:
        dtheta_dz = np.asarray(dphysical_dz(jnp.asarray(m), jl, ju), float)
        L = np.linalg.cholesky(gn_cov / np.outer(dtheta_dz, dtheta_dz))
        W = np.concatenate([np.zeros((1, k)), star, rng.normal(0.0, axial / 2, size=(k, k))])
    say(f"the model's Jacobians at {len(W)} design points")
    _, ok = run(m + W @ L.T)
    jacobians = 3 * k + 1
    record = [{"design_points": int(len(Z)), "failed_runs": int(np.sum(~ok))}]
    target = None
    for c in range(rounds + 1):
        Linv = np.linalg.inv(L)
        Wd = (Z - m) @ Linv.T
        kernel = np.exp(-0.5 * np.sum(Wd**2, axis=1) / reach**2)
        model = EMULATORS[emulator].fit(Wd, R, Jz @ L, weights=kernel)
        target = EmulatedObjective(objective, model, m, L)
        theta_m = np.asarray(physical(jnp.asarray(m), jl, ju), float)
        dtheta_dz = np.asarray(dphysical_dz(jnp.asarray(m), jl, ju), float)
        cov = L @ L.T * np.outer(dtheta_dz, dtheta_dz)
        whitening = types.SimpleNamespace(keys=keys, theta=dict(zip(keys, theta_m.tolist())),
                                          uncertainty=types.SimpleNamespace(cov=cov, stderr=np.sqrt(np.diag(cov)),
                                                                            withheld=False, noise=sigma))
        record[-1].update(emulator_rms=model.rms, kernel_points=float(kernel.sum()))
        say(f"NUTS on the emulator of {len(Z)} points")
        posterior = nuts_posterior(target, whitening, chains=chains, warmup=warmup, draws=draws, seed=seed + c,
                                   noise=sigma, target_accept=target_accept, prior=prior)
        flat = posterior.flat()
        z_draws = np.asarray(unconstrained(flat, lower, upper), float)
        z_draws = z_draws[np.all(np.isfinite(z_draws), axis=1)]  # a float32 draw rounded onto a bound
        m_new, cov_z = z_draws.mean(axis=0), np.cov(z_draws.T).reshape(k, k)
        moved = float(np.sqrt(np.sum((np.linalg.solve(np.linalg.cholesky(cov_z), m_new - m)) ** 2)))
        record[-1]["posterior_mean_from_centre_sd"] = moved
        record[-1]["settled"] = moved < settle
        say(f"the emulated posterior's mean lies {moved:.1f} of its sds from the design's centre"
            + (" (settled)" if moved < settle else ""))
        if c == rounds or moved < settle:
            break
        # Re-centre and re-whiten on the draws (in z), and a new star there.
        m, L = m_new, np.linalg.cholesky(cov_z)
        points = m + np.concatenate([np.zeros((1, k)), star]) @ L.T
        say(f"the model's Jacobians at the {len(points)} points of a star on the emulator's posterior")
        before = np.asarray(jax.vmap(target.residual_fn)(jnp.asarray(
            np.asarray(physical(jnp.asarray(points), jl, ju)), jnp.result_type(float)))[0], float)
        r_new, ok = run(points)
        jacobians += len(points)
        dchi2 = np.sum(weights * r_new**2, axis=-1) - np.sum(weights * before[ok] ** 2, axis=-1)
        record.append({"design_points": int(len(Z)), "failed_runs": int(np.sum(~ok)),
                       "new_points_dchi2": dchi2.tolist()})
        say(f"the model's chi2 minus the emulator's at the star: {np.array2string(dchi2, precision=1)}")
    pick = rng.choice(flat.shape[0], size=checks, replace=False)
    thetas = flat[pick]
    say(f"the model's runs at {checks} draws")
    results = residuals_at(objective, thetas, workers)
    chi2_model = np.array([np.sum(weights * np.asarray(r, float) ** 2) if int(np.max(pred["status"])) == 0
                           else np.inf for r, pred in results])
    emulated_r = np.asarray(jax.vmap(target.residual_fn)(jnp.asarray(thetas, jnp.result_type(float)))[0], float)
    log_w = -0.5 * (chi2_model - np.sum(weights * emulated_r**2, axis=-1))
    log_w[~np.isfinite(chi2_model)] = -np.inf
    smoothed, k_hat = psis(log_w)
    w = np.exp(smoothed)
    mean = {key: float(np.sum(w * thetas[:, j])) for j, key in enumerate(keys)}
    sd = {key: float(np.sqrt(np.sum(w * (thetas[:, j] - mean[key]) ** 2))) for j, key in enumerate(keys)}
    ci = {key: tuple(float(v) for v in weighted_quantile(thetas[:, j], w, [0.025, 0.975]))
          for j, key in enumerate(keys)}
    found = EmulatedPosterior(keys, mean, sd, ci, posterior, k_hat, float(1.0 / np.sum(w**2)), (thetas, log_w),
                              int(np.sum(~np.isfinite(chi2_model))), tuple(record), jacobians, checks,
                              time.perf_counter() - clock, emulator, chi2_model,
                              {k: float(v) for k, v in sigma.items()},
                              None if prior_terms is None else {k: tuple(map(float, v)) for k, v in prior.items()},
                              grid_note=grid_note)
    if not coarse:
        return found
    settings = dict(rounds=rounds, settle=settle, axial=axial, reach=reach, checks=checks, chains=chains,
                    warmup=warmup, draws=draws, seed=seed, emulator=emulator, target_accept=target_accept,
                    prior=prior, workers=workers, progress=progress)
    return with_grid_term(found, objective, coarse, grid_ratio,
                          lambda obj: emulated_posterior(obj, dict(found.mean), noise=found.noise, **settings),
                          lambda other: {"settled": other.settled,
                                         "pareto_k": other.pareto_k if math.isfinite(other.pareto_k) else None,
                                         "ess_importance": other.ess_importance, "model_jacobians": other.jacobians,
                                         "model_runs": other.runs}, say)


