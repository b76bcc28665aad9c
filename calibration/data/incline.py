"""An incline experiment in one file: steady flows of one material down a rough incline, the
flow-rule table measured on them (or a velocity profile's), optionally the thickness h_stop(θ) at
which its layers stop, and what to fit (docs/incline_fits.md).

    format = 1
    [experiment]
    kind = "incline"
    name = "glass-beads-chute"
    source = "my lab book, 2026-11-03"
    [material]
    d = { value = 0.5, unit = "mm", source = "sieved, 0.45-0.55 mm" }
    rho = "1550 kg/m^3"
    rho_s = "2500 kg/m^3"
    [flow_rule]
    file = "rule.csv"                    # slope_deg,h_m,u_m_s (docs/data_files.md), relative to this file;
                                         # or a profile's slope_deg,h_m,z_m,u_m_s (its header says which)
    [h_stop]                             # optional: reported beside the fit, never fitted
    file = "hstop.csv"                   # slope_deg,h_stop_m
    [boundaries]                         # optional: the chute's side walls, as a collapse file's
    side_walls = { width = "5 cm", friction = 0.3 }   # friction = "mu_w": [material] mu_w, fittable
    [fit]
    keys = ["mu1", "mu2", "I0"]
    init = { mu1 = 0.3, mu2 = 0.9, I0 = 0.8 }

Values are written as in a collapse's file (``jaxmpm.experiment``: a number in SI units, a string
with its unit, or ``{value, unit, source, note}``), and every error names the file, the line and
the key. The material's keys and rules are the parameter table's (``jaxmpm.params.PARAMS``).
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from collections.abc import Mapping

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from jaxmpm import SideWalls
from jaxmpm._experiment_checks import SIDE_WALLS, Invalid, side_walls_of
from jaxmpm._toml import ExperimentError, Units, Where, read_section
from jaxmpm.params import DEFAULTS, PARAMS, param_help, validate_params

from .flow_rule import FLOW_RULE_KEYS, flow_rule_keys_problem

__all__ = ["InclineExperiment", "incline_from_text", "is_incline_file", "load_incline"]


_SCHEMA = {
    "experiment": {"kind": "str", "name": "str", "title": "str", "source": "str", "note": "str"},
    "material": {key: Units(spec.units, spec.unit) for key, spec in PARAMS.items()},
    "flow_rule": {"file": "path"},
    "h_stop": {"file": "path"},
    "boundaries": {"side_walls": SIDE_WALLS},
    "fit": {"keys": "strings", "init": "numbers"},
}


@dataclasses.dataclass(frozen=True)
class InclineExperiment:
    """One incline experiment: its ``material`` (SI values, as given), the flow-rule table's
    ``table_file``, the ``keys`` to fit and their ``init`` (empty: not stated), the chute's
    ``side_walls`` (a ``jaxmpm.SideWalls``; None: none), the h_stop table's ``h_stop_file`` (None:
    none; it is reported, never fitted: the local model does not predict h_stop), and where every
    value came from (``sources``: "section.key" -> its ``source``/``note``/``unit`` entries);
    ``text``: the file's text as read (None: not read from a file), which a fit's record keeps
    (``calibration.problem.build.FitSetup.to_json``)."""

    name: str
    material: Mapping[str, float]
    table_file: pathlib.Path
    keys: tuple[str, ...] = FLOW_RULE_KEYS
    init: Mapping[str, float] = dataclasses.field(default_factory=dict)
    title: str = ""
    side_walls: SideWalls | None = None
    h_stop_file: pathlib.Path | None = None
    sources: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict, compare=False)
    path: pathlib.Path | None = dataclasses.field(default=None, compare=False)
    text: str | None = dataclasses.field(default=None, compare=False, repr=False)


def is_incline_file(path) -> bool:
    """Whether ``path`` is a TOML file whose ``[experiment] kind`` is "incline"."""
    path = pathlib.Path(path)
    if path.suffix != ".toml" or not path.is_file():
        return False
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    section = raw.get("experiment")
    return isinstance(section, dict) and section.get("kind") == "incline"


def load_incline(path, *, check_files: bool = True) -> InclineExperiment:
    """Read and check an incline experiment file (its flow-rule and h_stop tables relative to its
    folder and, with ``check_files``, present); every error is an ``ExperimentError`` naming the file, the
    line and the key."""
    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ExperimentError(f"{path}: cannot read the experiment file ({err.strerror or err})") from None
    return incline_from_text(text, path, check_files=check_files)


def incline_from_text(text: str, path=None, *, check_files: bool = True) -> InclineExperiment:
    """The incline experiment of a file's ``text`` as if read from ``path`` (its table is found
    relative to that folder; None: the working directory), checked as ``load_incline`` checks it."""
    given, path = path, pathlib.Path(path) if path is not None else pathlib.Path("<text>")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ExperimentError(f"{path}: not valid TOML: {err}") from None
    where = Where(path, text)
    unknown = sorted(k for k in raw if k not in _SCHEMA and k != "format")
    if unknown:
        raise where.error(unknown[0], None, "unknown section or key; an incline file holds format and the sections "
                                            + ", ".join(f"[{s}]" for s in _SCHEMA))
    sections, sources = {}, {}
    for name in _SCHEMA:
        takes = f"{param_help()} (docs/model.md §4)" if name == "material" else None
        sections[name], meta = read_section(raw, name, _SCHEMA[name], where, takes=takes)
        sources.update(meta)
    if sections["experiment"].get("kind") != "incline":
        raise where.error("experiment", "kind", f"must be \"incline\" in an incline file, got "
                                                f"{sections['experiment'].get('kind')!r}")
    material = sections["material"]
    try:
        validate_params({**DEFAULTS, **material})
    except ValueError as err:
        key = next((k for k in material if str(err).startswith(k + " ") or f" {k} " in str(err)), None)
        raise where.error("material", key, str(err)) from None
    if "file" not in sections["flow_rule"]:
        raise where.error("flow_rule", "file", "missing: the flow-rule table's CSV file (slope_deg,h_m,u_m_s)")
    table_file = (path.parent / sections["flow_rule"]["file"])
    if check_files and not table_file.is_file():
        raise where.error("flow_rule", "file", f"no such file: {table_file}")
    h_stop_file = None
    if "h_stop" in raw:
        if "file" not in sections["h_stop"]:
            raise where.error("h_stop", "file", "missing: the h_stop table's CSV file (slope_deg,h_stop_m)")
        h_stop_file = path.parent / sections["h_stop"]["file"]
        if check_files and not h_stop_file.is_file():
            raise where.error("h_stop", "file", f"no such file: {h_stop_file}")
    side_walls = _side_walls(sections["boundaries"], material, where)
    fit = sections["fit"]
    keys = tuple(fit.get("keys", FLOW_RULE_KEYS))
    problem = flow_rule_keys_problem(keys, side_walls)
    if problem:
        raise where.error("fit", "keys", problem)
    init = dict(fit.get("init", {}))
    if set(init) - set(keys):
        raise where.error("fit", "init", f"{sorted(set(init) - set(keys))} are not among the fitted keys {list(keys)}")
    experiment = sections["experiment"]
    return InclineExperiment(name=experiment.get("name", path.stem), material=material, table_file=table_file,
                             keys=keys, init=init, title=experiment.get("title", ""), side_walls=side_walls,
                             h_stop_file=h_stop_file, sources=sources,
                             path=None if given is None else path, text=text)


def _side_walls(boundaries, material, where: Where) -> SideWalls | None:
    """``[boundaries] side_walls`` read and checked as a collapse file's (``side_walls_of``); walls
    whose friction is "mu_w" need ``[material] mu_w`` (its value, or a fit's start)."""
    if "side_walls" not in boundaries:
        return None
    try:
        walls = side_walls_of(boundaries["side_walls"])
    except Invalid as err:
        raise where.error(err.section, err.key, err.what) from None
    if walls.friction == "mu_w" and "mu_w" not in material:
        raise where.error("material", "mu_w", "missing: the side walls' friction is the parameter mu_w (friction = "
                                              "\"mu_w\"); give its value here (the walls' friction, or a fit's "
                                              "start where [fit] keys has mu_w)")
    return walls
