"""The NUTS posterior (calibration.inference.mcmc) on targets whose answer is known: a linear
Gaussian model (exact mean and covariance), a posterior cut off by a bound (a truncated normal:
the flat prior in θ sampled in logit coordinates needs the log-Jacobian right), and a tiny S4
twin (in tests/test_likelihood.py, which fits it once for every check beyond Gauss–Newton)."""

import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from calibration.inference.mcmc import McmcPosterior, nuts_posterior
from calibration.problem.bounds import Bounds


class LinearObjective:
    """r = (A θ − y) / σ-free rows: χ² = Σ (A θ − y)² / σ² with one block, no simulation."""

    def __init__(self, A, y, lower, upper):
        self.keys = tuple(f"k{i}" for i in range(A.shape[1]))
        self.bounds = Bounds(self.keys, tuple(lower), tuple(upper))
        self.blocks = {"profile": slice(0, A.shape[0])}
        self.row_scale = np.ones(A.shape[0])
        self.n_residuals = A.shape[0]
        self.dtype = jnp.float64
        self.A, self.y = jnp.asarray(A), jnp.asarray(y)

    def residual_fn(self, theta):
        return self.A @ theta - self.y, {"status": jnp.zeros((), jnp.int32)}

    def coarsened(self, ratio):
        raise NotImplementedError("a closed form has no grid")


def _fit_result(keys, theta, cov, sigma):
    unc = types.SimpleNamespace(cov=np.asarray(cov), stderr=np.sqrt(np.diag(cov)), withheld=False,
                                noise={"profile": sigma})
    return types.SimpleNamespace(keys=keys, theta=dict(zip(keys, np.asarray(theta, float))), uncertainty=unc)


@pytest.mark.slow  # 24 s; the bound-cut posterior and one chain of NUTS stay in the default suite
def test_nuts_recovers_a_gaussian_posterior_from_a_wrong_preconditioner():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((30, 2)) @ np.array([[1.0, 0.9], [0.0, 0.3]])  # correlated columns
    sigma = 0.05
    y = A @ np.array([0.4, 0.6]) + sigma * rng.standard_normal(30)
    objective = LinearObjective(A, y, lower=(-5.0, -5.0), upper=(5.0, 5.0))  # bounds far: ~ no truncation
    mean = np.linalg.solve(A.T @ A, A.T @ y)
    cov = sigma ** 2 * np.linalg.inv(A.T @ A)
    # The preconditioner is off by a factor 2 in scale and uncorrelated: NUTS must still find the target.
    wrong = _fit_result(objective.keys, mean + np.sqrt(np.diag(cov)), np.diag(4 * np.diag(cov)), sigma)
    post = nuts_posterior(objective, wrong, chains=4, warmup=150, draws=250, seed=1)
    assert isinstance(post, McmcPosterior) and post.draws.shape == (4, 250, 2)
    # Mixing: R̂ near 1 and a few hundred effective draws. (The reporting rule `converged`, R̂ <
    # 1.01, is not asserted: 250 draws per chain on this badly preconditioned target sit at its edge.)
    assert sum(post.divergences) == 0
    assert all(v < 1.03 for v in post.rhat.values()) and all(v > 150 for v in post.ess_bulk.values()), (
        post.rhat, post.ess_bulk)
    assert post.converged == (all(v < 1.01 for v in post.rhat.values()) and min(post.ess_bulk.values()) >= 100)
    sd = np.sqrt(np.diag(cov))
    for j, key in enumerate(objective.keys):
        mc_error = sd[j] / np.sqrt(post.ess_bulk[key])
        assert abs(post.mean[key] - mean[j]) < 5 * mc_error
        assert 0.85 < post.sd[key] / sd[j] < 1.15
    corr = np.corrcoef(post.flat().T)[0, 1]
    assert abs(corr - cov[0, 1] / (sd[0] * sd[1])) < 0.08
    out = post.to_json()
    json.dumps(out, allow_nan=False)  # JSON-clean
    assert out["converged"] == post.converged and set(out["rhat"]) == set(objective.keys)


