"""Uncertainty beyond Gauss–Newton: profile likelihoods, the grid posterior, a
held-out prediction with its band and the NUTS sampler's plumbing through a real run, on a tiny
S4 twin (dx = L/6, 0.1 s) with 2 % noise."""

import dataclasses

import numpy as np
import pytest
from helpers import placeholder_objective, tiny_s4

from calibration import FrontTarget, Objective, ProfileTarget, fit
from calibration.inference.gridpost import grid_posterior, predict_heldout
from calibration.inference.likelihood import DELTA_CHI2_95, profile_likelihood

KEYS = ("beta", "mu1")
TRUTH = np.array([0.25, 0.38])
NOISE = 0.02
XS = np.linspace(0.0, 0.16, 17)


@pytest.fixture(scope="module")
def twin():
    scene = tiny_s4()
    gen = placeholder_objective(scene, KEYS, xs=XS)
    h = np.asarray(gen.predict(TRUTH)["h"])
    noisy = h + NOISE * h.max() * np.random.default_rng(3).standard_normal(h.shape)
    objective = Objective(scene, KEYS, profile=ProfileTarget(XS, noisy))
    assert objective.functions is gen.functions  # same observations, other data: one compilation
    result = fit(objective, dict(zip(KEYS, TRUTH * 1.05)), steps=12, noise=NOISE, roundoff_samples=0)
    assert result.verdict.is_fit and not result.uncertainty.withheld
    return scene, objective, result


@pytest.mark.slow  # 19 s; the grid posterior on the same twin stays in the default suite
def test_profile_likelihood_matches_gauss_newton_on_a_near_linear_twin(twin):
    _, objective, result = twin
    se = result.uncertainty.stderr
    for j, key in enumerate(KEYS):
        prof = profile_likelihood(objective, result, key, span=3.0, n=5, steps=3)
        assert prof.values.size == 5 and np.all(prof.status == 0) and np.all(np.isfinite(prof.chi2))
        assert prof.values[2] == result.theta[key]  # the fit's value is on the grid
        # The fit is a minimum: no refitted value lies below it by more than LM's stopping slack.
        assert np.nanmin(prof.chi2) > prof.chi2_hat - 0.2
        assert prof.delta_chi2[0] > DELTA_CHI2_95 and prof.delta_chi2[-1] > DELTA_CHI2_95  # closed at ±3 se
        lo, hi = prof.ci95
        assert lo < result.theta[key] < hi
        assert 0.7 < (hi - lo) / (2 * 1.959964 * se[j]) < 1.4  # a near-linear problem: Wilks ≈ Gauss–Newton
        other = prof.others[:, 0]
        assert np.ptp(other) > 0  # the other key was refitted along the profile
    with pytest.raises(ValueError, match="key: 'xi' is not a fitted key"):
        profile_likelihood(objective, result, "xi")


# 37 s; the posterior checks' plumbing is tested by default, this quadrature against Gauss-Newton here
@pytest.mark.slow
def test_grid_posterior_agrees_with_gauss_newton(twin):
    _, objective, result = twin
    post = grid_posterior(objective, result, span=4.0, n=7)
    assert post.points.shape == (49, 2) and post.shape == (7, 7) and post.whitened and post.failed == 0
    # The grid is the fit's covariance ellipse: its centre point is the fit.
    np.testing.assert_allclose(post.points[24], [result.theta[k] for k in KEYS], rtol=1e-12)
    for j, key in enumerate(KEYS):
        se = result.uncertainty.stderr[j]
        assert abs(post.mean[key] - result.theta[key]) < 0.5 * se
        assert 0.7 < post.sd[key] / se < 1.4
        lo, hi = post.ci95[key]
        assert lo < post.mean[key] < hi
    out = post.to_json()
    assert all(v is None or np.isfinite(v) for v in out["chi2"])  # JSON-clean: no NaN printed
    assert out["method"].startswith("quadrature on a grid") and set(out["sd_over_gauss_newton"]) == set(KEYS)
    three = Objective(objective.scene, ("beta", "mu1", "xi"), profile=objective.profiles[0])
    with pytest.raises(ValueError, match="quadrature is for one or two"):
        grid_posterior(three, result)


