"""The history of a fit: one row per iteration (model evaluation) and start, saved and resumed.

A ``History`` records, per start, the fields ``FIELDS``; with a ``path`` (one start) it rewrites
the whole file atomically after every iteration, with what the optimiser needs to continue.
``History.resume`` continues such a file and refuses one of another method, keys, optimiser
options or problem (``fingerprint``), naming what differs. ``check_out`` applies the rules for the
file before any work.
"""

from __future__ import annotations

import json
import pathlib
import re
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import h5py
import numpy as np

from jaxmpm.io import atomic_h5

__all__ = ["FIELDS", "read_history", "check_out", "History"]


FIELDS = ("theta", "z", "loss", "grad_norm", "status", "accepted", "lam", "wall_s")


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
        raise ValueError(f"{shown} is not a fit history written by calibration.optim.fit ({err})") from None
    except (OSError, KeyError, ValueError, TypeError) as err:  # h5py's errors for unreadable files are OSErrors
        raise ValueError(f"{shown} is not a readable fit history: {type(err).__name__}: {err} (an empty or "
                         "truncated file, or not HDF5 at all?)") from None
    missing = [k for k in FIELDS if k not in history] + [k for k in ("z", "lam", "done") if k not in resume]
    lengths = {k: len(history[k]) for k in FIELDS if k in history}
    if missing or len(set(lengths.values())) > 1:
        raise ValueError(f"{shown} is not a complete fit history (missing {missing}, lengths {lengths})")
    return {"attrs": attrs, "history": history, "resume": resume}


def check_out(out, *, resume: bool, overwrite: bool) -> pathlib.Path | None:
    """The history file ``out`` as a path, after the rules for it (before any work)."""
    if resume and out is None:
        raise ValueError("resume=True needs out (the history file to resume from)")
    if resume and overwrite:
        raise ValueError("resume and overwrite exclude each other: continue the history in out, or replace it")
    if out is None:
        return None
    path = pathlib.Path(out)
    if not path.parent.exists():
        raise ValueError(f"out: directory {str(path.parent)!r} does not exist")
    if path.is_dir():
        raise ValueError(f"out: {str(path)!r} is a folder, not a file")
    if resume and not path.exists():
        raise ValueError(f"resume: {str(path)!r} does not exist: there is nothing to resume (check the name; "
                         "without resume (--resume) a new fit starts)")
    if not resume and path.exists() and not overwrite:
        raise ValueError(f"out: {str(path)!r} exists (an earlier fit's history?); continue it with resume=True "
                         "(--resume) or replace it with overwrite=True (--overwrite)")
    return path


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
    """Nested dicts (and lists of dicts) as {"a.b[0].c": leaf}."""
    if isinstance(value, dict):
        items = [(f"{prefix}.{k}" if prefix else str(k), v) for k, v in value.items()]
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        items = [(f"{prefix}[{i}]", v) for i, v in enumerate(value)]
    else:
        return {prefix: value}
    return {key: leaf for name, v in items for key, leaf in _flatten(v, name).items()}


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