@pytest.mark.slow  # 24 s; the linear-Gaussian posterior and the gradient checks stay in the default suite
def test_nuts_samples_a_posterior_cut_by_a_bound():
    """θ ∈ (0, 1), the likelihood N(0.05, 0.1²): the posterior is that normal truncated at 0, whose
    mean (0.115) is far from the likelihood's peak. Sampled in z = logit θ, only the log-Jacobian
    of the flat prior in θ gets it right."""
    sigma = 0.1
    objective = LinearObjective(np.ones((1, 1)), np.array([0.05]), lower=(0.0,), upper=(1.0,))
    result = _fit_result(objective.keys, [0.1], [[sigma ** 2]], sigma)
    post = nuts_posterior(objective, result, chains=4, warmup=150, draws=250, seed=1)
    truth = stats.truncnorm(-0.05 / sigma, 0.95 / sigma, loc=0.05, scale=sigma)
    draws = post.flat()[:, 0]
    assert np.all((draws > 0) & (draws < 1))
    assert abs(post.mean["k0"] - truth.mean()) < 5 * truth.std() / np.sqrt(post.ess_bulk["k0"])
    assert 0.85 < post.sd["k0"] / truth.std() < 1.15
    assert stats.kstest(draws[::4], truth.cdf).pvalue > 1e-3  # thinned: draws are nearly independent


def test_nuts_refuses_bad_input_before_sampling():
    objective = LinearObjective(np.ones((2, 1)), np.zeros(2), lower=(0.0,), upper=(1.0,))
    good = _fit_result(objective.keys, [0.5], [[0.01]], 0.1)
    with pytest.raises(ValueError, match="draws must be an integer >= 4"):
        nuts_posterior(objective, good, draws=2)
    with pytest.raises(ValueError, match="target_accept must lie in"):
        nuts_posterior(objective, good, target_accept=1.0)
    withheld = _fit_result(objective.keys, [0.5], [[0.01]], 0.1)
    withheld.uncertainty.withheld = True
    with pytest.raises(ValueError, match="no Gauss-Newton covariance"):
        nuts_posterior(objective, withheld)
    at_bound = _fit_result(objective.keys, [1.0], [[0.01]], 0.1)
    with pytest.raises(ValueError, match="not strictly inside the bounds"):
        nuts_posterior(objective, at_bound)


def test_log_density_gradient_matches_finite_differences():
    """The forward-mode custom VJP of χ² (k Jacobian columns, not reverse mode) against central
    differences in float64, inside the bounds and near one (where the log-Jacobian is steep),
    on a nonlinear residual; a failed run gives −∞ and a finite gradient (χ²'s part zero), never NaN."""
    from calibration.inference.nuts import log_density_fn

    class Curved(LinearObjective):
        def residual_fn(self, theta):
            r = jnp.stack([theta[0] ** 2 - 0.2, jnp.sin(3 * theta[1]) - theta[0], theta[0] * theta[1] - 0.1])
            status = jnp.where(theta[1] > 0.95, 1, 0).astype(jnp.int32)  # "the run failed" up there
            return r, {"status": status}

    objective = Curved(np.ones((3, 2)), np.zeros(3), lower=(0.0, 0.0), upper=(1.0, 1.0))
    weights = jnp.asarray([4.0, 1.0, 9.0])
    z_hat = jnp.asarray([0.3, -0.2])
    L = jnp.asarray([[0.8, 0.0], [0.3, 0.5]])
    log_density, _ = log_density_fn(objective, weights, z_hat, L, jnp.zeros(2), jnp.ones(2))
    grad = jax.jit(jax.grad(log_density))
    for w in ([0.1, -0.4], [2.5, -3.0], [-1.0, 1.5]):
        w = jnp.asarray(w)
        g = np.asarray(grad(w))
        h = 1e-6
        fd = [(float(log_density(w.at[i].add(h))) - float(log_density(w.at[i].add(-h)))) / (2 * h) for i in range(2)]
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
    failed = jnp.asarray([0.0, 8.0])  # θ1 ≈ 1: status set
    assert float(log_density(failed)) == -np.inf
    g_failed = np.asarray(grad(failed))
    s = 1 / (1 + np.exp(-np.asarray(z_hat + L @ failed)))
    np.testing.assert_allclose(g_failed, np.asarray(L).T @ (1 - 2 * s), rtol=1e-10)  # the log-Jacobian's alone


@pytest.mark.slow  # 16 s; the custom-VJP gradient with a failed run stays in the default suite
def test_one_chain_prints_no_nan():
    """R-hat needs two chains: with one it is null in the JSON, never NaN, and not converged."""
    objective = LinearObjective(np.ones((2, 1)), np.full(2, 0.5), lower=(0.0,), upper=(1.0,))
    post = nuts_posterior(objective, _fit_result(objective.keys, [0.5], [[0.01]], 0.1), chains=1, warmup=5, draws=8)
    out = post.to_json()
    assert out["rhat"] == {"k0": None} and not out["converged"]
    json.dumps(out, allow_nan=False)


