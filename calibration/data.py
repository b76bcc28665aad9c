"""Loading the data that a calibration compares against: deposit profiles, front histories,
scaling laws, and the files shipped in ``experiments_data/``.

Formats
-------
**Project CSV** (the format of ``jaxmpm.tables``: what ``python -m jaxmpm run ... --profile-csv``,
``Profile.to_csv`` and ``FrontHistory.to_csv`` write)::

    # experiment: cohesive-collapse (synthetic, jaxmpm 0.1.0)
    # time_s: 0.5
    # units: m
    # source: python -m jaxmpm run cohesive-collapse --set beta=0.25 ...
    # parameters: {"beta": 0.25, ...}
    x_m,h_m
    -6.955788e-03,3.189269e-04
    ...

Comment lines ``# key: value`` form the header; a value is JSON-decoded where it parses as JSON
and kept as a string otherwise. A comment line indented by two or more blanks after the ``#``
right below a key line continues that key's value (joined with a blank), so a long citation may
span lines. Keys with a meaning here: ``experiment`` (str), ``time_s`` (s, the time the profile
was taken; ``None`` when absent, or when it is words starting with "final", such as ``final
deposit (the flow has stopped)``: the text is kept in ``meta["time_s_text"]``), ``units``
(``m``, ``cm`` or ``mm``), ``source`` (str: a citation or the command that made the file) and ``synthetic`` (bool; when
absent a profile is synthetic if the word "synthetic" is in ``experiment``). Every other key goes
to ``meta``. The column header is ``x_m,h_m``; ``x_cm,h_cm`` and ``x_mm,h_mm`` are converted to
metres, and ``x,h`` takes its units from the ``units`` key or the ``units=`` argument.
A front history has columns ``t_s,xf_m`` (or ``xf_cm``, ``xf_mm``); a scaling law has columns
``a,dL_over_L0[,Hf_over_L0]`` and a ``secondary`` key.

**WebPlotDigitizer export**: two numeric columns with no header, or with a first row ``X,Y``
(any case); or WPD's multi-dataset layout, a first row of dataset names (``Dataset 1,,Dataset
2,``), a second row ``X,Y,X,Y`` and then rows in which a shorter dataset's cells are empty. The
first dataset is taken unless ``dataset=`` names another. Such a file carries no units: pass
``units='m'|'cm'|'mm'`` (and ``experiment=``, ``time_s=`` for the metadata it lacks).

Either kind may use ``,``, ``;`` or tab as delimiter (or blanks, when a row has none of those),
Windows or Unix line endings and a UTF-8 byte-order mark. In ``;``- or tab-delimited files a
decimal comma (``1,5``) is read as a decimal point.

Validation
----------
Every error is a ``ValueError`` that names the file and, where it concerns one row, its 1-based
line number: a non-numeric or non-finite cell, a wrong number of columns, x (or t) not strictly
increasing (``sort=True`` sorts points in WebPlotDigitizer click order, and refuses duplicate
x), a negative height, fewer than 3 points, unknown or missing units. Nothing is silently
changed: ``clip_noise=True`` sets heights in [-1e-3 max h, 0) to zero (digitisation noise) and
lists their lines in ``meta["clipped_noise_lines"]``.

Shipped data
------------
``list_datasets()`` reads ``experiments_data/manifest.json``; ``dataset_path(name)`` finds a
file from its manifest name or its path inside ``experiments_data/``. The folder is where the
environment variable ``JAXMPM_EXPERIMENTS_DATA`` points if it is set, else the one next to the
``jaxmpm`` package (a source checkout or an editable install), else the installed package
``jaxmpm.experiments_data`` (``pip install .`` installs the folder under that name).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from jaxmpm import tables
from jaxmpm.datasets import DatasetInfo, data_dir, dataset_path, list_datasets  # the one finder, re-exported

__all__ = [
    "UNITS", "DatasetInfo", "FrontHistory", "Profile", "RunoutLaw", "data_dir", "data_end_time", "dataset_path",
    "list_datasets",
    "load_front_history", "load_measurements", "load_profile", "load_scaling_law", "load_setup", "read_table",
]

#: Length units a file may declare, as metres per unit.
UNITS: dict[str, float] = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3}
#: Header keys that map to fields rather than to ``meta``.
_FIELD_KEYS = ("experiment", "time_s", "units", "source", "synthetic")
#: Negative heights down to this fraction of max h count as digitisation noise (``clip_noise``).
NOISE_FRACTION = 1e-3
_MIN_POINTS = 3
#: A ``time_s`` header in words that starts with this word means the final deposit, after the
#: flow stopped (``time_s`` None: the end of the run).
_FINAL = "final"


# ---------------------------------------------------------------------------------------------
# Parsing (``jaxmpm.tables.read_table`` splits a file into header and cells; what they mean is here)
# ---------------------------------------------------------------------------------------------


_is_number, _numeric, _trim = tables.is_number, tables.numeric_rows, tables.trim_cells


def _columns(parsed: tables.Table, dataset: str | None):
    """The column names (lower case; ``None`` for a headerless file), the data rows, and the name
    of the WebPlotDigitizer dataset taken from a multi-dataset file (else ``None``)."""
    rows = parsed.rows
    if not rows:
        raise ValueError(f"{parsed.file}: no data rows")
    number, first = rows[0]
    if all(_is_number(c) for c in first if c) and any(first):
        if dataset is not None:
            raise ValueError(f"{parsed.file}: dataset={dataset!r} given but the file has no dataset names "
                             "(command line: --dataset)")
        return None, [(n, _trim(c)) for n, c in rows], None
    names = [c.lower() for c in first]
    second = rows[1][1] if len(rows) > 1 else []
    pairs = _trim([c.lower() for c in second])
    multi = len(pairs) >= 2 and len(pairs) % 2 == 0 and all(
        p == ("x" if k % 2 == 0 else "y") for k, p in enumerate(pairs))
    if not multi:
        if dataset is not None:
            raise ValueError(f"{parsed.file}: dataset={dataset!r} given but the file is not a multi-dataset "
                             "WebPlotDigitizer export (command line: --dataset)")
        return tuple(_trim(names)), [(n, _trim(c)) for n, c in rows[1:]], None
    # WebPlotDigitizer multi-dataset layout: names on line 1 (every other cell), X,Y,... on line 2.
    width = len(pairs)
    available = [first[k] if k < len(first) else "" for k in range(0, width, 2)]
    if dataset is None:
        index = 0
    elif dataset in available:
        index = available.index(dataset)
    else:
        raise ValueError(f"{parsed.file}: line {number}: no dataset named {dataset!r}; the file has {available}")
    picked = []
    for n, cells in rows[2:]:
        cells = _trim(cells)
        if len(cells) > width:
            raise ValueError(f"{parsed.file}: line {n}: expected at most {width} columns "
                             f"({len(available)} X,Y datasets), got {len(cells)}")
        cells = cells + [""] * (width - len(cells))
        pair = cells[2 * index: 2 * index + 2]
        if pair == ["", ""]:
            continue  # this dataset has fewer points than the longest one
        if "" in pair:
            raise ValueError(f"{parsed.file}: line {n}: dataset {available[index]!r} has an empty "
                             f"{'X' if pair[0] == '' else 'Y'} cell")
        picked.append((n, pair))
    return ("x", "y"), picked, available[index]


def _unit_scale(parsed: tables.Table, from_names: str | None, argument: str | None, table: Mapping[str, float],
                what: str, hint: str) -> tuple[str, float]:
    """Resolve units from the column names, the ``units`` header key and the argument, which must
    agree where more than one is given."""
    declared = []
    if from_names is not None:
        declared.append(("the column names", from_names))
    if what == "units" and "units" in parsed.header:
        where = f"line {parsed.header_line['units']}"
        declared.append((f"the header ({where})", str(parsed.header["units"])))
    if argument is not None:
        declared.append((f"the argument {what}= (--{what.replace('_', '-')})", argument))
    if not declared:
        raise ValueError(f"{parsed.file}: the file has no {'units' if what == 'units' else 'time units'} "
                         f"(a WebPlotDigitizer export never has); pass {hint}")
    for source, value in declared:
        if value not in table:
            raise ValueError(f"{parsed.file}: unknown {what} {value!r} in {source}; use one of {sorted(table)}")
    values = {value for _, value in declared}
    if len(values) > 1:
        raise ValueError(f"{parsed.file}: conflicting {what}: "
                         + ", ".join(f"{value!r} in {source}" for source, value in declared))
    unit = declared[0][1]
    return unit, table[unit]


def _check_increasing(file: str, values: np.ndarray, lines: np.ndarray, name: str, unit: str, sort: bool):
    """Strictly increasing ``values`` (or sorted, with ``sort``): returns the order to apply."""
    if sort:
        order = np.argsort(values, kind="stable")
        v, ln = values[order], lines[order]
        dup = np.nonzero(np.diff(v) == 0)[0]
        if dup.size:
            k = dup[0]
            raise ValueError(f"{file}: duplicate {name} = {v[k]:g} {unit} at lines {ln[k]} and {ln[k + 1]}")
        return order
    bad = np.nonzero(np.diff(values) <= 0)[0]
    if bad.size:
        shown = "; ".join(f"line {lines[k]} ({name} = {values[k]:g} {unit}) is followed by line {lines[k + 1]} "
                          f"({name} = {values[k + 1]:g} {unit})" for k in bad[:3])
        more = f" and {bad.size - 3} more" if bad.size > 3 else ""
        raise ValueError(f"{file}: {name} is not strictly increasing: {shown}{more}; if the points are in "
                         "WebPlotDigitizer click order, pass sort=True (command line: --sort)")
    return np.arange(values.size)


def _check_count(file: str, n: int):
    if n < _MIN_POINTS:
        raise ValueError(f"{file}: {n} data row(s); at least {_MIN_POINTS} are needed")


def _experiment(parsed: tables.Table, path: pathlib.Path, argument: str | None) -> str:
    value = parsed.header.get("experiment")
    if argument is not None:
        if value is not None and str(value) != argument:
            raise ValueError(f"{parsed.file}: experiment={argument!r} contradicts the header "
                             f"(line {parsed.header_line['experiment']}: {value!r})")
        return argument
    return str(value) if value is not None else path.stem


def _synthetic(parsed: tables.Table, experiment: str) -> bool:
    if "synthetic" in parsed.header:
        value = parsed.header["synthetic"]
        if not isinstance(value, bool):
            raise ValueError(f"{parsed.file}: line {parsed.header_line['synthetic']}: synthetic must be true "
                             f"or false, got {value!r}")
        return value
    return "synthetic" in experiment.lower()


def _final_deposit(parsed: tables.Table) -> bool:
    """True when the header's ``time_s`` is words that start with "final" (the final deposit)."""
    value = parsed.header.get("time_s")
    return isinstance(value, str) and value.strip().lower().startswith(_FINAL)


