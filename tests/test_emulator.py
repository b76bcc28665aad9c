"""The emulated posterior (calibration.inference.emulator): Pareto smoothing against tails whose shape is
known, the quadratic emulator on residuals that are quadratic, and the corrected posterior of a
curved two-key target against its quadrature on a fine grid."""

import importlib.util
import json
import pathlib
import types

import jax.numpy as jnp
import numpy as np
import pytest

from calibration.inference import emulator as emulator_module
from calibration.inference import surrogates
from calibration.inference.emulator import emulated_posterior, log_uniform
from calibration.inference.gridpost import weighted_quantile
from calibration.inference.surrogates import CorrectedQuadratic, EmulatedObjective, QuadraticEmulator, psis
from calibration.plots.posteriors import likelihood_figures
from calibration.problem.bounds import Bounds, dphysical_dz, physical

SIGMA = 0.1


def _banana(theta):
    """A curved valley: θ1 follows θ0² (the posterior is a crescent), plus a weak direct look."""
    return jnp.stack([theta[1] - theta[0] ** 2 - 0.3, 0.4 * theta[0] + 0.1 * theta[1] - 0.2,
                      jnp.sin(2.0 * theta[1]) - 0.5])


def _toy_column(data, z, tangent, lower, upper):
    import jax

    def r_of(z):
        return _banana(physical(z, lower, upper)) - data

    z = jnp.asarray(z)
    r, dr_z = jax.jvp(r_of, (z,), (jnp.asarray(tangent),))
    dr = dr_z / jnp.vdot(dphysical_dz(z, lower, upper), tangent)
    return np.asarray(r), np.asarray(dr_z), np.asarray(dr), {"status": np.zeros((), np.int32)}


def _toy_run(data, theta):
    failed = theta[0] > 1.4  # "the run fails" out there (no posterior mass: it is 7 σ away)
    return np.asarray(_banana(jnp.asarray(theta)) - data), {"status": np.int32(1 if failed else 0)}


class Banana:
    """A closed-form ObjectiveLike with the work pieces ``calibration.batch.workers`` runs."""

    def __init__(self, data):
        self.keys = ("k0", "k1")
        self.bounds = Bounds(self.keys, (-2.0, -1.0), (2.0, 3.0))
        self.blocks = {"profile": slice(0, 3)}
        self.row_scale = np.ones(3)
        self.n_residuals = 3
        self.dtype = jnp.float64
        self.data = np.asarray(data, float)

    def residual_fn(self, theta):
        return _banana(theta) - self.data, {"status": jnp.zeros((), jnp.int32)}

    @property
    def parts(self):
        return ((self, np.arange(2), self.bounds),)

    @staticmethod
    def join(outs):
        return outs[0]

    def column_task(self, z, tangent, bounds):
        return _toy_column, (self.data, np.asarray(z), tangent, np.asarray(bounds.lower), np.asarray(bounds.upper))

    def residual_task(self, theta, seed=None):
        return _toy_run, (self.data, np.asarray(theta))

    def coarsened(self, ratio):
        raise NotImplementedError("a closed form has no grid")

    def describe(self):
        return {"toy": "banana"}

    def residuals(self, theta):
        return _toy_run(self.data, np.asarray(theta, float))

    def check_thetas(self, thetas, name="thetas"):
        if not np.all((thetas >= self.bounds.lower) & (thetas <= self.bounds.upper)):
            raise ValueError(f"{name}: outside the bounds")


def _fit_result(objective, theta):
    """The Gauss–Newton covariance at ``theta`` (what a fit would carry)."""
    import jax

    J = np.asarray(jax.jacfwd(lambda t: objective.residual_fn(t)[0])(jnp.asarray(theta, float)))
    cov = SIGMA**2 * np.linalg.inv(J.T @ J)
    unc = types.SimpleNamespace(cov=cov, stderr=np.sqrt(np.diag(cov)), withheld=False, noise={"profile": SIGMA})
    return types.SimpleNamespace(keys=objective.keys, theta=dict(zip(objective.keys, map(float, theta))),
                                 uncertainty=unc)


