"""A collapse experiment described in one file: geometry, boundaries, material, numerics, the
measurements taken and what to fit (docs/experiments.md).

    [experiment]
    name = "my-collapse"
    [geometry]
    length = "60 mm"                     # the column, L x H (x W in 3D), on a bed inclined at slope
    height = "90 mm"
    [boundaries]
    gate = "front"                       # "front", "back", "both" or "none" (released at t = 0)
    gate_speed = "1.5 m/s"               # or gate_lift_time = "40 ms" (to clear the column's height)
    [material]
    beta = 0.1
    pc0 = { value = 0.4, unit = "kPa", source = "shear-box test, 12 May" }
    [numerics]
    dx = "4 mm"
    t_end = "0.6 s"
    [[profile]]
    file = "deposit.csv"                 # relative to this file
    [fit]
    keys = ["beta", "mu1"]

A value is a number in SI units (m, s, Pa, kg/m^3, degrees for angles), a string with its unit
("60 mm", "40 ms", "0.4 kPa") or a table ``{value, unit, source, note}`` that keeps where the value
came from. ``Experiment.from_toml`` reads and checks a file (every error names the file, the line
and the key, before anything is built or compiles); ``scene()`` builds it with
``jaxmpm.scenes.collapse``; ``to_toml`` writes it back, so that a run's HDF5 file can record the
experiment it ran (``Experiment.from_text``).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import re
import sys
from collections.abc import Mapping
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from .params import PARAM_KEYS

__all__ = ["Experiment", "ExperimentError", "ProfileMeasurement", "FrontMeasurement", "FitSpec", "shipped_experiment",
           "SHIPPED_EXPERIMENTS", "FORMAT"]

#: The file format's version, written by ``to_toml``; a file may state it as ``format = 1``.
FORMAT = 1

_LENGTH = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_TIME = {"s": 1.0, "ms": 1e-3}
_SPEED = {"m/s": 1.0, "cm/s": 1e-2, "mm/s": 1e-3}
_ANGLE = {"deg": 1.0, "rad": 180.0 / math.pi}
_PRESSURE = {"Pa": 1.0, "kPa": 1e3, "MPa": 1e6}
_DENSITY = {"kg/m^3": 1.0, "kg/m3": 1.0, "g/cm^3": 1e3, "g/cm3": 1e3}
_PURE = {"-": 1.0, "": 1.0}
#: The unit each material parameter may be given in (docs/model.md §4); the SI unit first.
MATERIAL_UNITS = {"E": _PRESSURE, "nu": _PURE, "rho": _DENSITY, "rho_s": _DENSITY, "d": _LENGTH, "mu1": _PURE,
                  "mu2": _PURE, "I0": _PURE, "beta": _PURE, "pc0": _PRESSURE, "xi": _PURE, "mu_w": _PURE}
_SI_NAME = {id(_LENGTH): "m", id(_TIME): "s", id(_SPEED): "m/s", id(_ANGLE): "deg", id(_PRESSURE): "Pa",
            id(_DENSITY): "kg/m^3", id(_PURE): "-"}

FLOORS = ("no-slip", "slip-stick", "separable")
GATES = ("none", "front", "back", "both")
SAMPLINGS = ("lattice", "jitter", "poisson")
DTYPES = ("float32", "float64")
TRANSFERS = ("pic", "apic", "flip", "aflip")

# section -> key -> kind: a unit table (a number), or "str", "int", "bool", "strings", "numbers", "path".
_SCHEMA: dict[str, dict[str, Any]] = {
    "experiment": {"name": "str", "title": "str", "source": "str", "note": "str"},
    "geometry": {"length": _LENGTH, "height": _LENGTH, "width": _LENGTH, "slope": _ANGLE},
    "boundaries": {"floor": "str", "floor_friction": _PURE, "back_wall": "bool", "gate": "str", "gate_speed": _SPEED,
                   "gate_lift_time": _TIME},
    "material": dict(MATERIAL_UNITS),
    "numerics": {"dim": "int", "dx": _LENGTH, "ppc": _PURE, "sampling": "str", "seed": "int", "dtype": "str",
                 "t_end": _TIME, "frames": "int", "runout": _LENGTH, "backward_runout": _LENGTH, "transfer": "str",
                 "alpha": _PURE, "cfl": _PURE},
    "profile": {"file": "path", "time": _TIME, "units": "str", "dataset": "str"},
    "front": {"file": "path", "units": "str", "time_units": "str", "correlation_time": _TIME},
    "fit": {"keys": "strings", "init": "numbers", "noise": _PURE, "weight_profile": _PURE, "weight_front": _PURE},
}
_TOP = ("format",)


class ExperimentError(ValueError):
    """An experiment file that cannot be used: the message names the file, the line and the key."""


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


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One collapse experiment (see the module docstring); lengths in m, times in s, speeds in
    m/s, angles in degrees, material parameters in SI units."""

    name: str
    length: float
    height: float
    t_end: float
    width: float | None = None
    slope: float = 0.0
    floor: str = "no-slip"
    floor_friction: float | None = None
    back_wall: bool = True
    gate: str = "none"
    gate_speed: float | None = None
    material: Mapping[str, float] = dataclasses.field(default_factory=dict)
    dim: int = 2
    dx: float | None = None
    ppc: float | None = None
    sampling: str | None = None
    seed: int = 0
    dtype: str | None = None
    frames: int = 0
    runout: float | None = None
    backward_runout: float | None = None
    transfer: str = "aflip"
    alpha: float = 0.95
    cfl: float = 0.5
    profiles: tuple[ProfileMeasurement, ...] = ()
    front: FrontMeasurement | None = None
    fit: FitSpec | None = None
    title: str = ""
    #: "section.key" -> where the value came from (the file's ``source``/``note``/``unit`` entries).
    sources: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict, compare=False)
    #: The file this experiment was read from (None: built in Python).
    path: pathlib.Path | None = dataclasses.field(default=None, compare=False)

    def __post_init__(self):
        _check_experiment(self)

    # -- reading and writing ---------------------------------------------------------------------------

    @classmethod
    def from_toml(cls, path) -> Experiment:
        """Read and check an experiment file; measurement files are relative to its folder."""
        path = pathlib.Path(path)
        if path.suffix != ".toml":
            raise ExperimentError(f"{path}: an experiment file ends in .toml")
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as err:
            raise ExperimentError(f"{path}: cannot read the experiment file ({err.strerror or err})") from None
        return cls.from_text(text, path)

    @classmethod
    def from_text(cls, text: str, path=None) -> Experiment:
        """An experiment from the text of a file (``path``: where it lives, for the measurement
        files and the error messages; None: measurement files relative to the working folder)."""
        path = None if path is None else pathlib.Path(path)
        label = str(path) if path is not None else "<experiment>"
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ExperimentError(f"{label}: not valid TOML: {err}") from None
        return _parse(raw, _Where(path, text))

    @classmethod
    def from_h5(cls, path) -> Experiment:
        """The experiment a run's HDF5 file records (``python -m jaxmpm run EXPERIMENT.toml --out``
        writes it), to run it again; its measurement files resolve where the original file was."""
        import h5py

        with h5py.File(path, "r") as f:
            text = f.attrs.get("experiment_toml")
            origin = f.attrs.get("experiment_path")
        if text is None:
            raise ExperimentError(f"{path}: records no experiment (a run of a named scene, or written before "
                                  "experiment files)")
        text = text.decode() if isinstance(text, bytes) else str(text)
        origin = None if origin is None else (origin.decode() if isinstance(origin, bytes) else str(origin))
        return cls.from_text(text, origin)

    def to_toml(self) -> str:
        """This experiment as the text of an experiment file (SI units; sources kept; measurement
        files as absolute paths unless they lie beside the file it was read from)."""
        return _write(self)

    def replace(self, **changes) -> Experiment:
        """A copy with some fields changed (checked again)."""
        return dataclasses.replace(self, **changes)

    def with_options(self, material: Mapping[str, float] | None = None, flags: Mapping[str, str] | None = None,
                     **options) -> Experiment:
        """A copy with the options that are not None changed (``dx``, ``ppc``, ``t_end``, ...: field
        names) and the ``material`` keys set: a command line's options over a file's values.
        ``flags`` maps a field to the option that set it, for the error message of a value that
        does not fit the experiment (e.g. ``{"dx": "--dx"}``)."""
        fields = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(options) - fields)
        if unknown:
            raise ValueError(f"with_options: unknown fields {unknown}")
        changes = {k: v for k, v in options.items() if v is not None}
        if material:
            unknown = sorted(set(material) - set(PARAM_KEYS))
            if unknown:
                raise ValueError(f"unknown parameter(s) {unknown}; valid keys are {list(PARAM_KEYS)}")
            changes["material"] = {**self.material, **material}
        try:
            return dataclasses.replace(self, **changes)
        except _Invalid as err:
            flag = (flags or {}).get(err.key)
            if flag is not None and err.key in changes:
                raise ValueError(f"{flag} {err.what}") from None
            label = str(self.path) if self.path is not None else self.name
            raise ExperimentError(f"{label}: {err}") from None

    # -- what it builds --------------------------------------------------------------------------------

    @property
    def gate_speeds(self) -> tuple[float | None, float | None]:
        """(front, back) gate speeds, m/s (None: no gate on that side)."""
        front = self.gate_speed if self.gate in ("front", "both") else None
        back = self.gate_speed if self.gate in ("back", "both") else None
        return front, back

    def builder_arguments(self) -> dict[str, Any]:
        """The arguments of ``jaxmpm.scenes.collapse`` that build this experiment."""
        from .scenes.collapse import default_runout

        dx = self.dx if self.dx is not None else min(self.length, self.height) / 16
        front, back = self.gate_speeds
        runout = self.runout if self.runout is not None else default_runout(self.length, self.height, self.slope, dx)
        backward = self.backward_runout
        if backward is None:
            backward = runout if self.gate in ("back", "both") else 0.0
        material = dict(self.material)
        if self.floor_friction is not None:
            material["mu_w"] = self.floor_friction
        return dict(name=self.name, length=self.length, height=self.height, dx=dx, ppc=self.ppc,
                    sampling=self.sampling, seed=self.seed, dim=self.dim, width=self.width, slope_deg=self.slope,
                    back_wall=self.back_wall, front_gate_speed=front, back_gate_speed=back, runout=runout,
                    backward_runout=backward, t_end=self.t_end, frames=self.frames, transfer=self.transfer,
                    alpha=self.alpha, cfl=self.cfl, dtype=self.dtype, floor=self.floor, base_params=material)

    def scene(self):
        """The ready-to-run ``Scene`` (``jaxmpm.scenes.collapse``); it keeps this experiment
        (``scene.experiment``)."""
        from .scenes.collapse import collapse

        scene = collapse(**self.builder_arguments())
        return dataclasses.replace(scene, experiment=self)

    def params(self):
        """The material as ``Params`` (unlisted keys take docs/model.md §4's defaults)."""
        from .params import Params

        return Params.create(dtype=self.dtype, **self.builder_arguments()["base_params"])