def _time(parsed: tables.Table, argument: float | None) -> float | None:
    value = parsed.header.get("time_s")
    if _final_deposit(parsed):
        value = None  # "final deposit": no single time; the argument (if any) supplies one
    if value is not None:
        line = parsed.header_line["time_s"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{parsed.file}: line {line}: time_s must be a finite number of seconds, got "
                             f"{value!r}")
        if argument is not None and float(argument) != float(value):
            raise ValueError(f"{parsed.file}: time_s={argument!r} contradicts the header (line {line}: {value!r})")
        return float(value)
    if argument is not None:
        if not (isinstance(argument, (int, float)) and math.isfinite(argument)):
            raise ValueError(f"time_s must be a finite number of seconds, got {argument!r}")
        return float(argument)
    return None


def _meta(parsed: tables.Table, extra: Mapping[str, Any] = ()) -> dict[str, Any]:
    meta = {k: v for k, v in parsed.header.items() if k not in _FIELD_KEYS}
    meta.update(extra)
    return meta


# ---------------------------------------------------------------------------------------------
# Writing (the header of a profile or front history; ``jaxmpm.tables`` writes the file)
# ---------------------------------------------------------------------------------------------


def _header(experiment: str, time_s: float | None, source: str, synthetic: bool, meta: Mapping[str, Any]):
    """The header of a written profile or front history: its fields in a fixed order, then ``meta``."""
    clash = sorted(set(meta) & set(_FIELD_KEYS))
    if clash:
        raise ValueError(f"meta must not hold the keys {clash}: they are fields")
    out = {"experiment": experiment}
    if time_s is not None:
        out["time_s"] = float(time_s)
    out.update(units="m", source=source, synthetic=bool(synthetic))
    out.update(meta)
    return out


