"""The probe of a fit's end point (calibration.inference.probe) on closed forms whose loss is
known: a linear model, where the χ² rise is exactly the quadratic model's, a point left on the
slope, and a loss with ripples finer than the interval, whose local minimum every test at the
point accepts."""

import types

import jax.numpy as jnp
import numpy as np
import pytest

from calibration import JudgeOptions, OptionError
from calibration.inference.noise import Z95
from calibration.inference.probe import PROBE_DROP, probe_loss
from calibration.inference.verdict import judge_point
from calibration.problem.bounds import Bounds

SIGMA = 0.05


class Closed:
    """r = A θ + ripple · sin(θ₀ / wavelength) − y: one block, no simulation."""

    def __init__(self, A, y, ripple=0.0, wavelength=1.0, lower=(-5.0, -5.0), upper=(5.0, 5.0)):
        self.keys = tuple(f"k{i}" for i in range(A.shape[1]))
        self.bounds = Bounds(self.keys, tuple(lower), tuple(upper))
        self.blocks = {"profile": slice(0, A.shape[0])}
        self.row_scale = np.ones(A.shape[0])
        self.dtype = jnp.float64
        self.A, self.y, self.ripple, self.wavelength = np.asarray(A), np.asarray(y), ripple, wavelength
        self.runs = 0

    def residuals(self, theta):
        self.runs += 1
        theta = np.asarray(theta, float)
        r = self.A @ theta - self.y + self.ripple * np.sin(theta[0] / self.wavelength)
        return r, {"status": np.zeros((), np.int32)}

    def jacobian(self, theta):
        d = self.ripple / self.wavelength * np.cos(np.asarray(theta, float)[0] / self.wavelength)
        return self.A + d * (np.arange(self.A.shape[1]) == 0)[None, :]

    def check_thetas(self, thetas, name="thetas"):
        pass


def _linear(seed=0, **kw):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((40, 2)) @ np.array([[1.0, 0.8], [0.0, 0.4]])  # correlated keys
    y = A @ np.array([0.4, 0.6]) + SIGMA * rng.standard_normal(40)
    return Closed(A, y, **kw)


def _probe(objective, theta, **kw):
    """The probe at θ with the data's Gauss–Newton covariance there (σ known)."""
    r, _ = objective.residuals(theta)
    J = objective.jacobian(theta)
    cov = SIGMA**2 * np.linalg.inv(J.T @ J)
    return probe_loss(objective, theta, r, J, cov, {"profile": SIGMA}, **kw)


def test_at_a_linear_models_minimum_the_rise_is_the_quadratic_models():
    objective = _linear()
    theta = np.linalg.lstsq(objective.A, objective.y, rcond=None)[0]
    found = _probe(objective, theta)
    assert found.passed and found.lowest_rise == 0.0 and np.array_equal(found.lowest, theta)
    assert objective.runs == 1 + 2 * len(found.steps)  # the point, then 8 probes a key
    # With the data's covariance the 95 % edge is where χ² has risen by 1.96² along each direction.
    np.testing.assert_allclose(found.predicted, Z95**2, rtol=1e-10)
    np.testing.assert_allclose(found.rise, np.outer(found.predicted, np.square(found.steps)), rtol=1e-8)
    np.testing.assert_allclose(found.vertex, 0.0, atol=1e-8)


def test_a_point_left_on_the_slope_is_found_lower_beside():
    objective = _linear()
    best = np.linalg.lstsq(objective.A, objective.y, rcond=None)[0]
    J = objective.jacobian(best)
    cov = SIGMA**2 * np.linalg.inv(J.T @ J)
    theta = best + 3 * Z95 * np.sqrt(np.diag(cov)) * np.array([1.0, 0.0])  # 3 half-widths of k0 away
    found = _probe(objective, theta)
    assert not found.passed and found.lowest_rise < -PROBE_DROP
    # The lowest probe lies towards the minimum, and is nearer to it than the point.
    assert np.linalg.norm(found.lowest - best) < np.linalg.norm(theta - best)
    text = found.reason(objective.keys)
    assert text.startswith("not the lowest loss near the point") and "k0 = " in text


