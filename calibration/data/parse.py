"""How the data files are read: the header keys, units and columns of the project CSV and of
WebPlotDigitizer exports, turned into arrays with every error naming the file and its line
(``calibration.data.loaders`` says what each format holds).
"""

from __future__ import annotations

import math
import pathlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from jaxmpm import tables
from jaxmpm.params import LENGTH_UNITS

__all__ = ["TIME_UNITS", "UNITS"]


#: Length units a file may declare, as metres per unit (``jaxmpm.params.LENGTH_UNITS``).
UNITS: dict[str, float] = dict(LENGTH_UNITS)
#: Time units a front history may declare, as seconds per unit.
TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3}


#: Header keys that map to fields rather than to ``meta``.
_FIELD_KEYS = ("experiment", "time_s", "units", "source", "synthetic")


#: Negative heights down to this fraction of max h count as digitisation noise (``clip_noise``).
NOISE_FRACTION = 1e-3


_MIN_POINTS = 3


#: A ``time_s`` header in words that starts with this word means the final deposit, after the
#: flow stopped (``time_s`` None: the end of the run).
_FINAL = "final"


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