def _record(objective, result, draws, step_size=1.0):
    """A stored posterior (``to_json`` form) whose chains end at ``draws`` (chains, n, k)."""
    from calibration.inference.likelihood import noise_levels
    keys = objective.keys
    by_key = {key: 0.0 for key in keys}
    chains, n = draws.shape[:2]
    return {"keys": list(keys), "chains": chains, "warmup": 5, "draws_per_chain": n, "seed": 3,
            "mean": by_key, "sd": by_key, "ci95": {key: [0.0, 0.0] for key in keys}, "rhat": by_key,
            "ess_bulk": by_key, "ess_tail": by_key, "theta_hat": dict(result.theta),
            "gauss_newton_stderr": dict(zip(keys, result.uncertainty.stderr.tolist())),
            "gauss_newton_cov": np.asarray(result.uncertainty.cov).tolist(),
            "step_size": [step_size] * chains, "divergences": [0] * chains, "acceptance": [0.9] * chains,
            "leapfrog_steps_per_draw": [3.0] * chains, "gradient_evaluations": 3 * chains * n,
            "noise": noise_levels(objective, result, None), "wall_s": 1.0,
            "draws": {key: draws[..., j].tolist() for j, key in enumerate(keys)}, "log_density": None}


@pytest.mark.slow  # 26 s; the refusal to resume another fit stays in the default suite
def test_resumed_chains_go_on_from_their_last_draws():
    """``resume=`` extends stored chains: the stored draws are kept bit for bit, the new ones
    follow from each chain's last draw with its step size (no warm-up), every diagnostic is that
    of the whole chains, and the segments are recorded. The record passes through JSON."""
    sigma = 0.1
    objective = LinearObjective(np.ones((1, 1)), np.array([0.5]), lower=(0.0,), upper=(1.0,))
    result = _fit_result(objective.keys, [0.5], [[sigma ** 2]], sigma)
    old = np.array([[0.45, 0.52, 0.61], [0.55, 0.38, 0.49]])[..., None]  # 2 chains, 3 draws
    record = json.loads(json.dumps(_record(objective, result, old)))
    stored = McmcPosterior.from_json(record)
    assert stored.segments == ((3, 3),) and stored.gn_cov.shape == (1, 1)
    post = nuts_posterior(objective, result, draws=40, resume=stored, seed=3)
    assert post.draws.shape == (2, 43, 1) and post.segments == ((3, 3), (3, 40))
    np.testing.assert_array_equal(post.draws[:, :3], old)
    assert post.step_size == (1.0, 1.0) and post.warmup == 5
    assert post.gradient_evaluations > record["gradient_evaluations"] + 2 * 40
    assert np.all(np.isnan(post.log_density[:, :3])) and np.all(np.isfinite(post.log_density[:, 3:]))
    flat = post.flat()[:, 0]
    assert post.mean["k0"] == pytest.approx(flat.mean()) and post.sd["k0"] == pytest.approx(flat.std(ddof=1))
    assert abs(post.mean["k0"] - 0.5) < 0.06 and 0.05 < post.sd["k0"] < 0.2  # N(0.5, 0.1²), 86 draws
    # the first new draw is one NUTS step from the last stored one: near it, on the target's scale
    assert np.all(np.abs(post.draws[:, 3, 0] - old[:, -1, 0]) < 0.5)
    again = McmcPosterior.from_json(json.loads(json.dumps(post.to_json(), allow_nan=False)))
    np.testing.assert_array_equal(again.draws, post.draws)
    assert again.segments == post.segments and again.rhat == pytest.approx(post.rhat)
    # a chain resumed apart (another process, say) draws what it draws beside the others, and the
    # parts join into the whole
    apart = nuts_posterior(objective, result, draws=40, resume=stored.take([1]), seed=3)
    assert apart.chain_ids == (1,) and apart.step_size == (1.0,)
    np.testing.assert_array_equal(apart.draws[0], post.draws[1])
    joined = McmcPosterior.join([apart, post.take([0])])
    np.testing.assert_array_equal(joined.draws, post.draws)
    assert joined.chain_ids == (0, 1) and joined.rhat == pytest.approx(post.rhat)
    assert joined.ess_bulk == pytest.approx(post.ess_bulk) and joined.divergences == post.divergences
    with pytest.raises(ValueError, match="a chain is in more than one part"):
        McmcPosterior.join([apart, post.take([1])])
    with pytest.raises(ValueError, match="chains must be distinct positions"):
        post.take([0, 0])
    short = stored.take([0]).to_json()  # three draws: no ESS, null in the JSON
    assert short["ess_bulk"] == {"k0": None} and short["rhat"] == {"k0": None}
    json.dumps(short, allow_nan=False)