def test_psis_estimates_the_tail_shape_of_known_importance_ratios():
    """Proposal N(0, 1), target N(0, s²): the ratio's tail is Pareto with k = 1 − 1/s² (P(w > t) ~
    t^(−1/(1 − 1/s²))). s² = 1.5: k = 1/3, reliable; s² = 4: k = 3/4, refused."""
    x = np.random.default_rng(0).standard_normal(4000)
    for s2, k in ((1.5, 1 / 3), (4.0, 0.75)):
        lw, k_hat = psis(0.5 * x**2 * (1 - 1 / s2))
        assert abs(k_hat - k) < 0.12, (s2, k_hat)
        w = np.exp(lw)
        assert abs(w.sum() - 1) < 1e-12 and np.all(w >= 0)
    lw, k_hat = psis(np.zeros(1000))  # equal weights: nothing to smooth
    np.testing.assert_allclose(np.exp(lw), 1e-3, rtol=1e-12)
    lw, _ = psis(np.r_[np.zeros(500), -np.inf])  # a failed run keeps weight zero
    assert lw[-1] == -np.inf
    with pytest.raises(ValueError, match="log_weights"):
        psis([0.0, -np.inf])
    assert np.isnan(psis(np.arange(20.0))[1])  # a tail of four: no shape to fit


def test_weighted_quantile():
    v = np.random.default_rng(1).standard_normal(20001)
    np.testing.assert_allclose(weighted_quantile(v, np.ones_like(v), [0.025, 0.5, 0.975]),
                               np.quantile(v, [0.025, 0.5, 0.975]), atol=2e-3)
    w = np.r_[np.zeros(10), 1.0]  # all the mass on the last point
    assert weighted_quantile(np.arange(11.0), w, 0.3) == 10.0


def test_quadratic_emulator_is_exact_on_quadratic_residuals():
    rng = np.random.default_rng(2)
    k, m = 3, 4
    a, b, C = rng.normal(size=m), rng.normal(size=(m, k)), rng.normal(size=(m, k, k))
    C = C + np.transpose(C, (0, 2, 1))
    r = lambda w: a + b @ w + 0.5 * np.einsum("mij,i,j->m", C, w, w)  # noqa: E731
    jac = lambda w: b + np.einsum("mij,j->mi", C, w)  # noqa: E731
    W = rng.normal(size=(4, k))  # 4 points x 4 equations = 16 >= 10 coefficients
    em = QuadraticEmulator.fit(W, np.stack([r(w) for w in W]), np.stack([jac(w) for w in W]))
    assert em.rms < 1e-12
    for w in rng.normal(size=(5, k)) * 3:
        np.testing.assert_allclose(np.asarray(em(jnp.asarray(w))), r(w), rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="needs 10"):
        QuadraticEmulator.fit(W[:2], np.zeros((2, m)), np.zeros((2, m, k)))


def test_gradient_kernel_is_the_kernel_and_its_derivatives():
    """The Gaussian process's covariances of values and gradients against finite differences of
    the squared-exponential kernel itself (in x and in y)."""
    rng = np.random.default_rng(1)
    k, length, h = 3, 1.3, 1e-6
    X, Y = rng.normal(size=(2, k)), rng.normal(size=(2, k))
    K = surrogates._gradient_kernel(X, Y, length)
    assert K.shape == (2 * (1 + k), 2 * (1 + k))

    def value(x, y):
        return np.exp(-0.5 * np.sum((x - y) ** 2) / length**2)

    x, y = X[1], Y[0]
    for b in range(k):
        e = np.eye(k)[b] * h
        assert K[4, 1 + b] == pytest.approx((value(x, y + e) - value(x, y - e)) / (2 * h), rel=1e-6)  # cov(f, ∂_b f)
        assert K[4 + 1 + b, 0] == pytest.approx((value(x + e, y) - value(x - e, y)) / (2 * h), rel=1e-6)
        for a in range(k):
            f, g = np.eye(k)[a] * 1e-4, np.eye(k)[b] * 1e-4  # a second difference: a wider step
            mixed = (value(x + f, y + g) - value(x + f, y - g) - value(x - f, y + g) + value(x - f, y - g)) / 4e-8
            assert K[4 + 1 + a, 1 + b] == pytest.approx(mixed, rel=1e-5, abs=1e-9)


