"""Granular collapses of docs/scenes.md: S2 (two lifted gates), S3 (sloping bed), S4 (cohesive),
S5 (aspect ratio), S7 (Bui et al. 2008's aluminium bars). All share one builder.

Coordinates: the column initially occupies [0, L] × [0, H] with the floor (bed) at y = 0 and the
back wall at x = 0; on a slope x runs along the bed and gravity is rotated,
g = 9.81 (sin θ, -cos θ). In 3D the channel spans z ∈ [0, W] between separable (slip-free) side walls. The
grid covers only where the flow can go (an estimate of the runout times a safety factor, plus
three cells of wall margin); a flow that reaches its edge sets the ``EDGE`` status bit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..boundary import Wall
from ..config import Config, Grid
from ..materials.critical_state import CriticalState
from ..observables import back_wall_x, deposit_profile, particle_volumes
from ..params import Params
from ..sampling import SAMPLINGS, particles_per_cell, seed_box
from ..state import State, init_state
from ..step import step_budget
from .info import SceneInfo

__all__ = [
    "DEFAULT_PPC", "DEFAULT_SAMPLING", "REST_SPEED", "REST_DURATION", "S2_DEFAULT_PPC", "S2_HEIGHT", "S2_LENGTH",
    "S3_HEIGHT", "S3_LENGTH", "S4_SIDE", "S5_LENGTH", "S7_HEIGHT", "S7_LENGTH", "Scene",
    "floor_lift",
    "S2_PARAMS", "S3_PARAMS",
    "S4_PARAMS", "S5_PARAMS", "S7_PARAMS", "gates_collapse", "slope_collapse", "cohesive_collapse",
    "aspect_ratio_collapse", "aluminium_bars",
    "collapse", "runout_law", "height_law", "default_runout",
]

G = 9.81
#: Default particle sampling and particles per cell (along each axis) of every collapse scene
#: and of the command line, chosen by the resolution study (docs/validation.md §1): a jittered
#: 3 × 3 lattice converges in particles per cell much faster than a regular lattice (S2 at 3 mm:
#: left runout −3.4 % from the converged answer, against −10.4 % for a 2 × 2 lattice, at 1.2× the
#: run time).
DEFAULT_SAMPLING = "jitter"
DEFAULT_PPC = 3
#: A collapse is at rest (``Config.rest_speed``) once every particle has stayed slower than
#: REST_SPEED √(gH) for REST_DURATION √(H/g), H the column's height: on S4 (H = 89 mm) 4.7 mm/s for
#: 24 ms, on S7 (H = 0.1 m) 5.0 mm/s for 25 ms. Settled deposits creep at about half that speed
#: (the front of S4 and S7 at 2-2.5 mm/s at dx = 4-6 mm), so a creeping particle would have gone
#: on by at most 0.5 mm over the 0.1 s that S4 and S7 skip (docs/performance.md).
REST_SPEED, REST_DURATION = 0.005, 0.25
#: docs/scenes.md S2 material; unlisted keys take docs/model.md §4 defaults (E = 1e6, ν = 0.3,
#: ρ = 1550, ρ_s = 2500, μ1 = tan 20.9°, μ2 = tan 32.76°, I0 = 0.279).
S2_PARAMS = {"d": 2e-3, "beta": 0.0, "pc0": 100.0, "xi": 50.0}
#: S3 glass beads (d = 0.7 mm, ρ_s = 2500, ρ = 1550). docs/scenes.md gives no p_c0, ξ: S2's are used.
S3_PARAMS = {"d": 0.7e-3, "rho_s": 2500.0, "rho": 1550.0, "beta": 0.0, "pc0": 100.0, "xi": 50.0}
#: S4 coated beads: d = 0.8 mm, ρ_s = 2600, packing 0.58 (ρ = 1508), p_c0 = 500, ξ = 50.
S4_PARAMS = {"d": 0.8e-3, "rho_s": 2600.0, "rho": 1508.0, "beta": 0.0, "pc0": 500.0, "xi": 50.0}
#: S5 dry glass beads, as S3.
S5_PARAMS = dict(S3_PARAMS)


@dataclasses.dataclass(frozen=True)
class Scene:
    """A ready-to-run scene. Unpacks as ``config, state, params = scene``."""

    name: str
    config: Config
    state: State
    params: Params
    info: SceneInfo  # geometry and set-up facts (body extents, slope, initial front, sampling, ...)
    #: seed -> the same body sampled with another seed (None: the scene's sampling has no seed).
    sampler: Callable[[int], State] | None = dataclasses.field(default=None, compare=False, repr=False)
    #: builder arguments -> the set-up built again with those changed (None: the builder cannot
    #: remake it); see ``variant`` and ``at_dx``.
    remake: Callable[..., Scene] | None = dataclasses.field(default=None, compare=False, repr=False)
    #: The ``jaxmpm.Experiment`` this scene was built from (None: built in Python).
    experiment: Any = dataclasses.field(default=None, compare=False, repr=False)

    def __iter__(self):
        return iter((self.config, self.state, self.params))

    @property
    def back_face(self) -> float | None:
        """The x (m) of the body's back face where it rests against a fixed back wall: where an
        experiment's back wall is (x = 0 for the collapses; the model's wall plane sits
        ``info.side_gap`` behind it so that no particle starts on the edge of its stencil).
        Deposit profiles are mirrored here (``jaxmpm.observables.deposit_profile``). None
        without a fixed wall facing +x."""
        wall = back_wall_x(self.config.walls)
        return None if wall is None else wall + float(self.info.side_gap or 0.0)

    def summary(self, result) -> dict:
        """What a run of this scene ended with (``simulate``'s ``Result``): sizes, extents, the
        runout beyond the body's initial front, the status and its meaning, the timings, and the
        experiment file it was built from; what ``python -m jaxmpm run`` prints."""
        from ..state import describe_status

        x = np.asarray(result.state.x)
        return {
            "scene": self.name, "n_particles": int(self.state.n_particles), "n_steps": int(result.state.steps),
            "dx": self.config.grid.dx, "t_end": self.config.t_end,
            "x_min": float(x[:, 0].min()), "x_max": float(x[:, 0].max()), "y_max": float(x[:, 1].max()),
            "runout": float(x[:, 0].max() - self.info.front0),
            "status": result.status, "status_text": describe_status(result.status),
            "compile_s": None if result.compile_s is None else round(result.compile_s, 3),
            "run_s": None if result.run_s is None else round(result.run_s, 3),
            **({} if self.experiment is None else {
                "experiment": str(self.experiment.path) if self.experiment.path else self.experiment.name}),
        }

    def run_attrs(self) -> dict:
        """The root attributes that record a run of this scene in its HDF5 file (``write_h5``'s
        ``attrs``): the scene's name and facts and, for a scene built from an experiment file, the
        file's TOML (``Experiment.from_h5`` makes the run again from it) and its path."""
        attrs = {"scene": self.name, **self.info.to_dict()}
        if self.experiment is not None:
            attrs["experiment_toml"] = self.experiment.to_toml()
            if self.experiment.path is not None:
                attrs["experiment_path"] = str(self.experiment.path.resolve())
        return attrs

    def profile_header(self, result, source: str) -> dict:
        """The header of this scene's final deposit profile as CSV (``tables.write_profile_csv``):
        a synthetic profile made by ``source`` (the command that ran it), with the run's time,
        parameters, scene facts and status."""
        from .._version import __version__

        float32 = np.asarray(self.state.x).dtype == np.float32
        return {
            "experiment": f"{self.name} (synthetic, jaxmpm {__version__})", "time_s": self.config.t_end,
            "units": "m", "synthetic": True, "source": source,
            # float32 leaves printed to the precision they hold (0.3, not 0.30000001192092896)
            "parameters": {k: float(f"{v:.7g}") if float32 else v for k, v in self.params.to_dict().items()},
            "scene": self.info.to_dict(), "status": result.status,
        }

    def final_profile(self, state) -> tuple[np.ndarray, np.ndarray]:
        """(x, h): the deposit's height profile of ``state``, smoothed over one particle spacing,
        sampled every half spacing from three spacings behind its rearmost particle to three
        beyond its front, mirrored at the back wall (``jaxmpm.observables.deposit_profile``)."""
        x = np.asarray(state.x)
        sigma = self.config.grid.dx / self.info.ppc
        xs = np.arange(x[:, 0].min() - 3 * sigma, x[:, 0].max() + 3 * sigma, sigma / 2)
        h = np.asarray(deposit_profile(state.x, particle_volumes(state), xs, sigma, width=self.info.width,
                                       mirror=self.back_face))
        return xs, h

    def resampled(self, seed: int) -> State:
        """The initial state of this scene with its particles sampled with ``seed`` instead of its
        own (same body, grid, walls and parameters; same particle count for lattice samplings):
        for ensembles over the sampling and for the sampling's share of a fit's uncertainty."""
        if self.sampler is None:
            raise ValueError(f"scene {self.name!r} has no seeded sampling to redraw")
        if not (isinstance(seed, int) and seed >= 0):
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        return self.sampler(seed)

    def variant(self, **changes) -> Scene:
        """This set-up built again with some of its builder's arguments changed (``collapse``'s:
        ``dx``, ``height``, ``length``, ``slope_deg``, ``front_gate_speed``, ``runout``, ``t_end``,
        ``ppc``, ``seed``, ...), with this scene's material (its ``params`` as they are now, set
        after building or not): the same material in another experiment, or the same experiment
        on another grid. Material keys are not builder arguments: replace ``params`` instead."""
        if self.remake is None:
            raise ValueError(f"scene {self.name!r} cannot be rebuilt (its builder records no recipe)")
        from ..params import PARAM_KEYS

        material = sorted(set(changes) & set(PARAM_KEYS))
        if material:
            raise ValueError(f"variant: {material} are material parameters, not builder arguments; "
                             "use scene.params.replace(...)")
        return dataclasses.replace(self.remake(**changes), params=self.params, name=self.name)

    def at_dx(self, dx: float) -> Scene:
        """This scene built at grid spacing ``dx`` (m): the same body, walls, gates, end time,
        sampling and seed, with this scene's parameters (``variant``); grid, particles and step
        budget follow from ``dx``. For the grid (discretisation) term of a fit
        (``calibration.grid_shift``) and resolution studies."""
        if not (isinstance(dx, (int, float)) and math.isfinite(dx) and dx > 0):
            raise ValueError(f"dx must be a positive number of metres, got {dx!r}")
        return self.variant(dx=float(dx))


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


def collapse(
    name: str,
    length: float,
    height: float,
    *,
    dx: float,
    ppc: float | None = None,
    sampling: str | None = None,
    seed: int = 0,
    wall_gap: float | None = None,
    dim: int = 2,
    width: float | None = None,
    slope_deg: float = 0.0,
    floor: str = "no-slip",
    back_wall: bool = True,
    front_gate_speed: float | None = None,
    back_gate_speed: float | None = None,
    runout: float,
    backward_runout: float = 0.0,
    t_end: float,
    frames: int = 0,
    max_steps: int | None = None,
    transfer: str = "aflip",
    alpha: float = 0.95,
    cfl: float = 0.5,
    rest: bool = True,
    dtype=None,
    base_params: dict | None = None,
    **param_values: float,
) -> Scene:
    """The common builder: a column [0, L] × [0, H] on a bed inclined at ``slope_deg``.

    ``floor``: the bed's contact (``jaxmpm.boundary``): ``"no-slip"`` (a rough bed, the default), or
    ``"slip-stick"`` / ``"separable"`` with Coulomb friction ``Params.mu_w`` (a material key here, so
    that it can be fitted).
    ``back_wall``: a separable (slip-free) wall behind x = 0. ``front_gate_speed`` /
    ``back_gate_speed``: separable gates in front of x = L / behind x = 0 lifted at that speed
    (their lower edge starts on the bed). ``runout`` and ``backward_runout``: how far beyond x = L
    and before x = 0 the grid reaches. ``ppc``, ``sampling``, ``seed``: particles per cell along
    each axis, the sampler (``jaxmpm.sampling``) and its seed. ``wall_gap``: the placement
    against the walls (default: the lowest particle half a cell above the floor; see the module
    docstring).
    """
    recipe = {k: v for k, v in locals().items() if k != "param_values"}
    recipe.update(param_values)
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
    sampling = DEFAULT_SAMPLING if sampling is None else sampling
    ppc = DEFAULT_PPC if ppc is None else ppc
    if sampling not in SAMPLINGS:
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    if sampling == "poisson":
        if not (isinstance(ppc, (int, float)) and math.isfinite(ppc) and ppc >= 1):
            raise ValueError(f"ppc must be a number >= 1, got {ppc!r}")
    elif not (isinstance(ppc, (int, float)) and int(ppc) == ppc and ppc >= 1):
        raise ValueError(f"ppc must be a positive integer for {sampling} sampling, got {ppc!r}")
    if sampling != "poisson":
        ppc = int(ppc)
    if wall_gap is not None and not (isinstance(wall_gap, (int, float)) and math.isfinite(wall_gap)
                                     and 0.0 <= wall_gap <= 2.0 * dx):
        raise ValueError(f"wall_gap must be in [0, 2 dx] (m), got {wall_gap!r}")
    # The side walls' gap (0.501: see floor_lift); the floor follows the sample.
    gap = 0.501 * dx if wall_gap is None else wall_gap
    if not (math.isfinite(slope_deg) and -60.0 < slope_deg < 60.0):
        raise ValueError(f"slope_deg must be in (-60, 60) degrees, got {slope_deg!r}")
    if not (isinstance(frames, int) and frames >= 0):
        raise ValueError(f"frames must be a non-negative integer, got {frames!r}")
    if floor not in ("no-slip", "slip-stick", "non-separable", "separable"):
        raise ValueError(f"floor must be 'no-slip', 'slip-stick' or 'separable', got {floor!r}")
    params = Params.create(dtype=dtype, **{**(base_params or {}), **param_values})

    margin = 3 * dx
    theta = math.radians(slope_deg)
    gravity = (G * math.sin(theta), -G * math.cos(theta)) + ((0.0,) if dim == 3 else ())
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
    gap_z = _side_gap(width, gap, dx) if dim == 3 else 0.0
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
        walls.append(Wall((0.0, 0.0, -gap_z), (0.0, 0.0, 1.0), "separable"))
        walls.append(Wall((0.0, 0.0, width + gap_z), (0.0, 0.0, -1.0), "separable"))

    if max_steps is None:
        # The elastic bound sets dt (flow speeds stay far below the wave speed); 25 % margin.
        max_steps = step_budget(CriticalState(), params, dx, t_end, extra=frames + 10)
    config = Config(
        grid=grid, t_end=t_end, max_steps=max_steps, material=CriticalState(), walls=tuple(walls),
        gravity=gravity, transfer=transfer, alpha=alpha, cfl=cfl,
        frame_times=tuple(t_end * (k + 1) / frames for k in range(frames)),
        rest_speed=REST_SPEED * math.sqrt(G * height) if rest else None,
        rest_duration=REST_DURATION * math.sqrt(height / G),
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


#: S2's own default particles per cell: with dx = 1.5 mm, the cheapest setting whose runouts, top
#: and deposit profile all lie within 2 % of the converged answer (docs/validation.md §1).
S2_DEFAULT_PPC = 4
#: S2's column length (docs/scenes.md S2), m.
S2_LENGTH = 0.08
#: S2's column height, m.
S2_HEIGHT = 0.05


def gates_collapse(dx: float = 0.0015, ppc: float | None = None, dim: int = 2, width: float | None = None,
                   t_end: float = 0.4198, frames: int = 0, **kw) -> Scene:
    """S2: a 0.08 m × 0.05 m column between two slip-free gates lifted at 0.45 m/s; it spreads to
    both sides (about 0.076 m each way by t = 0.42 s). The defaults (dx = 1.5 mm, a jittered 4 × 4
    lattice, 28,000 particles) are the cheapest settings whose every observable lies within 2 %
    of the converged answer (docs/validation.md §1)."""
    ppc = S2_DEFAULT_PPC if ppc is None else ppc
    kw.setdefault("runout", 0.09)
    kw.setdefault("backward_runout", kw["runout"])
    return collapse("gates-collapse", S2_LENGTH, S2_HEIGHT, dx=dx, ppc=ppc, dim=dim, width=width, back_wall=False,
                    front_gate_speed=0.45, back_gate_speed=0.45, t_end=t_end, frames=frames,
                    base_params=S2_PARAMS, **kw)


#: S3's column length (docs/scenes.md S3, Mangeney et al. 2010), m.
S3_LENGTH = 0.20
#: S3's column height, m.
S3_HEIGHT = 0.14


def slope_collapse(slope_deg: float = 10.0, dx: float = 0.01, ppc: float | None = None, dim: int = 2,
                   width: float | None = None, t_end: float | None = None, frames: int = 0, **kw) -> Scene:
    """S3 (Mangeney et al. 2010 set-up): a 0.20 m × 0.14 m column against a slip-free back wall
    on a no-slip bed inclined at ``slope_deg``, released at t = 0 with no gate."""
    t_end = t_end if t_end is not None else (1.0 if slope_deg < 15 else 1.5)
    # Runout estimate: the flat-bed law 1.2 a L (a = 0.7) grows on a slope; generous factors.
    kw.setdefault("runout", S3_LENGTH * (1.2 * 0.7) * 2.0 * (1.0 + max(slope_deg, 0.0) / 8.0))
    return collapse("slope-collapse", S3_LENGTH, S3_HEIGHT, dx=dx, ppc=ppc, dim=dim, width=width, slope_deg=slope_deg,
                    t_end=t_end, frames=frames, base_params=S3_PARAMS, **kw)


#: S4's column: a square of this side (m), Gans et al. 2023 (docs/scenes.md S4).
S4_SIDE = 0.089


def cohesive_collapse(beta: float = 0.0, dx: float = S4_SIDE / 16, ppc: float | None = None, dim: int = 2,
                      width: float | None = None, t_end: float = 0.5, frames: int = 0, **kw) -> Scene:
    """S4 (Gans et al. 2023 set-up): a 0.089 m square column of coated beads on a no-slip floor
    against a slip-free back wall; the front gate is lifted at 50 m/s (practically instantly)."""
    kw.setdefault("runout", 0.25)  # β = 0 runs out ~0.16 m at dx = 5.6 mm
    return collapse("cohesive-collapse", S4_SIDE, S4_SIDE, dx=dx, ppc=ppc, dim=dim, width=width,
                    front_gate_speed=50.0, t_end=t_end, frames=frames, base_params=S4_PARAMS, beta=beta, **kw)


def runout_law(a, sand: bool = False):
    """Normalised runout ΔL/L0 of quasi-2D collapses against aspect ratio a (secondary: glass
    beads, Lajeunesse et al. 2005; ``sand``: Lube et al. 2005; both as quoted by K. Kumar)."""
    import numpy as np

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
    import numpy as np

    a = np.asarray(a, float)
    return np.where(a <= 0.7, a, a ** (1.0 / 3.0))


#: S5's default column length L0 (docs/scenes.md S5), m.
S5_LENGTH = 0.05


def aspect_ratio_collapse(a: float = 1.0, L0: float = S5_LENGTH, dx: float | None = None, ppc: float | None = None,
                          dim: int = 2, width: float | None = None, t_end: float | None = None,
                          frames: int = 0, **kw) -> Scene:
    """S5: a column L0 × a L0 on a horizontal no-slip floor against a slip-free back wall,
    released at t = 0. The grid allows 1.6× the runout of the glass-bead scaling law
    (ΔL/L0 ≈ 1.2 a for a ≲ 2.3, 1.9 a^{2/3} above; Lajeunesse et al. 2005, secondary)."""
    _check_positive(a=a, L0=L0)
    dx = dx if dx is not None else L0 / 10
    height = a * L0
    kw.setdefault("runout", 1.6 * float(runout_law(a)) * L0 + 4 * dx)
    t_end = t_end if t_end is not None else 4.0 * math.sqrt(height / G) + 0.1
    scene = collapse("aspect-ratio", L0, height, dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end,
                     frames=frames, base_params=S5_PARAMS, **kw)
    return dataclasses.replace(
        scene, info=dataclasses.replace(scene.info, aspect=a),
        remake=lambda **c: aspect_ratio_collapse(**{"a": a, "L0": L0, "dx": dx, "ppc": ppc, "dim": dim, "width": width,
                                                    "t_end": t_end, "frames": frames, **kw, **c}))


#: S7's column length (docs/scenes.md S7), m.
S7_LENGTH = 0.20
#: S7's column height, m.
S7_HEIGHT = 0.10

#: S7 aluminium bars (Bui, Fukagawa, Sako & Ohno 2008), every value with its source
#: (experiments_data/experiments/S7_aluminium_bars.toml holds the same with longer notes):
#: - mu1 = tan 19.8°: the bars' friction angle reported with the data (docs/scenes.md S7). A modelling
#:   choice of convention: tan φ is the μ(I) law's friction coefficient (q/p̄ in simple shear);
#:   a plane-strain Mohr–Coulomb match of the same φ would give sin φ = 0.339 instead of 0.360.
#: - beta = 0: cohesionless (reported).
#: - rho = 2650 kg/m³: the bulk density of the numerical studies that use these data (2650–2700
#:   per the data file's header; 2650 in Bui et al.'s own simulation as later studies quote it).
#:   It is not a packing of aluminium (2700) but the value the benchmarks use; the deposit
#:   depends on it only through the elastic wave speed and the inertial number.
#: - rho_s = 2700 kg/m³: the density of aluminium (enters the inertial number only).
#: - E = 0.84 MPa, nu = 0.3: the elastic constants of Bui et al.'s own SPH simulation of this
#:   experiment (secondary: as later numerical studies quote them, e.g. K = 0.7 MPa with ν = 0.3);
#:   a softened stiffness like the 1 MPa of the other scenes, not a property of the bars.
#: - d = 1.2 mm: a modelling choice, a representative bar diameter (bars of about 1–1.5 mm,
#:   secondary, not checked in the primary paper); it enters only the inertial number I.
#: - mu2 = tan 32.76°, I0 = 0.279: no μ(I) measurement exists for the bars; the glass-bead
#:   values of docs/model.md §4 (Jop, Forterre & Pouliquen) as a modelling choice. The rate part is
#:   not negligible here: with mu2 = mu1 (no rate dependence) the deposit runs about 0.02 m
#:   further, and halving d about 0.005 m, so a final surface constrains mu1 only together
#:   with these choices.
#: - pc0 = rho g H = 2600 Pa: a modelling choice. Then no particle starts beyond the cap of the
#:   ellipse (no gravity compaction at t = 0, which would lower the back of the column, measured
#:   standing at its initial height), and the column's mean pressure ρ g H / 2 sits at the apex,
#:   where plastic flow has no volume change (the dilatancy 0 reported).
#: - xi = 50: the reference code's scenes' value (S2, S4), a modelling choice.
S7_PARAMS = {"mu1": math.tan(math.radians(19.8)), "mu2": math.tan(math.radians(32.76)), "I0": 0.279,
             "beta": 0.0, "rho": 2650.0, "rho_s": 2700.0, "E": 0.84e6, "nu": 0.3, "d": 1.2e-3,
             "pc0": round(2650.0 * G * S7_HEIGHT), "xi": 50.0}


def aluminium_bars(dx: float = S7_HEIGHT / 16, ppc: float | None = None, dim: int = 2, width: float | None = None,
                   t_end: float = 1.0, frames: int = 0, **kw) -> Scene:
    """S7 (Bui et al. 2008): a plane-strain column of aluminium bars, 0.20 m long × 0.10 m high,
    against a slip-free back wall (as S4's) on a rough floor, released at t = 0 with no gate.

    Floor: docs/model.md §5's no-slip wall, the type that stands for a rough base (the basal layer of
    grains does not slide on it); slip-stick would need a basal friction coefficient that is not
    reported. Release: the front side was "removed quickly" at a speed not reported, so the
    instantaneous release is taken, as the numerical studies of these data do; a 50 m/s gate
    (S4's) would clear the column in 2 ms, 2 % of sqrt(H/g), and change nothing but the cost.
    Material: ``S7_PARAMS`` (sources there).

    The grid reaches 0.35 m beyond the column (x ≈ 0.57 m): the measured deposit ends at
    x ≈ 0.44 m, and a fit must be free to try a lower friction. Defaults: dx = H/16 = 6.25 mm
    and a jittered 3 × 3 lattice (4,608 particles); t_end = 1 s, by when the deposit has stopped
    (at the defaults the kinetic energy falls below 1e-5 of its peak by t ≈ 0.7 s, at dx = 4 mm
    by 0.8 s, and without rate dependence, mu2 = mu1, by 0.9 s)."""
    kw.setdefault("runout", 0.35)
    return collapse("aluminium-bars", S7_LENGTH, S7_HEIGHT, dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end,
                    frames=frames, base_params=S7_PARAMS, **kw)
