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

import jax
import numpy as np

from ..problem.bounds import MAX_STEP
from .evaluate import Evaluation
from .loop import Optimiser, where_rows

__all__ = ["LAM0", "MODELS", "DEFAULT_MODEL", "JACOBIANS", "DEFAULT_JACOBIAN", "LMOptions", "propose", "judge",
           "secant_update", "broyden_update", "LMState", "levenberg_marquardt", "with_exact_jacobians"]


#: The damping of the first step.
LAM0 = 1e-3

#: The models of the loss's curvature a step may use: JᵀJ alone, or JᵀJ plus a secant estimate of
#: Σ rᵢ ∇²rᵢ where that predicted the last step's decrease better (Dennis, Gay & Welsch 1981).
MODELS = ("gauss-newton", "adaptive")

#: The default model: "adaptive" takes Gauss–Newton's steps where the residuals vanish at the
#: minimum and reaches a large-residual minimum in half the iterations (docs/fitting.md).
DEFAULT_MODEL = "adaptive"

#: Where a trial's Jacobian comes from: its own forward-mode runs ("exact"), or a run of the
#: residuals alone and Broyden's rank-one update of the last Jacobian ("broyden"; the exact one again
#: wherever a step taken with the estimate fails or would stop LM). Measured: docs/fitting.md.
JACOBIANS = ("exact", "broyden")

#: With Broyden's estimate, an accepted step that gained less than this fraction of what its
#: linear model forecast (a poor model: the trust-region ratio ρ of Moré 1978) is followed by the exact Jacobian.
POOR_RATIO = 0.25

#: The default source of the trials' Jacobians.
DEFAULT_JACOBIAN = "exact"

#: The smallest eigenvalue of (JᵀJ + S), scaled to JᵀJ's unit diagonal, for the secant model to be used.
SECANT_MIN_EIGENVALUE = 1e-2


@dataclasses.dataclass(frozen=True)
class LMOptions:
    xtol: float = 1e-6
    ftol: float = 1e-7
    stat_tol: float = 0.1
    max_rejections: int = 6
    model: str = DEFAULT_MODEL
    jacobian: str = DEFAULT_JACOBIAN


def propose(r, Jz, lam, secant=None):
    """Steps δ (k, n) and promised decreases (k,) from residuals r (k, m), their Jacobian in z,
    Jz (k, m, n), and the damping λ (k,). The step solves (H + λ diag JᵀJ) δ = −Jᵀr with H = JᵀJ,
    or JᵀJ + S where ``secant`` (k, n, n) gives S for a start (zeros: JᵀJ) and JᵀJ + S is
    positive definite (``secant_usable``). The promise is the linear model's decrease at its
    minimum (the undamped Gauss–Newton step, by least squares where JᵀJ is singular), not the
    damped step's: after rejected steps λ is large and the damped promise small wherever the
    minimum is. The step is capped at ``MAX_STEP`` in every z, so that no step lands in the
    bounds' flat sigmoid tail (dθ/dz ≈ 0), which no later step could leave."""
    r, Jz, lam = np.asarray(r, float), np.asarray(Jz, float), np.asarray(lam, float)
    A = np.einsum("kmi,kmj->kij", Jz, Jz)
    diag = np.diagonal(A, axis1=1, axis2=2)
    d = np.maximum(diag, 1e-12 * np.maximum(diag.max(axis=1, keepdims=True), 1e-300))
    rhs = -np.einsum("kmi,km->ki", Jz, r)
    H = A if secant is None else np.where(secant_usable(A, secant)[:, None, None], A + secant, A)
    delta = np.linalg.solve(H + lam[:, None, None] * (d[:, :, None] * np.eye(A.shape[1])), rhs[..., None])[..., 0]
    longest = np.max(np.abs(delta), axis=1, keepdims=True)
    delta = delta * np.minimum(1.0, MAX_STEP / np.maximum(longest, 1e-300))
    loss = np.sum(r * r, axis=1)
    gauss_newton = np.stack([np.linalg.lstsq(J, -ri, rcond=None)[0] for J, ri in zip(Jz, r)])
    promised = loss - np.sum((r + np.einsum("kmi,ki->km", Jz, gauss_newton)) ** 2, axis=1)
    return delta, promised


