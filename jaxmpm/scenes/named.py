"""The named collapse scenes of docs/scenes.md, S2–S5 and S7: gates-collapse, slope-collapse,
cohesive-collapse, aspect-ratio and aluminium-bars. Each is its shipped experiment file
(``experiments_data/experiments/S*_*.toml``, ``jaxmpm.experiment.SHIPPED_EXPERIMENTS``), the one
statement of its geometry, boundaries, material and numerics, with their sources.

``named_experiment`` gives the ``Experiment`` of a named scene with the command line's options over
the file's values; ``jaxmpm.scenes.build_scene`` and ``python -m jaxmpm run NAME`` build its scene.
The Python builders (``gates_collapse``, ``slope_collapse``, ``cohesive_collapse``,
``aspect_ratio_collapse``, ``aluminium_bars``) build the same scenes from the same files; an
argument left at None takes the file's value, and their ``**kw`` take ``collapse``'s other
arguments (``runout``, ``wall_gap``, ``max_steps``, ``rest``, ...) and material keys.

Two of the scenes are families whose file describes the default member: slope-collapse over the
bed's slope (``slope_member``) and aspect-ratio over the column's aspect ratio
(``aspect_member``). Their rules, what follows from the slope or the aspect ratio, are stated
there and nowhere else.

The constants S2_LENGTH, S2_HEIGHT, S3_LENGTH, S3_HEIGHT, S4_SIDE, S5_LENGTH, S7_LENGTH, S7_HEIGHT
(m) and S7_PARAMS (S7's material) are read from the files when first asked for (a file parses in
about a millisecond); nothing is read at import.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from .base import Scene
from .collapse import G, _check_positive, aspect_column, collapse, runout_law

if TYPE_CHECKING:
    from ..experiment import Experiment

__all__ = ["named_experiment", "slope_member", "aspect_member", "gates_collapse", "slope_collapse",
           "cohesive_collapse", "aspect_ratio_collapse", "aluminium_bars", "CONSTANTS"]

#: The module constants the named scenes' files give: name -> (scene, ``Experiment`` field).
CONSTANTS = {
    "S2_LENGTH": ("gates-collapse", "length"), "S2_HEIGHT": ("gates-collapse", "height"),
    "S3_LENGTH": ("slope-collapse", "length"), "S3_HEIGHT": ("slope-collapse", "height"),
    "S4_SIDE": ("cohesive-collapse", "length"), "S5_LENGTH": ("aspect-ratio", "length"),
    "S7_LENGTH": ("aluminium-bars", "length"), "S7_HEIGHT": ("aluminium-bars", "height"),
    "S7_PARAMS": ("aluminium-bars", "material"),
}


def __getattr__(name: str):
    if name in CONSTANTS:
        scene, field = CONSTANTS[name]
        value = getattr(_shipped(scene), field)
        return dict(value) if field == "material" else value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _shipped(name: str) -> Experiment:
    from ..experiment import shipped_experiment

    return shipped_experiment(name)


# ---- the families ----------------------------------------------------------------------------------

def slope_member(experiment: Experiment, slope: float) -> dict[str, float]:
    """The slope-collapse family (S3's column on a bed inclined at ``slope`` degrees; its shipped
    file is the 10° member): the changes to the file's ``experiment`` (``Experiment`` fields).
    The run lasts 1.0 s below 15° and 1.5 s from 15° on; the grid reaches twice the flat-bed
    runout law's estimate (``runout_law``: 1.2 a L = 1.2 H at a = H/L = 0.7) beyond the column,
    times 1 + slope/8 on a downward slope (the runout grows with the slope; generous factors)."""
    return {"slope": slope, "t_end": 1.0 if slope < 15 else 1.5,
            "runout": (1.2 * experiment.height) * 2.0 * (1.0 + max(slope, 0.0) / 8.0)}


def aspect_member(experiment: Experiment, a: float, *, length: float | None = None,
                  dx: float | None = None) -> dict[str, Any]:
    """The aspect-ratio family (S5: a column L0 × a L0; its shipped file is the member a = 1): the
    changes to the file's ``experiment`` (``Experiment`` fields). L0 is the file's length unless
    ``length`` is given, at the file's grid spacing or, for another L0, the file's cells per L0,
    unless ``dx`` is given. The run lasts 4 √(H/g) + 0.1 s; the grid reaches 1.6 times the
    glass-bead runout law's estimate (``runout_law``: ΔL/L0 ≈ 1.2 a for a ≲ 2.3, 1.9 a^{2/3}
    above; Lajeunesse et al. 2005, secondary) plus four cells beyond the column."""
    L0 = experiment.length if length is None else length
    if dx is None:
        dx = experiment.dx if length is None else L0 / (experiment.length / experiment.dx)
    height = a * L0
    return {"length": L0, "height": height, "aspect": a, "dx": dx, "t_end": 4.0 * math.sqrt(height / G) + 0.1,
            "runout": 1.6 * float(runout_law(a)) * L0 + 4 * dx}


# ---- the command line's options over a file ------------------------------------------------------

def named_experiment(name: str, *, dx=None, ppc=None, dim=None, width=None, t_end=None, frames=0, slope=None,
                     aspect=None, dtype=None, values=None, sampling=None, seed=None, side_walls=None) -> Experiment:
    """The ``Experiment`` of the named collapse ``name`` (``SHIPPED_EXPERIMENTS``: gates-collapse,
    slope-collapse, cohesive-collapse, aspect-ratio, aluminium-bars) with the command line's
    options over its shipped file's values: ``dx``, ``ppc``, ``dim``, ``width``, ``t_end``,
    ``frames``, ``dtype``, ``sampling``, ``seed``, ``side_walls`` (a 2D channel's,
    ``jaxmpm.SideWalls``) (None: the file's), ``values`` (material keys).
    slope-collapse is built at ``slope`` degrees (default: its file's, 10), aspect-ratio at the
    aspect ratio ``aspect`` (default: its file's, 1), by their families' rules (``slope_member``,
    ``aspect_member``); a ``t_end`` given overrides the rule's. A value that does not fit is
    refused naming its option."""
    from ..experiment import SHIPPED_EXPERIMENTS

    if name == "elastic-block":
        raise ValueError("elastic-block is not a collapse and has no experiment file: build it with "
                         "jaxmpm.scenes.build_scene('elastic-block') or jaxmpm.scenes.falling_block")
    if name not in SHIPPED_EXPERIMENTS:
        raise ValueError(f"name must be one of the named collapses {tuple(SHIPPED_EXPERIMENTS)}, got {name!r}")
    if slope is not None and name != "slope-collapse":
        raise ValueError(f"--slope applies to slope-collapse, not {name}")
    if aspect is not None and name != "aspect-ratio":
        raise ValueError(f"--aspect applies to aspect-ratio, not {name}")
    if slope is not None and not (isinstance(slope, (int, float)) and math.isfinite(slope)):
        raise ValueError(f"slope must be a finite number of degrees, got {slope!r}")
    if dim == 3 and width is None:
        raise ValueError("width (the channel width, m) is required when dim=3")
    experiment = _shipped(name)
    options = dict(dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames, dtype=dtype, sampling=sampling,
                   seed=seed, side_walls=side_walls)
    family = {}
    if name == "slope-collapse":
        slope = experiment.slope if slope is None else slope
        family = _with_sources(experiment, slope_member(experiment, slope), f"slope_member at {slope:g} degrees")
    elif name == "aspect-ratio":
        _check_positive(aspect=aspect)
        a = experiment.height / experiment.length if aspect is None else aspect
        family = _with_sources(experiment, aspect_member(experiment, a, dx=dx), f"aspect_member at a = {a:g}")
    changes = {**family, **{k: v for k, v in options.items() if v is not None}}
    return experiment.with_options(material=values, flags={field: field for field in [*options, "slope"]}, **changes)


def _with_sources(experiment: Experiment, family: dict[str, Any], rule: str) -> dict[str, Any]:
    """``family``'s changes, and the sources of the values they change: the family's rule (its
    ``dx`` is the command line's or the file's)."""
    sections = {"length": "geometry", "height": "geometry", "slope": "geometry"}
    sources = dict(experiment.sources)
    for key, value in family.items():
        if key not in ("aspect", "dx") and value != getattr(experiment, key):
            sources[f"{sections.get(key, 'numerics')}.{key}"] = {"source": f"jaxmpm.scenes.named.{rule}"}
    return {**family, "sources": sources}


# ---- the Python builders ---------------------------------------------------------------------------

def _build(name: str, options: dict[str, Any], kw: dict[str, Any], family: dict[str, Any] | None = None,
           experiment: Experiment | None = None) -> Scene:
    """``collapse`` on the shipped experiment ``name``: its arguments from the file, the family
    member's ``family`` changes (``Experiment`` fields) over them, then the builder's ``options``
    that are not None, then its ``**kw`` (``collapse``'s arguments and material keys). Every check
    is ``collapse``'s, so that a bad argument is refused as the builder has always refused it."""
    experiment = _shipped(name) if experiment is None else experiment
    arguments = experiment.builder_arguments()
    renamed = {"slope": "slope_deg"}
    arguments.update({renamed.get(k, k): v for k, v in (family or {}).items() if k != "aspect"})
    arguments.update({k: v for k, v in options.items() if v is not None})
    arguments.update(kw)
    return collapse(**arguments)


def gates_collapse(dx: float | None = None, ppc: float | None = None, dim: int = 2, width: float | None = None,
                   t_end: float | None = None, frames: int = 0, **kw) -> Scene:
    """S2 (``S2_gates_collapse.toml``): a 0.08 m × 0.05 m column between two slip-free gates
    lifted at 0.45 m/s; it spreads to both sides (about 0.076 m each way by t = 0.42 s). The
    file's numerics (dx = 1.5 mm, a jittered 4 × 4 lattice, 28,000 particles) are the cheapest
    settings whose every observable lies within 2 % of the converged answer (docs/validation.md
    §1). A ``runout`` given reaches behind the column too unless ``backward_runout`` is given."""
    if "runout" in kw:
        kw.setdefault("backward_runout", kw["runout"])
    return _build("gates-collapse", dict(dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames), kw)


def slope_collapse(slope_deg: float | None = None, dx: float | None = None, ppc: float | None = None, dim: int = 2,
                   width: float | None = None, t_end: float | None = None, frames: int = 0, **kw) -> Scene:
    """S3 (``S3_slope_collapse.toml``, the Mangeney et al. 2010 set-up): a 0.20 m × 0.14 m column
    against a slip-free back wall on a no-slip bed inclined at ``slope_deg`` (default: the
    file's, 10°), released at t = 0 with no gate; the end time and the grid's reach follow the
    slope (``slope_member``)."""
    experiment = _shipped("slope-collapse")
    family = slope_member(experiment, experiment.slope if slope_deg is None else slope_deg)
    return _build("slope-collapse", dict(dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames), kw,
                  family, experiment)


def cohesive_collapse(beta: float | None = None, dx: float | None = None, ppc: float | None = None, dim: int = 2,
                      width: float | None = None, t_end: float | None = None, frames: int = 0, **kw) -> Scene:
    """S4 (``S4_cohesive_collapse.toml``, the Gans et al. 2023 set-up): a 0.089 m square column of
    coated beads on a no-slip floor against a slip-free back wall; the front gate is lifted at
    50 m/s (practically instantly). ``beta``: the cohesion (default: the file's, 0)."""
    if beta is not None:
        kw["beta"] = beta
    return _build("cohesive-collapse", dict(dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames), kw)


def aspect_ratio_collapse(a: float = 1.0, L0: float | None = None, dx: float | None = None, ppc: float | None = None,
                          dim: int = 2, width: float | None = None, t_end: float | None = None,
                          frames: int = 0, **kw) -> Scene:
    """S5 (``S5_aspect_ratio.toml``): a column L0 × a L0 (L0 default: the file's, 0.05 m) on a
    horizontal no-slip floor against a slip-free back wall, released at t = 0. The grid spacing,
    end time and grid's reach follow (``aspect_member``); its facts record ``a``
    (``SceneInfo.aspect``), and its variants take ``a`` and ``L0``."""
    _check_positive(a=a, L0=L0)
    experiment = _shipped("aspect-ratio")
    family = aspect_member(experiment, a, length=L0, dx=dx)
    scene = _build("aspect-ratio", dict(ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames), kw, family,
                   experiment)
    return aspect_column(scene, a)


def aluminium_bars(dx: float | None = None, ppc: float | None = None, dim: int = 2, width: float | None = None,
                   t_end: float | None = None, frames: int = 0, **kw) -> Scene:
    """S7 (``S7_aluminium_bars.toml``, Bui et al. 2008): a plane-strain column of aluminium bars,
    0.20 m long × 0.10 m high, against a slip-free back wall (as S4's) on a rough (no-slip)
    floor, released at t = 0 with no gate. The file gives every value with its source: the floor,
    the release and the material (``S7_PARAMS``); dx = H/16 = 6.25 mm, a jittered 3 × 3 lattice
    (4,608 particles) and t_end = 1 s, by when the deposit has stopped; the grid reaches 0.35 m
    beyond the column (the measured deposit ends 0.24 m beyond it, and a fit must be free to try
    a lower friction)."""
    return _build("aluminium-bars", dict(dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames), kw)
