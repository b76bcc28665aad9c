"""The measurement sections of a collapse experiment file: what was measured and what to fit.

    [[profile]]
    file = "deposit.csv"                 # relative to the experiment file
    time = "0.5 s"                       # optional: when it was taken (else the file's header)
    [front]
    file = "front.csv"
    correlation_time = "20 ms"
    [fit]
    keys = ["beta", "mu1"]
    init = { beta = 0.1 }

The engine (``jaxmpm.Experiment``) reads the set-up of a file and keeps these sections as they
were written (``Experiment.measurements``), checking only that the data files they name exist.
``read_measurements`` reads and checks them here, every error naming the file, the line and the
key (``FILE:LINE: [section] key: what``), against the experiment's set-up as it stands (a
profile's time within its ``t_end``; ``mu_w`` fitted only where a boundary reads it).
``with_measurements`` is the reverse: an experiment with measurements built in Python.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from collections.abc import Mapping
from typing import Any, NamedTuple

from jaxmpm import Experiment
from jaxmpm._toml import PURE, TIME, Where, read_section
from jaxmpm.params import LENGTH_UNITS, PARAM_KEYS

__all__ = ["FitSpec", "FrontMeasurement", "Measurements", "ProfileMeasurement", "read_measurements",
           "with_measurements"]

_SCHEMA: dict[str, dict[str, Any]] = {
    "profile": {"time": TIME, "units": "str", "dataset": "str"},
    "front": {"units": "str", "time_units": "str", "correlation_time": TIME},
    "fit": {"keys": "strings", "init": "numbers", "noise": PURE, "weight_profile": PURE, "weight_front": PURE},
}
_FILE_OF = {"profile": "the profile's CSV file", "front": "the front history's CSV file"}


@dataclasses.dataclass(frozen=True)
class ProfileMeasurement:
    """A measured surface profile h(x) (``calibration.load_profile``): its CSV file, the time it
    was taken (None: the file's header says, or the final deposit), its length unit (None: the
    file's header says) and, for a file holding several, which data set."""

    file: pathlib.Path
    time: float | None = None
    units: str | None = None
    dataset: str | None = None


@dataclasses.dataclass(frozen=True)
class FrontMeasurement:
    """A measured front history x_f(t) (``calibration.load_front_history``)."""

    file: pathlib.Path
    units: str | None = None
    time_units: str | None = None
    correlation_time: float | None = None


@dataclasses.dataclass(frozen=True)
class FitSpec:
    """What to fit: the keys, optional starting values (a single start), the data's noise as a
    fraction of the peak height (None: estimated from the fit) and the blocks' weights."""

    keys: tuple[str, ...]
    init: Mapping[str, float] = dataclasses.field(default_factory=dict)
    noise: float | None = None
    weight_profile: float = 1.0
    weight_front: float = 1.0


class Measurements(NamedTuple):
    """An experiment's ``[[profile]]`` tables, its ``[front]`` (None: none) and its ``[fit]``
    (None: none)."""

    profiles: tuple[ProfileMeasurement, ...]
    front: FrontMeasurement | None
    fit: FitSpec | None


def read_measurements(experiment: Experiment) -> Measurements:
    """The measurement sections of ``experiment`` read and checked; raises ``ExperimentError``
    naming the file, the line and the key of the first value that fails."""
    where = Where(experiment.path, experiment.text)
    tables = experiment.measurements
    profiles = tuple(ProfileMeasurement(**_table(table, "profile", where, i))
                     for i, table in enumerate(tables.get("profile", ())))
    front = FrontMeasurement(**_table(tables["front"], "front", where)) if "front" in tables else None
    fit = None
    if "fit" in tables:
        spec, _ = read_section(tables, "fit", _SCHEMA["fit"], where)
        if "keys" not in spec:
            raise where.error("fit", "keys", "missing: the parameters to fit, e.g. [\"beta\", \"mu1\"]")
        fit = FitSpec(**spec)
    out = Measurements(profiles, front, fit)
    _check(experiment, out, where)
    return out


def with_measurements(experiment: Experiment, **changes) -> Experiment:
    """``experiment`` with some of its measurements replaced: ``profiles`` (ProfileMeasurements),
    ``front`` and ``fit`` (None: none); those not named are kept. Checked as a file's are."""
    unknown = sorted(set(changes) - set(Measurements._fields))
    if unknown:
        raise TypeError(f"with_measurements: unknown measurements {unknown}; give {list(Measurements._fields)}")
    kept = read_measurements(experiment)._asdict()
    new = Measurements(**{**kept, **changes})
    tables: dict[str, Any] = {}
    if new.profiles:
        tables["profile"] = [_entries(p) for p in new.profiles]
    if new.front is not None:
        tables["front"] = _entries(new.front)
    if new.fit is not None:
        fit = _entries(new.fit)
        fit.update(keys=list(new.fit.keys), init=dict(new.fit.init))
        tables["fit"] = {k: v for k, v in fit.items() if v != {} and not (k.startswith("weight_") and v == 1.0)}
    out = experiment.replace(measurements=tables)
    read_measurements(out)
    return out


def _entries(measurement) -> dict[str, Any]:
    """A measurement's fields as the entries of its table (those that are None left out)."""
    return {f.name: getattr(measurement, f.name) for f in dataclasses.fields(measurement)
            if getattr(measurement, f.name) is not None}


def _table(table: Mapping[str, Any], section: str, where: Where, index=None) -> dict[str, Any]:
    """The entries of a ``[[profile]]`` or ``[front]`` table, its file a path (the engine has
    placed it relative to the experiment file and, where asked, found it)."""
    values = {k: v for k, v in table.items() if k != "file"}
    values, _ = (read_section(values, section, _SCHEMA[section], where, index) if index is not None
                 else read_section({section: values}, section, _SCHEMA[section], where))
    file = table.get("file")
    if file is None:
        raise where.error(section, "file", "missing: " + _FILE_OF[section], index)
    if not isinstance(file, (str, os.PathLike)) or not str(file).strip():
        raise where.error(section, "file", f"expected a file name, got {file!r}", index)
    return {"file": pathlib.Path(file), **values}


def _names(units: Mapping[str, float]) -> str:
    """The unit names as text: "m, cm or mm"."""
    names = [u for u in units if u]
    return ", ".join(names[:-1]) + " or " + names[-1]


def _check(e: Experiment, measured: Measurements, where: Where) -> None:
    """The measurements' values against what they mean and against the set-up of ``e``."""
    def need(ok, section, key, what, index=None):
        if not ok:
            raise where.error(section, key, what, index)

    lengths, times = _names(LENGTH_UNITS), _names(TIME.table)
    for i, p in enumerate(measured.profiles):
        if p.time is not None:
            need(0.0 < p.time <= e.t_end * (1 + 1e-9), "profile", "time",
                 f"at {p.time:g} s: must be in (0, t_end = {e.t_end:g} s]", i)
        need(p.units is None or p.units in LENGTH_UNITS, "profile", "units", f"must be {lengths}, got {p.units!r}", i)
    if measured.front is not None:
        need(measured.front.units is None or measured.front.units in LENGTH_UNITS, "front", "units",
             f"must be {lengths}, got {measured.front.units!r}")
        need(measured.front.time_units is None or measured.front.time_units in TIME.table, "front", "time_units",
             f"must be {times}, got {measured.front.time_units!r}")
        tau = measured.front.correlation_time
        need(tau is None or (math.isfinite(tau) and tau > 0), "front", "correlation_time", f"must be > 0 s, got {tau}")
    if measured.fit is None:
        return
    keys = measured.fit.keys
    unknown = sorted(set(keys) - set(PARAM_KEYS))
    need(not unknown, "fit", "keys", f"unknown parameter(s) {unknown}; valid keys are {list(PARAM_KEYS)}")
    need(len(set(keys)) == len(keys), "fit", "keys", f"a key is listed twice: {list(keys)}")
    walls_read = e.side_walls is not None and e.side_walls.friction == "mu_w"
    need("mu_w" not in keys or e.floor != "no-slip" or walls_read, "fit", "keys",
         "mu_w is read by no boundary: the floor is no-slip and the side walls' friction is not \"mu_w\" (fit "
         "the floor's friction with floor = \"slip-stick\" and floor_friction, the side walls' with "
         "side_walls = { ..., friction = \"mu_w\" } and [material] mu_w as the start)")
    stray = sorted(set(measured.fit.init) - set(keys))
    need(not stray, "fit", "init", f"{stray} are not fitted (keys = {list(keys)})")
    noise = measured.fit.noise
    need(noise is None or noise >= 0, "fit", "noise", f"must be >= 0, got {noise}")
    for key in ("weight_profile", "weight_front"):
        need(getattr(measured.fit, key) >= 0, "fit", key, f"must be >= 0, got {getattr(measured.fit, key)}")

