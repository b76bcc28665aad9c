"""A fit's options, validated once: how it runs (``FitOptions``), how its end point is judged
(``JudgeOptions``) and how its objective reads and weighs the data (``DataOptions``).

Both are frozen dataclasses whose ``__post_init__`` refuses a bad value with an ``OptionError``
naming the field. The command line builds the same objects from its flags and reports the error
under the flag's name through one table (``FLAGS``), so that every check is written once.

``FitOptions`` is what a fit's history file records and what a resume must repeat: every field
but ``steps`` (a resumed fit may run further), compared whole (``FitOptions.differences``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from .uncertainty import GRID_DRAWS, ROUNDOFF_SAMPLES, check_grid_options

__all__ = ["FitOptions", "JudgeOptions", "DataOptions", "FitRequest", "OptionError", "FLAGS", "METHODS", "GRAD_MODES",
           "WEIGHTINGS", "cli_steps", "fit_request"]

METHODS = ("lm", "adam")
GRAD_MODES = ("fwd", "rev")
WEIGHTINGS = ("block", "row")
JACOBIANS = ("ad", "fd")

#: Library field -> command-line flag (None: the command line does not set it).
FLAGS: dict[str, str | None] = {
    "method": "--method", "steps": "--steps", "learning_rate": "--lr", "clip": None, "grad_mode": None,
    "xtol": None, "ftol": None, "stat_tol": None, "max_rejections": None,
    "noise": "--noise", "uncertainty": None, "roundoff_samples": "--roundoff-samples",
    "sampling_seeds": "--sampling-seeds", "reference_noise": "--reference-noise", "threshold": "--threshold",
    "grid_ratio": "--grid-check", "grid_draws": None, "grid_levels": "--grid-levels", "keys": "--fit",
    "init": "--init", "weighting": "--weighting", "weight_profile": "--weight-profile",
    "weight_front": "--weight-front", "front_threshold": "--front-threshold",
    "front_correlation_time": "--front-correlation-time", "jacobian": "--jacobian",
}


class OptionError(ValueError):
    """A bad option: ``field`` (the library's name) and ``what`` was wrong with it."""

    def __init__(self, field: str, what: str):
        super().__init__(f"{field} {what}")
        self.field, self.what = field, what

    def as_flag(self) -> ValueError:
        """The same error under the command-line flag's name (``FLAGS``)."""
        return ValueError(f"{FLAGS.get(self.field) or self.field} {self.what}")


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _require(ok: bool, field: str, what: str, value) -> None:
    if not ok:
        raise OptionError(field, f"must be {what}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How a fit runs. ``method``: "lm" (Levenberg–Marquardt) or "adam"; ``steps``: the most
    iterations (model evaluations), counted over resumes; ``learning_rate``, ``clip``,
    ``grad_mode`` ("fwd" or "rev"): Adam's; LM stops when the decrease its linearised model
    promises is below ``stat_tol`` × n σ², when an accepted step lowers the loss by less than
    ``ftol`` or moves θ by less than ``xtol`` (relative), or after ``max_rejections`` rejected
    steps in a row (``calibration.fit.fit`` says more)."""

    method: str = "lm"
    steps: int = 30
    learning_rate: float = 0.05
    clip: float = 1.0
    grad_mode: str = "fwd"
    xtol: float = 1e-6
    ftol: float = 1e-7
    stat_tol: float = 0.1
    max_rejections: int = 6

    def __post_init__(self):
        _require(self.method in METHODS, "method", f"one of {METHODS}", self.method)
        _require(_is_int(self.steps) and self.steps >= 1, "steps", "a positive integer", self.steps)
        _require(_is_number(self.learning_rate) and self.learning_rate > 0, "learning_rate", "a finite number > 0",
                 self.learning_rate)
        _require(_is_number(self.clip) and self.clip > 0, "clip", "a finite number > 0", self.clip)
        _require(self.grad_mode in GRAD_MODES, "grad_mode", f"one of {GRAD_MODES}", self.grad_mode)
        for name in ("xtol", "ftol", "stat_tol"):
            value = getattr(self, name)
            _require(_is_number(value) and value >= 0, name, "a finite number >= 0", value)
        _require(_is_int(self.max_rejections) and self.max_rejections >= 1, "max_rejections", "an integer >= 1",
                 self.max_rejections)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def differences(self, saved: Mapping[str, Any]) -> list[str]:
        """The fields (``steps`` apart) whose value differs from ``saved`` (a history file's
        record, ``to_json``), as "field: now … , the file's …"; a field the file does not record
        counts as different."""
        out = []
        for field in dataclasses.fields(self):
            if field.name == "steps":
                continue
            now = getattr(self, field.name)
            if field.name not in saved:
                out.append(f"{field.name}: {now!r} now, not recorded in the file")
            elif saved[field.name] != now:
                out.append(f"{field.name}: {now!r} now, {saved[field.name]!r} in the file")
        return out


def cli_steps(method: str, steps: int | None) -> int:
    """The command line's iteration budget: ``steps``, or 25 for LM and 150 for Adam."""
    return steps if steps is not None else (25 if method == "lm" else 150)


@dataclasses.dataclass(frozen=True)
class JudgeOptions:
    """How a fit's end point is judged (``calibration.uncertainty.judge_point``). ``noise``:
    the known noise (a number, or one per residual block; None: estimated); ``uncertainty``:
    compute intervals at all; ``roundoff_samples`` perturbed runs for the run's own scatter and
    ``sampling_seeds`` other particle draws (0, or 2 and more: 0 is not measured);
    ``reference_noise`` and ``threshold`` decide which parameters count as constrained;
    ``grid_ratio`` (None: not measured, else > 1), ``grid_draws`` and ``grid_levels`` (1 or 2
    coarser grids): the grid term (``calibration.uncertainty.grid_shift``)."""

    noise: Mapping[str, float] | float | None = None
    uncertainty: bool = True
    roundoff_samples: int = ROUNDOFF_SAMPLES
    sampling_seeds: int = 0
    reference_noise: float = 0.01
    threshold: float = 0.1
    grid_ratio: float | None = None
    grid_draws: int = GRID_DRAWS
    grid_levels: int = 1

    def __post_init__(self):
        noise = self.noise
        values = list(noise.values()) if isinstance(noise, Mapping) else ([] if noise is None else [noise])
        for value in values:
            _require(_is_number(value) and value >= 0, "noise", "None, a finite number >= 0 or one per block",
                     noise)
        _require(isinstance(self.uncertainty, bool), "uncertainty", "True or False", self.uncertainty)
        for name in ("roundoff_samples", "sampling_seeds"):
            value = getattr(self, name)
            _require(_is_int(value) and (value == 0 or value >= 2), name, "0 (not measured) or an integer >= 2",
                     value)
        for name in ("reference_noise", "threshold"):
            value = getattr(self, name)
            _require(_is_number(value) and value >= 0, name, "a finite number >= 0", value)
        check_grid_options(self.grid_ratio, self.grid_draws, self.grid_levels)

    def kwargs(self) -> dict[str, Any]:
        """The fields as keyword arguments (``judge_point``, ``search``)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def to_json(self) -> dict[str, Any]:
        out = self.kwargs()
        if isinstance(self.noise, Mapping):
            out["noise"] = dict(self.noise)
        return out


@dataclasses.dataclass(frozen=True)
class DataOptions:
    """How an objective reads and weighs its data (``calibration.problem.objective_of``).
    ``weighting``: "block" (each profile and the front history weigh their weight in total) or
    "row" (every point weighs it); ``weight_profile``, ``weight_front``: the blocks' weights
    (None: an experiment file's, else 1); ``front_threshold``: the height (m) below which the
    deposit has ended (None: dx/ppc/2); ``front_correlation_time``: the front's errors are
    exponentially correlated over this time, s (None: an experiment file's, else independent);
    ``jacobian``: "ad" (forward-mode autodiff) or "fd" (central differences)."""

    weighting: str = "block"
    weight_profile: float | None = None
    weight_front: float | None = None
    front_threshold: float | None = None
    front_correlation_time: float | None = None
    jacobian: str = "ad"

    def __post_init__(self):
        _require(self.weighting in WEIGHTINGS, "weighting", f"one of {WEIGHTINGS}", self.weighting)
        _require(self.jacobian in JACOBIANS, "jacobian", f"one of {JACOBIANS}", self.jacobian)
        for name in ("front_threshold", "front_correlation_time"):
            value = getattr(self, name)
            if value is not None:
                _require(_is_number(value) and value > 0, name, "a finite number > 0", value)
        for name in ("weight_profile", "weight_front"):
            value = getattr(self, name)
            if value is not None:
                _require(_is_number(value) and value >= 0, name, "a finite number >= 0", value)

    def weights(self, default: float | None = 1.0) -> dict[str, float | None]:
        """The blocks' weights by block name, ``default`` where none is given."""
        return {"profile": default if self.weight_profile is None else self.weight_profile,
                "front": default if self.weight_front is None else self.weight_front}


def split_fields(fields: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``fields`` (keyword arguments of ``fit``) divided into ``FitOptions``' and
    ``JudgeOptions``'; any other name is a ``TypeError``, as for a function's arguments."""
    run_names = {f.name for f in dataclasses.fields(FitOptions)}
    judge_names = {f.name for f in dataclasses.fields(JudgeOptions)}
    unknown = sorted(set(fields) - run_names - judge_names)
    if unknown:
        raise TypeError(f"unexpected keyword arguments {unknown}")
    return ({k: v for k, v in fields.items() if k in run_names},
            {k: v for k, v in fields.items() if k in judge_names})


@dataclasses.dataclass(frozen=True)
class FitRequest:
    """What to fit: the ``keys``, their starting values ``init`` (empty: the scene's values, or a
    search) and the data's known ``noise`` (None: estimated)."""

    keys: tuple[str, ...]
    init: Mapping[str, float] = dataclasses.field(default_factory=dict)
    noise: float | None = None

    def __post_init__(self):
        _require(bool(self.keys) and all(isinstance(k, str) and k for k in self.keys), "keys",
                 "a non-empty sequence of parameter names", self.keys)
        stray = sorted(set(self.init) - set(self.keys))
        if stray:
            raise OptionError("init", f"gives starting values for {stray}, which are not fitted "
                                      f"({', '.join(self.keys)})")


def fit_request(experiments=(), keys=None, init=None, noise=None) -> FitRequest:
    """The ``FitRequest`` of a fit of ``experiments`` (``jaxmpm.Experiment``): ``keys``,
    ``init`` and ``noise`` where given, else what every file's [fit] table agrees on (files that
    disagree must be overruled)."""
    specs = [e.fit for e in experiments if e.fit is not None]

    def agreed(name, values):
        if any(v != values[0] for v in values):
            raise OptionError(name, f"differs between the experiment files' [fit] tables ({values}); give it")
        return values[0] if values else None

    if keys:
        keys = tuple(keys)
    elif specs:
        if len(specs) < len(experiments):
            raise OptionError("keys", "is required: not every experiment file has a [fit] table with its keys")
        keys = agreed("keys", [tuple(s.keys) for s in specs])
    else:
        raise OptionError("keys", "is required (the keys to fit), or a [fit] table with keys in the experiment file")
    init = dict(init or {})
    if not init and specs:  # the files' starts, of the keys fitted (keys given here may be fewer)
        init = {k: v for k, v in (agreed("init", [dict(s.init) for s in specs]) or {}).items() if k in keys}
    if noise is None and specs:
        noise = agreed("noise", [s.noise for s in specs])
    return FitRequest(keys, init, noise)