# -- checking -------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class _Where:
    path: pathlib.Path | None
    text: str | None

    def error(self, section: str | None, key: str | None, what: str, index: int | None = None):
        label = str(self.path) if self.path is not None else "<experiment>"
        line = _line_of(self.text, section, key, index) if self.text is not None else None
        place = f"{label}:{line}" if line else label
        name = _key_name(section, key, index)
        return ExperimentError(f"{place}: {name}: {what}" if name else f"{place}: {what}")


def _key_name(section, key, index=None) -> str:
    if section is None:
        return key or ""
    head = f"[[{section}]] #{index + 1}" if index is not None else f"[{section}]"
    return f"{head} {key}" if key else head


_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=")


def _line_of(text: str, section: str | None, key: str | None, index: int | None = None) -> int | None:
    """The 1-based line of ``key`` in ``[section]`` (the ``index``-th ``[[section]]``), or of the
    section's header when the key is not written there (a missing key); None if not found."""
    current, seen, header_line = None, -1, None
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.split("#", 1)[0]
        head = _HEADER.match(stripped)
        if head:
            current = head.group(1)
            if current == section:
                seen += 1
                if index is None or seen == index:
                    header_line = number
            continue
        match = _KEY.match(stripped)
        if match and match.group(1) == key and current == section and (index is None or seen == index):
            return number
    return header_line


