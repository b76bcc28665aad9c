"""Fitting: Levenberg–Marquardt on the residual Jacobian, or optax Adam, with a resumable history.

Both optimisers work on unconstrained z (``calibration.problem.bounds``), so every iterate is a
physical parameter set. Each iteration is one model evaluation. ``fit`` runs one start (a batch
of one) of the optimiser through the driver loop ``calibration.optim.loop.run``, which records every
iteration in a ``calibration.optim.history.History``:

- ``method="lm"``: Levenberg–Marquardt with Marquardt's diagonal scaling
  (``calibration.optim.lm.levenberg_marquardt``: the step and the stopping rules the batched
  ``calibration.optim.search`` uses too). Every evaluation returns the residuals and their Jacobian
  together (forward mode, one batched tangent pass); a trial step is accepted when the loss
  falls and the run has no status bits. A run that fails (status bits: the flow left the grid,
  non-finite stress, ...) is a rejected trial, reported in the history; a failing run at the
  start is an error.
- ``method="adam"``: optax Adam with gradient clipping and a cosine learning-rate schedule
  (``calibration.optim.adam``); the gradient comes from forward mode (``grad_mode="fwd"``, J_θᵀ r) or
  reverse mode through the checkpointed rollout (``"rev"``). The best iterate is returned.

The result carries a ``Verdict`` (``calibration.inference.verdict.judge_point``): a point that is not a
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

import contextlib
import dataclasses
import json
import math
import types
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..batch.workers import using
from ..inference.gauss_newton import Uncertainty
from ..inference.options import JudgeOptions
from ..inference.verdict import Verdict, judge_point
from ..problem.protocol import ObjectiveLike
from .adam import adam
from .evaluate import evaluator
from .history import History, check_out
from .lm import LMOptions, LMState, levenberg_marquardt
from .loop import run, status_text
from .options import FitOptions, split_fields
from .record import write_record

__all__ = ["FitResult", "start_theta", "fit"]


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
    scene's values). How it runs is ``options`` (``calibration.optim.options.FitOptions``) and how its
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
    ``calibration.batch.workers.Workers``; with more than one, each iteration's forward-mode passes
    (one per key) and the verdict's extra runs go to that many single-threaded processes (the
    same numbers as one process; None or 1: everything in this process)."""
    run_fields, judge_fields = split_fields(fields)
    options = dataclasses.replace(options or FitOptions(), **run_fields)
    judge = dataclasses.replace(judge or JudgeOptions(), **judge_fields)
    method = options.method
    path = check_out(out, resume=resume, overwrite=overwrite)
    header = None if path is None else file_header(objective, options, judge, meta)
    optimiser = (levenberg_marquardt(LMOptions(xtol=options.xtol, ftol=options.ftol, stat_tol=options.stat_tol,
                                               max_rejections=options.max_rejections)) if method == "lm"
                 else adam(options.learning_rate, steps=options.steps, clip=options.clip))
    start_note = ""
    if resume:
        history, saved = History.resume(path, header, differences=options.differences, snapshot=_snapshot)
        state = _restore(optimiser, saved, history)
    else:
        theta0, start_note = start_theta(objective, init)
        history = History(path=path, header=header, snapshot=_snapshot)
        state = optimiser.init(objective.bounds.to_unconstrained(theta0)[None])
    with using(workers) as workers:
        evaluate = evaluator(objective, rev=method == "adam" and options.grad_mode == "rev", workers=workers)
        if method == "lm" and history.iterations:  # resumed: run the accepted point again (not an iteration)
            state = optimiser.update(evaluate(state.z_next), state)
        with _progress(objective.keys, history, options, progress, callback) as report:
            state = run(optimiser, state, evaluate, history, steps=options.steps,
                        check_start=_check_start if method == "lm" else None, report=report)
        result = _result(objective, state, history, method, start_note, judge, workers)
    if path is not None:
        write_record(path, result)
    return result


def file_header(objective, options: FitOptions, judge: JudgeOptions, meta) -> dict[str, Any]:
    """The attributes of a fit's file: what it fitted (keys, the objective's description and
    fingerprint), how (method, options) and the caller's ``meta`` (the command, its setup)."""
    fingerprint = objective.fingerprint()
    return {"keys": list(objective.keys), "method": options.method, "options": options.to_json(),
            "judge": judge.to_json(), "objective": objective.describe(), "meta": dict(meta or {}),
            "fingerprint": None if fingerprint is None else json.loads(json.dumps(fingerprint))}


def save_start(path, objective, result: FitResult, options: FitOptions, judge: JudgeOptions, meta) -> None:
    """Write ``result``, the best start of a search, as a finished single-start fit's file: its
    history, LM's state at its point (a resume goes on from there as one start) and its record."""
    hist = result.history
    z = objective.bounds.to_unconstrained(np.array([result.theta[k] for k in result.keys]))
    history = History(path=path, header=file_header(objective, options, judge, meta),
                      snapshot=lambda state: {"z": z, "lam": float(hist["lam"][-1])})
    history._starts = [{k: list(v) for k, v in hist.items()}]
    history.iterations = len(hist["loss"])
    history._save(types.SimpleNamespace(done=np.array([True]), message=np.array([result.message], object)))
    write_record(path, result)


def _check_start(evaluation) -> None:
    """Refuse a start whose run fails: nothing can be learnt from it."""
    status, loss = int(evaluation.status[0]), float(evaluation.loss[0])
    if status or not math.isfinite(loss):
        raise ValueError(f"init: the run at the initial parameters fails ({status_text(status)}; loss {loss}); "
                         "choose another start")


@contextlib.contextmanager
def _progress(keys, history, options: FitOptions, progress: bool, callback):
    """The loop's ``report(state, rows)``: a tqdm bar (with ``progress``, where tqdm is
    installed) and the user's ``callback(iteration, record)``, after each iteration is saved."""
    bar = None
    if progress:
        try:
            from tqdm import tqdm

            bar = tqdm(total=options.steps, initial=history.iterations, desc=f"fit ({options.method})", unit="it")
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

    try:
        yield report
    finally:
        if bar is not None:
            bar.close()


def _result(objective, state, history, method: str, start_note: str, judge: JudgeOptions, workers) -> FitResult:
    """The fit's result: its best valid iterate (LM's accepted point, with its run; else run again
    for its Jacobian), judged (``judge_point``)."""
    keys = objective.keys
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
                     method=method, converged=converged, message=message, history=hist, residuals=r_b, jacobian=J_b,
                     prediction=jax.tree.map(np.asarray, pred_b), uncertainty=unc,
                     start={k: float(v) for k, v in zip(keys, hist["theta"][0])}, start_note=start_note,
                     verdict=verdict)