def test_corrected_quadratic_follows_the_design_and_beats_the_quadratic_off_it():
    """On residuals that are not quadratic, the corrected emulator passes through every design
    point's values and slopes (the quadratic cannot) and is nearer the function between them."""
    import jax

    rng = np.random.default_rng(0)
    k, P = 3, 25

    def f(w):
        return jnp.stack([jnp.sin(w[0]) * jnp.cos(w[1]) + w[2] ** 3 / 10, jnp.exp(0.3 * jnp.sum(w))])

    W = 1.5 * rng.normal(size=(P, k))
    R = np.stack([np.asarray(f(jnp.asarray(w))) for w in W])
    JW = np.stack([np.asarray(jax.jacfwd(f)(jnp.asarray(w))) for w in W])
    em = CorrectedQuadratic.fit(W, R, JW)
    at = np.stack([np.asarray(em(jnp.asarray(w))) for w in W])
    slopes = np.stack([np.asarray(jax.jacfwd(em)(jnp.asarray(w))) for w in W])
    assert np.max(np.abs(at - R)) < 1e-3 * np.max(np.abs(R)) and np.max(np.abs(slopes - JW)) < 1e-3 * np.max(np.abs(JW))
    quad_at = np.stack([np.asarray(em.quadratic(jnp.asarray(w))) for w in W])
    assert np.max(np.abs(quad_at - R)) > 0.1  # the quadratic alone misses them
    T = rng.normal(size=(200, k))
    truth = np.stack([np.asarray(f(jnp.asarray(w))) for w in T])
    err = [np.sqrt(np.mean((np.stack([np.asarray(g(jnp.asarray(w))) for w in T]) - truth) ** 2))
           for g in (em, em.quadratic)]
    assert err[0] < 0.8 * err[1], err
    assert em.rms == em.quadratic.rms and em.length >= 0.5


def _quadrature(data):
    """The crescent's posterior (flat prior in the box) on an 801 × 801 grid of θ: the grid
    (T0, T1), log p up to a constant, and p normalised."""
    T0, T1 = np.meshgrid(np.linspace(-2, 2, 801), np.linspace(-1, 3, 801), indexing="ij")
    r = np.stack([T1 - T0**2 - 0.3, 0.4 * T0 + 0.1 * T1 - 0.2, np.sin(2 * T1) - 0.5], -1) - data
    logp = -0.5 * np.sum(r**2, -1) / SIGMA**2
    p = np.exp(logp - logp.max())
    return T0, T1, logp, p / p.sum()


@pytest.fixture(scope="module")
def banana():
    truth = np.array([0.5, 0.55])
    data = np.asarray(_banana(jnp.asarray(truth))) + SIGMA * np.random.default_rng(3).standard_normal(3)
    objective = Banana(data)
    # The quadrature on a fine grid of θ (flat prior in the box): the exact posterior moments.
    T0, T1, logp, p = _quadrature(data)
    g0, g1 = T0[:, 0], T1[0]
    mean = np.array([np.sum(p * T0), np.sum(p * T1)])
    sd = np.sqrt([np.sum(p * (T0 - mean[0]) ** 2), np.sum(p * (T1 - mean[1]) ** 2)])
    best = np.unravel_index(np.argmax(logp), logp.shape)
    chi2 = -2.0 * logp

    def level(c):  # the quadrature's mass where χ² < c
        return float(np.sum(p[chi2 < c]))

    def under(log_prior):  # the quadrature's mean and sd under a prior log_prior(T0, T1)
        q = p * np.exp(log_prior(T0, T1))
        q /= q.sum()
        m = np.array([np.sum(q * T0), np.sum(q * T1)])
        return m, np.sqrt([np.sum(q * (T0 - m[0]) ** 2), np.sum(q * (T1 - m[1]) ** 2)])

    level.under = under
    return objective, _fit_result(objective, [g0[best[0]], g1[best[1]]]), mean, sd, level


@pytest.mark.parametrize("whitening, emulator", [  # the first by default; the others 8 s each, slow
    ("fit", "quadratic"), *(pytest.param(*case, marks=pytest.mark.slow) for case in (
        ("laplace", "quadratic"), ("fit", "corrected"), ("laplace", "corrected")))])
