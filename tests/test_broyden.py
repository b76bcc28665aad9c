"""Levenberg–Marquardt with Broyden's updates of the Jacobian (``LMOptions(jacobian="broyden")``):
the update meets its secant condition with the least change; LM reaches exact LM's minimum on
test problems of Moré, Garbow & Hillstrom with fewer Jacobians; a step from an estimate
that fails asks for the exact Jacobian at the current point instead of counting as a rejection,
and once LM would stop on an estimate it goes on with exact Jacobians;
the judged point carries its exact Jacobian; and a fit of a tiny S4 twin through the library
recovers the point exact LM does."""

import numpy as np
import pytest
from helpers import model_data, tiny_s4
from test_lm import _Rows, jennrich_sampson, osborne

from calibration.optim.evaluate import Evaluation, evaluator
from calibration.optim.fit import fit
from calibration.optim.lm import LMOptions, broyden_update, levenberg_marquardt, with_exact_jacobians
from calibration.optim.loop import run
from calibration.problem.objective import Objective
from jaxmpm.scenes import S4_SIDE


def rosenbrock(x):
    """Rosenbrock's valley as residuals (MGH 1): minimum 0 at (1, 1)."""
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]), np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])


class _Counted:
    """A problem's runs as ``evaluate(Z, jacobian=mask)``, counting the Jacobians and the runs
    of the residuals alone (whose Jacobians are NaN, as the library's evaluators give them)."""

    def __init__(self, problem):
        self.problem, self.jacobians, self.residual_runs = problem, 0, 0

    def __call__(self, Z, jacobian=None):
        jacobian = np.ones(len(Z), bool) if jacobian is None else np.asarray(jacobian, bool)
        r, J = (np.stack(a) for a in zip(*(self.problem(z) for z in Z)))
        J = np.where(jacobian[:, None, None], J, np.nan)
        self.jacobians += int(jacobian.sum())
        self.residual_runs += int((~jacobian).sum())
        g = 2 * np.einsum("kmn,km->kn", J, r)
        k = len(Z)
        return Evaluation(theta=np.asarray(Z, float), loss=np.sum(r * r, axis=1), status=np.zeros(k, int), grad=g,
                          residuals=r, jacobian=J, jacobian_z=J, grad_z=g, prediction={"status": np.zeros(k, int)})


def _solve(problem, x0, jacobian, steps=400, **options):
    lm = levenberg_marquardt(LMOptions(model="gauss-newton", jacobian=jacobian, **options))
    evaluate = _Counted(problem)
    state = run(lm, lm.init(np.array([x0], float)), evaluate, _Rows(), steps=steps)
    return with_exact_jacobians(state, [0], evaluate), evaluate


def test_the_update_meets_its_secant_condition_with_the_least_change():
    rng = np.random.default_rng(2)
    J, s, r, r_new = rng.standard_normal((3, 7, 4)), rng.standard_normal((3, 4)), *rng.standard_normal((2, 3, 7))
    updated = broyden_update(J, s, r, r_new)
    np.testing.assert_allclose(np.einsum("kmi,ki->km", updated, s), r_new - r, rtol=1e-12, atol=1e-12)
    # Along any direction orthogonal to the step the model is unchanged, and the change has rank one.
    for k in range(3):
        q = np.linalg.svd(s[k][None])[2][1:]  # an orthonormal basis of the step's complement
        np.testing.assert_allclose(updated[k] @ q.T, J[k] @ q.T, rtol=1e-12, atol=1e-12)
        assert np.linalg.matrix_rank(updated[k] - J[k], tol=1e-10) == 1


@pytest.mark.parametrize("problem, x0, loss", [(osborne, [0.5, 1.5, -1.0, 0.01, 0.02], 5.46489e-5),
                                               (jennrich_sampson, [0.3, 0.4], 124.362182),
                                               (rosenbrock, [-1.2, 1.0], 0.0)])
def test_broyden_reaches_exact_lms_minimum_with_fewer_jacobians(problem, x0, loss):
    tight = dict(stat_tol=0.0, xtol=1e-10, ftol=1e-12)
    exact, exact_runs = _solve(problem, x0, "exact", **tight)
    broyden, broyden_runs = _solve(problem, x0, "broyden", **tight)
    assert exact.message[0].startswith("converged") and broyden.message[0].startswith("converged"), (
        exact.message[0], broyden.message[0])
    assert broyden.current.loss[0] == pytest.approx(exact.current.loss[0], rel=1e-6, abs=1e-20)
    assert broyden.current.loss[0] == pytest.approx(loss, rel=1e-5, abs=1e-20)
    np.testing.assert_allclose(broyden.z[0], exact.z[0], rtol=1e-3, atol=1e-8)
    assert exact_runs.residual_runs == 0
    # Fewer Jacobians (Osborne 18 against 31, Jennrich–Sampson 14 against 25, Rosenbrock 8 against
    # 29), paid for by more runs of the residuals alone (48, 33, 33): it pays where a Jacobian costs
    # several runs, as MPM's forward-mode columns do (docs/fitting.md).
    assert broyden_runs.jacobians < exact_runs.jacobians, (broyden_runs.jacobians, exact_runs.jacobians)
    # The judged point carries its own Jacobian, not an estimate.
    np.testing.assert_array_equal(broyden.current.jacobian_z[0], problem(broyden.z[0])[1])
    assert broyden.fresh[0]


