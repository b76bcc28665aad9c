"""Fitting: Levenberg–Marquardt on the residual Jacobian, or optax Adam, with a resumable history.

``fit`` runs one start (a batch of one) of ``calibration.optim.lm`` or ``calibration.optim.adam``
in the unconstrained z (every iterate is a physical parameter set) through the driver loop
``calibration.optim.loop.run``, one model evaluation per iteration. Every iteration is written to
``out`` (``calibration.optim.history``), from which ``resume=True`` continues exactly where it
stopped. The result carries a ``Verdict`` (``calibration.inference.verdict.judge_point``): a point
that is not a verified minimum, sits at a bound or leaves a misfit well above the noise is "not a
fit of the data", and gets no interval. docs/fitting.md describes the steps and the stops.
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

from ..batch.workers import progress_bar, using
from ..inference.gauss_newton import Uncertainty
from ..inference.options import JudgeOptions
from ..inference.scatter import model_scatter, roundoff_limit
from ..inference.verdict import Verdict, judge_point
from ..problem.protocol import ObjectiveLike
from .adam import adam
from .evaluate import evaluator
from .history import History, check_out
from .lm import LMState, levenberg_marquardt, with_exact_jacobians
from .loop import run, status_text
from .options import FitOptions, split_fields
from .record import write_record

__all__ = ["FitResult", "start_theta", "fit", "roundoff_stop", "measured_at", "ROUNDOFF_CHECK_AFTER"]


#: LM's point is judged against the run's round-off scatter after this many rejected steps in a row.
ROUNDOFF_CHECK_AFTER = 2


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
    restarts: list[dict[str, Any]] = dataclasses.field(default_factory=list)  # the fits before it (``_restarted``)

    def to_json(self) -> dict[str, Any]:
        out = {"params": self.theta, "loss": self.loss, "iterations": self.iterations,
               "wall_s": round(self.wall_s, 3), "method": self.method, "converged": self.converged,
               "message": self.message}
        if self.start is not None:
            out["start"] = self.start
        if self.start_note:
            out["start_note"] = self.start_note
        if self.restarts:
            out["restarts"] = self.restarts
        if self.verdict is not None:
            out["verdict"] = self.verdict.to_dict()
            if self.verdict.scatter is not None:
                out["roundoff"] = self.verdict.scatter.to_dict(self.keys)
            if self.verdict.probe is not None:
                out["probe"] = self.verdict.probe.to_dict(self.keys)
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
    accepted point, λ, and its secant estimate and model choice; Adam's current point and optax
    state (λ NaN)."""
    if isinstance(state, LMState):
        return {"z": state.z[0], "lam": state.lam[0], "secant": state.secant[0], "use_secant": state.use_secant[0]}
    leaves = jax.tree.leaves(state.inner)
    return {"z": state.z_next[0], "lam": np.nan, **{f"opt_{i}": np.asarray(leaf)[0] for i, leaf in enumerate(leaves)}}


def _restore(optimiser, saved: Mapping[str, Any], history: History):
    """The state of one start that ``_snapshot`` saved, continued: LM's rejections in a row
    are those at the end of the history, its secant estimate and model choice the file's (none
    in a file from before they were kept, which is a Gauss–Newton fit's); Adam's evaluations are
    its iterations."""
    state = optimiser.init(np.asarray(saved["z"], float)[None])
    common = {"done": np.array([bool(saved["done"])]), "message": np.array([saved["message"]], object)}
    if isinstance(state, LMState):
        accepted = history.arrays()["accepted"]
        rejections = len(accepted) - len(np.trim_zeros(accepted, "b"))
        secant = {"secant": np.asarray(saved["secant"], float)[None],
                  "use_secant": np.array([bool(saved["use_secant"])])} if "secant" in saved else {}
        return state._replace(lam=np.array([float(saved["lam"])]), rejections=np.array([rejections]), **secant,
                              **common)
    template = jax.tree.leaves(state.inner)
    leaves = [jnp.asarray(saved[f"opt_{i}"], t.dtype)[None] for i, t in enumerate(template)]
    return state._replace(inner=jax.tree.unflatten(jax.tree.structure(state.inner), leaves),
                          count=np.array([history.iterations]), **common)


