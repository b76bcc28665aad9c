"""Fitting: Levenberg–Marquardt on the residual Jacobian, or optax Adam, with a resumable history.

Both optimisers work on unconstrained z (``calibration.bounds``), so every iterate is a
physical parameter set. Each iteration is one model evaluation. ``fit`` runs one start (a batch
of one) of the optimiser through the driver loop ``calibration.loop.run``, which records every
iteration in a ``calibration.history.History``:

- ``method="lm"``: Levenberg–Marquardt with Marquardt's diagonal scaling
  (``calibration.lm.levenberg_marquardt``: the step and the stopping rules the batched
  ``calibration.search`` uses too). Every evaluation returns the residuals and their Jacobian
  together (forward mode, one batched tangent pass); a trial step is accepted when the loss
  falls and the run has no status bits. A run that fails (status bits: the flow left the grid,
  non-finite stress, ...) is a rejected trial, reported in the history; a failing run at the
  start is an error.
- ``method="adam"``: optax Adam with gradient clipping and a cosine learning-rate schedule
  (``calibration.adam``); the gradient comes from forward mode (``grad_mode="fwd"``, J_θᵀ r) or
  reverse mode through the checkpointed rollout (``"rev"``). The best iterate is returned.

The result carries a ``Verdict`` (``calibration.uncertainty.judge_point``): a point that is not a
verified minimum (LM stopped on its rejection or step budget), sits at a bound, or leaves a misfit
well above the noise is "not a fit of the data", and its uncertainty holds no interval. A scene
value on a bound (S4's β = 0) is not a usable start: the fit starts inside (``start_theta``) and
``start_note`` says where.

After every iteration the whole history (θ, z, loss, gradient norm, status, accepted flag, λ,
wall time) and what is needed to continue (LM: the accepted point and λ; Adam: the current
point and the optimiser state) is written to ``out`` (HDF5, written to a temporary file and
renamed, so a kill never leaves a partial file). ``resume=True`` continues from that file
exactly where it stopped (LM runs its accepted point again, not counted as an iteration): the
resumed trajectory equals the uninterrupted one. The file records the objective's
``fingerprint`` (the data's content, the scene and every option that changes the loss), and a
resume refuses an objective whose fingerprint differs, naming what differs; it also refuses a
missing file. An existing file is never replaced by a new fit unless ``overwrite=True``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .adam import adam
from .history import History, check_out, read_history
from .lm import LMOptions, LMState, levenberg_marquardt
from .loop import Evaluation, run, status_text
from .objective import jacobians_z
from .options import METHODS, FitOptions, JudgeOptions, split_fields
from .protocol import ObjectiveLike
from .uncertainty import Uncertainty, Verdict, judge_point
from .workers import using

__all__ = ["METHODS", "FitResult", "fit", "read_history", "start_theta"]

#: The optimiser options a resume must share with the file (the others may change).
@dataclasses.dataclass
class FitResult:
    keys: tuple[str, ...]
    theta: dict[str, float]
    loss: float
    iterations: int
    wall_s: float
    method: str
    converged: bool
    message: str
    history: dict[str, np.ndarray]
    residuals: np.ndarray
    jacobian: np.ndarray
    prediction: dict[str, Any]
    uncertainty: Uncertainty | None = None
    start: dict[str, float] | None = None  # where the fit started (physical values)
    start_note: str = ""  # why the start differs from the scene's values, if it does
    verdict: Verdict | None = None

    def to_json(self) -> dict[str, Any]:
        out = {"params": self.theta, "loss": self.loss, "iterations": self.iterations,
               "wall_s": round(self.wall_s, 3), "method": self.method, "converged": self.converged,
               "message": self.message}
        if self.start is not None:
            out["start"] = self.start
        if self.start_note:
            out["start_note"] = self.start_note
        if self.verdict is not None:
            out["verdict"] = self.verdict.to_dict()
            if self.verdict.scatter is not None:
                out["roundoff"] = self.verdict.scatter.to_dict(self.keys)
        if self.uncertainty is not None:
            u = self.uncertainty.to_dict()
            if "stderr" in u:
                out["stderr"] = u.pop("stderr")
            out.update(u)
        return out


def start_theta(objective: ObjectiveLike, init: Mapping[str, float] | None) -> tuple[np.ndarray, str]:
    """The start θ of a fit and a note saying where it differs from the scene's values.

    A key in ``init`` (the user's choice) must lie strictly inside its bounds (an error names
    it otherwise); a key left to the scene whose value sits on or next to a bound (S4's β = 0 on
    (0, 1)) starts ``Bounds.move_inside`` that bound instead, and the note says so."""
    init = dict(init or {})
    unknown = sorted(set(init) - set(objective.keys))
    if unknown:
        raise ValueError(f"init: {unknown} are not fitted keys {objective.keys}")
    bounds = objective.bounds
    scene = objective.initial()
    theta, moved = bounds.move_inside([float(scene[k]) for k in objective.keys])
    for k, v in init.items():
        theta[objective.keys.index(k)] = float(v)
        moved.pop(k, None)
    try:
        bounds.check(theta, "init")  # only the user's values can fail here
    except ValueError as err:
        notes = [note for note in objective.bound_notes if any(note.startswith(f"{k}'s") for k in init)]
        raise ValueError("; ".join([str(err)] + notes)) from None
    objective.check_thetas(theta, "init")  # the engine's rules (mu2 >= mu1, ...) on the full parameter set
    note = "; ".join(f"{k}: the scene's value {old:g} lies on or next to its bound "
                     f"({bounds.lower[objective.keys.index(k)]:g}, {bounds.upper[objective.keys.index(k)]:g}), "
                     f"so the fit starts at {new:g}" for k, (old, new) in moved.items())
    return theta, note


def _evaluator(objective: ObjectiveLike, rev: bool, workers=None) -> Callable[[np.ndarray], Evaluation]:
    """The model at the rows of z (k, n), one run each: residuals and their Jacobian from the
    objective (forward mode, or its differences), or with ``rev`` the reverse-mode gradient alone.
    With parallel ``workers`` (``calibration.workers``) the forward-mode passes, one per key and
    row, run in the worker processes."""
    bounds = objective.bounds
    z_space = objective.jacobian == "ad"  # else central differences in θ (``residuals_and_jacobian``)
    if z_space and not rev and workers is not None and workers.parallel:
        return _parallel_evaluator(objective, workers)

    def one(z):
        theta = np.asarray(bounds.to_physical(jnp.asarray(z)))
        dtheta_dz = np.asarray(bounds.jacobian_diag(jnp.asarray(z)))
        if rev:
            (loss, pred), g = objective.value_and_grad(theta)
            r = J = Jz = None
            g = np.asarray(g)
        else:
            if z_space:  # dr/dz and dr/dθ from one autodiff trace through the bounds transform
                r, Jz, J, pred = objective.residuals_and_jacobian_z(jnp.asarray(z))
                r, Jz, J = np.asarray(r, float), np.asarray(Jz, float), np.asarray(J, float)
            else:  # central differences in θ
                r, J, pred = objective.residuals_and_jacobian(theta)
                r, J = np.asarray(r, float), np.asarray(J, float)
                Jz = J * dtheta_dz[None, :]
            with np.errstate(invalid="ignore", over="ignore"):
                loss, g = np.sum(r * r), 2.0 * J.T @ r
            return theta, float(loss), int(np.asarray(pred["status"])), g, r, J, Jz, 2.0 * Jz.T @ r, pred
        return theta, float(loss), int(np.asarray(pred["status"])), g, r, J, Jz, g * dtheta_dz, pred

    def evaluate(z):
        theta, loss, status, g, r, J, Jz, g_z, pred = zip(*[one(row) for row in z])
        r, J, Jz = (None if parts[0] is None else np.stack(parts) for parts in (r, J, Jz))
        return Evaluation(theta=np.stack(theta), loss=np.array(loss), status=np.array(status), grad=np.stack(g),
                          residuals=r, jacobian=J, jacobian_z=Jz, grad_z=np.stack(g_z),
                          prediction=jax.tree.map(lambda *leaves: np.stack([np.asarray(a) for a in leaves]), *pred))

    return evaluate


def _parallel_evaluator(objective: ObjectiveLike, workers) -> Callable[[np.ndarray], Evaluation]:
    """``_evaluator`` for forward-mode LM with the passes in ``workers``: the same Evaluation."""
    bounds = objective.bounds

    def evaluate(Z):
        r, Jz, J, pred = jacobians_z(objective, Z, workers)
        r, Jz, J = np.asarray(r, float), np.asarray(Jz, float), np.asarray(J, float)
        with np.errstate(invalid="ignore", over="ignore"):  # dθ/dz = 0 at a bound: J, |g| inf
            g = np.einsum("kmn,km->kn", 2.0 * J, r)
        g_z = np.einsum("kmn,km->kn", 2.0 * Jz, r)
        return Evaluation(theta=np.asarray(bounds.to_physical(jnp.asarray(Z)), float), loss=np.sum(r * r, axis=1),
                          status=np.asarray(pred["status"], int).reshape(-1), grad=g, residuals=r, jacobian=J,
                          jacobian_z=Jz, grad_z=g_z, prediction=pred)

    return evaluate


def _snapshot(state) -> dict[str, Any]:
    """What a resume needs from the state of one start, by the names of the history file: LM's
    accepted point and λ; Adam's current point and optax state (λ NaN)."""
    if isinstance(state, LMState):
        return {"z": state.z[0], "lam": state.lam[0]}
    leaves = jax.tree.leaves(state.inner)
    return {"z": state.z_next[0], "lam": np.nan, **{f"opt_{i}": np.asarray(leaf)[0] for i, leaf in enumerate(leaves)}}


