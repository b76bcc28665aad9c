"""Calibration: bounds, objective, gradients against finite differences, LM/Adam fits, resume,
uncertainty. Tiny S4 scenes (dx = L/6, 144 particles) keep each run well under a second."""

import json
import os
import signal
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ROOT, S4_DATA, TINY_FLAGS, model_data, tiny_s4

from calibration import (
    Bounds,
    CompositeObjective,
    FrontTarget,
    Objective,
    ProfileTarget,
    fit,
    gauss_newton_uncertainty,
    read_history,
)
from jaxmpm.observables import deposit_profile, front_from_profile

KEYS = ("beta", "mu1")
#: Where the model's own data observe the tiny scene: the final profile and the front.
XS, TIMES = np.linspace(0.0, 0.16, 17), (0.05, 0.1)


@pytest.fixture(scope="module")
def problem():
    scene = tiny_s4()
    truth = np.array([0.25, float(scene.params.mu1)])
    profile, front = model_data(scene, KEYS, truth, XS, TIMES)
    return scene, truth, Objective(scene, KEYS, profile=profile, front=front)


# ---- bounds ------------------------------------------------------------------------------

def test_the_bounds_map_is_written_once():
    """``Bounds``' methods, the model functions' ``physical`` on arrays and the posterior's log
    Jacobian are one map: θ ↔ z round-trips, dθ/dz is the derivative, log |dθ/dz| its sum."""
    from calibration.problem.bounds import dphysical_dz, log_jacobian, physical, unconstrained

    b = Bounds.create(("beta", "mu1", "xi"))
    lo, hi = np.asarray(b.lower), np.asarray(b.upper)
    theta = np.array([0.25, 0.38, 50.0])
    z = unconstrained(theta, lo, hi)
    np.testing.assert_array_equal(z, b.to_unconstrained(theta))
    np.testing.assert_allclose(np.asarray(physical(jnp.asarray(z), lo, hi)), theta, rtol=1e-12)
    d = np.asarray(jax.vmap(jax.grad(physical))(jnp.asarray(z), lo, hi))
    np.testing.assert_allclose(np.asarray(dphysical_dz(jnp.asarray(z), lo, hi)), d, rtol=1e-12)
    np.testing.assert_allclose(float(log_jacobian(jnp.asarray(z), lo, hi)), np.sum(np.log(d)), rtol=1e-12)
    assert float(b.log_jacobian(jnp.asarray(z))) == float(log_jacobian(jnp.asarray(z), lo, hi))


def test_bounds_round_trip_and_stay_inside():
    b = Bounds.create(("beta", "mu1", "xi"))
    theta = np.array([0.25, 0.38, 50.0])
    np.testing.assert_allclose(np.asarray(b.to_physical(jnp.asarray(b.to_unconstrained(theta)))), theta, rtol=1e-12)
    z = jnp.array([-40.0, 0.0, 40.0])
    th = np.asarray(b.to_physical(z))
    assert np.all(th >= np.asarray(b.lower)) and np.all(th <= np.asarray(b.upper))
    jac = jax.jacfwd(b.to_physical)(jnp.asarray(b.to_unconstrained(theta)))
    np.testing.assert_allclose(np.diag(np.asarray(jac)),
                               np.asarray(b.jacobian_diag(jnp.asarray(b.to_unconstrained(theta)))), rtol=1e-12)


@pytest.mark.parametrize("keys, overrides, match", [
    ((), None, "at least one"),
    (("beta", "beta"), None, "repeated"),
    (("nope",), None, "no bounds known"),
    (("beta",), {"beta": (1.0, 0.0)}, "lo < hi"),
])
def test_bounds_reject_bad_input(keys, overrides, match):
    with pytest.raises(ValueError, match=match):
        Bounds.create(keys, overrides)


def test_init_outside_bounds_is_an_error_naming_the_key(problem):
    _, _, objective = problem
    with pytest.raises(ValueError, match="init: beta"):
        fit(objective, {"beta": 1.5}, steps=1)
    with pytest.raises(ValueError, match="not fitted keys"):
        fit(objective, {"xi": 3.0}, steps=1)


# ---- objective -----------------------------------------------------------------------------

