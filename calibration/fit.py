"""Fitting: Levenberg–Marquardt on the residual Jacobian, or optax Adam, with a resumable history.

Both optimisers work on unconstrained z (``calibration.bounds``), so every iterate is a
physical parameter set. Each iteration is one model evaluation.

- ``method="lm"``: Levenberg–Marquardt with Marquardt's diagonal scaling. Every evaluation
  returns the residuals and their Jacobian together (forward mode, one batched tangent pass);
  a trial step is accepted when the loss falls and the run has no status bits, and the damping
  λ falls by 3 after a success and rises by 4 after a failure. A run that fails (status bits:
  the flow left the grid, non-finite stress, ...) is a rejected trial, reported in the history.
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

from .uncertainty import Uncertainty, gauss_newton_uncertainty

__all__ = ["FitResult", "fit", "read_history", "METHODS"]

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

    def to_json(self) -> dict[str, Any]:
        out = {"params": self.theta, "loss": self.loss, "iterations": self.iterations,
               "wall_s": round(self.wall_s, 3), "method": self.method, "converged": self.converged,
               "message": self.message}
        if self.uncertainty is not None:
            u = self.uncertainty.to_dict()
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


def _as_theta(objective, init: Mapping[str, float] | None) -> np.ndarray:
    values = {**objective.initial(), **dict(init or {})}
    unknown = sorted(set(values) - set(objective.keys))
    if unknown:
        raise ValueError(f"init: {unknown} are not fitted keys {objective.keys}")
    theta = np.array([float(values[k]) for k in objective.keys])
    objective.bounds.check(theta, "init")
    check = getattr(objective, "check_thetas", None)
    if check is not None:  # the engine's rules (mu2 >= mu1, ...) on the full parameter set
        check(theta, "init")
    return theta


def fit(objective, init: Mapping[str, float] | None = None, *, method: str = "lm", steps: int = 30,
        out=None, resume: bool = False, overwrite: bool = False, learning_rate: float = 0.05, clip: float = 1.0,
        grad_mode: str = "fwd",
        xtol: float = 1e-6, ftol: float = 1e-7, stat_tol: float = 0.1, max_rejections: int = 6, progress: bool = False, callback: Callable | None = None,
        noise: Mapping[str, float] | float | None = None, uncertainty: bool = True,
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
    ``callback(iteration, record)`` is called after each iteration is written."""
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
        z = bounds.to_unconstrained(_as_theta(objective, init))
        lam = 1e-3
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
                Jz = J_c * dtheta_dz[None, :]
                A = Jz.T @ Jz
                d = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
                delta = np.linalg.solve(A + lam * np.diag(d), -Jz.T @ r_c)
                predicted_drop = loss_c - float(np.sum((r_c + Jz @ delta) ** 2))
                z_t = z_c + delta
                theta, loss, r, J, g, pred = evaluate(z_t)
                status = int(np.asarray(pred["status"]))
                accepted = status == 0 and math.isfinite(loss) and loss < loss_c
                rel_step = float(np.max(np.abs(theta - theta_c) / np.maximum(np.abs(theta_c), 1e-12)))
                # What fitting pure noise would promise: n σ² with σ² = loss / (m − n).
                noise_drop = stat_tol * len(keys) * loss_c / max(r_c.size - len(keys), 1)
                if accepted:
                    rejections = 0
                    rel_drop = (loss_c - loss) / max(loss_c, 1e-300)
                    current = (z_t, theta, loss, r, J, g, pred)
                    lam = max(lam / 3.0, 1e-9)
                else:
                    rejections += 1
                    lam = lam * 4.0
                if predicted_drop <= noise_drop:
                    done, message = True, (f"converged: the linearised model promises a loss decrease of "
                                           f"{predicted_drop:.2e}, below the residual noise level {noise_drop:.2e}")
                elif accepted and (rel_drop < ftol or rel_step < xtol):
                    done, message = True, (f"converged: relative loss decrease {rel_drop:.2e}, "
                                           f"relative step {rel_step:.2e}")
                elif not accepted and rel_step < xtol:
                    done, message = True, f"converged: rejected steps shorter than xtol ({rel_step:.2e})"
                elif rejections >= max_rejections:
                    done, message = True, (f"stopped: {rejections} rejected steps in a row (no decrease within the "
                                           f"runs' round-off and scatter)")
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
    unc = None
    if uncertainty:
        unc = gauss_newton_uncertainty(J_b, r_b, keys, theta_best, objective.blocks, objective.row_scale,
                                       noise=noise, bounds=bounds)
    return FitResult(keys=keys, theta={k: float(v) for k, v in zip(keys, theta_best)}, loss=float(loss_b),
                     iterations=len(hist["loss"]), wall_s=float(hist["wall_s"][-1]) if len(hist["wall_s"]) else 0.0,
                     method=method, converged=done and message.startswith("converged"), message=message,
                     history=hist, residuals=r_b, jacobian=J_b,
                     prediction=jax.tree.map(np.asarray, pred_b), uncertainty=unc)
