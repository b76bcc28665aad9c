"""The stops a fit and a search add to Levenberg–Marquardt's own: a start converged within the
run's round-off (``roundoff_stop``) and a refined start that cannot become the best
(``dominated_stop``), on a linear model whose runs carry a known round-off."""

from __future__ import annotations

import numpy as np

from calibration.inference.scatter import roundoff_limit
from calibration.optim.evaluate import Evaluation
from calibration.optim.fit import ROUNDOFF_CHECK_AFTER, measured_at, roundoff_stop
from calibration.optim.lm import LMState
from calibration.optim.search import DOMINATED_MARGIN, dominated_stop
from calibration.problem.bounds import Bounds

A = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0], [0.5, -1.0], [2.0, 0.3], [-1.0, 0.7]])
TRUTH = np.array([0.3, 0.5])
SIGMA = 1e-4  # the runs' round-off: every run adds its own N(0, σ²) to each residual


class NoisyLinear:
    """r(θ) = A(θ − truth) + round-off, the few members of an objective that ``model_scatter`` reads."""

    keys = ("beta", "mu1")
    bounds = Bounds.create(keys)
    blocks = {"profile": slice(0, len(A))}
    row_scale = np.ones(len(A))

    def __init__(self):
        self.rng, self.runs = np.random.default_rng(1), 0

    def residuals(self, theta):
        self.runs += 1
        return A @ (np.asarray(theta) - TRUTH) + SIGMA * self.rng.standard_normal(len(A)), {"status": 0}


def state_at(thetas, rejections, promised=None):
    """LM's state of k starts at ``thetas``, each with ``rejections`` rejected steps in a row."""
    thetas = np.atleast_2d(np.asarray(thetas, float))
    k = len(thetas)
    r = np.stack([A @ (t - TRUTH) for t in thetas])
    J = np.repeat(A[None], k, axis=0)
    current = Evaluation(theta=thetas, loss=np.sum(r * r, axis=1), status=np.zeros(k, int), grad=None, residuals=r,
                         jacobian=J, jacobian_z=J, grad_z=None, prediction={"status": np.zeros(k, int)})
    return LMState(z=thetas, current=current, lam=np.ones(k), rejections=np.asarray(rejections),
                   z_next=thetas, promised=np.full(k, np.nan) if promised is None else np.asarray(promised, float),
                   accepted=np.zeros(k, bool), done=np.zeros(k, bool), message=np.full(k, "", object))


def test_a_start_within_its_round_off_converges_and_one_beyond_goes_on():
    objective, scatters = NoisyLinear(), {}
    stop = roundoff_stop(objective, 8, None, scatters)
    # The Gauss–Newton step's scatter from the round-off is σ (AᵀA)^(-1/2) ~ 1e-4 per key.
    near, far = TRUTH + 5e-6, TRUTH + np.array([0.0, 0.02])
    state = stop(state_at([near, far], [ROUNDOFF_CHECK_AFTER] * 2))
    assert state.done.tolist() == [True, False]
    assert state.message[0].startswith("converged within the run's round-off")
    assert state.message[1] == ""
    assert objective.runs == 16  # measured once for each start
    scatter = scatters[0][1]
    assert scatter.gauss_newton_distance(A, state.current.residuals[0]) <= roundoff_limit(2, scatter.samples)
    assert measured_at(scatters, 0, near) is scatter and measured_at(scatters, 0, far) is None
    # Later checks of a start reuse its scatter; a start with fewer rejections is not checked.
    stop(state_at([far, far], [ROUNDOFF_CHECK_AFTER, 1]))
    assert objective.runs == 16


def test_the_round_off_stop_is_off_without_samples():
    objective = NoisyLinear()
    state = roundoff_stop(objective, 0, None, {})(state_at([TRUTH], [ROUNDOFF_CHECK_AFTER]))
    assert not state.done.any() and objective.runs == 0


def test_a_start_that_cannot_become_the_best_is_dropped():
    best, behind, hopeful = TRUTH + 1e-3, TRUTH + np.array([0.2, -0.1]), TRUTH + np.array([0.2, -0.1])
    state = state_at([best, behind, hopeful], [0, 0, 0])
    loss = state.current.loss
    # ``behind`` promises a tenth of what it needs to reach the best, ``hopeful`` all of it.
    needed = loss[1] - loss[0]
    state = state._replace(promised=np.array([loss[0], 0.1 * needed / DOMINATED_MARGIN, needed]))
    out = dominated_stop(2)(state)
    assert out.done.tolist() == [False, True, False]
    assert out.message[1].startswith("stopped: dominated by start 0")
    # Within the noise of the best (Δχ² at 95 %, σ² the best loss over m − n): kept.
    close = state_at([best, best * (1 + 1e-9)], [0, 0], promised=[0.0, 0.0])
    assert not dominated_stop(2)(close).done.any()
