"""How a fit runs (``FitOptions``), validated once; what its history file records and a resume must
repeat (every field but ``steps``, ``FitOptions.differences``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ..inference.options import JudgeOptions
from ..problem.options import _is_int, _is_number, _require
from .lm import DEFAULT_JACOBIAN, DEFAULT_MODEL, JACOBIANS, LMOptions
from .lm import MODELS as LM_MODELS

__all__ = ["METHODS", "GRAD_MODES", "LM_MODELS", "JACOBIANS", "FitOptions", "cli_steps"]


METHODS = ("lm", "adam")


GRAD_MODES = ("fwd", "rev")


#: What a field added since the first history files were written was before it was recorded there.
BEFORE_RECORDED = {"lm_model": "gauss-newton", "lm_jacobian": "exact"}


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How a fit runs. ``method``: "lm" (Levenberg–Marquardt) or "adam"; ``steps``: the most
    iterations (model evaluations), counted over resumes; ``learning_rate``, ``clip``,
    ``grad_mode`` ("fwd" or "rev"): Adam's; ``xtol``, ``ftol``, ``stat_tol``, ``max_rejections``:
    LM's stopping tests (``calibration.optim.lm``, docs/fitting.md); ``lm_model``: LM's curvature,
    JᵀJ plus a secant estimate of the residuals' own curvature wherever that forecast the last
    step better ("adaptive", the default) or JᵀJ alone ("gauss-newton"); Adam ignores it;
    ``lm_jacobian``: each trial's Jacobian from its own forward-mode runs ("exact") or from one run
    of its residuals and Broyden's update ("broyden", ``calibration.optim.lm``);
    ``restarts``: where the verdict's probe finds a lower loss near the end point, fit again from
    the lowest point it ran, at most this many times (``calibration.optim.search.fit_from_starts``;
    a resume does not compare it with the file's)."""

    method: str = "lm"
    steps: int = 30
    learning_rate: float = 0.05
    clip: float = 1.0
    grad_mode: str = "fwd"
    xtol: float = 1e-6
    ftol: float = 1e-7
    stat_tol: float = 0.1
    max_rejections: int = 6
    lm_model: str = DEFAULT_MODEL
    lm_jacobian: str = DEFAULT_JACOBIAN
    restarts: int = 2

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
        _require(self.lm_model in LM_MODELS, "lm_model", f"one of {LM_MODELS}", self.lm_model)
        _require(self.lm_jacobian in JACOBIANS, "lm_jacobian", f"one of {JACOBIANS}", self.lm_jacobian)
        _require(_is_int(self.restarts) and self.restarts >= 0, "restarts", "an integer >= 0", self.restarts)

    def lm_options(self) -> LMOptions:
        """LM's options (``calibration.optim.lm.LMOptions``) from these."""
        return LMOptions(xtol=self.xtol, ftol=self.ftol, stat_tol=self.stat_tol, max_rejections=self.max_rejections,
                         model=self.lm_model, jacobian=self.lm_jacobian)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def differences(self, saved: Mapping[str, Any]) -> list[str]:
        """The fields (``steps`` apart) whose value differs from ``saved`` (a history file's
        record, ``to_json``), as "field: now … , the file's …"; a field the file does not record
        counts as different, except one added since (``BEFORE_RECORDED``), which the file had at
        its value from before."""
        out = []
        for field in dataclasses.fields(self):
            if field.name in ("steps", "restarts"):  # how far a fit goes, not which path it takes
                continue
            now = getattr(self, field.name)
            if field.name not in saved and field.name in BEFORE_RECORDED:
                was = BEFORE_RECORDED[field.name]
                if now != was:
                    out.append(f"{field.name}: {now!r} now, {was!r} in the file (written before it was recorded)")
            elif field.name not in saved:
                out.append(f"{field.name}: {now!r} now, not recorded in the file")
            elif saved[field.name] != now:
                out.append(f"{field.name}: {now!r} now, {saved[field.name]!r} in the file")
        return out


def cli_steps(method: str, steps: int | None, lm_jacobian: str = DEFAULT_JACOBIAN) -> int:
    """The command line's iteration budget: ``steps``, or 25 for LM (50 with Broyden's updates,
    whose runs are more and cheaper) and 150 for Adam."""
    if steps is not None:
        return steps
    return (50 if lm_jacobian == "broyden" else 25) if method == "lm" else 150


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
