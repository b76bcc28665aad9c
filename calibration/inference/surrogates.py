"""The emulators of ``calibration.inference.emulator``: a quadratic per residual in whitened
coordinates, fitted to values and slopes, optionally corrected by a Gaussian process, and the
objective whose residuals they replace; Pareto-smoothed importance sampling (``psis``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..problem.protocol import ObjectiveLike

__all__ = ["QuadraticEmulator", "CorrectedQuadratic", "EMULATORS", "EmulatedObjective", "psis"]


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
    every design point's value and slope and returns to the quadratic away from the design.
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
    weights, whose tail is too short to fit). −∞ entries (a failed run) stay −∞. Not arviz-stats'
    ``psislw``, which floors the tail length where the reference (the R package posterior) takes
    the ceiling, and raises on equal weights (an exact emulator) or fewer than 25."""
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
