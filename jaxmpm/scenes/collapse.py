"""The common builder of the granular collapses (``collapse``): a column on a bed between walls and
gates. Every collapse is built by it: the named scenes of docs/scenes.md (S2–S5, S7; their facts
are their shipped experiment files, see ``jaxmpm.scenes.named``) and a user's experiment file
(``jaxmpm.Experiment.scene``).

Coordinates: the column initially occupies [0, L] × [0, H] with the floor (bed) at y = 0 and the
back wall at x = 0; on a slope x runs along the bed and gravity is rotated,
g = 9.81 (sin θ, -cos θ). In 3D the channel spans z ∈ [0, W] between separable (slip-free) side walls. The
grid covers only where the flow can go (an estimate of the runout times a safety factor, plus
three cells of wall margin); a flow that reaches its edge sets the ``EDGE`` status bit.

``S4_SIDE`` (S4's column side, m) is read from S4's shipped experiment file when first asked for:
it is importable from here as it always was, and this module sits below the experiment reader.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys

import numpy as np

from ..boundary import SideWalls, Wall
from ..config import Config, Grid
from ..materials.critical_state import CriticalState
from ..params import Params
from ..sampling import SAMPLINGS, particles_per_cell, seed_box
from ..state import init_state
from ..step import step_budget
from .base import Scene
from .info import SceneInfo

__all__ = [
    "DEFAULT_PPC", "DEFAULT_SAMPLING", "FLOORS", "REST_SPEED", "REST_DURATION", "Scene", "floor_lift",
    "collapse", "aspect_column", "runout_law", "height_law", "default_runout",
]

G = 9.81
#: Default particle sampling and particles per cell (along each axis) of every collapse scene
#: and of the command line, chosen by the resolution study (docs/validation.md §1): a jittered
#: 3 × 3 lattice converges in particles per cell much faster than a regular lattice (S2 at 3 mm:
#: left runout −3.4 % from the converged answer, against −10.4 % for a 2 × 2 lattice, at 1.2× the
#: run time).
DEFAULT_SAMPLING = "jitter"
DEFAULT_PPC = 3
#: The bed's contact (``collapse(floor=...)``, an experiment file's ``[boundaries] floor``):
#: ``jaxmpm.boundary``'s wall types under the reference code's names.
FLOORS = ("no-slip", "slip-stick", "separable")
#: A collapse is at rest (``Config.rest_speed``) once every particle has stayed slower than
#: REST_SPEED √(gH) for REST_DURATION √(H/g), H the column's height: on S4 (H = 89 mm) 4.7 mm/s for
#: 24 ms, on S7 (H = 0.1 m) 5.0 mm/s for 25 ms. Settled deposits creep at about half that speed
#: (the front of S4 and S7 at 2-2.5 mm/s at dx = 4-6 mm), so a creeping particle would have gone
#: on by at most 0.5 mm over the 0.1 s that S4 and S7 skip (docs/performance.md).
REST_SPEED, REST_DURATION = 0.005, 0.25


def _check_positive(**values):
    for name, value in values.items():
        if value is None:
            continue
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be > 0, got {value!r}")


def floor_lift(y, dx: float, wall_gap: float | None = None) -> float:
    """How far to raise a body sampled with its lower face on the floor (y = 0): so that its
    lowest particle lies half a cell above the floor (``wall_gap`` None), or by ``wall_gap``.
    "Half a cell" is 0.501 dx: exactly dx/2 would put the particle on the edge of its stencil,
    where a float32 rounding of x/dx picks the node row below the floor."""
    if wall_gap is not None:
        return float(wall_gap)
    return max(0.0, 0.501 * dx - float(min(y)))


def _side_gap(extent: float, gap: float, dx: float) -> float:
    """The gap on each side of a body of ``extent`` between two walls, at least ``gap``, such that
    both walls lie on node rows (the body is centred between them); 0 stays 0 (flush)."""
    if gap == 0.0:
        return 0.0
    cells = math.ceil((extent + 2.0 * gap) / dx - 1e-9)
    return 0.5 * (cells * dx - extent)


def collapse(name: str, length: float, height: float, *, dx: float, ppc: float | None = None,
             sampling: str | None = None, seed: int = 0, wall_gap: float | None = None, dim: int = 2,
             width: float | None = None, slope_deg: float = 0.0, floor: str = "no-slip", back_wall: bool = True,
             front_gate_speed: float | None = None, back_gate_speed: float | None = None, runout: float,
             backward_runout: float = 0.0, t_end: float, frames: int = 0, max_steps: int | None = None,
             transfer: str = "aflip", alpha: float = 0.95, cfl: float = 0.5, rest: bool = True, dtype=None,
             side_walls: SideWalls | None = None, base_params: dict | None = None, **param_values: float) -> Scene:
    """The common builder: a column [0, L] × [0, H] on a bed inclined at ``slope_deg``.

    ``floor``: the bed's contact (``jaxmpm.boundary``): ``"no-slip"`` (a rough bed, the default), or
    ``"slip-stick"`` / ``"separable"`` with Coulomb friction ``Params.mu_w`` (a material key here, so
    that it can be fitted).
    ``back_wall``: a separable (slip-free) wall behind x = 0. ``front_gate_speed`` /
    ``back_gate_speed``: separable gates in front of x = L / behind x = 0 lifted at that speed
    (their lower edge starts on the bed). ``runout`` and ``backward_runout``: how far beyond x = L
    and before x = 0 the grid reaches. ``ppc``, ``sampling``, ``seed``: particles per cell along
    each axis (an integral number is kept as an ``int``), the sampler (``jaxmpm.sampling``) and its
    seed. ``wall_gap``: the placement against the walls (default: the lowest particle half a cell
    above the floor; see the module docstring). ``frames``: that many equally spaced frame times,
    the last at ``t_end``. ``side_walls``: the friction of the channel's two side walls
    (``jaxmpm.SideWalls``): in 2D the width-averaged term of ``Config.side_walls``; in 3D the
    channel's walls themselves become Coulomb walls with that friction (its width must be
    ``width`` and its lateral pressure ratio 1: the walls' normal stress is computed).
    ``base_params`` and ``param_values``: the material (the latter over the former; unlisted keys
    take docs/model.md §4's defaults).
    """
    recipe = {k: v for k, v in locals().items() if k != "param_values"}
    recipe.update(param_values)
    sampling, ppc = _checked_column(length, height, dx=dx, ppc=ppc, sampling=sampling, wall_gap=wall_gap, dim=dim,
                                    width=width, slope_deg=slope_deg, floor=floor, runout=runout, t_end=t_end,
                                    frames=frames, side_walls=side_walls)
    params = Params.create(dtype=dtype, **{**(base_params or {}), **param_values})
    # The side walls' gap (0.501: see floor_lift); the floor follows the sample.
    gap = 0.501 * dx if wall_gap is None else wall_gap
    grid, walls, gap_x, channel = _grid_and_walls(length, height, dx, gap, dim=dim, width=width, floor=floor,
                                                  back_wall=back_wall, front_gate_speed=front_gate_speed,
                                                  back_gate_speed=back_gate_speed, runout=runout,
                                                  backward_runout=backward_runout,
                                                  wall_friction=side_walls.friction if side_walls else 0.0)
    if max_steps is None:
        # The elastic bound sets dt (flow speeds stay far below the wave speed); 25 % margin.
        max_steps = step_budget(CriticalState(), params, dx, t_end, extra=frames + 10)
    theta = math.radians(slope_deg)
    config = Config(
        grid=grid, t_end=t_end, max_steps=max_steps, material=CriticalState(), walls=walls,
        gravity=(G * math.sin(theta), -G * math.cos(theta)) + ((0.0,) if dim == 3 else ()),
        transfer=transfer, alpha=alpha, cfl=cfl,
        # min: t_end (k + 1) / frames can round one ulp above t_end at k + 1 = frames
        frame_times=tuple(min(t_end, t_end * (k + 1) / frames) for k in range(frames)),
        rest_speed=REST_SPEED * math.sqrt(G * height) if rest else None,
        rest_duration=REST_DURATION * math.sqrt(height / G), side_walls=side_walls if dim == 2 else None,
    )
    upper = (length, height) + ((width,) if dim == 3 else ())

    def body(seed_):
        x_, vol_ = seed_box((0.0,) * dim, upper, dx, ppc, sampling=sampling, seed=seed_)
        lift_ = floor_lift(x_[:, 1], dx, wall_gap)
        x_[:, 1] += lift_
        return x_, vol_, lift_

    x, vol, lift = body(seed)
    info = SceneInfo(dim=dim, dx=dx, ppc=ppc, sampling=sampling, seed=seed, front0=length, length=length,
                     height=height, width=channel, slope_deg=slope_deg, wall_gap=lift, side_gap=gap_x,
                     particles_per_cell=particles_per_cell(len(x), (0.0,) * dim, upper, dx))
    sampler = None
    if sampling != "lattice":  # a regular lattice has no seed

        def sampler(seed_):
            x_, vol_, _ = body(seed_)
            return init_state(config, x_, vol_, dtype=dtype)

    def remake(**changes):
        unknown = sorted(set(changes) - set(recipe))
        if unknown:
            raise ValueError(f"variant: {unknown} are not arguments of the collapse builder; it takes "
                             f"{sorted(k for k in recipe if k not in param_values)}")
        return collapse(**{**recipe, **changes})

    return Scene(name, config, init_state(config, x, vol, dtype=dtype), params, info, sampler, remake)


def channel_cells_problem(width: float, dx: float) -> str | None:
    """None if a 3D channel ``width`` wide is a whole number of cells of ``dx``, else what is wrong
    and two spacings that fit. The walls act on grid nodes: one between two node rows would act at
    the row behind it, and the channel would be wider than asked (docs/channel.md)."""
    n = width / dx
    if abs(n - round(n)) <= 1e-6:
        return None
    return (f"{width:g} m is {n:.4g} cells of dx = {dx:g} m: a 3D channel's walls stand on node rows, so the width "
            f"must be a whole number of cells; use dx = width/{math.floor(n)} = {width / math.floor(n):.6g} m or "
            f"width/{math.ceil(n)} = {width / math.ceil(n):.6g} m")


def _checked_column(length, height, *, dx, ppc, sampling, wall_gap, dim, width, slope_deg, floor, runout, t_end,
                    frames, side_walls=None) -> tuple[str, float]:
    """``collapse``'s checks, before anything is built; (the sampling, the particles per cell)
    with their defaults filled in."""
    _check_positive(dx=dx, length=length, height=height, runout=runout, t_end=t_end, width=width)
    thinnest = min(length, height, width if dim == 3 and width is not None else math.inf)
    if dx > thinnest:
        raise ValueError(f"dx = {dx:g} m is larger than the body ({length:g} m long, {height:g} m high"
                         + (f", {width:g} m wide" if dim == 3 and width is not None else "")
                         + "): a body needs at least one grid cell across each side; use a smaller dx")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    if dim == 3 and width is None:
        raise ValueError("width (the channel width, m) is required when dim=3")
    if dim == 3 and (problem := channel_cells_problem(width, dx)):
        raise ValueError(f"width = {problem}")
    if side_walls is not None:
        if not isinstance(side_walls, SideWalls):
            raise ValueError(f"side_walls must be a jaxmpm.SideWalls or None, got {type(side_walls).__name__}")
        if dim == 3 and not (math.isclose(side_walls.width, width, rel_tol=1e-9)
                             and side_walls.lateral_pressure_ratio == 1.0):
            raise ValueError(f"side_walls in 3D gives the friction of the channel's own walls: its width must be the "
                             f"channel's ({width:g} m, got {side_walls.width:g}) and its lateral_pressure_ratio 1 "
                             f"(got {side_walls.lateral_pressure_ratio:g}; the walls' normal stress is computed)")
    sampling = DEFAULT_SAMPLING if sampling is None else sampling
    ppc = DEFAULT_PPC if ppc is None else ppc
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    if sampling == "poisson":
        if not (isinstance(ppc, (int, float)) and math.isfinite(ppc) and ppc >= 1):
            raise ValueError(f"ppc must be a number >= 1, got {ppc!r}")
    elif not (isinstance(ppc, (int, float)) and int(ppc) == ppc and ppc >= 1):
        raise ValueError(f"ppc must be a positive integer for {sampling} sampling, got {ppc!r}")
    if sampling != "poisson" or float(ppc).is_integer():
        ppc = int(ppc)
    if wall_gap is not None and not (isinstance(wall_gap, (int, float)) and math.isfinite(wall_gap)
                                     and 0.0 <= wall_gap <= 2.0 * dx):
        raise ValueError(f"wall_gap must be in [0, 2 dx] (m), got {wall_gap!r}")
    if not (math.isfinite(slope_deg) and -60.0 < slope_deg < 60.0):
        raise ValueError(f"slope_deg must be in (-60, 60) degrees, got {slope_deg!r}")
    if not (isinstance(frames, int) and frames >= 0):
        raise ValueError(f"frames must be a non-negative integer, got {frames!r}")
    if floor not in FLOORS:
        raise ValueError(f"floor must be one of {FLOORS}, got {floor!r}")
    return sampling, ppc


def _grid_and_walls(length, height, dx, gap, *, dim, width, floor, back_wall, front_gate_speed, back_gate_speed,
                    runout, backward_runout, wall_friction=0.0) -> tuple[Grid, tuple[Wall, ...], float, float | None]:
    """(the grid, the walls, the gap between the back wall and the body, the channel's width in
    3D) of ``collapse``'s column, with ``gap`` between the body and the walls around it."""
    margin = 3 * dx
    # The grid's node rows lie on the floor (y = 0) and on the wall behind the body; with walls
    # on both sides (gates, a 3D channel) the gap is widened so that both lie on node rows.
    has_back = back_wall or back_gate_speed is not None
    gap_x = _side_gap(length, gap, dx) if (has_back and front_gate_speed is not None) else gap
    x_back = -gap_x
    x0 = x_back - math.ceil((backward_runout + margin) / dx) * dx
    span_x = (length + gap_x + runout + margin) - x0
    # Height: the column plus room for a splash (material rarely rises above its start).
    span_y = height * 1.15 + 0.5 * dx + gap + 2 * margin
    cells = [math.ceil(span_x / dx), math.ceil(span_y / dx)]
    origin = [x0, -margin]
    channel = None
    # A 3D channel's walls stand on the body's faces: the channel is as wide as asked. A gap there
    # would widen it, and the material would spread into it (docs/validation.md §9).
    gap_z = 0.0
    if dim == 3:
        channel = width + 2.0 * gap_z
        cells.append(math.ceil((channel + 2 * margin) / dx))
        origin.append(-gap_z - margin)
    grid = Grid(tuple(cells), dx, origin=tuple(origin))

    def vec(*c):
        return tuple(c) + ((0.0,) if dim == 3 else ())

    walls = [Wall(vec(0.0, 0.0), vec(0.0, 1.0), "no-slip") if floor == "no-slip"
             else Wall(vec(0.0, 0.0), vec(0.0, 1.0), floor, friction="mu_w")]
    if back_gate_speed is not None:
        walls.append(Wall(vec(x_back, 0.0), vec(1.0, 0.0), "separable", velocity=vec(0.0, back_gate_speed),
                          edge=vec(0.0, 1.0), thickness=2 * dx))
    elif back_wall:
        walls.append(Wall(vec(x_back, 0.0), vec(1.0, 0.0), "separable"))
    if front_gate_speed is not None:
        walls.append(Wall(vec(length + gap_x, 0.0), vec(-1.0, 0.0), "separable",
                          velocity=vec(0.0, front_gate_speed), edge=vec(0.0, 1.0), thickness=2 * dx))
    if dim == 3:
        walls.append(Wall((0.0, 0.0, -gap_z), (0.0, 0.0, 1.0), "separable", friction=wall_friction))
        walls.append(Wall((0.0, 0.0, width + gap_z), (0.0, 0.0, -1.0), "separable", friction=wall_friction))
    return grid, tuple(walls), gap_x, channel


def aspect_column(scene: Scene, a: float) -> Scene:
    """``scene``, a column of height a·L built by ``collapse``, recording its aspect ratio ``a``
    (``SceneInfo.aspect``). Its variants take ``a`` and ``L0`` (the column's length) besides
    ``collapse``'s arguments but not ``height``, which follows as a·L0, and record their own
    aspect ratio."""
    rebuild = scene.remake

    def remake(**changes):
        if "height" in changes:
            raise ValueError(f"variant: the height of this column is a L0 (a = {a:g}); give a, the aspect ratio, "
                             "or L0 instead of height")
        a_new = changes.pop("a", a)
        if "L0" in changes:
            changes["length"] = changes.pop("L0")
        return aspect_column(rebuild(**changes, height=a_new * changes.get("length", scene.info.length)), a_new)

    return dataclasses.replace(scene, info=dataclasses.replace(scene.info, aspect=a), remake=remake)


def runout_law(a, sand: bool = False):
    """Normalised runout ΔL/L0 of quasi-2D collapses against aspect ratio a (secondary: glass
    beads, Lajeunesse et al. 2005; ``sand``: Lube et al. 2005; both as quoted by K. Kumar)."""
    a = np.asarray(a, float)
    low, high = (1.6, 2.2) if sand else (1.2, 1.9)
    return np.where(a <= 2.3, low * a, high * a ** (2.0 / 3.0))


def default_runout(length: float, height: float, slope_deg: float, dx: float) -> float:
    """How far beyond the column a collapse's grid reaches when the set-up does not say: 1.6 times
    the glass-bead runout law's estimate (``runout_law``, at the aspect ratio H/L), 1 + slope/8
    times that on a downward slope (degrees), plus four cells. A flow that still reaches the
    grid's edge sets the ``EDGE`` status bit; give the runout then."""
    a = height / length
    return 1.6 * float(runout_law(a)) * length * (1.0 + max(slope_deg, 0.0) / 8.0) + 4 * dx


def height_law(a):
    """Normalised final height H_f/L0 of glass-bead collapses (secondary): a below 0.7, a^{1/3} above."""
    a = np.asarray(a, float)
    return np.where(a <= 0.7, a, a ** (1.0 / 3.0))


def __getattr__(name: str):
    if name == "S4_SIDE":
        return _s4_side()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@functools.cache
def _s4_side() -> float:
    """S4's column side (m): its shipped experiment file's ``[geometry] length``, read by the
    experiment reader's own number parser (units and all); ``jaxmpm.scenes.S4_SIDE`` is the same
    number read through ``jaxmpm.Experiment``."""
    from .._toml import LENGTH, Where, number
    from ..datasets import data_dir

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover - Python 3.10
        import tomli as tomllib

    path = data_dir() / "experiments" / "S4_cohesive_collapse.toml"
    text = path.read_text(encoding="utf-8")
    return number(tomllib.loads(text)["geometry"]["length"], LENGTH, Where(path, text), "geometry", "length")[0]
