"""Fitting: Levenberg–Marquardt on the residual Jacobian, or optax Adam, with a resumable history.

Both optimisers work on unconstrained z (``calibration.bounds``), so every iterate is a
physical parameter set. Each iteration is one model evaluation.

- ``method="lm"``: Levenberg–Marquardt with Marquardt's diagonal scaling (the step and the
  stopping rules of ``calibration.lm``, shared with the batched ``calibration.search``). Every
  evaluation returns the residuals and their Jacobian together (forward mode, one batched
  tangent pass); a trial step is accepted when the loss falls and the run has no status bits.
  A run that fails (status bits: the flow left the grid, non-finite stress, ...) is a rejected
  trial, reported in the history.

The result carries a ``Verdict`` (``calibration.uncertainty.assess_fit``): a point that is not a
verified minimum (LM stopped on its rejection or step budget), sits at a bound, or leaves a misfit
well above the noise is "not a fit of the data", and its uncertainty holds no interval. A scene
value on a bound (S4's β = 0) is not a usable start: the fit starts inside (``start_theta``) and
``start_note`` says where.
- ``method="adam"``: optax Adam with gradient clipping and a cosine learning-rate schedule; the
  gradient comes from forward mode (``grad_mode="fwd"``, J_θᵀ r) or reverse mode through the
  checkpointed rollout (``"rev"``). The best iterate is returned.

After every iteration the whole history (θ, z, loss, gradient norm, status, accepted flag, λ,
wall time) and what is needed to continue (the current point, λ or the optimiser state) is
written to ``out`` (HDF5, written to a temporary file and renamed, so a kill never leaves a
partial file). ``resume=True`` continues from that file exactly where it stopped: the resumed
trajectory equals the uninterrupted one. The file records the objective's ``fingerprint`` (the
data's content, the scene and every option that changes the loss), and a resume refuses an
objective whose fingerprint differs, naming what differs; it also refuses a missing file. An
existing file is never replaced by a new fit unless ``overwrite=True``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import re
import time
import uuid
from typing import Any, Callable, Mapping

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxmpm import describe_status

from .lm import LAM0, LMOptions, judge, propose
from .uncertainty import ROUNDOFF_SAMPLES, Uncertainty, Verdict, judge_point

__all__ = ["METHODS", "FitResult", "fit", "read_history", "start_theta"]

METHODS = ("lm", "adam")
_HISTORY_FIELDS = ("theta", "z", "loss", "grad_norm", "status", "accepted", "lam", "wall_s")


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


def _atomic_h5(path: pathlib.Path, write: Callable[[h5py.File], None]) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with h5py.File(tmp, "w") as f:
            write(f)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


class _NotAHistory(Exception):
    pass


def read_history(path) -> dict[str, Any]:
    """A history file as ``{"attrs": {...}, "history": {field: array}, "resume": {...}}``.

    Raises ``ValueError`` naming the file when it does not exist, is not a readable HDF5 file
    (empty, truncated, some other format) or is an HDF5 file of another kind (a run's output)."""
    path = pathlib.Path(path)
    shown = repr(str(path))
    if not path.exists():
        raise ValueError(f"out: {shown} does not exist (nothing to resume)")
    if not path.is_file():
        raise ValueError(f"out: {shown} is not a file")
    try:
        with h5py.File(path, "r") as f:
            missing = [f"attribute {k!r}" for k in ("keys_json", "method", "options_json") if k not in f.attrs]
            missing += [f"group {g!r}" for g in ("history", "resume") if g not in f]
            if missing:
                raise _NotAHistory(f"no {', '.join(missing)}")
            attrs = {k: (json.loads(v) if k.endswith("_json") else v) for k, v in f.attrs.items()}
            history = {k: np.asarray(f["history"][k]) for k in f["history"]}
            resume = {k: np.asarray(f["resume"][k]) for k in f["resume"]}
    except _NotAHistory as err:
        raise ValueError(f"{shown} is not a fit history written by calibration.fit ({err})") from None
    except (OSError, KeyError, ValueError, TypeError) as err:  # h5py's errors for unreadable files are OSErrors
        raise ValueError(f"{shown} is not a readable fit history: {type(err).__name__}: {err} (an empty or "
                         "truncated file, or not HDF5 at all?)") from None
    missing = [k for k in _HISTORY_FIELDS if k not in history] + [k for k in ("z", "lam", "done") if k not in resume]
    lengths = {k: len(history[k]) for k in _HISTORY_FIELDS if k in history}
    if missing or len(set(lengths.values())) > 1:
        raise ValueError(f"{shown} is not a complete fit history (missing {missing}, lengths {lengths})")
    return {"attrs": attrs, "history": history, "resume": resume}


#: Which command-line option sets each entry of ``Objective.fingerprint`` (for resume errors).
_FINGERPRINT_OPTIONS = {
    "scene": "--scene", "data": "--data/--front: their content", "keys": "--fit", "dx": "--dx", "ppc": "--ppc",
    "sampling": "--sampling", "seed": "--seed", "dim": "--dim", "width": "--width", "slope_deg": "--slope",
    "L": "--aspect", "H": "--aspect", "t_end": "--t-end", "fixed": "--set",
    "weights": "--weight-profile/--weight-front", "sigma": "sigma", "front_threshold": "--front-threshold",
    "x_ref": "x_ref", "bounds": "bounds", "dtype": "--dtype", "jacobian": "--jacobian", "fd_step": "--fd-step",
    "n_particles": "--dx/--ppc/--sampling", "particles": "--ppc/--sampling/--seed",
    "config": "the scene's run configuration",
}


def _flatten(value, prefix="") -> dict[str, Any]:
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        out = {}
        for i, v in enumerate(value):
            out.update(_flatten(v, f"{prefix}[{i}]"))
        return out
    return {prefix: value}


def _fingerprint_differences(saved: dict, now: dict) -> list[str]:
    """Human-readable differences between two fingerprints: 'dx (--dx): 0.0148 in the file, 0.0111 now'."""
    a, b = _flatten(saved), _flatten(now)
    out = []
    for key in list(a) + [k for k in b if k not in a]:
        if a.get(key, "<absent>") == b.get(key, "<absent>"):
            continue
        top = re.sub(r"^(\w+\[\d+\]\.)+", "", key).split(".")[0]  # "members[0].fixed.pc0" -> "fixed"
        option = _FINGERPRINT_OPTIONS.get(top, top)
        out.append(f"{key} ({option}): {a.get(key, '<absent>')!r} in the file, {b.get(key, '<absent>')!r} now")
    return out


def _status_text(status: int) -> str:
    return f"status {status}: {'; '.join(describe_status(status))}" if status else "status 0"


def start_theta(objective, init: Mapping[str, float] | None) -> tuple[np.ndarray, str]:
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
        notes = [note for note in getattr(objective, "bound_notes", ()) if any(
            note.startswith(f"{k}'s") for k in init)]
        raise ValueError("; ".join([str(err)] + notes)) from None
    check = getattr(objective, "check_thetas", None)
    if check is not None:  # the engine's rules (mu2 >= mu1, ...) on the full parameter set
        check(theta, "init")
    note = "; ".join(f"{k}: the scene's value {old:g} lies on or next to its bound "
                     f"({bounds.lower[objective.keys.index(k)]:g}, {bounds.upper[objective.keys.index(k)]:g}), "
                     f"so the fit starts at {new:g}" for k, (old, new) in moved.items())
    return theta, note


def fit(objective, init: Mapping[str, float] | None = None, *, method: str = "lm", steps: int = 30,
        out=None, resume: bool = False, overwrite: bool = False, learning_rate: float = 0.05, clip: float = 1.0,
        grad_mode: str = "fwd",
        xtol: float = 1e-6, ftol: float = 1e-7, stat_tol: float = 0.1, max_rejections: int = 6, progress: bool = False, callback: Callable | None = None,
        noise: Mapping[str, float] | float | None = None, uncertainty: bool = True,
        roundoff_samples: int = ROUNDOFF_SAMPLES, reference_noise: float = 0.01, threshold: float = 0.1,
        meta: Mapping[str, Any] | None = None) -> FitResult:
    """Fit ``objective.keys`` from ``init`` (physical values by key; missing keys start at the
    scene's values). ``steps``: the maximum number of iterations (model evaluations), counted
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
    ``reference_noise`` and ``threshold`` decide which parameters count as constrained."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if grad_mode not in ("fwd", "rev"):
        raise ValueError(f"grad_mode must be 'fwd' or 'rev', got {grad_mode!r}")
    if not (isinstance(steps, int) and steps >= 1):
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if not (math.isfinite(learning_rate) and learning_rate > 0):
        raise ValueError(f"learning_rate must be > 0, got {learning_rate!r}")
    if resume and out is None:
        raise ValueError("resume=True needs out (the history file to resume from)")
    if resume and overwrite:
        raise ValueError("resume and overwrite exclude each other: continue the history in out, or replace it")
    bounds, keys = objective.bounds, objective.keys
    path = pathlib.Path(out) if out is not None else None
    if path is not None and not path.parent.exists():
        raise ValueError(f"out: directory {str(path.parent)!r} does not exist")
    if path is not None and path.is_dir():
        raise ValueError(f"out: {str(path)!r} is a folder, not a file")
    if path is not None and resume and not path.exists():
        raise ValueError(f"resume: {str(path)!r} does not exist: there is nothing to resume (check the name; "
                         "without resume (--resume) a new fit starts)")
    if path is not None and not resume and path.exists() and not overwrite:
        raise ValueError(f"out: {str(path)!r} exists (an earlier fit's history?); continue it with resume=True "
                         "(--resume) or replace it with overwrite=True (--overwrite)")
    fingerprint_of = getattr(objective, "fingerprint", None)
    fingerprint = json.loads(json.dumps(fingerprint_of())) if fingerprint_of is not None else None
    options = {"method": method, "steps": steps, "learning_rate": learning_rate, "clip": clip,
               "grad_mode": grad_mode, "xtol": xtol, "ftol": ftol}

    history = {k: [] for k in _HISTORY_FIELDS}
    lm_options = LMOptions(xtol=xtol, ftol=ftol, stat_tol=stat_tol, max_rejections=max_rejections)
    start_note = ""
    optimizer = None
    if method == "adam":
        schedule = optax.cosine_decay_schedule(learning_rate, decay_steps=steps, alpha=0.05)
        optimizer = optax.chain(optax.clip_by_global_norm(clip), optax.adam(schedule))

    if resume:
        saved = read_history(path)
        attrs = saved["attrs"]
        if tuple(attrs["keys_json"]) != keys or attrs["method"] != method:
            raise ValueError(f"out: {str(path)!r} holds a {attrs['method']} fit of {attrs['keys_json']}, "
                             f"not a {method} fit of {list(keys)}")
        for k in ("learning_rate", "clip", "grad_mode"):
            if attrs["options_json"].get(k) != options[k]:
                raise ValueError(f"resume: {k} = {options[k]!r} differs from the file's "
                                 f"{attrs['options_json'].get(k)!r}")
        if fingerprint is not None:
            if "fingerprint_json" not in attrs:
                raise ValueError(f"resume: {str(path)!r} does not record the problem it was made for (written by an "
                                 "older calibration.fit), so it cannot be checked against this one; start a new fit "
                                 "(another out, or overwrite=True / --overwrite)")
            differences = _fingerprint_differences(attrs["fingerprint_json"], fingerprint)
            if differences:
                raise ValueError(f"resume: {str(path)!r} holds a fit of a different problem, which a resume would "
                                 "mix into one history; what differs (option): " + "; ".join(differences))
        history = {k: list(saved["history"][k]) for k in _HISTORY_FIELDS}
        z = saved["resume"]["z"]
        lam = float(saved["resume"]["lam"])
        opt_state = None
        if optimizer is not None:
            template = optimizer.init(jnp.asarray(z))
            leaves = [saved["resume"][f"opt_{i}"] for i in range(len(jax.tree.leaves(template)))]
            opt_state = jax.tree.unflatten(jax.tree.structure(template),
                                           [jnp.asarray(v, t.dtype) for v, t in zip(leaves, jax.tree.leaves(template))])
        done = bool(saved["resume"]["done"])
        message = str(attrs.get("message", ""))
    else:
        theta0, start_note = start_theta(objective, init)
        z = bounds.to_unconstrained(theta0)
        lam = LAM0
        opt_state = optimizer.init(jnp.asarray(z)) if optimizer is not None else None
        done, message = False, ""
    wall0 = history["wall_s"][-1] if history["wall_s"] else 0.0
    t0 = time.perf_counter()

    def evaluate(z_):
        theta_ = np.asarray(bounds.to_physical(jnp.asarray(z_)))
        if method == "adam" and grad_mode == "rev":
            (loss_, pred_), g_theta = objective.value_and_grad(theta_)
            return theta_, float(loss_), None, None, np.asarray(g_theta), pred_
        r_, J_, pred_ = objective.residuals_and_jacobian(theta_)
        r_, J_ = np.asarray(r_, float), np.asarray(J_, float)
        return theta_, float(np.sum(r_ * r_)), r_, J_, 2.0 * J_.T @ r_, pred_

    def save(state_z, state_lam, state_opt, is_done, msg):
        if path is None:
            return

        def write(f):
            f.attrs["keys_json"] = json.dumps(list(keys))
            f.attrs["method"] = method
            f.attrs["options_json"] = json.dumps(options)
            f.attrs["objective_json"] = json.dumps(objective.describe())
            if fingerprint is not None:
                f.attrs["fingerprint_json"] = json.dumps(fingerprint)
            f.attrs["meta_json"] = json.dumps(dict(meta or {}))
            f.attrs["message"] = msg
            g = f.create_group("history")
            n = len(history["loss"])
            for k in _HISTORY_FIELDS:
                arr = np.asarray(history[k]) if n else np.zeros((0, len(keys)) if k in ("theta", "z") else 0)
                g.create_dataset(k, data=arr)
            res = f.create_group("resume")
            res.create_dataset("z", data=np.asarray(state_z))
            res.create_dataset("lam", data=state_lam)
            res.create_dataset("done", data=is_done)
            if state_opt is not None:
                for i, leaf in enumerate(jax.tree.leaves(state_opt)):
                    res.create_dataset(f"opt_{i}", data=np.asarray(leaf))

        _atomic_h5(path, write)

    def record(z_, theta_, loss_, g_theta, status_, accepted_, lam_):
        history["z"].append(np.asarray(z_, float))
        history["theta"].append(np.asarray(theta_, float))
        history["loss"].append(loss_)
        history["grad_norm"].append(float(np.linalg.norm(g_theta)))
        history["status"].append(int(status_))
        history["accepted"].append(bool(accepted_))
        history["lam"].append(lam_)
        history["wall_s"].append(wall0 + time.perf_counter() - t0)

    bar = None
    if progress:
        try:
            from tqdm import tqdm

            bar = tqdm(total=steps, initial=len(history["loss"]), desc=f"fit ({method})", unit="it")
        except ImportError:
            bar = None

    def report(k):
        if bar is not None:
            theta_ = history["theta"][-1]
            bar.set_postfix_str(f"loss {history['loss'][-1]:.3e} " +
                                " ".join(f"{key}={v:.4g}" for key, v in zip(keys, theta_)))
            bar.update(1)
        if callback is not None:
            callback(k, {f: history[f][-1] for f in _HISTORY_FIELDS})

    rejections = 0
    current = None  # (z, theta, loss, r, J, g, pred) at the accepted point (LM) or the last point (Adam)
    if history["loss"] and method == "lm":
        current = (z, *evaluate(z))  # re-evaluate the accepted point (not a new iteration)

    while len(history["loss"]) < steps and not done:
        k = len(history["loss"])
        if method == "lm":
            if current is None:  # the first evaluation
                theta, loss, r, J, g, pred = evaluate(z)
                status = int(np.asarray(pred["status"]))
                if status or not math.isfinite(loss):
                    raise ValueError(f"init: the run at the initial parameters fails ({_status_text(status)}; "
                                     f"loss {loss}); choose another start")
                current = (z, theta, loss, r, J, g, pred)
                record(z, theta, loss, g, status, True, lam)
            else:
                z_c, theta_c, loss_c, r_c, J_c, g_c, _ = current
                dtheta_dz = np.asarray(bounds.jacobian_diag(jnp.asarray(z_c)))
                delta, promised = propose(r_c[None], (J_c * dtheta_dz[None, :])[None], np.array([lam]))
                z_t = z_c + delta[0]
                theta, loss, r, J, g, pred = evaluate(z_t)
                status = int(np.asarray(pred["status"]))
                accepted, lams, rej, stop, messages = judge(
                    [loss_c], theta_c[None], [loss], theta[None], [status == 0], promised, [lam], [rejections],
                    r_c.size, lm_options)
                accepted, lam, rejections = bool(accepted[0]), float(lams[0]), int(rej[0])
                if accepted:
                    current = (z_t, theta, loss, r, J, g, pred)
                if stop[0]:
                    done, message = True, messages[0]
                record(z_t, theta, loss, g, status, accepted, lam)
            save(current[0], lam, None, done, message)
        else:
            theta, loss, r, J, g, pred = evaluate(z)
            status = int(np.asarray(pred["status"]))
            ok = status == 0 and math.isfinite(loss) and np.all(np.isfinite(g))
            record(z, theta, loss, g, status, ok, float("nan"))
            if not ok:
                done, message = True, f"stopped: the run at iteration {k} failed ({_status_text(status)})"
                save(z, lam, opt_state, done, message)
                report(k)
                break
            g_z = jnp.asarray(g * np.asarray(bounds.jacobian_diag(jnp.asarray(z))))
            with jax.numpy_dtype_promotion("standard"):  # optax's schedules mix int counts and floats
                updates, opt_state = optimizer.update(g_z, opt_state, jnp.asarray(z))
                z = np.asarray(optax.apply_updates(jnp.asarray(z), updates), float)
            save(z, lam, opt_state, done, message)
        report(k)
    if bar is not None:
        bar.close()
    if not done:
        message = message or f"stopped after {len(history['loss'])} iterations (steps = {steps})"

    hist = {k: np.asarray(v) for k, v in history.items()}
    ok_rows = np.flatnonzero((hist["status"] == 0) & np.isfinite(hist["loss"]))
    if ok_rows.size == 0:
        raise ValueError("fit: no iteration produced a valid run")
    i_best = ok_rows[np.argmin(hist["loss"][ok_rows])]
    theta_best = hist["theta"][i_best]
    if current is not None and np.array_equal(current[1], theta_best) and current[3] is not None:
        _, _, loss_b, r_b, J_b, _, pred_b = current
    else:
        r_b, J_b, pred_b = objective.residuals_and_jacobian(theta_best)
        r_b, J_b = np.asarray(r_b, float), np.asarray(J_b, float)
        loss_b = float(np.sum(r_b * r_b))
    converged = done and message.startswith("converged")
    verdict, unc = judge_point(objective, r_b, J_b, theta_best, converged=converged, message=message, noise=noise,
                               uncertainty=uncertainty, roundoff_samples=roundoff_samples,
                               reference_noise=reference_noise, threshold=threshold)
    return FitResult(keys=keys, theta={k: float(v) for k, v in zip(keys, theta_best)}, loss=float(loss_b),
                     iterations=len(hist["loss"]), wall_s=float(hist["wall_s"][-1]) if len(hist["wall_s"]) else 0.0,
                     method=method, converged=converged, message=message,
                     history=hist, residuals=r_b, jacobian=J_b,
                     prediction=jax.tree.map(np.asarray, pred_b), uncertainty=unc,
                     start={k: float(v) for k, v in zip(keys, hist["theta"][0])}, start_note=start_note,
                     verdict=verdict)