class History:
    """The iterations of ``starts`` starts of a fit.

    ``path`` (one start): the file written after every iteration, with the attributes
    ``header`` (a string is written as it is, anything else as JSON under ``NAME_json``; a value
    None is left out) and ``snapshot(state)``, the arrays a resume needs. ``wall0``: the wall
    time already spent (a resumed fit's); the clock starts at ``t0`` (default: now)."""

    def __init__(self, starts: int = 1, *, path: pathlib.Path | None = None,
                 header: Mapping[str, Any] | None = None, snapshot: Callable[[Any], dict] | None = None,
                 wall0: float = 0.0, t0: float | None = None):
        if path is not None and starts != 1:
            raise ValueError(f"a history file holds one start, got {starts}")
        self.path, self.header, self.snapshot = path, dict(header or {}), snapshot
        self._starts = [{f: [] for f in FIELDS} for _ in range(starts)]  # per start: field -> list
        self.iterations = 0
        self.wall0 = wall0
        self.t0 = time.perf_counter() if t0 is None else t0

    @classmethod
    def resume(cls, path: pathlib.Path, header: Mapping[str, Any], *,
               differences: Callable[[Mapping[str, Any]], Sequence[str]],
               snapshot: Callable[[Any], dict]) -> tuple[History, dict[str, Any]]:
        """The history in ``path``, to be continued by a fit with this ``header`` (keys, method,
        options, fingerprint), which must agree with the file's in keys, method and fingerprint,
        and whose options ``differences(the file's options)`` finds none; and the file's resume
        arrays, with its message."""
        saved = read_history(path)
        attrs = saved["attrs"]
        keys, method = tuple(header["keys"]), header["method"]
        if tuple(attrs["keys_json"]) != keys or attrs["method"] != method:
            raise ValueError(f"out: {str(path)!r} holds a {attrs['method']} fit of {attrs['keys_json']}, "
                             f"not a {method} fit of {list(keys)}")
        changed = differences(attrs["options_json"])
        if changed:
            raise ValueError(f"resume: the fit's options differ from those {str(path)!r} was made with, which a "
                             "resume would mix into one history: " + "; ".join(changed))
        fingerprint = header.get("fingerprint")
        if fingerprint is not None:
            if "fingerprint_json" not in attrs:
                raise ValueError(f"resume: {str(path)!r} does not record the problem it was made for (written by an "
                                 "older calibration.optim.fit), so it cannot be checked against this one; start a new "
                                 "fit (another out, or overwrite=True / --overwrite)")
            differences = _fingerprint_differences(attrs["fingerprint_json"], fingerprint)
            if differences:
                raise ValueError(f"resume: {str(path)!r} holds a fit of a different problem, which a resume would "
                                 "mix into one history; what differs (option): " + "; ".join(differences))
        saved_rows = {k: list(saved["history"][k]) for k in FIELDS}
        history = cls(path=path, header=header, snapshot=snapshot,
                      wall0=saved_rows["wall_s"][-1] if saved_rows["wall_s"] else 0.0)
        history._starts, history.iterations = [saved_rows], len(saved_rows["loss"])
        return history, {**saved["resume"], "message": str(attrs.get("message", ""))}

    def length(self, i: int = 0) -> int:
        """Start ``i``'s iterations."""
        return len(self._starts[i]["loss"])

    def arrays(self, i: int = 0) -> dict[str, np.ndarray]:
        """Start ``i``'s history, a field an array."""
        return {f: np.asarray(v) for f, v in self._starts[i].items()}

    def last(self, i: int = 0) -> dict[str, Any]:
        """Start ``i``'s last iteration, a field a value."""
        return {f: v[-1] for f, v in self._starts[i].items()}

    def record(self, rows, z, evaluation, state) -> None:
        """One iteration of the starts ``rows``, evaluated at z (len(rows), n), after the update
        to ``state``; then the file is written."""
        wall = self.wall0 + time.perf_counter() - self.t0
        lam = getattr(state, "lam", None)  # LM's damping; NaN for an optimiser without one
        for j, i in enumerate(rows):
            row = self._starts[i]
            row["z"].append(np.asarray(z[j], float))
            row["theta"].append(np.asarray(evaluation.theta[j], float))
            row["loss"].append(float(evaluation.loss[j]))
            row["grad_norm"].append(float(np.linalg.norm(evaluation.grad[j])))
            row["status"].append(int(evaluation.status[j]))
            row["accepted"].append(bool(state.accepted[i]))
            row["lam"].append(float("nan") if lam is None else float(lam[i]))
            row["wall_s"].append(wall)
        self.iterations += 1
        if self.path is not None:
            self._save(state)

    def _save(self, state) -> None:
        resume = self.snapshot(state)
        row = self._starts[0]

        def write(f):
            for name, value in self.header.items():
                if isinstance(value, str):
                    f.attrs[name] = value
                elif value is not None:
                    f.attrs[f"{name}_json"] = json.dumps(value)
            f.attrs["message"] = str(state.message[0])
            g = f.create_group("history")
            for k in FIELDS:
                g.create_dataset(k, data=np.asarray(row[k]))
            res = f.create_group("resume")
            res.create_dataset("done", data=bool(state.done[0]))
            for name, value in resume.items():
                res.create_dataset(name, data=value)

        atomic_h5(self.path, write)