def secant_usable(A, S):
    """(k,) whether JᵀJ + S (A = JᵀJ and S, (k, n, n)) is positive definite enough to step with:
    its smallest eigenvalue, scaled to A's unit diagonal, at least ``SECANT_MIN_EIGENVALUE``."""
    scale = 1.0 / np.sqrt(np.maximum(np.diagonal(A, axis1=1, axis2=2), 1e-300))
    H = (A + S) * scale[:, :, None] * scale[:, None, :]
    return np.any(S != 0, axis=(1, 2)) & (np.linalg.eigvalsh(H)[:, 0] >= SECANT_MIN_EIGENVALUE)


def secant_update(S, step, r, J, r_new, J_new):
    """The structured secant estimate S (k, n, n) of Σ rᵢ ∇²rᵢ after accepted steps ``step``
    (k, n) from (r, J) to (r_new, J_new): NL2SOL's update (Dennis, Gay & Welsch 1981). With
    y = J₊ᵀr₊ − Jᵀr (the change of the gradient) and y♯ = (J₊ − J)ᵀ r₊ (its part from the
    residuals' curvature), S is first sized by min(1, |sᵀy♯| / |sᵀSs|) and then changed by the
    least symmetric amount that gives S s = y♯. Where yᵀs ≤ 0 (no positive curvature along the
    step) S is only sized."""
    S, s = np.asarray(S, float), np.asarray(step, float)
    g_new = np.einsum("kmi,km->ki", J_new, r_new)
    y = g_new - np.einsum("kmi,km->ki", J, r)
    y_sharp = g_new - np.einsum("kmi,km->ki", J, r_new)
    sSs = np.einsum("ki,kij,kj->k", s, S, s)
    tau = np.where(np.abs(sSs) > 0, np.minimum(1.0, np.abs(np.sum(s * y_sharp, 1)) / np.maximum(np.abs(sSs), 1e-300)),
                   1.0)
    S = tau[:, None, None] * S
    v = y_sharp - np.einsum("kij,kj->ki", S, s)
    ys = np.sum(y * s, axis=1)
    ok = ys > 1e-12 * np.linalg.norm(y, axis=1) * np.linalg.norm(s, axis=1)
    ys = np.where(ok, ys, 1.0)
    change = ((v[:, :, None] * y[:, None, :] + y[:, :, None] * v[:, None, :]) / ys[:, None, None]
              - (np.sum(v * s, 1) / ys**2)[:, None, None] * y[:, :, None] * y[:, None, :])
    return S + np.where(ok[:, None, None], change, 0.0)


def broyden_update(Jz, step, r, r_new):
    """Broyden's rank-one update (k, m, n) of the Jacobians ``Jz`` after the steps ``step`` (k, n)
    took the residuals from ``r`` to ``r_new`` (k, m): the least change of Jz (in the Frobenius
    norm) whose linear model gives r_new at the step, Jz + (r_new − r − Jz s) sᵀ / sᵀs."""
    Jz, s = np.asarray(Jz, float), np.asarray(step, float)
    miss = np.asarray(r_new, float) - np.asarray(r, float) - np.einsum("kmi,ki->km", Jz, s)
    return Jz + miss[:, :, None] * s[:, None, :] / np.maximum(np.sum(s * s, axis=1), 1e-300)[:, None, None]


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
    secant: np.ndarray | None = None  # (k, n, n) the secant estimate S of Σ rᵢ ∇²rᵢ ("adaptive")
    use_secant: np.ndarray | None = None  # (k,) whether the next step's model is JᵀJ + S
    fresh: np.ndarray | None = None  # (k,) current.jacobian_z is the runs' own, not Broyden's ("broyden")
    want_jacobian: np.ndarray | None = None  # (k,) the next runs must give their Jacobian ("broyden"; None: all)
    polish: np.ndarray | None = None  # (k,) LM would have stopped on an estimate: exact Jacobians from then on


