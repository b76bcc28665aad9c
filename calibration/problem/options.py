"""How an objective reads and weighs its data (``DataOptions``), and the error every option object
raises (``OptionError``): a frozen dataclass whose ``__post_init__`` refuses a bad value naming the
field; the command line reports it under the flag's name.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

__all__ = ["WEIGHTINGS", "OptionError", "DataOptions", "FitRequest", "fit_request"]


WEIGHTINGS = ("block", "row")


JACOBIANS = ("ad", "fd")


class OptionError(ValueError):
    """A bad option: ``field`` (the library's name) and ``what`` was wrong with it."""

    def __init__(self, field: str, what: str):
        super().__init__(f"{field} {what}")
        self.field, self.what = field, what


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_int(name: str, value, least: int = 1) -> int:
    """``value`` as an int, or a ``ValueError`` unless it is an integer (numpy's too, not a bool) >= ``least``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < least:
        raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    return int(value)


def _require(ok: bool, field: str, what: str, value) -> None:
    if not ok:
        raise OptionError(field, f"must be {what}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class DataOptions:
    """How an objective reads and weighs its data (``calibration.problem.build.objective_of``).
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
    """The ``FitRequest`` of a fit of ``experiments`` (``jaxmpm.Experiment``, or an incline's
    ``InclineExperiment``): ``keys``, ``init`` and ``noise`` where given, else what every file's
    [fit] table agrees on (files that disagree must be overruled). An incline's [fit] keys
    (μ1, μ2, I0 where it states none) and init take part as a collapse's do; it states no noise."""
    specs = [_fit_spec(e) for e in experiments]
    specs = [s for s in specs if s is not None]

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
    stated = [s.noise for s in specs if not isinstance(s, _InclineSpec)]
    if noise is None and stated:
        noise = agreed("noise", stated)
    return FitRequest(keys, init, noise)


@dataclasses.dataclass(frozen=True)
class _InclineSpec:
    """An incline file's [fit] table as a collapse's ``FitSpec`` is read here (no noise)."""

    keys: tuple[str, ...]
    init: Mapping[str, float]


def _fit_spec(experiment):
    """An experiment file's [fit] table (None: it has none)."""
    from ..data.collapse import read_measurements
    from ..data.incline import InclineExperiment

    if isinstance(experiment, InclineExperiment):
        return _InclineSpec(experiment.keys, experiment.init)
    return read_measurements(experiment).fit
