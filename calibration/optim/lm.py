"""Levenberg–Marquardt in the unconstrained variables z, for a batch of starts, as an ``(init, update)`` pair.

``fit`` (a batch of one) and ``search`` (k starts) both run ``levenberg_marquardt(options)``
through ``calibration.optim.loop.run``, so both take the same steps and stop by the same rules:
``propose`` gives the damped, Marquardt-scaled step and the loss decrease the linear model
promises; ``judge`` accepts or rejects the trials, adapts λ and applies the stopping tests. A start
whose first run fails is done with a message that begins "stopped". Arrays carry a leading batch
axis k; everything is numpy (the model runs are the cost). The rules, and why this is not
optimistix's ``LevenbergMarquardt``: docs/fitting.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from ..problem.bounds import MAX_STEP
from .evaluate import Evaluation
from .loop import Optimiser, where_rows

__all__ = ["LAM0", "LMOptions", "propose", "judge", "LMState", "levenberg_marquardt"]


#: The damping of the first step.
LAM0 = 1e-3


@dataclasses.dataclass(frozen=True)
class LMOptions:
    xtol: float = 1e-6
    ftol: float = 1e-7
    stat_tol: float = 0.1
    max_rejections: int = 6


def propose(r, Jz, lam):
    """Steps δ (k, n) and promised decreases (k,) from residuals r (k, m), their Jacobian in z,
    Jz (k, m, n), and the damping λ (k,). The promise is the linear model's decrease at its
    minimum (the undamped Gauss–Newton step, by least squares where JᵀJ is singular), not the
    damped step's: after rejected steps λ is large and the damped promise small wherever the
    minimum is. The step is capped at ``MAX_STEP`` in every z, so that no step lands in the
    bounds' flat sigmoid tail (dθ/dz ≈ 0), which no later step could leave."""
    r, Jz, lam = np.asarray(r, float), np.asarray(Jz, float), np.asarray(lam, float)
    A = np.einsum("kmi,kmj->kij", Jz, Jz)
    diag = np.diagonal(A, axis1=1, axis2=2)
    d = np.maximum(diag, 1e-12 * np.maximum(diag.max(axis=1, keepdims=True), 1e-300))
    rhs = -np.einsum("kmi,km->ki", Jz, r)
    delta = np.linalg.solve(A + lam[:, None, None] * (d[:, :, None] * np.eye(A.shape[1])), rhs[..., None])[..., 0]
    longest = np.max(np.abs(delta), axis=1, keepdims=True)
    delta = delta * np.minimum(1.0, MAX_STEP / np.maximum(longest, 1e-300))
    loss = np.sum(r * r, axis=1)
    gauss_newton = np.stack([np.linalg.lstsq(J, -ri, rcond=None)[0] for J, ri in zip(Jz, r)])
    promised = loss - np.sum((r + np.einsum("kmi,ki->km", Jz, gauss_newton)) ** 2, axis=1)
    return delta, promised