def _split_unit(text: str) -> tuple[float, str] | None:
    match = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\s\d].*?)?\s*", text)
    if not match:
        return None
    return float(match.group(1)), (match.group(2) or "")


def _provenance(value, where: _Where, section, key, index=None) -> tuple[Any, dict, str | None]:
    """(the value, its provenance entries, its unit entry) of a plain value or of a
    ``{value, unit, source, note, expression}`` table."""
    meta: dict[str, str] = {}
    if not isinstance(value, dict):
        return value, meta, None
    unknown = sorted(set(value) - {"value", "unit", "source", "note", "expression"})
    if unknown:
        raise where.error(section, key, f"unknown entries {unknown}; a value table holds value, unit, source, "
                                        "note, expression", index)
    if "value" not in value:
        raise where.error(section, key, "a value table needs 'value'", index)
    for entry in ("source", "note", "expression"):
        if entry in value:
            if not isinstance(value[entry], str):
                raise where.error(section, key, f"'{entry}' must be text", index)
            meta[entry] = value[entry]
    unit = value.get("unit")
    if unit is not None and not isinstance(unit, str):
        raise where.error(section, key, f"'unit' must be text, got {unit!r}", index)
    return value["value"], meta, unit


def _number(value, units: dict, where: _Where, section, key, index=None) -> tuple[float, dict]:
    """(the value in SI units, its provenance entries) of a number, a "value unit" string or a
    ``{value, unit, source, note}`` table."""
    value, meta, unit = _provenance(value, where, section, key, index)
    if isinstance(value, str):
        split = _split_unit(value)
        if split is None:
            raise where.error(section, key, f"expected a number or 'number unit', got {value!r}", index)
        if unit is not None and split[1]:
            raise where.error(section, key, f"the unit is given twice ({split[1]!r} and unit = {unit!r})", index)
        value, unit = split[0], (split[1] or unit)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise where.error(section, key, f"expected a number, got {value!r}", index)
    unit = "" if unit is None else unit.strip()
    if unit == "":  # a bare number is in SI units
        unit = _SI_NAME[id(units)]
    if unit not in units:
        accepted = ", ".join(repr(u) for u in units if u)
        raise where.error(section, key, f"unit {unit!r} is not one of {accepted}" if accepted
                          else f"takes no unit (a pure number), got {unit!r}", index)
    value = float(value) * units[unit]
    if not math.isfinite(value):
        raise where.error(section, key, f"must be finite, got {value}", index)
    if unit != _SI_NAME[id(units)]:
        meta["unit"] = unit
    return value, meta