def test_a_failed_step_from_an_estimate_asks_for_the_exact_jacobian_and_is_not_a_rejection():
    lm = levenberg_marquardt(LMOptions(jacobian="broyden"))
    evaluate = _Counted(rosenbrock)
    state = lm.init(np.array([[0.9, 0.7]]))
    np.testing.assert_array_equal(state.want_jacobian, [True])  # the start: its own Jacobian
    state = lm.update(evaluate(state.z_next, state.want_jacobian), state)
    assert state.fresh[0] and not state.want_jacobian[0]
    # A worse trial from the exact Jacobian is an ordinary rejection.
    z0 = state.z.copy()
    worse = evaluate(z0 + 3.0, np.array([False]))
    after = lm.update(worse._replace(theta=z0 + 3.0), state._replace(z_next=z0 + 3.0))
    assert after.rejections[0] == 1 and not after.want_jacobian[0] and after.fresh[0]
    # Take an accepted step: the Jacobian becomes Broyden's estimate.
    better = lm.update(evaluate(state.z_next, state.want_jacobian), state)
    assert better.accepted[0] and not better.fresh[0]
    # A worse trial from the estimate: the exact Jacobian at the current point comes next.
    z1 = better.z.copy()
    failed = lm.update(evaluate(z1 + 3.0, np.array([False]))._replace(theta=z1 + 3.0), better._replace(z_next=z1 + 3.0))
    assert failed.rejections[0] == 0 and failed.want_jacobian[0] and not failed.done[0]
    np.testing.assert_array_equal(failed.z_next, z1)
    refreshed = lm.update(evaluate(failed.z_next, failed.want_jacobian), failed)
    assert refreshed.fresh[0] and not refreshed.want_jacobian[0] and not refreshed.accepted[0]
    np.testing.assert_array_equal(refreshed.current.jacobian_z[0], rosenbrock(z1[0])[1])
    assert refreshed.lam[0] == failed.lam[0]


def test_once_lm_would_stop_on_an_estimate_it_polishes_with_exact_jacobians():
    """The last steps, at the round-off, are exact LM's: after the first stop claimed on Broyden's
    estimate, every run a start asks for comes with its Jacobian. Whether a run's stop is first
    claimed on an estimate or on an exact Jacobian is decided at the round-off (with numpy 2.4.6
    Osborne's and Jennrich–Sampson's runs below end on exact Jacobians, with the numpy before on
    estimates), so the property is checked on five runs and at least two must exercise it."""
    polished = 0
    for problem, x0 in ((osborne, [0.5, 1.5, -1.0, 0.01, 0.02]), (jennrich_sampson, [0.3, 0.4]),
                        (rosenbrock, [-1.2, 1.0]), (rosenbrock, [2.0, 2.0]), (rosenbrock, [0.5, -0.5])):
        lm = levenberg_marquardt(LMOptions(model="gauss-newton", jacobian="broyden", stat_tol=0.0, xtol=1e-10,
                                           ftol=1e-12))
        evaluate, log = _Counted(problem), []

        def report(state, rows, log=log):
            log.append((bool(state.polish[0]), bool(state.want_jacobian[0])))

        run(lm, lm.init(np.array([x0], float)), evaluate, _Rows(), steps=400, report=report)
        flags = np.array(log)
        if flags[:, 0].any():
            first = int(np.argmax(flags[:, 0]))
            assert flags[first:, 0].all() and flags[first:, 1].all()
            polished += 1
    assert polished >= 2


def test_exact_lm_asks_for_nothing_new():
    lm = levenberg_marquardt(LMOptions())
    state = lm.init(np.array([[-1.2, 1.0]]))
    assert state.want_jacobian is None and state.fresh is None
    with pytest.raises(ValueError, match="jacobian must be one of"):
        levenberg_marquardt(LMOptions(jacobian="secant"))


@pytest.fixture(scope="module")
def objective():
    scene = tiny_s4(beta=0.0, dx=S4_SIDE / 4)
    profile, _ = model_data(scene, ("beta", "mu1"), np.array([0.2, 0.4]), xs=np.linspace(0.0, 0.2, 25))
    return Objective(scene, ("beta", "mu1"), profile=profile)


@pytest.mark.slow  # 22 s cold, one more program of the run; the Broyden twin fit below runs by default
def test_the_evaluators_runs_of_the_residuals_alone_are_the_jacobian_runs_residuals(objective):
    evaluate = evaluator(objective, rev=False)
    Z = np.stack([objective.bounds.to_unconstrained(np.array(t)) for t in ([0.1, 0.3], [0.3, 0.45])])
    both = evaluate(Z, jacobian=np.array([True, False]))
    assert np.all(np.isfinite(both.jacobian_z[0])) and np.all(np.isnan(both.jacobian_z[1]))
    full = evaluate(Z)
    np.testing.assert_allclose(both.residuals, full.residuals, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(both.jacobian_z[0], full.jacobian_z[0])


def test_a_twin_fit_with_broyden_recovers_exact_lms_point(objective):
    # Broyden's runs are more, and cheaper: on this tiny grid both reach the float32 round-off floor,
    # where the run's own scatter stops them (``roundoff_stop``).
    common = dict(steps=60, roundoff_samples=4, probe=False)
    exact = fit(objective, {"beta": 0.05, "mu1": 0.3}, **common)
    broyden = fit(objective, {"beta": 0.05, "mu1": 0.3}, lm_jacobian="broyden", **common)
    assert exact.converged and broyden.converged, (exact.message, broyden.message)
    for k, truth in (("beta", 0.2), ("mu1", 0.4)):
        assert broyden.theta[k] == pytest.approx(truth, abs=1e-4)
        assert broyden.theta[k] == pytest.approx(exact.theta[k], abs=1e-4)
    # The result's Jacobian is the runs' own at its point.
    r, J, _ = objective.residuals_and_jacobian(np.array([broyden.theta["beta"], broyden.theta["mu1"]]))
    np.testing.assert_allclose(broyden.jacobian, np.asarray(J), rtol=1e-4, atol=1e-8)