def _restore(optimiser, saved: Mapping[str, Any], history: History):
    """The state of one start that ``_snapshot`` saved, continued: LM's rejections in a row
    are those at the end of the history; Adam's evaluations are its iterations."""
    state = optimiser.init(np.asarray(saved["z"], float)[None])
    common = {"done": np.array([bool(saved["done"])]), "message": np.array([saved["message"]], object)}
    if isinstance(state, LMState):
        accepted = history.arrays()["accepted"]
        rejections = len(accepted) - len(np.trim_zeros(accepted, "b"))
        return state._replace(lam=np.array([float(saved["lam"])]), rejections=np.array([rejections]), **common)
    template = jax.tree.leaves(state.inner)
    leaves = [jnp.asarray(saved[f"opt_{i}"], t.dtype)[None] for i, t in enumerate(template)]
    return state._replace(inner=jax.tree.unflatten(jax.tree.structure(state.inner), leaves),
                          count=np.array([history.iterations]), **common)


def fit(objective: ObjectiveLike, init: Mapping[str, float] | None = None, *, options: FitOptions | None = None,
        judge: JudgeOptions | None = None, out=None, resume: bool = False, overwrite: bool = False,
        progress: bool = False, callback: Callable | None = None, meta: Mapping[str, Any] | None = None,
        workers=None, **fields) -> FitResult:
    """Fit ``objective.keys`` from ``init`` (physical values by key; missing keys start at the
    scene's values). How it runs is ``options`` (``calibration.options.FitOptions``) and how its
    end point is judged ``judge`` (``JudgeOptions``); any of their fields may also be given by
    name (``steps=10``, ``grid_ratio=1.5``), replacing the object's value. ``steps``: the
    maximum number of iterations (model evaluations), counted
    over resumes. ``out``: the HDF5 history file; ``resume``: continue from it (it must exist
    and hold a fit of the same objective: same fingerprint, keys, method and optimiser options);
    ``overwrite``: replace an existing ``out`` with a new fit (without it an existing file is an
    error, so that no history is lost by accident). ``noise``: the
    known noise per residual block, for the uncertainty (None: estimated from the residuals).
    LM stops when the decrease its linearised model promises for the next step is below
    ``stat_tol`` × n σ² (σ² = loss / (m − n), what fitting pure noise would promise: the step is
    then a fraction sqrt(stat_tol) of a standard error, and the loss differences are at the
    level of the runs' round-off or chaotic scatter), when an accepted step lowers the loss by
    less than ``ftol`` (relative) or moves θ by less than ``xtol`` (relative), or after
    ``max_rejections`` rejected steps in a row.
    ``callback(iteration, record)`` is called after each iteration is written.
    ``roundoff_samples`` perturbed runs at the end point measure the run's own round-off scatter
    for the verdict and the interval (``uncertainty.model_scatter``; 0: not measured);
    ``sampling_seeds`` other draws of the particles add the sampling's share to the interval
    (``uncertainty.sampling_scatter``; 0, the default: not measured); ``reference_noise`` and
    ``threshold`` decide which parameters count as constrained. ``grid_ratio``: the grid's
    share of the interval from the objective rebuilt at that multiple of its dx, ``grid_draws``
    particle draws there (``uncertainty.grid_shift``; None, the default: not measured; the
    command line's ``--grid-check`` is 1.5). ``workers``: an integer or a
    ``calibration.workers.Workers``; with more than one, each iteration's forward-mode passes
    (one per key) and the verdict's extra runs go to that many single-threaded processes (the
    same numbers as one process; None or 1: everything in this process)."""
    run_fields, judge_fields = split_fields(fields)
    options = dataclasses.replace(options or FitOptions(), **run_fields)
    judge = dataclasses.replace(judge or JudgeOptions(), **judge_fields)
    method, steps, grad_mode = options.method, options.steps, options.grad_mode
    path = check_out(out, resume=resume, overwrite=overwrite)
    bounds, keys = objective.bounds, objective.keys
    fingerprint = objective.fingerprint()
    fingerprint = None if fingerprint is None else json.loads(json.dumps(fingerprint))
    header = None if path is None else {
        "keys": list(keys), "method": method, "options": options.to_json(), "judge": judge.to_json(),
        "objective": objective.describe(), "fingerprint": fingerprint, "meta": dict(meta or {})}
    if method == "lm":
        optimiser = levenberg_marquardt(LMOptions(xtol=options.xtol, ftol=options.ftol, stat_tol=options.stat_tol,
                                                  max_rejections=options.max_rejections))
    else:
        optimiser = adam(options.learning_rate, steps=steps, clip=options.clip)

    start_note = ""
    if resume:
        history, saved = History.resume(path, header, differences=options.differences, snapshot=_snapshot)
        state = _restore(optimiser, saved, history)
    else:
        theta0, start_note = start_theta(objective, init)
        history = History(path=path, header=header, snapshot=_snapshot)
        state = optimiser.init(bounds.to_unconstrained(theta0)[None])
    with using(workers) as workers:
        evaluate = _evaluator(objective, rev=method == "adam" and grad_mode == "rev", workers=workers)
        if method == "lm" and history.iterations:  # resumed: run the accepted point again (not an iteration)
            state = optimiser.update(evaluate(state.z_next), state)

        def check_start(evaluation):
            status, loss = int(evaluation.status[0]), float(evaluation.loss[0])
            if status or not math.isfinite(loss):
                raise ValueError(f"init: the run at the initial parameters fails ({status_text(status)}; "
                                 f"loss {loss}); choose another start")

        bar = None
        if progress:
            try:
                from tqdm import tqdm

                bar = tqdm(total=steps, initial=history.iterations, desc=f"fit ({method})", unit="it")
            except ImportError:
                bar = None

        def report(state, rows):
            last = history.last()
            if bar is not None:
                bar.set_postfix_str(f"loss {last['loss']:.3e} " +
                                    " ".join(f"{key}={v:.4g}" for key, v in zip(keys, last["theta"])))
                bar.update(1)
            if callback is not None:
                callback(history.iterations - 1, last)

        state = run(optimiser, state, evaluate, history, steps=steps,
                    check_start=check_start if method == "lm" else None, report=report)
        if bar is not None:
            bar.close()
        done, message = bool(state.done[0]), str(state.message[0])

        hist = history.arrays()
        ok_rows = np.flatnonzero((hist["status"] == 0) & np.isfinite(hist["loss"]))
        if ok_rows.size == 0:
            raise ValueError("fit: no iteration produced a valid run")
        i_best = ok_rows[np.argmin(hist["loss"][ok_rows])]
        theta_best = hist["theta"][i_best]
        current = state.current if method == "lm" else None  # LM's accepted point, with its run
        if current is not None and np.array_equal(current.theta[0], theta_best):
            loss_b, r_b, J_b = float(current.loss[0]), current.residuals[0], current.jacobian[0]
            pred_b = jax.tree.map(lambda a: a[0], current.prediction)
        else:
            r_b, J_b, pred_b = objective.residuals_and_jacobian(theta_best)
            r_b, J_b = np.asarray(r_b, float), np.asarray(J_b, float)
            loss_b = float(np.sum(r_b * r_b))
        converged = done and message.startswith("converged")
        verdict, unc = judge_point(objective, r_b, J_b, theta_best, converged=converged, message=message,
                                   workers=workers, **judge.kwargs())
        return FitResult(keys=keys, theta={k: float(v) for k, v in zip(keys, theta_best)}, loss=float(loss_b),
                         iterations=len(hist["loss"]), wall_s=float(hist["wall_s"][-1]) if len(hist["wall_s"]) else 0.0,
                         method=method, converged=converged, message=message,
                         history=hist, residuals=r_b, jacobian=J_b,
                         prediction=jax.tree.map(np.asarray, pred_b), uncertainty=unc,
                         start={k: float(v) for k, v in zip(keys, hist["theta"][0])}, start_note=start_note,
                         verdict=verdict)