def test_objective_rejects_bad_input():
    scene = tiny_s4()
    xs = np.linspace(0, 0.1, 5)
    with pytest.raises(ValueError, match="nothing to fit"):
        Objective(scene, KEYS)
    with pytest.raises(ValueError, match="keys: unknown"):
        Objective(scene, ("friction",), profile=ProfileTarget(xs, xs))
    with pytest.raises(ValueError, match="time_s"):
        Objective(scene, KEYS, profile=ProfileTarget(xs, xs, time_s=0.5))
    with pytest.raises(ValueError, match="finite"):
        Objective(scene, KEYS, profile=ProfileTarget(xs, xs * np.nan))
    with pytest.raises(ValueError, match="front.t must lie"):
        Objective(scene, KEYS, front=FrontTarget(np.array([0.05, 0.2]), np.array([0.1, 0.1])))
    with pytest.raises(ValueError, match="weights"):
        Objective(scene, KEYS, profile=ProfileTarget(xs, xs), weights={"profile": -1.0})


# 28 s (the reverse-mode compilation); reverse equals forward mode by default
# (test_reverse_mode_gradient_equals_forward_mode)
@pytest.mark.slow
def test_exact_data_give_zero_residual_and_finite_gradient(problem):
    _, truth, objective = problem
    r, pred = objective.residuals(truth)
    assert int(pred["status"]) == 0
    np.testing.assert_array_equal(np.asarray(r), 0.0)
    (loss, _), g = objective.value_and_grad(truth)
    assert float(loss) == 0.0
    assert np.all(np.isfinite(np.asarray(g)))  # the square has a zero, finite derivative at zero


@pytest.mark.slow  # 13 s; the finite-difference Jacobian option is tested by default
def test_jacobian_matches_central_differences(problem):
    """Forward-mode residual Jacobian through the whole rollout against float64 central
    differences, at a point away from the data (so the residuals are not zero).

    The run is piecewise smooth in θ: a particle that switches between elastic and plastic
    steps makes a kink (the return map itself is continuous, with no tip rule since docs/model.md §2
    was corrected), so the differences use steps of 1e-7 and 3e-8, which must agree with each
    other and with autodiff."""
    _, truth, objective = problem
    theta = truth * np.array([0.9, 1.05])
    r, J, _ = objective.residuals_and_jacobian(theta)
    J = np.asarray(J)
    assert np.all(np.isfinite(J))
    for j in range(len(theta)):
        for rel in (1e-7, 3e-8):
            h = rel * abs(theta[j])
            e = np.zeros_like(theta)
            e[j] = h
            fd = (np.asarray(objective.residuals(theta + e)[0])
                  - np.asarray(objective.residuals(theta - e)[0])) / (2 * h)
            scale = np.max(np.abs(fd))
            assert scale > 0, "the data must depend on every fitted parameter"
            np.testing.assert_allclose(J[:, j], fd, atol=1e-5 * scale, rtol=0)


@pytest.mark.slow  # 12 s; the forward-mode Jacobian against differences stays in the default suite
def test_finite_difference_jacobian_option(problem):
    """``jacobian="fd"``: one vmapped batch of 2n + 1 runs; with a tiny step it is the autodiff
    Jacobian (on one branch of the run, see above); ``check_jacobian`` reports the match."""
    scene, truth, objective = problem
    fd = Objective(scene, KEYS, profile=objective.profiles[0], front=objective.front, jacobian="fd", fd_step=1e-7)
    theta = truth * np.array([0.9, 1.05])
    r_fd, J_fd, pred = fd.residuals_and_jacobian(theta)
    r_ad, J_ad, _ = objective.residuals_and_jacobian(theta)
    assert J_fd.shape == J_ad.shape == (objective.n_residuals, 2) and int(pred["status"]) == 0
    np.testing.assert_allclose(np.asarray(r_fd), np.asarray(r_ad), rtol=1e-12, atol=1e-15)  # vmap: last bits
    check = fd.check_jacobian(theta)
    assert max(check["rel_diff"].values()) < 1e-5, check["rel_diff"]
    with pytest.raises(ValueError, match="jacobian must be"):
        Objective(scene, KEYS, front=objective.front, jacobian="cd")