class Rippled(Closed):
    """Each residual with its own ripple, a · sin(θ / wavelength + φ_i): the loss's ripples are
    incoherent across the rows, as a particle draw's are."""

    def __init__(self, A, y, phase, **kw):
        super().__init__(A, y, **kw)
        self.phase = phase

    def residuals(self, theta):
        self.runs += 1
        theta = np.asarray(theta, float)
        r = self.A @ theta - self.y + self.ripple * np.sin(theta[0] / self.wavelength + self.phase)
        return r, {"status": np.zeros((), np.int32)}

    def jacobian(self, theta):
        d = self.ripple / self.wavelength * np.cos(np.asarray(theta, float)[0] / self.wavelength + self.phase)
        return self.A + d[:, None]


def test_the_ripples_local_minima_are_told_from_the_lowest():
    """One key whose loss has ripples finer than its interval (a period of 0.025 against a 95 %
    half-width of 0.004): eight local minima within ±0.1 of 0.4, each with a zero slope. The probe
    passes the lowest and refuses the seven others, 6 to 24 half-widths off (the nearest with a χ²
    only 7 units above the lowest's), naming a point of lower loss."""
    rng = np.random.default_rng(0)
    A = 1.0 + 0.1 * rng.standard_normal((40, 1))
    y = A[:, 0] * 0.4 + SIGMA * rng.standard_normal(40)
    objective = Rippled(A, y, rng.uniform(0, 2 * np.pi, 40), ripple=0.02, wavelength=0.004, lower=(-5.0,),
                        upper=(5.0,))
    loss = lambda t: float(np.sum(objective.residuals(np.atleast_1d(t))[0] ** 2))  # noqa: E731
    grid = 0.4 + np.linspace(-0.1, 0.1, 20001)
    values = np.array([loss(g) for g in grid])
    local = [i for i in range(1, grid.size - 1) if values[i] < values[i - 1] and values[i] < values[i + 1]]
    assert len(local) == 8
    lowest = int(np.argmin(values))
    for i in local:
        found = _probe(objective, grid[i:i + 1])
        assert found.passed == (i == lowest), grid[i]
        if i != lowest:
            assert loss(found.lowest) < values[i]


def test_an_interval_too_narrow_for_the_loss_is_widened_to_where_chi2_has_risen():
    """The Jacobian handed in is twice the model's, as a local slope steeper than the loss's trend
    is: the Gauss–Newton interval is half the true one. At its edges χ² rises by 1.96²/4, at twice
    them by 1.96²: the probe stretches every side by 2, back to the true interval."""
    objective = _linear()
    theta = np.linalg.lstsq(objective.A, objective.y, rcond=None)[0]
    true_half = Z95 * SIGMA * np.sqrt(np.diag(np.linalg.inv(objective.A.T @ objective.A)))
    r, _ = objective.residuals(theta)
    verdict, unc = judge_point(objective, r, 2 * objective.A, theta, converged=True, message="converged",
                               noise=SIGMA, roundoff_samples=0)
    assert verdict.is_fit and verdict.probe.passed
    np.testing.assert_allclose(verdict.probe.edge_steps(), 2.0, rtol=1e-8)
    np.testing.assert_allclose(unc.ci95_linearised, np.stack([theta - true_half / 2, theta + true_half / 2], 1),
                               rtol=1e-8)
    np.testing.assert_allclose(unc.ci95, np.stack([theta - true_half, theta + true_half], 1), rtol=1e-8)
    assert "widened" in unc.statement and "ci95_linearised" in unc.to_dict()
    # With the model's own Jacobian nothing moves.
    verdict, unc = judge_point(objective, r, objective.A, theta, converged=True, message="converged", noise=SIGMA,
                               roundoff_samples=0)
    assert unc.ci95_linearised is None and "ci95_linearised" not in unc.to_dict()
    np.testing.assert_allclose(verdict.probe.edge_steps(), 1.0)


def test_probes_outside_the_bounds_are_not_run():
    objective = _linear(lower=(0.39, -5.0), upper=(0.41, 5.0))  # k0's box narrower than the probes
    theta = np.linalg.lstsq(objective.A, objective.y, rcond=None)[0]
    found = _probe(objective, theta)
    inside = np.all((theta + np.asarray(found.steps)[None, :, None] * found.directions[:, None, :]
                     > objective.bounds.lower) & (theta + np.asarray(found.steps)[None, :, None]
                                                  * found.directions[:, None, :] < objective.bounds.upper), axis=-1)
    assert np.array_equal(np.isfinite(found.rise), inside) and not inside.all()
    assert found.passed


