"""calibration.studies.coverage: the rates, their Clopper–Pearson intervals and the plumbing, on a
linear-Gaussian stand-in for the twin (exact answers are known there; the real study is
`python -m calibration coverage`, docs/twin.md)."""

import dataclasses
import types

import numpy as np
import pytest

from calibration.inference.gauss_newton import gauss_newton_uncertainty
from calibration.inference.verdict import assess_fit
from calibration.optim.fit import FitResult
from calibration.studies.coverage import CoverageResult, clopper_pearson, coverage
from calibration.studies.twin import TwinResult

M, TRUTH = 60, {"a": 1.0, "b": 2.0}
KEYS = tuple(TRUTH)
X = np.linspace(0.0, 1.0, M)
J = np.stack([np.ones(M), X], axis=1) / np.sqrt(M)  # r = (model − data) · sqrt(1/M): the objective's weights
BLOCKS, ROW_SCALE = {"profile": slice(0, M)}, np.full(M, 1 / np.sqrt(M))


def linear_twin(*, quick, noise, keys, seed, width=1.0):
    """Least squares of a line through noisy points, returned as calibration.studies.twin returns a twin
    (a TwinResult), exactly solvable. ``width`` scales the reported interval (1: honest; 0.5: too narrow)."""
    rng = np.random.default_rng(seed)
    theta_true = np.array([TRUTH[k] for k in keys])
    data = J @ theta_true / ROW_SCALE + noise * rng.standard_normal(M)
    theta = np.linalg.lstsq(J, data * ROW_SCALE, rcond=None)[0]
    r = J @ theta - data * ROW_SCALE
    verdict = assess_fit(r, ROW_SCALE, BLOCKS, theta, converged=True, message="converged")
    unc = gauss_newton_uncertainty(J, r, keys, theta, BLOCKS, ROW_SCALE, verdict=verdict)
    ci = np.stack([theta - width * (theta - unc.ci95[:, 0]), theta + width * (unc.ci95[:, 1] - theta)], axis=1)
    chi2 = lambda res: float(np.sum((res / ROW_SCALE) ** 2)) / unc.noise["profile"] ** 2  # noqa: E731
    r_true = J @ theta_true - data * ROW_SCALE
    params = dict(zip(keys, theta.tolist()))
    result = FitResult(keys=tuple(keys), theta=params, loss=float(r @ r), iterations=1, wall_s=0.0, method="lm",
                       converged=True, message="converged", history={}, residuals=r, jacobian=J, prediction={},
                       uncertainty=dataclasses.replace(unc, ci95=ci), verdict=verdict)
    objective = types.SimpleNamespace(blocks=BLOCKS, row_scale=ROW_SCALE, bounds=None)
    return TwinResult(fit=result, objective=objective, keys=tuple(keys), truth=TRUTH, start=params,
                      rel_error={k: params[k] / TRUTH[k] - 1.0 for k in keys},
                      in_ci95={k: bool(lo <= TRUTH[k] <= hi) for k, (lo, hi) in zip(keys, ci)},
                      delta_chi2_truth=chi2(r_true) - chi2(r), noise=noise, seed=seed, dx=0.0, n_particles=0,
                      wall_s=0.0)


def test_clopper_pearson_matches_the_exact_binomial_interval():
    assert clopper_pearson(19, 20) == pytest.approx((0.7513, 0.9987), abs=1e-4)
    assert clopper_pearson(0, 10) == pytest.approx((0.0, 0.3085), abs=1e-4)
    assert clopper_pearson(10, 10)[1] == 1.0


def test_honest_intervals_cover_at_the_nominal_rate_and_narrow_ones_are_caught():
    honest = coverage(200, noise=0.02, keys=KEYS, run=linear_twin)
    for k in KEYS:
        for given in (False, True):
            rate = honest.rate(k, given=given)
            assert rate["of"] == 200 and rate["rate_ci95"][0] <= 0.95 <= rate["rate_ci95"][1], (k, given, rate)
    assert 0.9 <= honest.joint_rate()["rate"] <= 0.99
    narrow = coverage(200, noise=0.02, keys=KEYS, run=lambda **kw: linear_twin(**kw, width=0.5))
    assert all(narrow.rate(k)["rate_ci95"][1] < 0.95 for k in KEYS)  # half-width intervals: ~67 %, detected
    out = honest.to_json()
    assert out["seeds"] == 200 and set(out["coverage_given_noise"]) == set(KEYS) and not out["not_a_fit"]
    again = CoverageResult.from_json(out)
    assert again.rate("a") == honest.rate("a") and again.rows[3].ci95 == honest.rows[3].ci95


def test_coverage_refuses_noise_free_or_single_seed_studies():
    with pytest.raises(ValueError, match="noise must be in"):
        coverage(5, noise=0.0, run=linear_twin)
    with pytest.raises(ValueError, match="seeds must be at least two"):
        coverage([3, 3], noise=0.02, run=linear_twin)