def levenberg_marquardt(options: LMOptions = LMOptions()) -> Optimiser:
    """LM as ``(init, update)``: ``init(z)`` asks for the runs at the starts z (k, n);
    ``update(evaluation, state)`` judges the trials (the first evaluation: takes the starts
    whose runs succeed) and proposes the next ones. With ``options.model == "adaptive"`` each step
    uses JᵀJ or JᵀJ + S, whichever forecast the last accepted step's decrease better
    (``_choose_model``), S kept by ``secant_update``; "gauss-newton" steps with JᵀJ alone. With
    ``options.jacobian == "broyden"`` a trial is one run of its residuals (``want_jacobian`` false)
    and an accepted one updates the Jacobian by ``broyden_update``; where a step proposed from such
    an estimate is rejected, gains less than ``POOR_RATIO`` of its forecast, or would stop LM, the
    next runs are the exact Jacobian at the current point (``want_jacobian`` true) and the next
    step is proposed from it; a rejection from an estimate is not counted. Once LM would have
    stopped on an estimate, the start takes exact Jacobians from then on (``polish``): the last
    steps, at the runs' round-off, are exact LM's. A start can stop holding
    an estimate (a stop judged on a step from the exact Jacobian): ``with_exact_jacobians``
    replaces it before the point is judged."""
    if options.model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {options.model!r}")
    if options.jacobian not in JACOBIANS:
        raise ValueError(f"jacobian must be one of {JACOBIANS}, got {options.jacobian!r}")
    adaptive, broyden = options.model == "adaptive", options.jacobian == "broyden"

    def init(z):
        z = np.asarray(z, float)
        k = z.shape[0]
        return LMState(z=z, current=None, lam=np.full(k, LAM0), rejections=np.zeros(k, int), z_next=z,
                       promised=np.full(k, np.nan), accepted=np.zeros(k, bool), done=np.zeros(k, bool),
                       message=np.full(k, "", object), secant=np.zeros((k, z.shape[1], z.shape[1])),
                       use_secant=np.zeros(k, bool), fresh=np.zeros(k, bool) if broyden else None,
                       want_jacobian=np.ones(k, bool) if broyden else None,
                       polish=np.zeros(k, bool) if broyden else None)

    def update(evaluation: Evaluation, state: LMState) -> LMState:
        secant, use_secant, fresh, polish = state.secant, state.use_secant, state.fresh, state.polish
        redo = np.zeros(len(state.z), bool)
        if state.current is None:  # the runs at the starts
            accepted = (evaluation.status == 0) & np.isfinite(evaluation.loss)
            z, lam, rejections, stop = state.z_next, state.lam, state.rejections, ~accepted
            current = evaluation._replace(loss=np.where(accepted, evaluation.loss, np.nan))
            messages = [f"stopped: the run at the start fails (status {s}; loss {v})"
                        for s, v in zip(evaluation.status, evaluation.loss)]
            fresh = None if fresh is None else np.ones(len(z), bool)
        else:
            c, step = state.current, state.z_next - state.z
            refreshed = state.want_jacobian & (step == 0).all(axis=1) if broyden else redo  # the runs at z again
            if broyden:
                evaluation, own = _broyden_filled(evaluation, c, step)
            accepted, lam, rejections, stop, messages = judge(
                c.loss, c.theta, evaluation.loss, evaluation.theta, evaluation.status == 0, state.promised,
                state.lam, state.rejections, c.residuals.shape[1], options)
            accepted &= ~refreshed
            if adaptive:
                secant, use_secant = _choose_model(state, evaluation, accepted)
            z = np.where(accepted[:, None], state.z_next, state.z)
            current = where_rows(accepted | refreshed, evaluation, c)
            if broyden:  # a step from an estimate that fails, gains little or would stop: the exact Jacobian next
                with np.errstate(all="ignore"):
                    poor = accepted & ~((c.loss - evaluation.loss) >= POOR_RATIO * _linear_decrease(c, step))
                redo = ~state.fresh & ~refreshed & (~accepted | stop | poor)
                polish = polish | (~state.fresh & ~refreshed & stop)
                keep = redo | refreshed
                lam, rejections = np.where(refreshed, state.lam, lam), np.where(keep, state.rejections, rejections)
                stop = stop & ~keep
                use_secant = np.where(refreshed, state.use_secant, use_secant)
                messages = ["" if keep[i] else m for i, m in enumerate(messages)]
                fresh = np.where(refreshed, True, np.where(accepted, own, state.fresh))
        done = state.done | stop
        message = np.where(stop, np.array(messages, object), state.message)
        z_next, promised = z.copy(), np.full(len(z), np.nan)
        go = ~done & ~redo
        if go.any():
            model = np.where(use_secant[go, None, None], secant[go], 0.0) if adaptive else None
            delta, promised[go] = propose(current.residuals[go], current.jacobian_z[go], lam[go], model)
            z_next[go] = z[go] + delta
        return LMState(z=z, current=current, lam=lam, rejections=rejections, z_next=z_next, promised=promised,
                       accepted=accepted, done=done, message=message, secant=secant, use_secant=use_secant,
                       fresh=fresh, want_jacobian=redo | polish if broyden else None, polish=polish)

    return Optimiser(init, update)


