"""A collapse experiment described in one file: geometry, boundaries, material, numerics and,
for calibration, the measurements taken and what to fit (docs/experiments.md).

    [experiment]
    name = "my-collapse"
    [geometry]
    length = "60 mm"                     # the column, L x H (x W in 3D), on a bed inclined at slope
    height = "90 mm"
    [boundaries]
    gate = "front"                       # "front", "back", "both" or "none" (released at t = 0)
    gate_speed = "1.5 m/s"               # or gate_lift_time = "40 ms" (to clear the column's height)
    side_walls = { width = "20 mm", friction = 0.25 }   # a 2D channel's walls (lateral_pressure_ratio = 1)
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
and the key, before anything is built or compiles): the material against the parameter table
``jaxmpm.params.PARAMS`` (its units, rules and relations), each choice against the list of the
module that owns it (``jaxmpm.config.TRANSFERS``, ``jaxmpm.sampling.SAMPLINGS``,
``jaxmpm.precision.DTYPES``, ``jaxmpm.scenes.collapse.FLOORS``), and each measurement file for
its existence. The measurement sections (``MEASUREMENT_SECTIONS``) are calibration's: kept as
written and read by ``calibration.data.read_measurements``. ``scene()`` builds it with
``jaxmpm.scenes.collapse``; ``to_toml`` writes it back, so that a run's HDF5 file can record the
experiment it ran (``Experiment.from_h5``).
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from collections.abc import Mapping
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from ._experiment_checks import GATES, MEASUREMENT_SECTIONS, SIDE_WALLS, Invalid, check_experiment, side_walls_of
from ._toml import (
    ANGLE,
    LENGTH,
    PURE,
    SPEED,
    TIME,
    ExperimentError,
    Units,
    Where,
    read_section,
    relative,
    toml_entry,
    toml_value,
)
from .boundary import SideWalls
from .params import DEFAULTS, PARAM_KEYS, PARAMS, Params, param_help, validate_params
from .scenes.collapse import aspect_column, collapse, default_runout

__all__ = ["Experiment", "ExperimentError", "shipped_experiment", "SHIPPED_EXPERIMENTS", "FORMAT", "GATES",
           "MEASUREMENT_SECTIONS"]

#: The file format's version, written by ``to_toml``; a file may state it as ``format = 1``.
FORMAT = 1

# section -> key -> kind: ``Units`` (a number; the material's from ``jaxmpm.params.PARAMS``), or "str", "int",
# "bool", "strings", "numbers", "path".
_SCHEMA: dict[str, dict[str, Any]] = {
    "experiment": {"kind": "str", "name": "str", "title": "str", "source": "str", "note": "str"},
    "geometry": {"length": LENGTH, "height": LENGTH, "width": LENGTH, "slope": ANGLE},
    "boundaries": {"floor": "str", "floor_friction": PURE, "back_wall": "bool", "gate": "str", "gate_speed": SPEED,
                   "gate_lift_time": TIME, "side_walls": SIDE_WALLS},
    "material": {key: Units(spec.units, spec.unit) for key, spec in PARAMS.items()},
    "numerics": {"dim": "int", "dx": LENGTH, "ppc": PURE, "sampling": "str", "seed": "int", "dtype": "str",
                 "t_end": TIME, "frames": "int", "runout": LENGTH, "backward_runout": LENGTH, "transfer": "str",
                 "alpha": PURE, "cfl": PURE},
}
_TOP = ("format",)


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
    #: The side walls of a 2D channel (``jaxmpm.SideWalls``: width m, friction, lateral pressure ratio).
    side_walls: SideWalls | None = None
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
    #: The measurement sections as written (``MEASUREMENT_SECTIONS``: "profile" -> a list of
    #: tables, "front" and "fit" -> a table), each data file (``file``) a path placed relative to
    #: the experiment file; read by ``calibration.data.read_measurements``.
    measurements: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    title: str = ""
    #: "section.key" -> where the value came from (the file's ``source``/``note``/``unit`` entries).
    sources: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict, compare=False)
    #: The file this experiment was read from (None: built in Python).
    path: pathlib.Path | None = dataclasses.field(default=None, compare=False)
    #: The file's text (None: built in Python), for the line of an error in a measurement section.
    text: str | None = dataclasses.field(default=None, compare=False, repr=False)
    #: The aspect ratio a the column was made at (height = a x length) by the aspect-ratio family
    #: (``jaxmpm.scenes.named_experiment``), which its scene records (``SceneInfo.aspect``); None
    #: for any other experiment. Not a key of the file, which states the height.
    aspect: float | None = dataclasses.field(default=None, compare=False)

    def __post_init__(self):
        check_experiment(self)

    # -- reading and writing ---------------------------------------------------------------------------

    @classmethod
    def from_toml(cls, path, *, check_files: bool = True) -> Experiment:
        """Read and check an experiment file; its measurement files are relative to its folder and
        must exist (``check_files=False``: not looked for, when only the set-up is needed)."""
        path = pathlib.Path(path)
        if path.suffix != ".toml":
            raise ExperimentError(f"{path}: an experiment file ends in .toml")
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as err:
            raise ExperimentError(f"{path}: cannot read the experiment file ({err.strerror or err})") from None
        return cls.from_text(text, path, check_files=check_files)

    @classmethod
    def from_text(cls, text: str, path=None, *, check_files: bool = True) -> Experiment:
        """An experiment from the text of a file (``path``: where it lives, for the measurement
        files and the error messages; None: measurement files relative to the working folder).
        ``check_files``: as for ``from_toml``."""
        path = None if path is None else pathlib.Path(path)
        label = str(path) if path is not None else "<experiment>"
        try:
            raw = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ExperimentError(f"{label}: not valid TOML: {err}") from None
        return _parse(raw, Where(path, text), check_files)

    @classmethod
    def from_h5(cls, path, *, check_files: bool = True) -> Experiment:
        """The experiment a run's HDF5 file records (``python -m jaxmpm run EXPERIMENT.toml --out``
        writes it), to run it again; its measurement files resolve where the original file was.
        A measurement file that is no longer there is refused, as when the file itself is read;
        ``check_files=False`` gives the set-up alone (the recorded paths kept, not looked for),
        which is all that a run needs."""
        import h5py

        with h5py.File(path, "r") as f:
            text = f.attrs.get("experiment_toml")
            origin = f.attrs.get("experiment_path")
        if text is None:
            raise ExperimentError(f"{path}: records no experiment (a run of a named scene, or written before "
                                  "experiment files)")
        text = text.decode() if isinstance(text, bytes) else str(text)
        origin = None if origin is None else (origin.decode() if isinstance(origin, bytes) else str(origin))
        return cls.from_text(text, origin, check_files=check_files)

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
            # The file's own values were checked when it was read: a broken rule is the option's,
            # named as the option names it ("nu must be in (-1, 0.5), got 0.7").
            validate_params({**DEFAULTS, **changes["material"]})
        try:
            return dataclasses.replace(self, **changes)
        except Invalid as err:
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
                    alpha=self.alpha, cfl=self.cfl, dtype=self.dtype, floor=self.floor, side_walls=self.side_walls,
                    base_params=material)

    def scene(self):
        """The ready-to-run ``Scene`` (``jaxmpm.scenes.collapse``); it keeps this experiment
        (``scene.experiment``) and, where the aspect-ratio family made it, its aspect ratio
        (``aspect``, ``jaxmpm.scenes.aspect_column``)."""
        scene = collapse(**self.builder_arguments())
        if self.aspect is not None:
            scene = aspect_column(scene, self.aspect)
        return dataclasses.replace(scene, experiment=self)

    def params(self):
        """The material as ``Params`` (unlisted keys take docs/model.md §4's defaults)."""
        return Params.create(dtype=self.dtype, **self.builder_arguments()["base_params"])


# -- reading --------------------------------------------------------------------------------------------

def _section(raw: dict, name: str, where: Where, index=None) -> tuple[dict, dict]:
    """(values, provenance) of one section, every key known and of its kind."""
    takes = f"{param_help()} (docs/model.md §4)" if name == "material" else None
    return read_section(raw, name, _SCHEMA[name], where, index, takes)


def _parse(raw: dict, where: Where, check_files: bool) -> Experiment:
    kind = raw.get("experiment", {}).get("kind", "collapse") if isinstance(raw.get("experiment"), dict) else "collapse"
    if kind != "collapse":  # before the sections: another kind's are not this format's
        what = (" (steady flows down an incline: fitted by `python -m calibration flow-rule FILE`, "
                "docs/incline_fits.md)" if kind == "incline" else "")
        raise where.error("experiment", "kind", f"this file describes a collapse; got kind = {kind!r}{what}")
    unknown = sorted(k for k in raw if k not in _SCHEMA and k not in _TOP and k not in MEASUREMENT_SECTIONS)
    if unknown:
        sections = ", ".join("[" + s + "]" for s in (*_SCHEMA, *MEASUREMENT_SECTIONS))
        raise where.error(None, unknown[0], f"unknown section or key; a file holds {', '.join(_TOP)} and the "
                                            f"sections {sections}")
    if "format" in raw and raw["format"] != FORMAT:
        raise where.error(None, "format", f"this jaxmpm reads format {FORMAT}, got {raw['format']!r}")
    sources: dict[str, Mapping[str, str]] = {}
    sections = {}
    for name in ("experiment", "geometry", "boundaries", "material", "numerics"):
        sections[name], meta = _section(raw, name, where)
        sources.update(meta)
    sections["experiment"].pop("kind", None)  # "collapse" (checked first)
    for name in ("geometry", "numerics"):
        if name not in raw:
            raise where.error(None, None, f"[{name}] is missing")
    measurements = _measurements(raw, where, check_files)
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
    kwargs = dict(name=name, title=sections["experiment"].get("title", ""), **geometry, **boundaries,
                  material=sections["material"], **numerics, measurements=measurements, sources=sources,
                  path=where.path, text=where.text)
    for key in ("source", "note"):
        if key in sections["experiment"]:
            sources[f"experiment.{key}"] = {key: sections["experiment"][key]}
    try:
        if "side_walls" in boundaries:
            kwargs["side_walls"] = side_walls_of(boundaries["side_walls"])
        return Experiment(**kwargs)
    except Invalid as err:
        raise where.error(err.section, err.key, err.what) from None


def _measurements(raw: dict, where: Where, check_files: bool) -> dict[str, Any]:
    """The measurement sections of a file as written, each data file (``file``) placed relative
    to the file's folder and, with ``check_files``, present. Nothing else in them is read here."""
    base = where.path.parent if where.path is not None else pathlib.Path(".")

    def placed(table, section, index=None) -> dict:
        if not isinstance(table, dict):
            raise where.error(None, section, f"must be a table ([{section}])")
        table = dict(table)
        if isinstance(table.get("file"), str) and table["file"].strip():
            table["file"] = base / table["file"]
            if check_files and not table["file"].is_file():
                raise where.error(section, "file", f"no such file: {table['file']}", index)
        return table

    out: dict[str, Any] = {}
    if "profile" in raw:
        if not isinstance(raw["profile"], list):
            raise where.error(None, "profile", "write each profile as [[profile]] (a list of tables)")
        out["profile"] = [placed(table, "profile", i) for i, table in enumerate(raw["profile"])]
    for section in ("front", "fit"):
        if section in raw:
            out[section] = placed(raw[section], section)
    return out


# -- writing --------------------------------------------------------------------------------------------

def _write(e: Experiment) -> str:
    meta = e.sources
    lines = [f"format = {FORMAT}", "", "[experiment]", toml_entry("name", e.name, None)]
    if e.title:
        lines.append(toml_entry("title", e.title, None))
    for key in ("source", "note"):
        if f"experiment.{key}" in meta:
            lines.append(toml_entry(key, meta[f"experiment.{key}"][key], None))

    def section(name, pairs):
        lines.extend(["", f"[{name}]"])
        for key, value in pairs:
            if value is not None:
                lines.append(toml_entry(key, value, meta.get(f"{name}.{key}")))

    section("geometry", [("length", e.length), ("height", e.height), ("width", e.width), ("slope", e.slope)])
    section("boundaries", [("floor", e.floor), ("floor_friction", e.floor_friction), ("back_wall", e.back_wall),
                           ("gate", e.gate), ("gate_speed", e.gate_speed), ("side_walls", _side_walls_entry(e))])
    section("material", list(e.material.items()))
    section("numerics", [(k, getattr(e, k)) for k in ("dim", "dx", "ppc", "sampling", "seed", "dtype", "t_end",
                                                        "frames", "runout", "backward_runout", "transfer", "alpha",
                                                        "cfl")])
    for section in MEASUREMENT_SECTIONS:
        tables = e.measurements.get(section, [] if section == "profile" else None)
        for table in (tables if section == "profile" else [tables] if tables is not None else []):
            lines.extend(["", f"[[{section}]]" if section == "profile" else f"[{section}]"])
            for key, value in table.items():
                value = relative(value, e.path) if isinstance(value, pathlib.PurePath) else value
                lines.append(f"{key} = {toml_value(value)}")
    return "\n".join(lines) + "\n"


def _side_walls_entry(e: Experiment) -> dict[str, float] | None:
    """``[boundaries] side_walls`` as the inline table it is written as (None: no side walls)."""
    if e.side_walls is None:
        return None
    return {f.name: getattr(e.side_walls, f.name) for f in dataclasses.fields(e.side_walls)}


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