def test_the_runs_round_off_raises_the_drop_that_counts():
    objective = _linear()
    theta = np.linalg.lstsq(objective.A, objective.y, rcond=None)[0]
    quiet = types.SimpleNamespace(noise={"profile": 1e-6})
    loud = types.SimpleNamespace(noise={"profile": 0.02})
    assert _probe(objective, theta, scatter=quiet).threshold == PROBE_DROP
    chi2 = float(np.sum(objective.residuals(theta)[0] ** 2)) / SIGMA**2
    assert _probe(objective, theta, scatter=loud).threshold == pytest.approx(3 * 2 * np.sqrt(chi2) * 0.02 / SIGMA)


def test_a_point_that_fails_the_probe_is_no_fit_and_gets_no_interval():
    objective = _linear()
    best = np.linalg.lstsq(objective.A, objective.y, rcond=None)[0]
    slope = best + 2.5 * _probe(objective, best).directions[-1]  # 2.5 half-widths: χ² up by 24, within the noise
    for theta, is_fit in ((best, True), (slope, False)):
        r, _ = objective.residuals(theta)
        verdict, unc = judge_point(objective, r, objective.jacobian(theta), theta, converged=True,
                                   message="converged", noise=SIGMA, roundoff_samples=0)
        assert verdict.probe is not None and verdict.is_fit == is_fit == verdict.probe.passed
        assert unc.withheld != is_fit
        if not is_fit:
            assert "not the lowest loss near the point" in verdict.statement
    verdict, _ = judge_point(objective, r, objective.jacobian(theta), theta, converged=True, message="converged",
                             noise=SIGMA, roundoff_samples=0, probe=False)
    assert verdict.probe is None and verdict.is_fit  # without the probe the slope goes unseen
    # A verified minimum whose misfit is above the (given, too small) noise is probed too.
    r, _ = objective.residuals(best)
    verdict, unc = judge_point(objective, r, objective.jacobian(best), best, converged=True, message="converged",
                               noise=SIGMA / 3, roundoff_samples=0)
    assert verdict.probe is not None and verdict.probe.passed and unc.withheld
    assert len(verdict.reasons) == 1 and "misfit well above the noise" in verdict.reasons[0]
    with pytest.raises(OptionError, match="probe"):
        JudgeOptions(probe="yes")


class TwoBlocks(Closed):
    """Two blocks of rows weighted 1 and 5 (``row_scale``), as a fit weighs a short block: the
    loss Σ r² and the data's χ² have different minima."""

    def __init__(self, A, y):
        super().__init__(A, y)
        self.blocks = {"a": slice(0, 20), "b": slice(20, 40)}
        self.row_scale = np.where(np.arange(40) < 20, 1.0, 5.0)

    def residuals(self, theta):
        r, pred = super().residuals(theta)
        return self.row_scale * r, pred

    def jacobian(self, theta):
        return self.row_scale[:, None] * super().jacobian(theta)


def test_the_probe_measures_the_loss_the_fit_minimises():
    """At the minimum of the weighted loss the probe passes (a lower χ² elsewhere is the weights'
    choice, not a lower loss a restart could descend to), and each rise is the loss's, scaled."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((40, 2)) @ np.array([[1.0, 0.8], [0.0, 0.4]])
    y = A @ np.array([0.4, 0.6]) + SIGMA * rng.standard_normal(40) + np.where(np.arange(40) < 20, 0.1, 0.0)
    objective = TwoBlocks(A, y)
    w = objective.row_scale
    theta = np.linalg.lstsq(w[:, None] * A, w * y, rcond=None)[0]
    r, _ = objective.residuals(theta)
    J = objective.jacobian(theta)
    cov = SIGMA**2 * np.linalg.inv(A.T @ A)
    found = probe_loss(objective, theta, r, J, cov, {"a": SIGMA, "b": SIGMA})
    assert found.passed and np.all(found.rise > 0)
    loss = lambda t: float(np.sum(objective.residuals(t)[0] ** 2))  # noqa: E731
    d = found.directions[0]
    scale = found.predicted[0] / float(np.sum((J @ d) ** 2))
    assert found.rise[0, -1] == pytest.approx(scale * (loss(theta + 8 * d) - loss(theta)), rel=1e-10)