def test_emulated_posterior_matches_the_quadrature_of_a_curved_target(banana, whitening, emulator, tmp_path):
    """Whitened by a fit's Gauss–Newton covariance or by the Laplace covariance at a point given by
    value (the model's Jacobian there, the prior's curvature): the corrected moments are the
    quadrature's. (The crescent is not quadratic in the whitened coordinates: the emulator alone is
    off, the importance weights correct it; Pareto k̂ is reported, and on nearly equal weights
    like these it is noisy, 0.5-1.3 over seeds, so it is not asserted here.)"""
    objective, result, mean, sd, level = banana
    centre = result if whitening == "fit" else dict(result.theta)
    post = emulated_posterior(objective, centre, noise=None if whitening == "fit" else SIGMA, rounds=1, checks=400,
                              seed=0, emulator=emulator)
    assert post.emulator == emulator
    assert post.failed_checks == 0 and np.isfinite(post.pareto_k) and post.ess_importance > 300
    assert post.jacobians == 3 * 2 + 1 + (2 * 2 + 1) * (len(post.rounds) - 1) and post.runs == 400
    for j, key in enumerate(objective.keys):
        se = sd[j] / np.sqrt(post.ess_importance)  # the importance sample's Monte Carlo error
        assert abs(post.mean[key] - mean[j]) < 4 * se, (key, post.mean[key], mean[j])
        assert 0.85 < post.sd[key] / sd[j] < 1.15, (key, post.sd[key], sd[j])
    assert all(len(r["new_points_dchi2"]) == 5 for r in post.rounds[1:])
    # The joint credible level of points from the middle out to the tail (0.32-0.96), against the quadrature's.
    for offset in ([0.0, 0.0], [1.0, 0.0], [2.0, -1.0], [0.0, 1.0]):
        point = mean + sd * np.array(offset)
        chi2 = post.chi2_at(objective, dict(zip(objective.keys, point)))
        assert chi2 == pytest.approx(float(np.sum(_toy_run(objective.data, np.array(point))[0] ** 2)) / SIGMA**2)
        exact = level(chi2)
        se = np.sqrt(exact * (1 - exact) / post.ess_importance) + 1e-3
        assert abs(post.credible_level(chi2) - exact) < 4 * se, (point, post.credible_level(chi2), exact)
    assert post.credible_level(0.0) == 0.0 and post.credible_level(np.inf) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="theta: no value for the key"):
        post.chi2_at(objective, {"k0": 0.1})
    with pytest.raises(ValueError, match="chi2 must be a number"):
        post.credible_level(float("nan"))
    # Another prior from the same checks: a Gaussian on k0 (sd 0.2 about 0: the posterior's is 0.27).
    same = post.reweighted(lambda t: np.zeros(len(t)))
    assert same["mean"] == pytest.approx(post.mean) and same["sd"] == pytest.approx(post.sd)
    new = post.reweighted(lambda t: -0.5 * (t[:, 0] / 0.2) ** 2)
    exact_mean, exact_sd = level.under(lambda t0, t1: -0.5 * (t0 / 0.2) ** 2)
    assert new["ess_importance"] > 100 and new["pareto_k"] < 0.7
    for j, key in enumerate(objective.keys):
        assert abs(new["mean"][key] - exact_mean[j]) < 4 * exact_sd[j] / np.sqrt(new["ess_importance"]), key
        assert 0.8 < new["sd"][key] / exact_sd[j] < 1.2, (key, new["sd"][key], exact_sd[j])
    assert new["sd"]["k0"] < 0.85 * post.sd["k0"]
    with pytest.raises(ValueError, match="one log density per check"):
        post.reweighted(lambda t: np.zeros(3))
    out = post.to_json()
    json.dumps(out, allow_nan=False)
    assert out["converged"] == (post.emulated.converged and post.pareto_k < 0.7 and post.ess_importance >= 100)
    assert out["model_runs"] == 400
    assert len(out["check_chi2"]) == 400 and out["noise"] == {"profile": SIGMA}
    # What `calibration posterior --emulated N --plot DIR` draws (before, nothing).
    pytest.importorskip("matplotlib")
    figures = likelihood_figures(tmp_path, [], emulated=post)
    assert [pathlib.Path(f).name for f in figures] == ["posterior_emulated.png"]
    assert pathlib.Path(figures[0]).stat().st_size > 0


@pytest.mark.slow  # 14 s; the emulated posterior's refusals before any run are tested by default
def test_a_misplaced_emulator_is_refused(banana):
    """An emulator fitted in a small patch far from the posterior (the Laplace whitening at a point
    on the crescent's far arm, no refinement): NUTS samples the emulator's wrong posterior, the
    model's runs say so through the weights' heavy tail, and the answer is not reported as converged."""
    objective, *_ = banana
    for seed in (0, 1):
        post = emulated_posterior(objective, {"k0": 1.0, "k1": 1.4}, noise=SIGMA, rounds=0, axial=0.3, checks=400,
                                  warmup=100, draws=500, seed=seed)
        assert post.pareto_k > 0.7 and post.ess_importance < 100 and not post.converged, (post.pareto_k, seed)