def test_resume_refuses_another_fit_before_sampling():
    sigma = 0.1
    objective = LinearObjective(np.ones((1, 1)), np.array([0.5]), lower=(0.0,), upper=(1.0,))
    result = _fit_result(objective.keys, [0.5], [[sigma ** 2]], sigma)
    stored = McmcPosterior.from_json(_record(objective, result, np.full((2, 3, 1), 0.5)))
    with pytest.raises(ValueError, match="warmup: a resumed chain"):
        nuts_posterior(objective, result, resume=stored, warmup=10)
    with pytest.raises(ValueError, match="chains: resume holds 2 chains"):
        nuts_posterior(objective, result, resume=stored, chains=4)
    moved = _fit_result(objective.keys, [0.51], [[sigma ** 2]], sigma)
    with pytest.raises(ValueError, match="the fit's point differs"):
        nuts_posterior(objective, moved, resume=stored)
    wider = _fit_result(objective.keys, [0.5], [[4 * sigma ** 2]], sigma)
    with pytest.raises(ValueError, match="standard errors differs"):
        nuts_posterior(objective, wider, resume=stored)
    with pytest.raises(ValueError, match="the noise differs"):
        nuts_posterior(objective, result, resume=stored, noise=0.2)
    with pytest.raises(ValueError, match="resume must be a McmcPosterior"):
        nuts_posterior(objective, result, resume={"draws": []})
    other = LinearObjective(np.ones((1, 2)), np.array([0.5]), lower=(0.0, 0.0), upper=(1.0, 1.0))
    two = _fit_result(other.keys, [0.5, 0.5], np.eye(2) * sigma ** 2, sigma)
    with pytest.raises(ValueError, match="resume samples"):
        nuts_posterior(other, two, resume=stored)
    # the prior is part of the target: a chain goes on only with the one it was drawn with
    with pytest.raises(ValueError, match=r"drawn with the flat prior, got \{'k0': \(0.5, 0.2\)\}"):
        nuts_posterior(objective, result, resume=stored, prior={"k0": (0.5, 0.2)})
    with_prior = McmcPosterior.from_json({**_record(objective, result, np.full((2, 3, 1), 0.5)),
                                          "normal_prior": {"k0": [0.5, 0.2]}})
    assert with_prior.prior == {"k0": (0.5, 0.2)}
    record = with_prior.to_json()
    assert record["normal_prior"] == {"k0": [0.5, 0.2]} and record["prior"].endswith("a normal in θ for k0")
    assert McmcPosterior.from_json(json.loads(json.dumps(record))).prior == with_prior.prior
    assert stored.to_json()["normal_prior"] is None and stored.to_json()["prior"] == "flat inside the bounds"
    for prior in (None, {"k0": (0.5, 0.3)}):
        with pytest.raises(ValueError, match=r"drawn with \{'k0': \(0.5, 0.2\)\}"):
            nuts_posterior(objective, result, resume=with_prior, prior=prior)
    with pytest.raises(ValueError, match="every part must sample the same"):
        McmcPosterior.join([with_prior.take([0]), stored.take([1])])


def test_whitening_round_trips():
    """``whitened`` inverts the chains' map θ = physical(ẑ + L w), near the bounds too."""
    from calibration.inference.nuts import whitened
    from calibration.problem.bounds import physical as to_physical

    rng = np.random.default_rng(0)
    lower, upper = np.array([0.0, 0.1]), np.array([1.0, 0.9])
    z_hat, L = np.array([0.3, -1.0]), np.array([[0.7, 0.0], [0.4, 0.2]])
    w = rng.standard_normal((50, 2)) * 3
    theta = np.asarray(jax.vmap(lambda v: to_physical(jnp.asarray(z_hat) + jnp.asarray(L) @ v, jnp.asarray(lower),
                                                      jnp.asarray(upper)))(jnp.asarray(w)))
    np.testing.assert_allclose(whitened(theta, z_hat, L, lower, upper), w, rtol=1e-7, atol=1e-7)


class GriddedLinear(LinearObjective):
    """θ measured directly (one row) by a model off by 0.2 dx: the posterior N(y − 0.2 dx, σ²)
    moves by −0.1 dx on a grid 1.5 times coarser; ``coarsened`` rebuilds it, as for an ``Objective``."""

    def __init__(self, y, dx):
        super().__init__(np.ones((1, 1)), np.array([y - 0.2 * dx]), lower=(-5.0,), upper=(5.0,))
        self.true_y, self.dx = y, dx

    def coarsened(self, ratio):
        return GriddedLinear(self.true_y, ratio * self.dx)