def _plain(value, kind: str, where: _Where, section, key, index=None):
    if kind == "str":
        if not isinstance(value, str):
            raise where.error(section, key, f"expected text, got {value!r}", index)
        return value
    if kind == "path":
        if not isinstance(value, str) or not value.strip():
            raise where.error(section, key, f"expected a file name, got {value!r}", index)
        return value
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.error(section, key, f"expected an integer, got {value!r}", index)
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise where.error(section, key, f"expected true or false, got {value!r}", index)
        return value
    if kind == "strings":
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",")]
        if not (isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)):
            raise where.error(section, key, f"expected a list of names, got {value!r}", index)
        return tuple(value)
    if kind == "numbers":
        if not isinstance(value, dict):
            raise where.error(section, key, f"expected a table of key = number, got {value!r}", index)
        out = {}
        for k, v in value.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise where.error(section, f"{key}.{k}", f"expected a finite number, got {v!r}", index)
            out[k] = float(v)
        return out
    raise AssertionError(kind)


def _section(raw: dict, name: str, where: _Where, index=None) -> tuple[dict, dict]:
    """(values, provenance) of one section, every key known and of its kind."""
    table = raw if index is not None else raw.get(name, {})
    if not isinstance(table, dict):
        raise where.error(None, name, "must be a table ([" + name + "])")
    schema = _SCHEMA[name]
    values, sources = {}, {}
    for key, value in table.items():
        if key not in schema:
            known = ", ".join(schema)
            hint = ""
            if name == "material":
                hint = " (docs/model.md §4)"
            raise where.error(name, key, f"unknown key; [{name}] takes {known}{hint}", index)
        kind = schema[key]
        if isinstance(kind, dict):
            values[key], meta = _number(value, kind, where, name, key, index)
            if meta:
                sources[f"{name}.{key}"] = meta
        elif kind == "numbers":
            values[key] = _plain(value, kind, where, name, key, index)
        else:
            value, meta, unit = _provenance(value, where, name, key, index)
            if unit is not None:
                raise where.error(name, key, f"takes no unit, got unit = {unit!r}", index)
            values[key] = _plain(value, kind, where, name, key, index)
            if meta:
                sources[f"{name}.{key}"] = meta
    return values, sources


