"""Correlated front-history errors: the whitening of FrontTarget.correlation_time is
the exact Cholesky factor of the exponential (Ornstein–Uhlenbeck) covariance at any spacing, its
inverse restores metres, and the estimator finds the correlation time of a known series."""

import jax.numpy as jnp
import numpy as np
import pytest

from calibration.inference.noise import front_correlation
from calibration.problem.observe import unwhiten_front, whiten_front


def _ou_covariance(t, tau):
    return np.exp(-np.abs(t[:, None] - t[None, :]) / tau)


def test_whitening_is_the_exact_precision_of_the_exponential_covariance():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.02, 0.12, 12))  # uneven frames
    tau = 0.15
    phi = np.concatenate([[0.0], np.exp(-np.diff(t) / tau)])
    e = rng.standard_normal(t.size)
    w = np.asarray(whiten_front(jnp.asarray(e), jnp.asarray(phi)))
    np.testing.assert_allclose(np.sum(w * w), e @ np.linalg.solve(_ou_covariance(t, tau), e), rtol=1e-10)
    np.testing.assert_allclose(unwhiten_front(w, phi), e, rtol=1e-12, atol=1e-14)
    # φ = 0 (independent errors) leaves the residuals as they are.
    np.testing.assert_array_equal(np.asarray(whiten_front(jnp.asarray(e), jnp.zeros(t.size))), e)
    # Draws of the correlated error come out white: unit variance, no lag-1 correlation.
    L = np.linalg.cholesky(_ou_covariance(t, tau))
    draws = np.stack([np.asarray(whiten_front(jnp.asarray(L @ z), jnp.asarray(phi)))
                      for z in rng.standard_normal((4000, t.size))])
    np.testing.assert_allclose(draws.var(axis=0), 1.0, atol=0.08)
    assert abs(np.mean(draws[:, 1:] * draws[:, :-1])) < 0.03


def test_front_correlation_finds_the_correlation_time():
    rng = np.random.default_rng(1)
    t = np.arange(3000) * 0.01
    tau = 0.05  # lag-1 correlation exp(-0.2) = 0.82
    rho = np.exp(-0.01 / tau)
    e = np.empty(t.size)
    e[0] = rng.standard_normal()
    for i in range(1, t.size):
        e[i] = rho * e[i - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal()
    out = front_correlation(t, 1e-3 * e)
    assert abs(out["lag1"] - rho) < 0.03
    assert abs(out["correlation_time_s"] / tau - 1) < 0.15
    assert out["n_effective"] < 0.15 * t.size
    white = front_correlation(t, rng.standard_normal(t.size))
    assert white["correlation_time_s"] is None and white["n_effective"] > 0.9 * t.size
    with pytest.raises(ValueError, match="1-D of one length >= 3"):
        front_correlation(t[:2], e[:2])