# 19 s; the posterior's grid term is checked in this slow set (tests/test_emulator.py too); its refusals
# before any run stay in the default suite.
@pytest.mark.slow
def test_the_nuts_posterior_carries_its_grid_term():
    """The same chains on a grid 1.5 times coarser: the mean moves by the exact −0.1 dx (here 2 σ)
    within the two chains' Monte Carlo error, the index is 3 |shift| / 0.5, and the interval with
    the grid term holds both; refused with ``resume``, said where the objective has no coarser grid."""
    sigma, dx = 0.05, 1.0
    objective = GriddedLinear(0.5, dx)
    result = _fit_result(objective.keys, [0.3], [[sigma ** 2]], sigma)
    post = nuts_posterior(objective, result, chains=2, warmup=60, draws=150, seed=2, grid_ratio=1.5)
    (coarse,) = post.grid_posteriors
    se = sigma * np.sqrt(1 / post.ess_bulk["k0"] + 1 / 100)  # the coarse run's ESS is of the same size
    assert abs(post.grid.shift[0] - (-0.1 * dx)) < 4 * se, (post.grid.shift, se)
    assert post.grid.halfwidth[0] == pytest.approx(6 * abs(post.grid.shift[0]))
    assert coarse["dx"] == 1.5 and coarse["divergences"] == 0 and coarse["gradient_evaluations"] > 0
    lo, hi = post.ci95["k0"]
    m, h = post.mean["k0"], post.grid.halfwidth[0]
    assert post.ci95_with_grid["k0"] == pytest.approx((m - np.hypot(m - lo, h), m + np.hypot(hi - m, h)))
    assert post.grid_converged == {"k0": False} and "Not converged in the grid" in post.grid_statement
    record = post.to_json()
    json.dumps(record, allow_nan=False)
    assert record["grid"]["posteriors"][0]["dx"] == 1.5 and record["grid_converged"] == {"k0": False}
    assert post.take([0]).grid is None and "grid" not in post.take([0]).to_json()
    with pytest.raises(ValueError, match="grid_ratio: the grid term samples fresh chains"):
        nuts_posterior(objective, result, draws=10, resume=post, grid_ratio=1.5)
    with pytest.raises(ValueError, match="grid_ratio must be off"):
        nuts_posterior(objective, result, grid_ratio=0.5)
    plain = LinearObjective(np.ones((1, 1)), np.array([0.3]), lower=(-5.0,), upper=(5.0,))
    bare = nuts_posterior(plain, result, chains=2, warmup=20, draws=20, seed=2, grid_ratio=1.5)
    assert bare.grid is None and "has no coarser grid" in bare.to_json()["grid"]["why"]


def test_the_diagnostics_read_chains_whose_answers_are_known():
    """R̂ and the bulk and tail ESS (arviz-stats', through ``_summary``) of 4 chains × 1000 draws:
    independent draws give R̂ ≈ 1 and ESS ≈ 4000; an AR(1) chain with φ = 0.9 keeps about
    n (1 − φ)/(1 + φ) ≈ 210 of them; one chain shifted by a standard deviation is not mixed (R̂ >
    1.05). One chain has no R̂; three draws a chain, no diagnostic at all."""
    from calibration.inference.mcmc import _summary

    rng = np.random.default_rng(0)
    iid = rng.standard_normal((4, 1000))
    ar = np.zeros((4, 1000))
    for t, e in enumerate(rng.standard_normal((999, 4)), start=1):
        ar[:, t] = 0.9 * ar[:, t - 1] + e
    shifted = iid + np.array([1.0, 0.0, 0.0, 0.0])[:, None]
    *_, rhat, bulk, tail = _summary(("iid", "ar", "shifted"), np.stack([iid, ar, shifted], axis=-1))
    assert abs(rhat["iid"] - 1) < 0.01 and bulk["iid"] == pytest.approx(4000, rel=0.15)
    assert tail["iid"] == pytest.approx(4000, rel=0.15)
    assert bulk["ar"] == pytest.approx(4000 * 0.1 / 1.9, rel=0.3) and rhat["ar"] < 1.05
    assert rhat["shifted"] > 1.05
    one = _summary(("x",), iid[:1, :, None])
    assert np.isnan(one[3]["x"]) and one[4]["x"] == pytest.approx(1000, rel=0.2)
    assert all(np.isnan(d["x"]) for d in _summary(("x",), iid[:, :3, None])[3:])
