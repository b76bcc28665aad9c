"""The checks of an experiment's values (``jaxmpm.experiment``), made whenever an ``Experiment``
is built: in a file or in Python. The parser has checked kinds and units; these check what the
values mean, each against the one list or table that owns it: the material against
``jaxmpm.params.PARAMS`` (rules and relations; ``[boundaries] floor_friction`` is the floor's
``mu_w``), the transfer against ``jaxmpm.config.TRANSFERS``, the sampling against
``jaxmpm.sampling.SAMPLINGS``, the dtype against ``jaxmpm.precision.DTYPES`` and the floor
against ``jaxmpm.scenes.collapse.FLOORS``. A failed check raises ``Invalid`` naming the section and
the key, which the reader turns into ``FILE:LINE: [section] key: what``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from ._toml import LENGTH, PURE, ExperimentError, Table, key_name
from .boundary import SideWalls
from .config import TRANSFERS
from .params import DEFAULTS, PARAM_KEYS, RELATIONS, param_help, param_problem
from .precision import DTYPES
from .sampling import SAMPLINGS
from .scenes.collapse import DEFAULT_SAMPLING, FLOORS, channel_cells_problem

if TYPE_CHECKING:
    from .experiment import Experiment

__all__ = ["GATES", "MEASUREMENT_SECTIONS", "SIDE_WALLS", "Invalid", "check_experiment", "side_walls_of"]

#: The sections a file holds for calibration: what was measured (``[[profile]]``, ``[front]``) and
#: what to fit (``[fit]``). The engine keeps them as written (``Experiment.measurements``) and reads
#: nothing in them but the data files they name (``file``, relative to the experiment file), which
#: must exist; ``calibration.data.read_measurements`` reads them.
MEASUREMENT_SECTIONS = ("profile", "front", "fit")
#: The gates of ``[boundaries] gate`` (``Experiment.gate_speeds``).
GATES = ("none", "front", "back", "both")
#: ``[boundaries] side_walls``, the walls of a 2D channel (``jaxmpm.SideWalls``): its entries.
#: Their friction may be the parameter "mu_w" (fitted, or given as [material] mu_w).
SIDE_WALLS = Table({"width": LENGTH, "friction": PURE._replace(parameter="mu_w"), "lateral_pressure_ratio": PURE})


class Invalid(ExperimentError):
    """A value that fails a check: its section, its key and what is wrong."""

    def __init__(self, section, key, what):
        super().__init__(f"{key_name(section, key)}: {what}")
        self.section, self.key, self.what = section, key, what


def _need(ok, section, key, what) -> None:
    if not ok:
        raise Invalid(section, key, what)


def _positive(section, key, value, unit) -> None:
    _need(value is not None and math.isfinite(value) and value > 0, section, key, f"must be > 0 {unit}, got {value}")


def _one_of(choices: tuple[str, ...], value) -> str:
    return f"must be one of {choices}, got {value!r}"


def check_experiment(e: Experiment) -> None:
    """Check the values of ``e``; raises ``Invalid`` at the first that fails."""
    _need(isinstance(e.name, str) and e.name.strip() != "", "experiment", "name", "must be a non-empty name")
    _positive("geometry", "length", e.length, "m")
    _positive("geometry", "height", e.height, "m")
    if e.aspect is not None:  # made by the aspect-ratio family: the height is a x length
        _need(math.isclose(e.height, e.aspect * e.length, rel_tol=1e-12), "geometry", "height",
              f"must be aspect x length ({e.aspect:g} x {e.length:g} m) for a column made at aspect ratio "
              f"{e.aspect:g}, got {e.height:g} m; change aspect with the height (None: not made at an aspect ratio)")
    _need(e.dim in (2, 3), "numerics", "dim", f"must be 2 or 3, got {e.dim!r}")
    if e.dim == 3:
        _need(e.width is not None, "geometry", "width", "missing: a 3D run (dim = 3) needs the channel's width")
        _positive("geometry", "width", e.width, "m")
    else:
        _need(e.width is None, "geometry", "width", "applies to dim = 3 (a 2D run has no width); set "
                                                    "[numerics] dim = 3 or drop it (a 2D channel's walls are "
                                                    "[boundaries] side_walls = { width = ..., friction = ... })")
    _need(-60.0 < e.slope < 60.0, "geometry", "slope", f"must be in (-60, 60) degrees, got {e.slope}")
    _check_boundaries(e)
    _check_material(e)
    _check_numerics(e)
    _check_measurement_tables(e)


def _check_boundaries(e: Experiment) -> None:
    _need(e.floor in FLOORS, "boundaries", "floor", _one_of(FLOORS, e.floor))
    if e.floor == "no-slip":
        _need(e.floor_friction is None, "boundaries", "floor_friction",
              "a no-slip floor has no friction coefficient; set floor = \"slip-stick\" to use one")
    else:
        _need(e.floor_friction is not None, "boundaries", "floor_friction",
              f"missing: a {e.floor} floor needs its Coulomb friction coefficient")
        problem = param_problem("mu_w", e.floor_friction)  # the floor's friction is the parameter mu_w
        _need(problem is None, "boundaries", "floor_friction", f"{problem} (the floor's mu_w)")
        _need("mu_w" not in e.material, "material", "mu_w", "the floor's friction is [boundaries] floor_friction")
    _need(e.gate in GATES, "boundaries", "gate", _one_of(GATES, e.gate))
    if e.gate == "none":
        _need(e.gate_speed is None, "boundaries", "gate_speed", "there is no gate (gate = \"none\"); set gate = "
                                                                "\"front\", \"back\" or \"both\" or drop it")
    else:
        _need(e.gate_speed is not None, "boundaries", "gate_speed",
              f"missing: the {e.gate} gate needs gate_speed or gate_lift_time")
        _positive("boundaries", "gate_speed", e.gate_speed, "m/s")
    _need(not (e.gate in ("back", "both") and e.back_wall), "boundaries", "back_wall",
          "a back gate stands where the back wall would: set back_wall = false")
    if e.side_walls is not None:
        _need(isinstance(e.side_walls, SideWalls), "boundaries", "side_walls",
              f"must be a jaxmpm.SideWalls, got {type(e.side_walls).__name__}")
        _need(e.side_walls.friction != "mu_w" or e.floor != "no-slip" or "mu_w" in e.material, "material", "mu_w",
              "missing: the side walls' friction is the parameter mu_w (friction = \"mu_w\"); give its value here "
              "(a fit's start; on the command line --set mu_w=...)")
        if e.dim == 3 and e.width is not None:
            _need(math.isclose(e.side_walls.width, e.width, rel_tol=1e-9), "boundaries", "side_walls",
                  f"in 3D the channel's own walls: its width must be [geometry] width ({e.width:g} m), got "
                  f"{e.side_walls.width:g} m")
            _need(e.side_walls.lateral_pressure_ratio == 1.0, "boundaries", "side_walls",
                  "in 3D the walls' normal stress is computed: drop lateral_pressure_ratio")


def side_walls_of(values: Mapping[str, float]) -> SideWalls:
    """The ``SideWalls`` of ``[boundaries] side_walls`` (its entries read, in SI units); raises
    ``Invalid`` naming what is missing or out of range."""
    for entry, what in (("width", "the channel's width, e.g. \"20 mm\""),
                        ("friction", "the walls' Coulomb friction coefficient mu_w, e.g. 0.25")):
        _need(entry in values, "boundaries", "side_walls", f"missing {entry}: {what}")
    width, friction = values["width"], values["friction"]
    ratio = values.get("lateral_pressure_ratio", 1.0)
    _need(width > 0, "boundaries", "side_walls", f"width must be > 0 m, got {width:g} m")
    _need(friction == "mu_w" or friction >= 0, "boundaries", "side_walls", f"friction must be >= 0 or \"mu_w\", "
                                                                          f"got {friction!r}")
    _need(ratio >= 0, "boundaries", "side_walls", f"lateral_pressure_ratio must be >= 0, got {ratio:g}")
    return SideWalls(width, friction, ratio)


def _check_material(e: Experiment) -> None:
    """The parameter table's rules on each key given, then its relations, the defaults standing
    for the keys not given (reported at the relation's key)."""
    unknown = sorted(set(e.material) - set(PARAM_KEYS))
    _need(not unknown, "material", unknown[0] if unknown else None,
          f"unknown parameter; [material] takes {param_help()}")
    for key, value in e.material.items():
        problem = param_problem(key, value)
        _need(problem is None, "material", key, problem)
    values = {**DEFAULTS, **e.material}

    def shown(key) -> str:
        return f"{key} = {values[key]!r}" + ("" if key in e.material else " (the default)")

    for relation in RELATIONS:
        if relation.key in e.material or relation.other in e.material:
            at_least = np.all(np.asarray(values[relation.key]) >= np.asarray(values[relation.other]))
            _need(at_least, "material", relation.key,
                  f"must be >= {relation.other} ({relation.key} is {relation.why}), got {shown(relation.other)} "
                  f"and {shown(relation.key)}")


def _check_numerics(e: Experiment) -> None:
    if e.dx is not None:
        _positive("numerics", "dx", e.dx, "m")
        thinnest = min(e.length, e.height, e.width if e.dim == 3 else math.inf)
        _need(e.dx <= thinnest, "numerics", "dx", f"must be at most the column's thinnest side ({thinnest:g} m): a "
                                                  f"body needs at least one cell across, got {e.dx:g} m")
        if e.dim == 3 and e.width is not None:
            problem = channel_cells_problem(e.width, e.dx)
            _need(problem is None, "numerics", "dx", f"must fit a whole number of cells across the 3D channel: "
                                                      f"[geometry] width {problem}")
    sampling = e.sampling or DEFAULT_SAMPLING
    _need(sampling in SAMPLINGS, "numerics", "sampling", _one_of(SAMPLINGS, e.sampling))
    if e.ppc is not None:
        if sampling == "poisson":
            _need(e.ppc >= 1, "numerics", "ppc", f"must be a number >= 1, got {e.ppc}")
        else:
            _need(e.ppc >= 1 and float(e.ppc).is_integer(), "numerics", "ppc",
                  f"must be a positive integer for {sampling} sampling, got {e.ppc}")
    _need(isinstance(e.seed, int) and e.seed >= 0, "numerics", "seed", f"must be an integer >= 0, got {e.seed!r}")
    _need(e.dtype is None or e.dtype in DTYPES, "numerics", "dtype", _one_of(DTYPES, e.dtype))
    _positive("numerics", "t_end", e.t_end, "s")
    _need(isinstance(e.frames, int) and e.frames >= 0, "numerics", "frames",
          f"must be an integer >= 0, got {e.frames!r}")
    if e.runout is not None:
        _positive("numerics", "runout", e.runout, "m")
    if e.backward_runout is not None:
        _need(e.backward_runout >= 0, "numerics", "backward_runout", f"must be >= 0 m, got {e.backward_runout}")
    _need(e.transfer in TRANSFERS, "numerics", "transfer", _one_of(TRANSFERS, e.transfer))
    _need(0.0 <= e.alpha <= 1.0, "numerics", "alpha", f"must be in [0, 1], got {e.alpha}")
    _need(0.0 < e.cfl <= 1.0, "numerics", "cfl", f"must be in (0, 1], got {e.cfl}")


def _check_measurement_tables(e: Experiment) -> None:
    """The measurement sections' shape only: what they hold is calibration's to read."""
    _need(isinstance(e.measurements, Mapping), None, "measurements", "must be a mapping of section -> tables")
    unknown = sorted(set(e.measurements) - set(MEASUREMENT_SECTIONS))
    _need(not unknown, None, "measurements", f"unknown sections {unknown}; they are {list(MEASUREMENT_SECTIONS)}")
    profiles = e.measurements.get("profile", [])
    _need(isinstance(profiles, (list, tuple)) and all(isinstance(t, Mapping) for t in profiles), None, "profile",
          "must be a list of tables ([[profile]])")
    for section in ("front", "fit"):
        _need(isinstance(e.measurements.get(section, {}), Mapping), None, section, f"must be a table ([{section}])")