def _parse(raw: dict, where: _Where) -> Experiment:
    unknown = sorted(k for k in raw if k not in _SCHEMA and k not in _TOP)
    if unknown:
        raise where.error(None, unknown[0], f"unknown section or key; a file holds {', '.join(_TOP)} and the "
                                            f"sections {', '.join('[' + s + ']' for s in _SCHEMA)}")
    if "format" in raw and raw["format"] != FORMAT:
        raise where.error(None, "format", f"this jaxmpm reads format {FORMAT}, got {raw['format']!r}")
    sources: dict[str, Mapping[str, str]] = {}
    sections = {}
    for name in ("experiment", "geometry", "boundaries", "material", "numerics", "fit"):
        if name == "fit" and name not in raw:
            continue
        sections[name], meta = _section(raw, name, where)
        sources.update(meta)
    for name in ("geometry", "numerics"):
        if name not in raw:
            raise where.error(None, None, f"[{name}] is missing")
    base = where.path.parent if where.path is not None else pathlib.Path(".")
    profiles = []
    listed = raw.get("profile", [])
    if isinstance(listed, dict):
        raise where.error(None, "profile", "write each profile as [[profile]] (a list of tables)")
    for i, table in enumerate(listed):
        values, meta = _section(table, "profile", where, index=i)
        sources.update({f"profile.{i}.{k.split('.', 1)[1]}": v for k, v in meta.items()})
        if "file" not in values:
            raise where.error("profile", "file", "missing: the profile's CSV file", i)
        profiles.append(ProfileMeasurement(base / values.pop("file"), **values))
    front = None
    if "front" in raw:
        values, meta = _section(raw, "front", where)
        if "file" not in values:
            raise where.error("front", "file", "missing: the front history's CSV file")
        front = FrontMeasurement(base / values.pop("file"), **values)
    geometry, boundaries, numerics = sections["geometry"], sections["boundaries"], sections["numerics"]
    for key in ("length", "height"):
        if key not in geometry:
            raise where.error("geometry", key, "missing: the column's " + key + ", e.g. \"90 mm\"")
    if "t_end" not in numerics:
        raise where.error("numerics", "t_end", "missing: when the run ends, e.g. \"0.6 s\"")
    if "gate_lift_time" in boundaries:
        if "gate_speed" in boundaries:
            raise where.error("boundaries", "gate_lift_time", "give gate_speed or gate_lift_time, not both")
        time = boundaries.pop("gate_lift_time")
        if not time > 0:
            raise where.error("boundaries", "gate_lift_time", f"must be > 0 s, got {time}")
        boundaries["gate_speed"] = geometry["height"] / time
    name = sections["experiment"].get("name") or (where.path.stem if where.path is not None else "experiment")
    fit = None
    if "fit" in sections:
        spec = dict(sections["fit"])
        if "keys" not in spec:
            raise where.error("fit", "keys", "missing: the parameters to fit, e.g. [\"beta\", \"mu1\"]")
        fit = FitSpec(**spec)
    kwargs = dict(name=name, title=sections["experiment"].get("title", ""), **geometry, **boundaries,
                  material=sections["material"], **numerics, profiles=tuple(profiles), front=front, fit=fit,
                  sources=sources, path=where.path)
    for key in ("source", "note"):
        if key in sections["experiment"]:
            sources[f"experiment.{key}"] = {key: sections["experiment"][key]}
    try:
        return Experiment(**kwargs)
    except _Invalid as err:
        raise where.error(err.section, err.key, err.what) from None