def test_emulated_objective_delegates_and_never_fails(banana):
    objective, result, *_ = banana
    em = QuadraticEmulator.fit(np.zeros((3, 2)) + np.eye(3, 2), np.zeros((3, 3)), np.zeros((3, 3, 2)))
    target = EmulatedObjective(objective, em, np.zeros(2), np.eye(2))
    assert target.bounds is objective.bounds and target.blocks is objective.blocks
    r, pred = target.residual_fn(jnp.asarray([0.1, 0.2]))
    assert r.shape == (3,) and int(pred["status"]) == 0 and target.fingerprint() is None


def test_emulated_posterior_refuses_bad_input_before_any_run(banana):
    objective, result, *_ = banana
    calls = []
    objective_spy = Banana(objective.data)
    objective_spy.column_task = lambda *a: calls.append(a) or []
    for kwargs, match in (({"checks": 5}, "checks must be an integer >= 30"),
                          ({"reach": -1.0}, "reach must be a positive number"),
                          ({"settle": 0.0}, "settle must be a positive number"),
                          ({"rounds": -1}, "rounds must be an integer >= 0"),
                          ({"axial": 0.0}, "axial must be a positive number"),
                          ({"checks": 100, "chains": 2, "draws": 10}, "the chains keep only 20"),
                          ({"emulator": "cubic"}, "emulator must be one of"),
                          ({"target_accept": 1.0}, "target_accept must be a float strictly between 0 and 1")):
        with pytest.raises(ValueError, match=match):
            emulated_posterior(objective_spy, result, **kwargs)
    withheld = _fit_result(objective, [0.5, 0.5])
    withheld.uncertainty.withheld = True
    with pytest.raises(ValueError, match="carries no Gauss-Newton covariance"):
        emulated_posterior(objective_spy, withheld)
    with pytest.raises(ValueError, match="needs the data's noise"):
        emulated_posterior(objective_spy, {"k0": 0.1, "k1": 0.2})
    with pytest.raises(ValueError, match="must give every key"):
        emulated_posterior(objective_spy, {"k0": 0.1}, noise=0.1)
    with pytest.raises(ValueError, match="not strictly inside the bounds"):
        emulated_posterior(objective_spy, {"k0": 2.0, "k1": 0.2}, noise=0.1)
    assert not calls


