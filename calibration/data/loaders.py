"""Loading the data that a calibration compares against: deposit profiles, front histories and
scaling laws, from the project's CSV or WebPlotDigitizer exports. The formats, and what is
refused (every error names the file and, for a row, its line), are in docs/data_files.md.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import re
from typing import Any

import numpy as np

from jaxmpm import tables

from .parse import (
    _MIN_POINTS,
    NOISE_FRACTION,
    TIME_UNITS,
    UNITS,
    _check_count,
    _check_increasing,
    _columns,
    _experiment,
    _final_deposit,
    _frozen_array,
    _header,
    _meta,
    _numeric,
    _synthetic,
    _time,
    _unit_scale,
)

__all__ = [
    "Profile", "load_profile", "FrontHistory", "load_front_history", "read_table", "RunoutLaw", "load_scaling_law",
]


def _set_series(data, along: str, value: str) -> None:
    """Check a data set's two columns (``along`` strictly increasing, ``value`` as long, at least
    ``_MIN_POINTS`` points, both finite and 1-D) and store them as read-only float64 arrays, with
    a copy of its ``meta``."""
    owner = type(data).__name__
    a, v = _frozen_array(along, getattr(data, along), owner), _frozen_array(value, getattr(data, value), owner)
    if a.shape != v.shape:
        raise ValueError(f"{owner}: {along} and {value} must have equal length, got {a.size} and {v.size}")
    if a.size < _MIN_POINTS:
        raise ValueError(f"{owner}: at least {_MIN_POINTS} points are needed, got {a.size}")
    if np.any(np.diff(a) <= 0):
        raise ValueError(f"{owner}: {along} must be strictly increasing")
    for name, array in ((along, a), (value, v), ("meta", dict(data.meta))):
        object.__setattr__(data, name, array)


@dataclasses.dataclass(frozen=True, eq=False)
class Profile:
    """A deposit (or flow) height profile h(x) in metres, with where it came from.

    ``x`` is strictly increasing and ``h >= 0`` (both float64, read-only). ``time_s`` is the time
    the profile was taken (``None`` if unknown); ``synthetic`` is true for profiles that this
    project computed rather than measured; ``meta`` holds every other header key.
    """

    x: np.ndarray
    h: np.ndarray
    experiment: str
    time_s: float | None = None
    source: str = ""
    synthetic: bool = False
    meta: dict = dataclasses.field(default_factory=dict)
    path: str | None = None

    def __post_init__(self):
        _set_series(self, "x", "h")
        if np.any(self.h < 0):
            raise ValueError("Profile: h must be >= 0")
        if self.time_s is not None and not math.isfinite(self.time_s):
            raise ValueError(f"Profile: time_s must be finite or None, got {self.time_s!r}")

    @property
    def n(self) -> int:
        """Number of points."""
        return int(self.x.size)

    def to_csv(self, path: str | os.PathLike) -> pathlib.Path:
        """Write the project CSV (via ``jaxmpm.tables.write_profile_csv``); ``load_profile`` reads it
        back identically to the printed precision (7 significant digits)."""
        header = _header(self.experiment, self.time_s, self.source, self.synthetic, self.meta)
        return tables.write_profile_csv(path, self.x, self.h, header)


def load_profile(
    path: str | os.PathLike,
    *,
    units: str | None = None,
    experiment: str | None = None,
    time_s: float | None = None,
    dataset: str | None = None,
    sort: bool = False,
    clip_noise: bool = False,
) -> Profile:
    """Read a deposit profile: the project CSV or a WebPlotDigitizer export (docs/data_files.md).

    ``units`` (``'m'``, ``'cm'``, ``'mm'``) is required when the file does not declare them and must
    agree with the file when it does; ``experiment`` and ``time_s`` supply what the file lacks (and
    must agree with it otherwise); ``dataset`` picks a dataset of a multi-dataset WPD export;
    ``sort`` sorts points in click order by x; ``clip_noise`` zeroes negative heights down to
    -1e-3 max h. Raises ``ValueError`` naming the file and line on any invalid input.
    """
    path = pathlib.Path(path)
    parsed = tables.read_table(path)
    names, rows, wpd_dataset = _columns(parsed, dataset)
    file = parsed.file
    column_units = None
    wpd = names is None or names == ("x", "y")
    if names is None or names in (("x", "y"), ("x", "h")):
        pass
    elif len(names) == 2 and all(re.fullmatch(rf"{c}_(m|cm|mm)", n) for c, n in zip("xh", names)):
        if names[0][2:] != names[1][2:]:
            raise ValueError(f"{file}: line {parsed.rows[0][0]}: x and h columns have different units: {names}")
        column_units = names[0][2:]
    else:
        raise ValueError(f"{file}: line {parsed.rows[0][0]}: unrecognised column names {list(names)}; expected "
                         "x_m,h_m (or x_cm,h_cm / x_mm,h_mm), x,h with a '# units:' line, or a WebPlotDigitizer "
                         "export (no header, X,Y, or its multi-dataset layout)")
    unit, scale = _unit_scale(parsed, column_units, units, UNITS, "units",
                              "units='m'|'cm'|'mm' (command line: --units m|cm|mm)")
    values, lines = _numeric(parsed, rows, ("x", "h"))
    _check_count(file, len(values))
    x_raw, h_raw = values[:, 0], values[:, 1]
    order = _check_increasing(file, x_raw, lines, "x", unit, sort)
    x_raw, h_raw, lines = x_raw[order], h_raw[order], lines[order]

    extra: dict[str, Any] = {}
    if wpd_dataset is not None:
        extra["wpd_dataset"] = wpd_dataset
    if _final_deposit(parsed):
        extra["time_s_text"] = parsed.header["time_s"]
    h_max = float(h_raw.max())
    if not h_max * scale > 0:  # in metres: a peak of a few 1e-324 mm underflows to zero
        raise ValueError(f"{file}: h is zero or negative everywhere (max h = {h_max:g} {unit})")
    negative = np.nonzero(h_raw < 0)[0]
    if negative.size:
        tol = NOISE_FRACTION * h_max
        beyond = negative[h_raw[negative] < -tol]
        listed = beyond if (clip_noise and beyond.size) else negative
        shown = ", ".join(f"line {lines[k]} (h = {h_raw[k]:g} {unit})" for k in listed[:5])
        more = f" and {listed.size - 5} more" if listed.size > 5 else ""
        if not clip_noise:
            raise ValueError(f"{file}: negative height at {shown}{more}; heights must be >= 0 (pass clip_noise=True, "
                             f"on the command line --clip-noise, to zero digitisation noise down to "
                             f"-{NOISE_FRACTION:g} x max h = {-tol:g} {unit})")
        if beyond.size:
            raise ValueError(f"{file}: negative height beyond the noise tolerance -{NOISE_FRACTION:g} x max h = "
                             f"{-tol:g} {unit} at {shown}{more}")
        h_raw = np.where(h_raw < 0, 0.0, h_raw)
        extra["clipped_noise_lines"] = [int(lines[k]) for k in negative]

    name = _experiment(parsed, path, experiment)
    source = parsed.header.get("source")
    if source is None:
        source = (f"WebPlotDigitizer export {path.name}" + (f", dataset {wpd_dataset!r}" if wpd_dataset else "")
                  + f", units {unit}") if wpd else ""
    x_m = x_raw * scale
    if not np.all(np.diff(x_m) > 0):  # distinct in the file's units, equal in metres (underflow)
        raise ValueError(f"{file}: x values that differ by less than float64 resolves in metres; x must be "
                         "strictly increasing")
    return Profile(
        x=x_m, h=h_raw * scale, experiment=name, time_s=_time(parsed, time_s), source=str(source),
        synthetic=_synthetic(parsed, name), meta=_meta(parsed, extra), path=str(path),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class FrontHistory:
    """Front position x_front(t) in metres against time t in seconds (t strictly increasing)."""

    t: np.ndarray
    x_front: np.ndarray
    experiment: str
    source: str = ""
    synthetic: bool = False
    meta: dict = dataclasses.field(default_factory=dict)
    path: str | None = None

    def __post_init__(self):
        _set_series(self, "t", "x_front")

    @property
    def n(self) -> int:
        """Number of points."""
        return int(self.t.size)

    def to_csv(self, path: str | os.PathLike) -> pathlib.Path:
        """Write columns ``t_s,xf_m`` with the header convention of the profile CSV (via
        ``jaxmpm.tables.write_table``)."""
        header = _header(self.experiment, None, self.source, self.synthetic, self.meta)
        return tables.write_table(path, dict(zip(tables.FRONT_COLUMNS, (self.t, self.x_front))), header)


def load_front_history(
    path: str | os.PathLike,
    *,
    units: str | None = None,
    time_units: str | None = None,
    experiment: str | None = None,
    dataset: str | None = None,
    sort: bool = False,
) -> FrontHistory:
    """Read a front history: columns ``t_s,xf_m`` (``xf_cm``, ``xf_mm``) or a WebPlotDigitizer
    export of (t, x_front), for which ``units`` (length) and ``time_units`` (``'s'``, ``'ms'``) must
    be given. Errors as for ``load_profile``; t must be strictly increasing (or ``sort=True``)."""
    path = pathlib.Path(path)
    parsed = tables.read_table(path)
    names, rows, wpd_dataset = _columns(parsed, dataset)
    file = parsed.file
    column_units = column_time = None
    wpd = names is None or names == ("x", "y")
    if not wpd:
        match = len(names) == 2 and re.fullmatch(r"t_(s|ms)", names[0]) and re.fullmatch(r"xf_(m|cm|mm)", names[1])
        if not match:
            raise ValueError(f"{file}: line {parsed.rows[0][0]}: unrecognised column names {list(names)}; expected "
                             "t_s,xf_m (or xf_cm / xf_mm) or a WebPlotDigitizer export")
        column_time, column_units = names[0][2:], names[1][3:]
    _, scale = _unit_scale(parsed, column_units, units, UNITS, "units",
                           "units='m'|'cm'|'mm' (command line: --units m|cm|mm)")
    time_unit, time_scale = _unit_scale(parsed, column_time, time_units, TIME_UNITS, "time_units",
                                        "time_units='s'|'ms' (command line: --time-units s|ms)")
    values, lines = _numeric(parsed, rows, ("t", "xf"))
    _check_count(file, len(values))
    order = _check_increasing(file, values[:, 0], lines, "t", time_unit, sort)
    values = values[order]
    name = _experiment(parsed, path, experiment)
    source = parsed.header.get("source")
    if source is None:
        source = f"WebPlotDigitizer export {path.name}" if wpd else ""
    extra = {"wpd_dataset": wpd_dataset} if wpd_dataset is not None else {}
    if "time_s" in parsed.header:
        raise ValueError(f"{file}: line {parsed.header_line['time_s']}: a front history has no single time_s")
    return FrontHistory(
        t=values[:, 0] * time_scale, x_front=values[:, 1] * scale, experiment=name, source=str(source),
        synthetic=_synthetic(parsed, name), meta=_meta(parsed, extra), path=str(path),
    )


read_table = tables.read_columns


@dataclasses.dataclass(frozen=True, eq=False)
class RunoutLaw:
    """An empirical law of column collapse against aspect ratio a = H0/L0, sampled: normalised runout
    ``runout`` = ΔL/L0 = (L_f - L0)/L0 and, where known, final height ``height`` = H_f/L0.
    ``secondary`` is true when the law was quoted from a secondary source."""

    a: np.ndarray
    runout: np.ndarray
    height: np.ndarray | None
    secondary: bool
    source: str
    experiment: str = ""
    meta: dict = dataclasses.field(default_factory=dict)
    path: str | None = None

    def __post_init__(self):
        a = _frozen_array("a", self.a, "RunoutLaw")
        runout = _frozen_array("runout", self.runout, "RunoutLaw")
        height = None if self.height is None else _frozen_array("height", self.height, "RunoutLaw")
        if runout.shape != a.shape or (height is not None and height.shape != a.shape):
            raise ValueError("RunoutLaw: a, runout and height must have equal length")
        if np.any(a <= 0) or np.any(np.diff(a) <= 0):
            raise ValueError("RunoutLaw: a must be positive and strictly increasing")
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "runout", runout)
        object.__setattr__(self, "height", height)

    @property
    def n(self) -> int:
        return int(self.a.size)


def load_scaling_law(path: str | os.PathLike) -> RunoutLaw:
    """Read a scaling-law CSV: columns ``a,dL_over_L0`` and optionally ``Hf_over_L0``, and a header
    with ``secondary`` (true/false) and ``source``."""
    path = pathlib.Path(path)
    header, columns = read_table(path)
    file = str(path)
    if set(columns) not in ({"a", "dL_over_L0"}, {"a", "dL_over_L0", "Hf_over_L0"}):
        raise ValueError(f"{file}: expected columns a,dL_over_L0[,Hf_over_L0], got {list(columns)}")
    secondary = header.get("secondary")
    if secondary is not True and secondary is not False:
        raise ValueError(f"{file}: the header must say 'secondary: true' or 'secondary: false', got {secondary!r}")
    if "source" not in header:
        raise ValueError(f"{file}: the header has no 'source'")
    try:
        return RunoutLaw(
            a=columns["a"], runout=columns["dL_over_L0"], height=columns.get("Hf_over_L0"), secondary=secondary,
            source=str(header["source"]), experiment=str(header.get("experiment", path.stem)),
            meta={k: v for k, v in header.items() if k not in ("secondary", "source", "experiment")},
            path=file,
        )
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None