def _frozen_array(name: str, value, owner: str) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{owner}.{name} must be 1-D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}.{name} must be finite")
    arr.flags.writeable = False
    return arr


# ---------------------------------------------------------------------------------------------
# Profiles
# ---------------------------------------------------------------------------------------------


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
        x = _frozen_array("x", self.x, "Profile")
        h = _frozen_array("h", self.h, "Profile")
        if x.shape != h.shape:
            raise ValueError(f"Profile: x and h must have equal length, got {x.size} and {h.size}")
        if x.size < _MIN_POINTS:
            raise ValueError(f"Profile: at least {_MIN_POINTS} points are needed, got {x.size}")
        if np.any(np.diff(x) <= 0):
            raise ValueError("Profile: x must be strictly increasing")
        if np.any(h < 0):
            raise ValueError("Profile: h must be >= 0")
        if self.time_s is not None and not math.isfinite(self.time_s):
            raise ValueError(f"Profile: time_s must be finite or None, got {self.time_s!r}")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "h", h)
        object.__setattr__(self, "meta", dict(self.meta))

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
    """Read a deposit profile: the project CSV or a WebPlotDigitizer export (module docstring).

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
    if h_max <= 0:
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
    return Profile(
        x=x_raw * scale, h=h_raw * scale, experiment=name, time_s=_time(parsed, time_s), source=str(source),
        synthetic=_synthetic(parsed, name), meta=_meta(parsed, extra), path=str(path),
    )


# ---------------------------------------------------------------------------------------------
# Front histories
# ---------------------------------------------------------------------------------------------


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
        t = _frozen_array("t", self.t, "FrontHistory")
        xf = _frozen_array("x_front", self.x_front, "FrontHistory")
        if t.shape != xf.shape:
            raise ValueError(f"FrontHistory: t and x_front must have equal length, got {t.size} and {xf.size}")
        if t.size < _MIN_POINTS:
            raise ValueError(f"FrontHistory: at least {_MIN_POINTS} points are needed, got {t.size}")
        if np.any(np.diff(t) <= 0):
            raise ValueError("FrontHistory: t must be strictly increasing")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "x_front", xf)
        object.__setattr__(self, "meta", dict(self.meta))

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
    time_unit, time_scale = _unit_scale(parsed, column_time, time_units, _TIME_UNITS, "time_units",
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


# ---------------------------------------------------------------------------------------------
# Tables and scaling laws
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Shipped data
# ---------------------------------------------------------------------------------------------


def data_end_time(profiles, front=None) -> float | None:
    """The latest time (s) at which the data were taken (profiles that state their time, the
    front history's last), or None where nothing says: the end time a run needs to be compared
    with them, when none is given."""
    times = [float(p.time_s) for p in profiles if getattr(p, "time_s", None) is not None]
    if front is not None:
        times.append(float(front.t[-1]))
    return max(times) if times else None


def load_measurements(experiment, *, sort: bool = False, clip_noise: bool = False) -> tuple[list, Any]:
    """(profiles, front history or None) that a ``jaxmpm.Experiment`` lists ([[profile]],
    [front]), read with the units and times it states; ``sort`` and ``clip_noise`` as for
    ``load_profile``."""
    profiles = [load_profile(p.file, units=p.units, time_s=p.time, dataset=p.dataset, sort=sort, clip_noise=clip_noise)
                for p in experiment.profiles]
    front = None
    if experiment.front is not None:
        front = load_front_history(experiment.front.file, units=experiment.front.units,
                                   time_units=experiment.front.time_units, sort=sort)
    return profiles, front


def load_setup(name: str | os.PathLike) -> dict[str, Any]:
    """A scene set-up (``setups/*.json``: S1's) by manifest name (``'setups/S1_incline'``) or path.
    The collapses' set-ups are experiment files: ``jaxmpm.experiment.shipped_experiment``."""
    path = pathlib.Path(name)
    if not path.is_file():
        path = dataset_path(str(name))
    return json.loads(path.read_text())