# 37 s: compiles the reverse-mode gradient of a whole run; reverse mode through the engine is
# checked against finite differences in the default suite (test_gradients, test_column).
@pytest.mark.slow
def test_reverse_mode_gradient_equals_forward_mode(problem):
    _, truth, objective = problem
    theta = truth * np.array([1.1, 0.95])
    r, J, _ = objective.residuals_and_jacobian(theta)
    (loss, _), g = objective.value_and_grad(theta)
    np.testing.assert_allclose(float(loss), float(np.sum(np.asarray(r) ** 2)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(g), 2 * np.asarray(J).T @ np.asarray(r), rtol=1e-8)


def test_front_from_profile_and_empty_profile_gradients():
    xs = jnp.linspace(0.0, 1.0, 201)
    h = jnp.where(xs < 0.4, 0.1, 0.0)
    assert abs(float(front_from_profile(xs, h, 0.01)) - 0.4) < 0.01
    # A profile sampled far from every particle is exactly zero there; its gradient is finite.
    x = jnp.array([[0.1, 0.05], [0.12, 0.02]])
    vol = jnp.array([1e-4, 1e-4])

    def far(x):
        h = deposit_profile(x, vol, jnp.linspace(5.0, 6.0, 11), 0.005)
        return jnp.sum(h**2) + front_from_profile(jnp.linspace(5.0, 6.0, 11), h, 0.01, x_ref=5.0)

    g = jax.grad(far)(x)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.slow  # 18 s
def test_several_profiles_and_composite_objective(problem):
    """Two profiles at two times in one objective; objectives that observe the same run the same
    way share one compilation whatever their data; a composite's loss is its members' sum."""
    scene, truth, _ = problem
    xs = np.linspace(0.0, 0.16, 9)
    gen = Objective(scene, KEYS,
                    profile=[ProfileTarget(xs, np.ones_like(xs), 0.05), ProfileTarget(xs, np.ones_like(xs))],
                    check_data=False)  # placeholders
    _, pred = gen.residuals(truth)
    h = np.asarray(pred["h"])
    early, late = ProfileTarget(xs, h[:9], 0.05), ProfileTarget(xs, h[9:])
    both = Objective(scene, KEYS, profile=[early, late])
    assert both.functions is gen.functions and both.observations == gen.observations
    r, _ = both.residuals(truth)
    np.testing.assert_array_equal(np.asarray(r), 0.0)
    assert set(both.blocks) == {"profile[0]", "profile[1]"}
    np.testing.assert_array_equal(np.asarray(both.predict(truth)["h"]), h)  # the prediction needs no data
    other = Objective(scene, KEYS, profile=[early, ProfileTarget(xs, 1.1 * h[9:])])
    comp = CompositeObjective([both, other])
    r, J, pred = comp.residuals_and_jacobian(truth * 1.1)
    assert r.shape == (36,) and J.shape == (36, 2) and int(pred["status"]) == 0
    assert comp.loss(truth * 1.1) == pytest.approx(both.loss(truth * 1.1) + other.loss(truth * 1.1))
    assert other.loss(truth) > 0 and both.loss(truth) == 0.0  # same compiled run, each its own data


def test_row_weighting_weighs_every_point_alike(problem):
    """weighting="block" gives the profile (17 points) and the front (2 times) their weight in
    total; "row" gives it to every point, so the loss is the plain sum of squared relative
    residuals (the noise-weighted fit for equal relative noise)."""
    scene, truth, objective = problem
    rows = Objective(scene, KEYS, profile=objective.profiles[0], front=objective.front, weighting="row")
    np.testing.assert_array_equal(rows.row_scale, 1.0)
    n_prof = objective.blocks["profile"].stop - objective.blocks["profile"].start
    np.testing.assert_allclose(objective.row_scale[objective.blocks["profile"]], np.sqrt(1 / n_prof))
    theta = truth * np.array([1.2, 0.95])
    r_block, _ = objective.residuals(theta)
    r_row, _ = rows.residuals(theta)
    np.testing.assert_allclose(np.asarray(r_row), np.asarray(r_block) / objective.row_scale, rtol=1e-12)
    assert rows.fingerprint()["weighting"] == "row" and "weighting" not in objective.fingerprint()
    assert rows.at_dx(rows.dx * 1.5).weighting == "row"
    with pytest.raises(ValueError, match="weighting must be one of"):
        Objective(scene, KEYS, profile=objective.profiles[0], weighting="points")


@pytest.fixture(scope="module")
def sharing():
    """Two experiments of one scene at β 0.25 and 0.35 sharing μ1: (composite, a, b, μ1)."""
    scene = tiny_s4()
    mu1 = float(scene.params.mu1)
    members = []
    for beta in (0.25, 0.35):
        profile, front = model_data(scene, KEYS, np.array([beta, mu1]), XS, TIMES)
        members.append(Objective(scene, KEYS, profile=profile, front=front))
    return CompositeObjective.sharing(members, shared=("mu1",), labels=("A", "B")), *members, mu1


def test_composite_with_keys_per_experiment(sharing):
    """``CompositeObjective.sharing``: μ1 one value, β each experiment's own (``beta@label``).
    Residuals, Jacobian and gradient are the members' own at their slices of θ, scattered into
    the composite's columns (zero where a member does not fit a key); the gradient is checked in
    the slow set (test_composite_gradient_is_its_members)."""
    comp, a, b, mu1 = sharing
    assert comp.keys == ("mu1", "beta@A", "beta@B")
    assert comp.initial() == {"mu1": mu1, "beta@A": 0.25, "beta@B": 0.25}
    assert comp.expand({"beta": 0.2, "mu1": 0.4}) == {"beta@A": 0.2, "beta@B": 0.2, "mu1": 0.4}
    theta = np.array([0.9 * mu1, 0.22, 0.31])
    r, J, _ = comp.residuals_and_jacobian(theta)
    ra, Ja, _ = a.residuals_and_jacobian(theta[[1, 0]])
    rb, Jb, _ = b.residuals_and_jacobian(theta[[2, 0]])
    na = a.n_residuals
    np.testing.assert_allclose(np.asarray(r), np.concatenate([ra, rb]), rtol=1e-12)
    J = np.asarray(J)
    np.testing.assert_allclose(J[:na, [1, 0]], Ja, rtol=1e-12)
    np.testing.assert_allclose(J[na:, [2, 0]], Jb, rtol=1e-12)
    assert np.all(J[:na, 2] == 0) and np.all(J[na:, 1] == 0)
    with pytest.raises(ValueError, match="shared: \\['xi'\\] are not fitted by members\\[0\\]"):
        CompositeObjective.sharing([a, b], shared=("xi",), labels=("A", "B"))
    with pytest.raises(ValueError, match="one distinct, non-empty label per member"):
        CompositeObjective.sharing([a, b], shared=("mu1",), labels=("A", "A"))


# 35 s: compiles the reverse-mode gradient of both members' runs (as the test of one objective's).
@pytest.mark.slow
def test_composite_gradient_is_its_members(sharing):
    """A composite's loss is its members' sum and its reverse-mode gradient is 2 Jᵀ r."""
    comp, a, b, mu1 = sharing
    theta = np.array([0.9 * mu1, 0.22, 0.31])
    r, J, _ = comp.residuals_and_jacobian(theta)
    (loss, _), grad = comp.value_and_grad(theta)
    assert float(loss) == pytest.approx(a.loss(theta[[1, 0]]) + b.loss(theta[[2, 0]]), rel=1e-10)
    np.testing.assert_allclose(np.asarray(grad), 2 * np.asarray(J).T @ np.asarray(r), rtol=1e-6, atol=1e-12)


@pytest.mark.slow  # 60-100 s: two worker processes compile, then a fit of three keys
def test_composite_with_keys_per_experiment_fits_and_spreads_columns(sharing):
    """The workers' column tasks, scattered, are the traced Jacobian; a fit finds each
    experiment's β and the shared μ1."""
    from calibration.batch.workers import Workers, jacobians_z

    comp, _, _, mu1 = sharing
    z = np.asarray(comp.bounds.to_unconstrained(np.array([0.9 * mu1, 0.22, 0.31])))
    with Workers(2) as workers:
        Jz_tasks = jacobians_z(comp, z[None], workers)[1][0]
    _, Jz, _, _ = comp.residuals_and_jacobian_z(z)
    np.testing.assert_allclose(np.asarray(Jz_tasks), np.asarray(Jz), rtol=1e-10, atol=1e-14)
    result = fit(comp, {"beta@A": 0.2, "beta@B": 0.3, "mu1": mu1}, steps=20, uncertainty=False)
    np.testing.assert_allclose([result.theta["beta@A"], result.theta["beta@B"], result.theta["mu1"]],
                               [0.25, 0.35, mu1], rtol=2e-2)


# ---- fitting ---------------------------------------------------------------------------

@pytest.mark.slow  # 25 s: LM's iterations run by default in test_interrupted_fit_resumes_without_losing_iterations,
# its steps and stops on the library's problems in tests/test_lm.py, the documented fit in tests/test_calibration_cli.py
def test_lm_recovers_the_truth(problem):
    _, truth, objective = problem
    result = fit(objective, {"beta": 0.18, "mu1": 0.45}, method="lm", steps=30)
    got = np.array([result.theta[k] for k in KEYS])
    # The issue asks for 2 %. On this very coarse grid (144 particles) the tension-tip branch
    # switches of docs/model.md §2 leave jumps of ~1e-9 in the loss near the truth, which the
    # Jacobian cannot see: LM stops 3e-3 from the truth (1e-4 on the S4 twin at 256 particles).
    np.testing.assert_allclose(got, truth, rtol=1e-2)
    assert result.loss < 1e-4 * result.history["loss"][0]
    assert result.uncertainty is not None and result.uncertainty.stderr.shape == (2,)
    assert np.all(result.history["status"] == 0)


@pytest.mark.slow  # 20-28 s; Adam's iterations stay in test_interrupted_fit_resumes_without_losing_iterations
def test_adam_lowers_the_loss(problem):
    _, truth, objective = problem
    for mode in ("fwd", "rev"):
        result = fit(objective, {"beta": 0.18, "mu1": 0.45}, method="adam", steps=8, learning_rate=0.1,
                     grad_mode=mode)
        loss = result.history["loss"]
        assert loss[-1] < 0.5 * loss[0], (mode, loss)
        assert np.all(np.isfinite(result.history["grad_norm"]))


# Adam by default; LM (a Jacobian program, 20 s) slow: the command line's --resume of an LM fit stays by
# default (tests/test_robust_calibration.py)
@pytest.mark.parametrize("method", [pytest.param("lm", marks=pytest.mark.slow), "adam"])
def test_interrupted_fit_resumes_without_losing_iterations(problem, tmp_path, method):
    _, _, objective = problem
    init = {"beta": 0.18, "mu1": 0.45}
    kw = dict(method=method, steps=5, learning_rate=0.1, uncertainty=False, stat_tol=0.0, ftol=0.0, xtol=0.0)
    full = fit(objective, init, out=tmp_path / "full.h5", **kw)

    class Killed(Exception):
        pass

    def kill_after_two(k, record):
        if k == 1:
            raise Killed

    with pytest.raises(Killed):
        fit(objective, init, out=tmp_path / "cut.h5", callback=kill_after_two, **kw)
    saved = read_history(tmp_path / "cut.h5")["history"]
    assert saved["loss"].size == 2
    resumed = fit(objective, init, out=tmp_path / "cut.h5", resume=True, **kw)
    for field in ("theta", "loss", "accepted", "status"):
        np.testing.assert_array_equal(resumed.history[field], full.history[field], err_msg=field)
    np.testing.assert_array_equal(read_history(tmp_path / "cut.h5")["history"]["loss"], full.history["loss"])


def test_resume_refuses_a_different_fit(problem, tmp_path):
    _, _, objective = problem
    fit(objective, {"beta": 0.2}, steps=1, out=tmp_path / "f.h5", uncertainty=False)
    with pytest.raises(ValueError, match="holds a lm fit"):
        fit(objective, {"beta": 0.2}, method="adam", steps=2, out=tmp_path / "f.h5", resume=True)


@pytest.mark.parametrize("change", [dict(stat_tol=0.2), dict(max_rejections=3), dict(xtol=1e-4)])
def test_resume_compares_every_run_option(problem, tmp_path, change):
    """The history records the fit's options whole; a resume that changes any of them but the
    iteration budget is refused (stat_tol and max_rejections once escaped the check)."""
    _, _, objective = problem
    fit(objective, {"beta": 0.2}, steps=1, out=tmp_path / "f.h5", uncertainty=False)
    (field,) = change
    with pytest.raises(ValueError, match=f"options differ.*{field}"):
        fit(objective, {"beta": 0.2}, steps=2, out=tmp_path / "f.h5", resume=True, uncertainty=False, **change)


#: ``python KILLED.py OUT ROWS ARGS...`` runs ``python -m calibration ARGS...`` and SIGKILLs it
#: at a known point: when the fit is about to rename a newly written history onto OUT (the
#: temporary file already complete beside it) while OUT holds ROWS iterations. Python's audit
#: hook on ``os.rename`` (which ``os.replace`` raises) finds the moment, so the kill depends on
#: no timing: a fast machine cannot finish the fit first.
KILLED = """
import os, runpy, signal, sys

out, rows, argv = os.path.abspath(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
busy = []


def kill_at_rows(event, args):
    if event != "os.rename" or busy or os.path.abspath(os.fspath(args[1])) != out or not os.path.exists(out):
        return
    busy.append(True)
    from calibration.optim.history import read_history

    if read_history(out)["history"]["loss"].size >= rows:
        os.kill(os.getpid(), signal.SIGKILL)
    busy.pop()


sys.addaudithook(kill_at_rows)
sys.argv = ["calibration", *argv]
runpy.run_module("calibration", run_name="__main__", alter_sys=True)
"""


# 40-60 s; the resume logic itself is tested in-process above and by the CLI in test_robust_calibration.
@pytest.mark.slow
def test_killed_command_line_fit_resumes(tmp_path):
    """SIGKILL a running ``python -m calibration fit`` as it writes its third iteration (its file
    holds two); the resumed run keeps them and finishes with the same history as an
    uninterrupted one."""
    args = ["fit", "--scene", "cohesive-collapse", "--data", str(S4_DATA), "--fit", "beta,mu1", "--init", "beta=0.15",
            "--steps", "4", "--roundoff-samples", "0", "--grid-check", "0", *TINY_FLAGS]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = tmp_path / "fit.h5"
    script = tmp_path / "killed.py"
    script.write_text(KILLED)
    killed = subprocess.run([sys.executable, str(script), str(out), "2", *args, "--out", str(out)], cwd=tmp_path,
                            env=env, capture_output=True, text=True, timeout=180)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    before = read_history(out)["history"]
    assert before["loss"].size == 2
    assert list(tmp_path.glob(".fit.h5.*.tmp")), "killed between writing the third iteration and renaming it"
    command = [sys.executable, "-m", "calibration", *args]
    done = subprocess.run([*command, "--out", str(out), "--resume"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    after = read_history(out)["history"]
    np.testing.assert_array_equal(after["loss"][: before["loss"].size], before["loss"])
    assert after["loss"].size == 4
    ref = subprocess.run([*command, "--out", str(tmp_path / "ref.h5")], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=180)
    assert ref.returncode == 0, ref.stderr[-2000:]
    np.testing.assert_array_equal(read_history(tmp_path / "ref.h5")["history"]["theta"], after["theta"])
    assert json.loads(done.stdout)["iterations"] == 4


# ---- uncertainty -------------------------------------------------------------------------

def test_gauss_newton_covariance_of_a_linear_model():
    rng = np.random.default_rng(0)
    m, sigma = 400, 0.02
    J = np.column_stack([np.ones(m), np.linspace(0, 1, m), np.zeros(m)])
    wiggle = np.cos(np.linspace(0, 7 * np.pi, m))
    q, _ = np.linalg.qr(np.column_stack([J[:, :2], wiggle]))
    J[:, 2] = 1e-9 * q[:, 2]  # a parameter the data barely see (orthogonal to the others)
    r = sigma * rng.standard_normal(m)
    blocks = {"profile": slice(0, m)}
    u = gauss_newton_uncertainty(J, r, ("a", "b", "c"), np.array([1.0, 1.0, 1.0]), blocks, np.ones(m), noise=sigma)
    expected = sigma**2 * np.linalg.inv(J[:, :2].T @ J[:, :2])
    np.testing.assert_allclose(u.cov[:2, :2], expected, rtol=1e-6)
    assert u.stderr[2] > 1e3  # unidentifiable: a huge (finite) standard error, not zero
    assert u.constrained == ("a", "b")
    assert "do not constrain c" in u.statement
    # estimated noise ~ sigma
    u2 = gauss_newton_uncertainty(J, r, ("a", "b", "c"), np.ones(3), blocks, np.ones(m))
    assert abs(u2.noise["profile"] / sigma - 1) < 0.1


def test_jacobian_by_columns_equals_jacfwd():
    """The column passes give jax.jacfwd's Jacobian, the primal output and the aux of one pass."""
    import jax
    import jax.numpy as jnp

    from calibration.problem.residuals import jacobian_by_columns

    def fn(x):
        y = jnp.stack([jnp.sin(x[0]) * x[1], x[0] ** 2, jnp.exp(x[1] - x[2])])
        return y, {"status": jnp.int32(3), "sum": jnp.sum(y)}

    x = jnp.asarray([0.3, -1.2, 0.5])
    J, (y, aux) = jacobian_by_columns(fn, x)
    np.testing.assert_allclose(J, jax.jacfwd(lambda x: fn(x)[0])(x), rtol=1e-13)
    np.testing.assert_allclose(y, fn(x)[0], rtol=1e-15)
    assert int(aux["status"]) == 3 and J.shape == (3, 3)