def _linear_decrease(current: Evaluation, step):
    """(k,) the loss decrease the linear model at ``current`` forecasts for ``step``: ‖r‖² − ‖r + J s‖²."""
    return current.loss - np.sum((current.residuals + np.einsum("kmi,ki->km", current.jacobian_z, step)) ** 2, axis=1)


def _broyden_filled(evaluation: Evaluation, current: Evaluation, step):
    """``evaluation`` with ``jacobian_z`` Broyden's estimate (``broyden_update`` from ``current``)
    in the rows whose runs did not give their own (``jacobian`` stays NaN there), and (k,) whether
    each row's is its own."""
    own = np.all(np.isfinite(evaluation.jacobian_z), axis=(1, 2))
    with np.errstate(all="ignore"):  # a failed trial's residuals may be NaN; it is rejected
        estimate = broyden_update(current.jacobian_z, step, current.residuals, evaluation.residuals)
    return evaluation._replace(jacobian_z=np.where(own[:, None, None], evaluation.jacobian_z, estimate)), own


def with_exact_jacobians(state: LMState, rows, evaluate) -> LMState:
    """``state`` with the current evaluation of each of ``rows`` whose Jacobian is Broyden's
    estimate replaced by runs with their own (``evaluate(z, jacobian=...)``, at the accepted
    points): what a verdict or an interval needs. Unchanged for "exact" LM."""
    if state.fresh is None:
        return state
    rows = np.array([i for i in np.atleast_1d(rows) if not state.fresh[i]], int)
    if rows.size == 0:
        return state
    evaluation = evaluate(state.z[rows], jacobian=np.ones(rows.size, bool))

    def put(full, part):
        full = np.array(full, copy=True)
        full[rows] = part
        return full

    fresh = state.fresh.copy()
    fresh[rows] = True
    return state._replace(current=jax.tree.map(put, state.current, evaluation), fresh=fresh)


def _choose_model(state: LMState, evaluation: Evaluation, accepted):
    """The secant estimate and the next step's model after a batch of trials. Each accepted step
    updates S (``secant_update``) and picks the model whose forecast of the step's decrease was
    nearer the decrease the runs gave: Gauss–Newton's ‖r‖² − ‖r + J s‖², or that less sᵀ S s
    with the S the step was taken with (the updated S while S was still zero, so that the first
    accepted step can start using it). A rejected step taken with S makes the next one
    Gauss–Newton's."""
    c, secant = state.current, state.secant
    step = state.z_next - state.z
    r, J = c.residuals, c.jacobian_z
    with np.errstate(all="ignore"):  # a rejected trial's residuals may be NaN; only accepted rows are used
        updated = secant_update(secant, step, r, J, evaluation.residuals, evaluation.jacobian_z)
        gauss_newton = _linear_decrease(c, step)
        forecast_with = np.where(np.any(secant != 0, axis=(1, 2))[:, None, None], secant, updated)
        with_secant = gauss_newton - np.einsum("ki,kij,kj->k", step, forecast_with, step)
        actual = c.loss - evaluation.loss
        better = np.abs(actual - with_secant) < np.abs(actual - gauss_newton)
    secant = np.where(accepted[:, None, None] & np.isfinite(updated), updated, secant)
    return secant, accepted & better