def test_log_uniform_prior():
    log_prior = log_uniform(("beta", "I0", "xi"), "I0", "xi")
    thetas = np.array([[0.1, 0.5, 10.0], [0.2, 2.0, 40.0]])
    assert log_prior(thetas) == pytest.approx([-np.log(5.0), -np.log(80.0)])
    with pytest.raises(ValueError, match="a log-uniform prior needs"):
        log_prior(np.array([[0.1, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="names must be keys"):
        log_uniform(("beta", "I0"), "mu2")


def test_prior_sensitivity_moves_a_key_the_data_leave_to_the_prior():
    """Checks spread flat over a key's box (the data say nothing about it) and one the data fix:
    under a log-uniform prior the first's posterior is the prior's (its mean, (b − a) / ln(b / a),
    moves by over half an sd), the second's does not move."""
    from calibration.inference.emulator import EmulatedPosterior, prior_sensitivity, scale_keys

    bounds = Bounds(("beta", "I0", "xi"), (0.0, 0.01, 10.0), (1.0, 1.0, 500.0))
    assert scale_keys(bounds) == ("I0",) and scale_keys(bounds, decades=2.5) == ()
    rng = np.random.default_rng(0)
    n = 20_000
    thetas = np.stack([rng.normal(0.3, 0.01, n), rng.uniform(0.01, 1.0, n), rng.normal(50.0, 2.0, n)], axis=1)
    keys = bounds.keys
    mean = {k: float(thetas[:, j].mean()) for j, k in enumerate(keys)}
    sd = {k: float(thetas[:, j].std()) for j, k in enumerate(keys)}
    post = EmulatedPosterior(keys, mean, sd, {}, None, 0.0, float(n), (thetas, np.zeros(n)), 0, ({},), 0, n, 0.0)
    found = prior_sensitivity(post, ("I0",))
    exact = (1.0 - 0.01) / np.log(100.0)
    assert found["mean"]["I0"] == pytest.approx(exact, rel=0.03)
    assert found["mean_shift_sd"]["I0"] < -0.5
    assert abs(found["mean_shift_sd"]["beta"]) < 0.1 and abs(found["mean_shift_sd"]["xi"]) < 0.1
    assert found["log_uniform_keys"] == ["I0"] and found["ess_importance"] < n


@pytest.mark.slow  # 11 s: a whole emulated posterior; the priors' forms and refusals run by default
def test_a_measured_key_enters_as_a_normal_prior(banana):
    """k0 measured elsewhere as 0 ± 0.2 (the data's posterior sd is 0.27): the emulated posterior
    sampled with that prior matches the quadrature of likelihood × prior, and records it."""
    objective, result, mean, sd, level = banana
    post = emulated_posterior(objective, result, rounds=1, checks=400, seed=0, prior={"k0": (0.0, 0.2)})
    exact_mean, exact_sd = level.under(lambda t0, t1: -0.5 * (t0 / 0.2) ** 2)
    assert post.ess_importance > 300 and post.prior == {"k0": (0.0, 0.2)}
    for j, key in enumerate(objective.keys):
        assert abs(post.mean[key] - exact_mean[j]) < 4 * exact_sd[j] / np.sqrt(post.ess_importance), key
        assert 0.85 < post.sd[key] / exact_sd[j] < 1.15, (key, post.sd[key], exact_sd[j])
    assert post.sd["k0"] < 0.85 * sd[0]
    assert post.to_json()["prior"] == {"k0": [0.0, 0.2]}


@pytest.mark.parametrize("prior, match", [({"k2": (0.0, 1.0)}, r"\['k2'\] not among the fitted keys"),
                                          ({"k0": (0.0, 0.0)}, "k0 must be a finite mean and sd > 0"),
                                          ({"k0": 0.3}, r"k0 must be \(mean, sd\)"),
                                          ({"k0": (float("nan"), 1.0)}, "k0 must be a finite mean"),
                                          ([("k0", 1.0)], "prior must be a mapping")])
def test_a_bad_prior_is_refused_before_any_run(banana, prior, match):
    from calibration.inference.mcmc import nuts_posterior

    objective, result, *_ = banana
    spy = Banana(objective.data)
    spy.column_task = lambda *a: pytest.fail("ran the model")
    with pytest.raises(ValueError, match=match):
        emulated_posterior(spy, result, prior=prior)
    with pytest.raises(ValueError, match=match):
        nuts_posterior(spy, result, prior=prior)


GRID_ERROR = np.array([0.8, -0.5, 0.3])  # the model's error per unit dx^2 (order 2), in residual units


class GriddedBanana(Banana):
    """The crescent with a grid: its model is off by GRID_ERROR dx² (dx = 0.25 here), and it can be
    rebuilt on a coarser grid, as an ``Objective`` can (``coarsened``)."""

    def __init__(self, data, dx=0.25):
        super().__init__(np.asarray(data, float) - GRID_ERROR * dx**2)
        self.true_data, self.dx = np.asarray(data, float), dx

    def coarsened(self, ratio):
        return GriddedBanana(self.true_data, ratio * self.dx)


def _quadrature_mean(data):
    T0, T1, _, p = _quadrature(data)
    return np.array([np.sum(p * T0), np.sum(p * T1)])


# 16 s (one level) and 33 s (two): a posterior sampled again on coarser grids; the refusals of a grid
# term that cannot be made stay in the default suite.
@pytest.mark.slow
@pytest.mark.parametrize("levels", [1, 2])
def test_the_grid_term_of_a_posterior_is_the_shift_of_its_mean_on_coarser_grids(banana, levels, tmp_path):
    """The same posterior on grids 1.5 and 2.25 times coarser: its grid term is the shift of the
    mean, which the quadratures of the three grids' posteriors give exactly; from two grids the
    index is Roache's with order 1 and safety factor 3, from three the order the grids show (the
    model's error is of order 2 in dx; on the crescent the mean's shifts, in its sds, show 1.5),
    and the interval with the grid term holds the data's interval and the index in quadrature."""
    from calibration.inference.gridcheck import three_grid_index

    objective = GriddedBanana(banana[0].data)
    post = emulated_posterior(objective, banana[1], rounds=1, checks=400, seed=0, grid_ratio=1.5, grid_levels=levels)
    exact = [_quadrature_mean(GriddedBanana(objective.true_data, objective.dx * 1.5**lv).data) for lv in range(3)]
    runs = [post.ess_importance] + [g["ess_importance"] for g in post.grid_posteriors]
    assert len(post.grid_posteriors) == levels and min(runs) > 300
    sd = np.array([post.sd[k] for k in objective.keys])
    for shift, lv in [(post.grid.shift, 1)] + ([(post.grid.shift2, 2)] if levels == 2 else []):
        se = sd * np.sqrt(1.0 / runs[0] + 1.0 / runs[lv])  # the two importance samples' Monte Carlo error
        assert np.all(np.abs(shift - (exact[lv] - exact[0])) < 4 * se), (lv, shift, exact[lv] - exact[0])
        assert np.max(np.abs(exact[lv] - exact[0]) / se) > 5  # the grid moves the posterior: a real test
    assert post.grid.dx == 0.25 and post.grid.dx_coarse == pytest.approx(0.375)
    if levels == 1:
        assert post.grid.halfwidth == pytest.approx(3.0 * np.abs(post.grid.shift) / 0.5)
    else:
        exact_order = three_grid_index(exact[1] - exact[0], exact[2] - exact[0], 1.5, sd)[1]
        assert exact_order is not None and 1.0 < exact_order <= 2.0  # the quadratures' order (1.5 in sds)
        halfwidth, order, _ = three_grid_index(post.grid.shift, post.grid.shift2, 1.5, sd)
        assert post.grid.halfwidth == pytest.approx(halfwidth) and post.grid.order == order
        assert order is not None and "three posteriors' means converging with observed order" in post.grid.method
    for j, k in enumerate(objective.keys):
        lo, hi = post.ci95[k]
        wlo, whi = post.ci95_with_grid[k]
        m, h = post.mean[k], post.grid.halfwidth[j]
        assert wlo == pytest.approx(max(m - np.hypot(m - lo, h), objective.bounds.lower[j]))
        assert whi == pytest.approx(min(m + np.hypot(hi - m, h), objective.bounds.upper[j]))
        assert post.grid_converged[k] == (h <= (hi - lo) / 2)
        p = post.grid.order or 1.0  # where the index, scaled as dx^p, meets the data's half-width
        assert post.adequate_dx[k] == pytest.approx(0.25 * min(((hi - lo) / 2 / h) ** (1 / p), 1.0))
    out = post.to_json()
    json.dumps(out, allow_nan=False)
    assert out["grid"]["shift"] == pytest.approx(dict(zip(objective.keys, post.grid.shift)))
    assert len(out["grid"]["posteriors"]) == levels and set(out["ci95_with_grid"]) == set(objective.keys)
    assert out["grid_statement"].startswith(("Not converged in the grid", "Converged in the grid"))
    if not all(post.grid_converged.values()):
        assert "finer for" in out["grid_statement"] and out["adequate_dx"] == post.adequate_dx
    if levels == 2 and importlib.util.find_spec("matplotlib"):
        from calibration.plots.posteriors import plot_grid_term

        assert plot_grid_term(post, tmp_path / "grid.png", truth={"k0": 0.5, "k1": 0.55}).stat().st_size > 0


def test_a_grid_term_that_cannot_be_made_is_refused_or_said(banana):
    """A bad ratio or level count is refused before any run; an objective with no coarser grid
    gets its posterior and the reason the grid term is missing."""
    objective, result, *_ = banana
    spy = GriddedBanana(objective.data)
    spy.column_task = lambda *a: pytest.fail("ran the model")
    for kwargs, match in (({"grid_ratio": 1.0}, "grid_ratio must be off"), ({"grid_ratio": 1.5, "grid_levels": 3},
                                                                            "grid_levels must be 1 or 2")):
        with pytest.raises(ValueError, match=match):
            emulated_posterior(spy, result, **kwargs)
    post = emulated_posterior(objective, result, rounds=0, checks=30, draws=100, warmup=50, grid_ratio=1.5)
    assert post.grid is None and post.grid_converged is None and "has no coarser grid" in post.grid_note
    assert post.to_json()["grid"] == {"measured": False, "why": post.grid_note}
    assert post.grid_statement.startswith("The grid's share was not measured")
    if importlib.util.find_spec("matplotlib"):
        from calibration.plots.posteriors import plot_grid_term

        with pytest.raises(ValueError, match="carries no grid term"):
            plot_grid_term(post, "unused.png")


def test_fit_checks_pass_the_grid_term_to_the_emulated_posterior(banana, monkeypatch):
    """``posterior_checks`` (what ``posterior --emulated`` runs, with ``--grid-check`` and
    ``--grid-levels``) asks the emulated posterior for its grid term and reports it."""
    from calibration.optim.report import PosteriorOptions, posterior_checks

    objective, result, *_ = banana
    seen = {}

    def spy(objective, centre, **kwargs):
        seen.update(kwargs)
        return types.SimpleNamespace(to_json=lambda: {"grid": {"ratio": kwargs["grid_ratio"]}})

    monkeypatch.setattr(emulator_module, "emulated_posterior", spy)
    checks = posterior_checks(objective, result, PosteriorOptions(emulated=30, grid_ratio=1.5, grid_levels=2))
    assert seen["grid_ratio"] == 1.5 and seen["grid_levels"] == 2 and seen["checks"] == 30
    assert checks.report["emulated_posterior"]["grid"] == {"ratio": 1.5}


def test_the_profile_and_grid_posterior_intervals_carry_the_fits_grid_term(banana, monkeypatch):
    """``posterior_checks`` adds the fit's own grid term (one Gauss–Newton step at ρ dx) to the
    profile likelihood's and the grid posterior's intervals, in quadrature on each side, inside
    the bounds; an end a profile does not reach stays open."""
    import calibration.inference.gridpost as gridpost_module
    import calibration.inference.likelihood as likelihood_module
    from calibration.inference.gridcheck import GridCheck
    from calibration.optim.report import PosteriorOptions, posterior_checks

    objective, result, *_ = banana
    keys = objective.keys
    term = GridCheck(0.01, 0.015, 2, np.array([0.1, -0.02]), np.array([0.6, 0.12]), 1.0)
    result = types.SimpleNamespace(keys=keys, theta=result.theta, uncertainty=types.SimpleNamespace(
        **vars(result.uncertainty), grid=term))
    scans = {"k0": (-1.2, None), "k1": (0.4, 0.7)}

    def profile(objective, result, key, n, noise):
        ci = scans[key]
        return types.SimpleNamespace(key=key, ci95=ci, theta_hat=result.theta[key],
                                     to_json=lambda: {"ci95_profile": list(ci)})

    post = types.SimpleNamespace(keys=keys, ci95={"k0": (-0.5, 1.9), "k1": (0.3, 0.8)},
                                 mean={"k0": 0.6, "k1": 0.55}, to_json=lambda: {})
    monkeypatch.setattr(likelihood_module, "profile_likelihood", profile)
    monkeypatch.setattr(gridpost_module, "grid_posterior", lambda *a, **kw: post)
    report = posterior_checks(objective, result, PosteriorOptions(profiles=3, posterior=3)).report
    t0, t1 = result.theta["k0"], result.theta["k1"]
    assert report["profile_likelihood"]["k0"]["ci95_profile_with_grid"] == pytest.approx(
        [t0 - np.hypot(t0 + 1.2, 0.6), None])
    assert report["profile_likelihood"]["k1"]["ci95_profile_with_grid"] == pytest.approx(
        [t1 - np.hypot(t1 - 0.4, 0.12), t1 + np.hypot(0.7 - t1, 0.12)])
    wide = report["posterior"]["ci95_with_grid"]
    assert wide["k0"] == pytest.approx([0.6 - np.hypot(1.1, 0.6), 2.0])  # the upper bound of k0's box
    assert wide["k1"] == pytest.approx([0.55 - np.hypot(0.25, 0.12), 0.55 + np.hypot(0.25, 0.12)])
    assert "grid term" in report["posterior"]["grid_term"]


def test_psis_is_arviz_stats_psislw_given_the_same_tail():
    """Our Pareto smoothing is the reference's (arviz-stats' ``psislw``, a port of the R package
    posterior) to round-off once the tails are equally long: arviz-stats floors 3√S where we take
    the ceiling, which its ``r_eff`` can undo."""
    array_stats = pytest.importorskip("arviz_stats.base").array_stats
    rng = np.random.default_rng(1)
    for S, s2 in ((200, 1.5), (1000, 1.5), (5000, 4.0)):
        lw = 0.5 * rng.standard_normal(S) ** 2 * (1 - 1 / s2)
        ours, k = psis(lw)
        tail = np.ceil(min(0.2 * S, 3 * np.sqrt(S)))
        theirs, k_ref = array_stats.psislw(-lw, r_eff=9 * S / tail**2 * (1 - 1e-12) if S > 225 else 1.0)
        assert k == pytest.approx(float(k_ref), abs=1e-12)
        np.testing.assert_allclose(ours, theirs - np.logaddexp.reduce(theirs), atol=1e-12)