@pytest.mark.slow  # 20 s
def test_held_out_prediction_with_its_band(twin):
    """Fit the final profile, predict the front the fit never saw: the prediction at the fit's
    point, a band from its covariance (twice the covariance's square root: twice the band)."""
    scene, _, result = twin
    times = np.array([0.05, 0.1])
    gen = placeholder_objective(scene, KEYS, times=times)
    truth_front = np.asarray(gen.predict(TRUTH)["front"])
    held = Objective(scene, KEYS, front=FrontTarget(times, truth_front))
    out = predict_heldout(result, held)
    b = out.blocks["front"]
    np.testing.assert_allclose(b["predicted"], np.asarray(held.predict(list(result.theta.values()))["front"]),
                               rtol=1e-10)
    np.testing.assert_array_equal(b["at"], times)
    assert np.all(np.isfinite(b["band"])) and np.all(b["band"] > 0)
    wide = dataclasses.replace(result, uncertainty=dataclasses.replace(result.uncertainty,
                                                                     cov=4.0 * result.uncertainty.cov))
    np.testing.assert_allclose(predict_heldout(wide, held).blocks["front"]["band"], 2.0 * b["band"], rtol=1e-9)
    assert out.rms["front"] == pytest.approx(float(np.sqrt(np.mean((b["predicted"] - truth_front) ** 2))))
    with pytest.raises(ValueError, match="fits"):
        predict_heldout(result, Objective(scene, ("mu1",), front=FrontTarget(times, truth_front)))
    # Correlated front errors (FrontTarget.correlation_time): the residuals are whitened, so the
    # second one changes, but everything reported in metres, the band included, is the same.
    tau = 0.05
    corr = Objective(scene, KEYS, front=FrontTarget(times, truth_front, correlation_time=tau))
    assert corr.functions is held.functions  # the correlation is data, not a new compilation
    theta = np.array(list(result.theta.values()))
    r_plain, r_corr = np.asarray(held.residuals(theta)[0]), np.asarray(corr.residuals(theta)[0])
    phi = np.exp(-0.05 / tau)
    np.testing.assert_allclose(r_corr, [r_plain[0], (r_plain[1] - phi * r_plain[0]) / np.sqrt(1 - phi ** 2)],
                               rtol=1e-9)
    np.testing.assert_allclose(corr.in_metres(r_corr)["front"], held.in_metres(r_plain)["front"], rtol=1e-9)
    np.testing.assert_allclose(predict_heldout(result, corr).blocks["front"]["band"], b["band"], rtol=1e-8)
    assert corr.fingerprint()["data"] != held.fingerprint()["data"]
    with pytest.raises(ValueError, match="correlation_time must be None or a positive"):
        Objective(scene, KEYS, front=FrontTarget(times, truth_front, correlation_time=-1.0))


@pytest.mark.slow  # 60 s, most of it compiling NUTS around the run; tests/test_mcmc.py checks the sampler by default
def test_nuts_through_the_twin(twin):
    """The sampler through a real run: a few draws only (the statistics are tests/test_mcmc.py's
    exact targets and the docs' study; a warm-up this short leaves the step size unsettled and
    divergences are possible), finite, inside the bounds, near the fit, and the posterior
    predictive of the fitted profile."""
    from calibration.inference.mcmc import nuts_posterior, posterior_predictive

    _, objective, result = twin
    post = nuts_posterior(objective, result, chains=2, warmup=3, draws=4, seed=0)
    assert post.draws.shape == (2, 4, 2) and np.all(np.isfinite(post.draws))
    lower, upper = np.asarray(objective.bounds.lower), np.asarray(objective.bounds.upper)
    assert np.all((post.flat() > lower) & (post.flat() < upper))
    assert np.all(np.isfinite(post.log_density)) and post.gradient_evaluations >= 2 * 6
    # Per chain: an adapted step size, a divergence count and at least one leapfrog step per draw,
    # each step one Jacobian that the count of evaluations holds (the 3 warm-up steps and a start
    # per chain on top of the 4 draws' steps).
    assert len(post.divergences) == len(post.steps) == 2 and all(np.isfinite(post.step_size))
    assert all(s > 0 for s in post.step_size) and min(post.steps) >= 1
    assert post.gradient_evaluations >= 2 * (1 + 3) + round(4 * sum(post.steps))
    se = result.uncertainty.stderr
    assert np.all(np.abs(post.flat() - [result.theta[k] for k in KEYS]) < 6 * se)
    pred = posterior_predictive(objective, post, n=3)
    b = pred["blocks"]["profile"]
    assert b["predicted"].shape == (3, XS.size) and pred["failed"] == 0
    np.testing.assert_allclose(b["data"], np.asarray(objective.data["h"]), rtol=1e-12)


# 57 s on 2 cores; the emulated posterior's algorithm is tested by default on a closed-form crescent
# (tests/test_emulator.py)
@pytest.mark.slow
def test_emulated_posterior_through_the_twin_agrees_with_the_quadrature(twin):
    """The emulated posterior (calibration.inference.emulator) through real runs: 7 to 12 Jacobians and 60
    checked runs give the corrected moments of the grid quadrature on the same target (its 15 × 15
    points: a finer answer than the emulator's Monte Carlo error), with the importance weights
    nearly equal (the emulator is close) and every check run a good one."""
    from calibration.inference.emulator import emulated_posterior

    _, objective, result = twin
    grid = grid_posterior(objective, result, span=5.0, n=15)
    post = emulated_posterior(objective, result, rounds=1, checks=60, warmup=100, draws=300, seed=1)
    assert post.failed_checks == 0 and post.jacobians == 7 + 5 * (len(post.rounds) - 1) and post.runs == 60
    assert post.ess_importance > 45 and post.emulated.converged
    for key in KEYS:
        tol = 3 * grid.sd[key] / np.sqrt(post.ess_importance)  # the importance sample's Monte Carlo error
        assert abs(post.mean[key] - grid.mean[key]) < tol, (key, post.mean[key], grid.mean[key])
        assert 0.75 < post.sd[key] / grid.sd[key] < 1.3, (key, post.sd[key], grid.sd[key])