def judge(loss_c, theta_c, loss_t, theta_t, ok_t, promised, lam, rejections, m: int, options: LMOptions):
    """Accept or reject k trials and apply the stopping tests.

    ``loss_c``/``theta_c``: the current (accepted) points; ``loss_t``/``theta_t``/``ok_t``: the
    trials (``ok_t``: the run has no status bits); ``promised``: from ``propose``; ``m``: the
    number of residuals. Returns ``(accepted, lam, rejections, done, messages)``, ``messages``
    a list with "" for the starts that go on; a finished start's message begins with
    "converged" (a verified minimum) or "stopped"."""
    loss_c, loss_t = np.asarray(loss_c, float), np.asarray(loss_t, float)
    theta_c, theta_t = np.asarray(theta_c, float), np.asarray(theta_t, float)
    n = theta_c.shape[1]
    accepted = np.asarray(ok_t, bool) & np.isfinite(loss_t) & (loss_t < loss_c)
    rel_step = np.max(np.abs(theta_t - theta_c) / np.maximum(np.abs(theta_c), 1e-12), axis=1)
    rel_drop = (loss_c - loss_t) / np.maximum(loss_c, 1e-300)
    noise_drop = options.stat_tol * n * loss_c / max(m - n, 1)
    rejections = np.where(accepted, 0, np.asarray(rejections) + 1)
    lam = np.where(accepted, np.maximum(np.asarray(lam) / 3.0, 1e-9), np.asarray(lam) * 4.0)
    messages = []
    for i in range(loss_c.size):
        if promised[i] <= noise_drop[i]:
            msg = (f"converged: the linearised model promises a loss decrease of {promised[i]:.2e}, below the "
                   f"residual noise level {noise_drop[i]:.2e}")
        elif accepted[i] and (rel_drop[i] < options.ftol or rel_step[i] < options.xtol):
            msg = f"converged: relative loss decrease {rel_drop[i]:.2e}, relative step {rel_step[i]:.2e}"
        elif not accepted[i] and rel_step[i] < options.xtol:
            msg = f"converged: rejected steps shorter than xtol ({rel_step[i]:.2e})"
        elif rejections[i] >= options.max_rejections:
            msg = (f"stopped: {rejections[i]} rejected steps in a row (no decrease within the runs' round-off "
                   "and scatter)")
        else:
            msg = ""
        messages.append(msg)
    done = np.array([bool(msg) for msg in messages])
    return accepted, lam, rejections, done, messages


class LMState(NamedTuple):
    z: np.ndarray  # (k, n) the accepted points
    current: Evaluation | None  # the evaluation at z (None before the first)
    lam: np.ndarray  # (k,) the damping of the next step
    rejections: np.ndarray  # (k,) rejected steps in a row
    z_next: np.ndarray  # (k, n) the next trials
    promised: np.ndarray  # (k,) the loss decreases their steps promise
    accepted: np.ndarray  # (k,) whether the last evaluation was accepted
    done: np.ndarray  # (k,)
    message: np.ndarray  # (k,) object: "" while a start goes on


def levenberg_marquardt(options: LMOptions = LMOptions()) -> Optimiser:
    """LM as ``(init, update)``: ``init(z)`` asks for the runs at the starts z (k, n);
    ``update(evaluation, state)`` judges the trials (the first evaluation: takes the starts
    whose runs succeed) and proposes the next ones."""

    def init(z):
        z = np.asarray(z, float)
        k = z.shape[0]
        return LMState(z=z, current=None, lam=np.full(k, LAM0), rejections=np.zeros(k, int), z_next=z,
                       promised=np.full(k, np.nan), accepted=np.zeros(k, bool), done=np.zeros(k, bool),
                       message=np.full(k, "", object))

    def update(evaluation: Evaluation, state: LMState) -> LMState:
        if state.current is None:  # the runs at the starts
            accepted = (evaluation.status == 0) & np.isfinite(evaluation.loss)
            z, lam, rejections, stop = state.z_next, state.lam, state.rejections, ~accepted
            current = evaluation._replace(loss=np.where(accepted, evaluation.loss, np.nan))
            messages = [f"stopped: the run at the start fails (status {s}; loss {v})"
                        for s, v in zip(evaluation.status, evaluation.loss)]
        else:
            c = state.current
            accepted, lam, rejections, stop, messages = judge(
                c.loss, c.theta, evaluation.loss, evaluation.theta, evaluation.status == 0, state.promised,
                state.lam, state.rejections, c.residuals.shape[1], options)
            z = np.where(accepted[:, None], state.z_next, state.z)
            current = where_rows(accepted, evaluation, c)
        done = state.done | stop
        message = np.where(stop, np.array(messages, object), state.message)
        z_next, promised = z.copy(), np.full(len(z), np.nan)
        go = ~done
        if go.any():
            delta, promised[go] = propose(current.residuals[go], current.jacobian_z[go], lam[go])
            z_next[go] = z[go] + delta
        return LMState(z=z, current=current, lam=lam, rejections=rejections, z_next=z_next, promised=promised,
                       accepted=accepted, done=done, message=message)

    return Optimiser(init, update)