class _Invalid(ExperimentError):
    def __init__(self, section, key, what):
        super().__init__(f"{_key_name(section, key)}: {what}")
        self.section, self.key, self.what = section, key, what


def _check_experiment(e: Experiment) -> None:
    """Checks of the values (the parser has checked kinds and units); raises ``_Invalid``."""

    def need(ok, section, key, what):
        if not ok:
            raise _Invalid(section, key, what)

    def positive(section, key, value, unit):
        need(value is not None and math.isfinite(value) and value > 0, section, key, f"must be > 0 {unit}, got {value}")

    need(isinstance(e.name, str) and e.name.strip() != "", "experiment", "name", "must be a non-empty name")
    positive("geometry", "length", e.length, "m")
    positive("geometry", "height", e.height, "m")
    need(e.dim in (2, 3), "numerics", "dim", f"must be 2 or 3, got {e.dim!r}")
    if e.dim == 3:
        need(e.width is not None, "geometry", "width", "missing: a 3D run (dim = 3) needs the channel's width")
        positive("geometry", "width", e.width, "m")
    else:
        need(e.width is None, "geometry", "width", "applies to dim = 3 (a 2D run has no width); set "
                                                   "[numerics] dim = 3 or drop it")
    need(-60.0 < e.slope < 60.0, "geometry", "slope", f"must be in (-60, 60) degrees, got {e.slope}")
    need(e.floor in FLOORS, "boundaries", "floor", f"must be one of {FLOORS}, got {e.floor!r}")
    if e.floor == "no-slip":
        need(e.floor_friction is None, "boundaries", "floor_friction",
             "a no-slip floor has no friction coefficient; set floor = \"slip-stick\" to use one")
    else:
        need(e.floor_friction is not None, "boundaries", "floor_friction",
             f"missing: a {e.floor} floor needs its Coulomb friction coefficient")
        need(e.floor_friction >= 0, "boundaries", "floor_friction", f"must be >= 0, got {e.floor_friction}")
        need("mu_w" not in e.material, "material", "mu_w", "the floor's friction is [boundaries] floor_friction")
    need(e.gate in GATES, "boundaries", "gate", f"must be one of {GATES}, got {e.gate!r}")
    if e.gate == "none":
        need(e.gate_speed is None, "boundaries", "gate_speed", "there is no gate (gate = \"none\"); set gate = "
                                                               "\"front\", \"back\" or \"both\" or drop it")
    else:
        need(e.gate_speed is not None, "boundaries", "gate_speed",
             f"missing: the {e.gate} gate needs gate_speed or gate_lift_time")
        positive("boundaries", "gate_speed", e.gate_speed, "m/s")
    need(not (e.gate in ("back", "both") and e.back_wall), "boundaries", "back_wall",
         "a back gate stands where the back wall would: set back_wall = false")
    unknown = sorted(set(e.material) - set(PARAM_KEYS))
    need(not unknown, "material", unknown[0] if unknown else None, f"unknown parameter; [material] takes {PARAM_KEYS}")
    if e.dx is not None:
        positive("numerics", "dx", e.dx, "m")
        thinnest = min(e.length, e.height, e.width if e.dim == 3 else math.inf)
        need(e.dx <= thinnest, "numerics", "dx", f"must be at most the column's thinnest side ({thinnest:g} m): a "
                                                 f"body needs at least one cell across, got {e.dx:g} m")
    sampling = e.sampling or "jitter"
    need(sampling in SAMPLINGS, "numerics", "sampling", f"must be one of {SAMPLINGS}, got {e.sampling!r}")
    if e.ppc is not None:
        if sampling == "poisson":
            need(e.ppc >= 1, "numerics", "ppc", f"must be a number >= 1, got {e.ppc}")
        else:
            need(e.ppc >= 1 and float(e.ppc).is_integer(), "numerics", "ppc",
                 f"must be a positive integer for {sampling} sampling, got {e.ppc}")
    need(isinstance(e.seed, int) and e.seed >= 0, "numerics", "seed", f"must be an integer >= 0, got {e.seed!r}")
    need(e.dtype is None or e.dtype in DTYPES, "numerics", "dtype", f"must be one of {DTYPES}, got {e.dtype!r}")
    positive("numerics", "t_end", e.t_end, "s")
    need(isinstance(e.frames, int) and e.frames >= 0, "numerics", "frames",
         f"must be an integer >= 0, got {e.frames!r}")
    if e.runout is not None:
        positive("numerics", "runout", e.runout, "m")
    if e.backward_runout is not None:
        need(e.backward_runout >= 0, "numerics", "backward_runout", f"must be >= 0 m, got {e.backward_runout}")
    need(e.transfer in TRANSFERS, "numerics", "transfer", f"must be one of {TRANSFERS}, got {e.transfer!r}")
    need(0.0 <= e.alpha <= 1.0, "numerics", "alpha", f"must be in [0, 1], got {e.alpha}")
    need(0.0 < e.cfl <= 1.0, "numerics", "cfl", f"must be in (0, 1], got {e.cfl}")
    for i, p in enumerate(e.profiles):
        if p.time is not None:
            need(0.0 < p.time <= e.t_end * (1 + 1e-9), "profile", "time",
                 f"#{i + 1} at {p.time:g} s: must be in (0, t_end = {e.t_end:g} s]")
        need(p.units in (None, "m", "cm", "mm"), "profile", "units", f"#{i + 1}: must be m, cm or mm, got {p.units!r}")
    if e.front is not None:
        need(e.front.units in (None, "m", "cm", "mm"), "front", "units", f"must be m, cm or mm, got {e.front.units!r}")
        need(e.front.time_units in (None, "s", "ms"), "front", "time_units",
             f"must be s or ms, got {e.front.time_units!r}")
        if e.front.correlation_time is not None:
            positive("front", "correlation_time", e.front.correlation_time, "s")
    if e.fit is not None:
        unknown = sorted(set(e.fit.keys) - set(PARAM_KEYS))
        need(not unknown, "fit", "keys", f"unknown parameter(s) {unknown}; valid keys are {list(PARAM_KEYS)}")
        need(len(set(e.fit.keys)) == len(e.fit.keys), "fit", "keys", f"a key is listed twice: {list(e.fit.keys)}")
        need(e.fit.keys != ("mu_w",) or e.floor != "no-slip", "fit", "keys", "mu_w is the floor's friction: a no-slip "
                                                                             "floor has none to fit")
        stray = sorted(set(e.fit.init) - set(e.fit.keys))
        need(not stray, "fit", "init", f"{stray} are not fitted (keys = {list(e.fit.keys)})")
        if e.fit.noise is not None:
            need(e.fit.noise >= 0, "fit", "noise", f"must be >= 0, got {e.fit.noise}")
        for key in ("weight_profile", "weight_front"):
            need(getattr(e.fit, key) >= 0, "fit", key, f"must be >= 0, got {getattr(e.fit, key)}")


