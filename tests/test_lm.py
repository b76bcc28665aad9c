"""Levenberg–Marquardt's statistical stop (``calibration.optim.lm``) judges what is left to gain:
the linear model's decrease at its own minimum, whatever the damping."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from calibration.optim.evaluate import Evaluation
from calibration.optim.lm import LMOptions, levenberg_marquardt, propose, secant_update
from calibration.optim.loop import run

# Osborne 1 (Moré, Garbow & Hillstrom 1981, problem 17): 33 points, 5 parameters, a flat valley.
OSBORNE1_Y = np.array([0.844, 0.908, 0.932, 0.936, 0.925, 0.908, 0.881, 0.850, 0.818, 0.784, 0.751, 0.718, 0.685,
                       0.658, 0.628, 0.603, 0.580, 0.558, 0.538, 0.522, 0.506, 0.490, 0.478, 0.467, 0.457, 0.448,
                       0.438, 0.431, 0.424, 0.420, 0.414, 0.411, 0.406])
T = 10.0 * np.arange(33)


def osborne(th):
    e3, e4 = np.exp(-T * th[3]), np.exp(-T * th[4])
    r = th[0] + th[1] * e3 + th[2] * e4 - OSBORNE1_Y
    J = np.stack([np.ones_like(T), e3, e4, -T * th[1] * e3, -T * th[2] * e4], axis=1)
    return r, J


class _Rows:
    iterations = 0

    def record(self, rows, z, evaluation, state):
        self.iterations += 1

    def length(self, i):
        return self.iterations


def _evaluate(Z):
    r, J = zip(*(osborne(z) for z in Z))
    r, J = np.stack(r), np.stack(J)
    g = 2 * np.einsum("kmn,km->kn", J, r)
    k = len(Z)
    return Evaluation(theta=np.asarray(Z, float), loss=np.sum(r * r, axis=1), status=np.zeros(k, int), grad=g,
                      residuals=r, jacobian=J, jacobian_z=J, grad_z=g, prediction={"status": np.zeros(k, int)})


def test_the_promise_is_the_gauss_newton_decrease_whatever_the_damping():
    rng = np.random.default_rng(0)
    r, J = rng.standard_normal((2, 12)), rng.standard_normal((2, 12, 3))
    exact = [ri @ Ji @ np.linalg.solve(Ji.T @ Ji, Ji.T @ ri) for ri, Ji in zip(r, J)]
    for lam in (0.0, 1e-3, 1e3, 1e9):
        delta, promised = propose(r, J, np.full(2, lam))
        np.testing.assert_allclose(promised, exact, rtol=1e-10)
    # The step itself is still damped: a large λ shortens it.
    assert np.all(np.abs(propose(r, J, np.full(2, 1e9))[0]) < 1e-6)


def test_a_statistical_stop_in_a_flat_valley_is_within_the_tolerance_it_states():
    """Judged on the damped step's promise, LM stopped on Osborne 1 at 1.83 σ² above the minimum
    (1.29 standard errors away), where stat_tol = 0.1 allows 0.1 n σ² = 0.5 σ²."""
    ref = least_squares(lambda th: osborne(th)[0], [0.5, 1.5, -1.0, 0.01, 0.02], jac=lambda th: osborne(th)[1],
                        method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    loss_ref = float(np.sum(ref.fun**2))
    m, n = OSBORNE1_Y.size, 5
    sigma2 = loss_ref / (m - n)
    options = LMOptions()
    lm = levenberg_marquardt(options)
    state = run(lm, lm.init(np.array([[0.5, 1.5, -1.0, 0.01, 0.02]])), _evaluate, _Rows(), steps=200)
    assert state.message[0].startswith("converged: the linearised model promises")
    excess = (float(state.current.loss[0]) - loss_ref) / sigma2
    assert 0.0 <= excess <= options.stat_tol * n, excess
    J = osborne(ref.x)[1]
    se = np.sqrt(sigma2 * np.diag(np.linalg.inv(J.T @ J)))
    assert np.max(np.abs(state.z[0] - ref.x) / se) < 1.0
    assert state.z[0] == pytest.approx(ref.x, rel=0.05)


# Brown & Dennis (MGH 16): 20 points, 4 parameters, a large residual at the minimum (loss 85822.2).
BD_T = np.arange(1, 21) / 5.0


def brown_dennis(x):
    a = x[0] + BD_T * x[1] - np.exp(BD_T)
    b = x[2] + x[3] * np.sin(BD_T) - np.cos(BD_T)
    return a * a + b * b, np.stack([2 * a, 2 * a * BD_T, 2 * b, 2 * b * np.sin(BD_T)], axis=1)


# Jennrich & Sampson (MGH 6): 10 points, 2 parameters, loss 124.362 at the minimum.
JS_I = np.arange(1, 11.0)


def jennrich_sampson(x):
    r = 2 + 2 * JS_I - (np.exp(JS_I * x[0]) + np.exp(JS_I * x[1]))
    return r, -np.stack([JS_I * np.exp(JS_I * x[0]), JS_I * np.exp(JS_I * x[1])], axis=1)


def _solve(problem, x0, model, **options):
    lm = levenberg_marquardt(LMOptions(model=model, **options))
    rows = _Rows()
    state = run(lm, lm.init(np.array([x0], float)), _evaluator(problem), rows, steps=300)
    return state, rows.iterations


def _evaluator(problem):
    def evaluate(Z):
        r, J = (np.stack(a) for a in zip(*(problem(z) for z in Z)))
        g = 2 * np.einsum("kmn,km->kn", J, r)
        k = len(Z)
        return Evaluation(theta=np.asarray(Z, float), loss=np.sum(r * r, axis=1), status=np.zeros(k, int), grad=g,
                          residuals=r, jacobian=J, jacobian_z=J, grad_z=g, prediction={"status": np.zeros(k, int)})

    return evaluate


def test_the_adaptive_model_reaches_a_large_residual_minimum_gauss_newton_does_not():
    """NL2SOL's test case: Gauss–Newton's JᵀJ misses the residuals' own curvature, and its steps
    stall far above the minimum; the secant term gets there."""
    tight = dict(stat_tol=0.0, xtol=1e-10, ftol=1e-12)
    plain, _ = _solve(brown_dennis, [25, 5, -5, -1], "gauss-newton", **tight)
    adaptive, _ = _solve(brown_dennis, [25, 5, -5, -1], "adaptive", **tight)
    assert plain.current.loss[0] > 10 * 85822.2, plain.message[0]
    assert adaptive.message[0].startswith("converged"), adaptive.message[0]
    assert adaptive.current.loss[0] == pytest.approx(85822.2016, rel=1e-8)
    plain, n_plain = _solve(jennrich_sampson, [0.3, 0.4], "gauss-newton", **tight)
    adaptive, n_adaptive = _solve(jennrich_sampson, [0.3, 0.4], "adaptive", **tight)
    assert plain.current.loss[0] == pytest.approx(adaptive.current.loss[0], rel=1e-10)
    assert adaptive.current.loss[0] == pytest.approx(124.362182, rel=1e-8)
    assert n_adaptive < n_plain


def test_the_adaptive_model_takes_gauss_newtons_path_on_a_small_residual():
    """Where the residuals vanish at the minimum the secant term stays out of the way: Osborne 1's
    fit ends at the same point in as many iterations."""
    x0 = [0.5, 1.5, -1.0, 0.01, 0.02]
    plain, n_plain = _solve(osborne, x0, "gauss-newton")
    adaptive, n_adaptive = _solve(osborne, x0, "adaptive")
    assert n_adaptive == n_plain
    np.testing.assert_allclose(adaptive.z[0], plain.z[0], rtol=1e-6)


def test_the_secant_update_meets_its_secant_condition_and_stays_symmetric():
    rng = np.random.default_rng(1)
    k, m, n = 3, 9, 4
    S = rng.standard_normal((k, n, n))
    S = S + np.swapaxes(S, 1, 2)
    r, r_new = rng.standard_normal((2, k, m))
    J, J_new = rng.standard_normal((2, k, m, n))
    step = rng.standard_normal((k, n))
    y = np.einsum("kmi,km->ki", J_new, r_new) - np.einsum("kmi,km->ki", J, r)
    step = np.where((np.sum(y * step, 1) > 0)[:, None], step, -step)  # the update needs yᵀs > 0
    new = secant_update(S, step, r, J, r_new, J_new)
    y_sharp = np.einsum("kmi,km->ki", J_new - J, r_new)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", new, step), y_sharp, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(new, np.swapaxes(new, 1, 2), rtol=1e-12, atol=1e-12)