def fit(objective: ObjectiveLike, init: Mapping[str, float] | None = None, *, options: FitOptions | None = None,
        judge: JudgeOptions | None = None, out=None, resume: bool = False, overwrite: bool = False,
        progress: bool = False, callback: Callable | None = None, meta: Mapping[str, Any] | None = None,
        workers=None, **fields) -> FitResult:
    """Fit ``objective.keys`` from ``init`` (physical values by key; missing keys start at the
    scene's values, moved off a bound: ``start_theta``). How it runs is ``options``
    (``FitOptions``: the method, ``steps`` counted over resumes, LM's stops) and how its end point
    is judged ``judge`` (``JudgeOptions``: noise, round-off, sampling and grid terms); any of their
    fields may also be given by name (``steps=10``, ``grid_ratio=1.5``), replacing the object's
    value. ``out``: the HDF5 history file; ``resume``: continue from it (it must exist and hold a
    fit of the same objective: same fingerprint, keys, method and optimiser options);
    ``overwrite``: replace an existing ``out`` (without it an existing file is an error, so that no
    history is lost by accident). ``callback(iteration, record)`` is called after each iteration
    is written. ``workers``: an integer or a ``calibration.batch.workers.Workers``; with more than
    one, each iteration's forward-mode passes and the verdict's extra runs go to that many
    single-threaded processes (the same numbers as one process)."""
    run_fields, judge_fields = split_fields(fields)
    options = dataclasses.replace(options or FitOptions(), **run_fields)
    judge = dataclasses.replace(judge or JudgeOptions(), **judge_fields)
    method = options.method
    path = check_out(out, resume=resume, overwrite=overwrite)
    header = None if path is None else file_header(objective, options, judge, meta)
    optimiser = (levenberg_marquardt(options.lm_options()) if method == "lm"
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
        scatters: dict = {}
        stop = roundoff_stop(objective, judge.roundoff_samples, workers, scatters) if method == "lm" else None
        with _progress(objective.keys, history, options, progress, callback) as report:
            state = run(optimiser, state, evaluate, history, steps=options.steps,
                        check_start=_check_start if method == "lm" else None, report=report, stop=stop)
        if method == "lm":  # the verdict's Jacobian, not Broyden's estimate
            state = with_exact_jacobians(state, [0], evaluate)
        result = _result(objective, state, history, method, start_note, judge, workers, scatters)
    if path is not None:
        write_record(path, result)
    return result


def roundoff_stop(objective: ObjectiveLike, samples: int, workers, scatters: dict):
    """The loop's ``stop`` for LM: a start whose last ``ROUNDOFF_CHECK_AFTER`` steps were rejected
    is converged when its remaining Gauss–Newton step lies within the run's round-off scatter, as
    the verdict judges it (``roundoff_limit``): no run can resolve a better point. The scatter is
    measured once per start (``model_scatter``, ``samples`` perturbed runs; 0: never) and kept in
    ``scatters`` as {start: (θ, scatter)}, for the verdict to reuse at the same point."""
    n = len(objective.keys)

    def stop(state):
        check = ~state.done & (state.rejections == ROUNDOFF_CHECK_AFTER) if samples >= 2 else []
        done, message, c = state.done.copy(), state.message.copy(), state.current
        for i in np.flatnonzero(check):
            if i not in scatters and np.all(np.isfinite(c.jacobian[i])):
                scatter = model_scatter(objective, c.theta[i], c.residuals[i], c.jacobian[i], samples=samples,
                                        workers=workers)
                scatters[i] = (np.array(c.theta[i]), scatter)
            scatter = scatters.get(i, (None, None))[1]
            if scatter is None:
                continue
            distance, limit = scatter.gauss_newton_distance(c.jacobian[i], c.residuals[i]), roundoff_limit(
                n, scatter.samples)
            if distance <= limit:
                done[i] = True
                message[i] = (f"converged within the run's round-off: the remaining Gauss–Newton step is "
                              f"{distance:.2g} standard deviations of the scatter {scatter.samples} perturbed runs "
                              f"show (limit {limit:.2g})")
        return state._replace(done=done, message=message)

    return stop


def measured_at(scatters: dict, start: int, theta):
    """The scatter ``roundoff_stop`` measured for ``start`` if it was measured at ``theta``, else None."""
    theta0, scatter = scatters.get(start, (None, None))
    return scatter if theta0 is not None and np.array_equal(theta0, theta) else None


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
    bar = progress_bar(progress, total=options.steps, initial=history.iterations, desc=f"fit ({options.method})",
                       unit="it")

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


def _result(objective, state, history, method: str, start_note: str, judge: JudgeOptions, workers,
            scatters: dict) -> FitResult:
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
                               workers=workers, scatter=measured_at(scatters, 0, theta_best), **judge.kwargs())
    return FitResult(keys=keys, theta={k: float(v) for k, v in zip(keys, theta_best)}, loss=float(loss_b),
                     iterations=len(hist["loss"]), wall_s=float(hist["wall_s"][-1]) if len(hist["wall_s"]) else 0.0,
                     method=method, converged=converged, message=message, history=hist, residuals=r_b, jacobian=J_b,
                     prediction=jax.tree.map(np.asarray, pred_b), uncertainty=unc,
                     start={k: float(v) for k, v in zip(keys, hist["theta"][0])}, start_note=start_note,
                     verdict=verdict)