# -- writing --------------------------------------------------------------------------------------------

def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {value!r} as TOML")


def _entry(key: str, value, meta: Mapping[str, str] | None) -> str:
    """``key = value``, as a ``{value, source, ...}`` table where the value has a provenance (its
    value in SI units: the unit it was written in is kept as a note, not applied)."""
    if meta:
        table = {"value": value, **{k: v for k, v in meta.items() if k != "unit"}}
        if "unit" in meta:
            table["note"] = (table.get("note", "") + f" (given in {meta['unit']})").strip()
        return f"{key} = {_toml_value(table)}"
    return f"{key} = {_toml_value(value)}"


def _relative(file: pathlib.Path, base: pathlib.Path | None) -> str:
    if base is not None:
        try:
            return str(file.relative_to(base.parent))
        except ValueError:
            pass
    return str(file.resolve())


def _write(e: Experiment) -> str:
    meta = e.sources
    lines = [f"format = {FORMAT}", "", "[experiment]", _entry("name", e.name, None)]
    if e.title:
        lines.append(_entry("title", e.title, None))
    for key in ("source", "note"):
        if f"experiment.{key}" in meta:
            lines.append(_entry(key, meta[f"experiment.{key}"][key], None))

    def section(name, pairs):
        lines.extend(["", f"[{name}]"])
        for key, value in pairs:
            if value is not None:
                lines.append(_entry(key, value, meta.get(f"{name}.{key}")))

    section("geometry", [("length", e.length), ("height", e.height), ("width", e.width), ("slope", e.slope)])
    section("boundaries", [("floor", e.floor), ("floor_friction", e.floor_friction), ("back_wall", e.back_wall),
                           ("gate", e.gate), ("gate_speed", e.gate_speed)])
    section("material", list(e.material.items()))
    section("numerics", [(k, getattr(e, k)) for k in ("dim", "dx", "ppc", "sampling", "seed", "dtype", "t_end",
                                                        "frames", "runout", "backward_runout", "transfer", "alpha",
                                                        "cfl")])
    for i, p in enumerate(e.profiles):
        lines.extend(["", "[[profile]]", _entry("file", _relative(p.file, e.path), None)])
        for key in ("time", "units", "dataset"):
            if getattr(p, key) is not None:
                lines.append(_entry(key, getattr(p, key), meta.get(f"profile.{i}.{key}")))
    if e.front is not None:
        lines.extend(["", "[front]", _entry("file", _relative(e.front.file, e.path), None)])
        for key in ("units", "time_units", "correlation_time"):
            if getattr(e.front, key) is not None:
                lines.append(_entry(key, getattr(e.front, key), None))
    if e.fit is not None:
        lines.extend(["", "[fit]", _entry("keys", list(e.fit.keys), None)])
        if e.fit.init:
            lines.append(_entry("init", dict(e.fit.init), None))
        if e.fit.noise is not None:
            lines.append(_entry("noise", e.fit.noise, None))
        for key in ("weight_profile", "weight_front"):
            if getattr(e.fit, key) != 1.0:
                lines.append(_entry(key, getattr(e.fit, key), None))
    return "\n".join(lines) + "\n"


# -- the shipped experiments ----------------------------------------------------------------------------

#: Scene name -> the shipped experiment file (``experiments_data/experiments/``) that describes it.
SHIPPED_EXPERIMENTS = {
    "gates-collapse": "S2_gates_collapse.toml",
    "slope-collapse": "S3_slope_collapse.toml",
    "cohesive-collapse": "S4_cohesive_collapse.toml",
    "aspect-ratio": "S5_aspect_ratio.toml",
    "aluminium-bars": "S7_aluminium_bars.toml",
}


def shipped_experiment(name: str) -> Experiment:
    """A shipped experiment by its scene name (``SHIPPED_EXPERIMENTS``) or file name."""
    from .datasets import data_dir

    file = SHIPPED_EXPERIMENTS.get(name, name)
    path = data_dir() / "experiments" / file
    if not path.is_file():
        raise ValueError(f"no shipped experiment {name!r}; known: {sorted(SHIPPED_EXPERIMENTS)}")
    return Experiment.from_toml(path)
