"""S6: a snow avalanche on a terrain profile (docs/scenes.md S6).

A 2D section along the path: the terrain is a polyline (x, z) read from a CSV (default: the
ISeeSnow *CoulombOnly* centre line shipped in ``experiments_data/terrain/``), acting as a
``Terrain`` boundary with Coulomb friction μ_w (the parameter ``mu_w``, so it can be
differentiated). The release is the ISeeSnow one: from x = 1045 m to 1345 m, 1.5 m thick normal
to the slope. The grid is sparse (``Config.active_nodes``): the bounding box of a 5 km path at
dx = 1 m holds 7.5 million nodes, the flow touches a few thousand of them.

Snow. No source fixes the μ(I)/critical-state parameters of the ISeeSnow snow (the intercomparison's
depth-averaged codes have only the basal friction), so both sets below are illustrative
choices, stated as such; the study ``python -m jaxmpm validate avalanche`` (docs/avalanche.md)
reports how the runout depends on μ1 and β.

- ``"dry"``: ρ = 300 kg/m³ (docs/scenes.md), E = 1 MPa, ν = 0.3, μ1 = tan 20° = 0.364 (a low internal
  friction, since the test case prescribes only basal friction), μ2 = tan 30° = 0.577, I0 = 0.279
  and d = 1 mm (the model's defaults scale), grain density 917 kg/m³ (ice), β = 0 (no cohesion),
  p_c0 = 20 kPa (above the 1.5 m slab's ~3.7 kPa basal pressure, so that the snow does not compact
  under its own weight), ξ = 50 (stiff hardening: the volume changes little). With ξ = 0, as
  first chosen, the critical-state model has no volume to settle at: on the dilatant side of
  the cap (p < p_c/2) every shear dilates it further (the median particle volume reached 2.5 V0
  in the deposit), and under an obstacle's impact it compacted without bound (docs/avalanche.md).
- ``"wet"``: the same with cohesion and compressibility: β = 0.1 (tensile strength β p_c0 = 1 kPa,
  the order of wet-snow cohesion), p_c0 = 10 kPa, ξ = 20 (the snow densifies under load).
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from ..boundary import Terrain, Wall
from ..config import Config, Grid
from ..materials import CriticalState
from ..params import Params
from ..sampling import seed_box
from ..state import init_state
from ..step import step_budget
from .base import Scene
from .info import SceneInfo

__all__ = ["SNOW", "DEFAULT_TERRAIN", "OBSTACLE", "avalanche", "default_terrain_path"]

SNOW = {
    "dry": {"rho": 300.0, "rho_s": 917.0, "E": 1.0e6, "nu": 0.3, "mu1": math.tan(math.radians(20.0)),
            "mu2": math.tan(math.radians(30.0)), "I0": 0.279, "d": 1.0e-3, "beta": 0.0, "pc0": 2.0e4, "xi": 50.0},
    "wet": {"rho": 300.0, "rho_s": 917.0, "E": 1.0e6, "nu": 0.3, "mu1": math.tan(math.radians(20.0)),
            "mu2": math.tan(math.radians(30.0)), "I0": 0.279, "d": 1.0e-3, "beta": 0.1, "pc0": 1.0e4, "xi": 20.0},
}
#: The obstacle's place in ``config.walls`` (the terrain is 0).
OBSTACLE = 1
#: The shipped terrain: experiments_data/terrain/iseesnow_coulombonly_centerline.csv.
DEFAULT_TERRAIN = "terrain/iseesnow_coulombonly_centerline"


def default_terrain_path() -> pathlib.Path:
    from ..datasets import dataset_path

    return dataset_path(DEFAULT_TERRAIN)


def avalanche(terrain: str | pathlib.Path | Terrain | None = None, dx: float = 1.0, ppc: int = 2,
              release: tuple[float, float] = (1045.0, 1345.0), thickness: float = 1.5, mu_w: float = 0.4,
              snow: str = "dry", t_end: float = 100.0, frames: int = 100, x_end: float | None = None,
              kind: str = "separable", active_nodes: int | None = None, transfer: str = "aflip",
              obstacle: tuple[float, float] | None = None, dtype=None, **param_values: float) -> Scene:
    """The S6 avalanche. ``terrain``: a CSV path (``x_m,z_m``), a ``Terrain``, or None for the
    shipped ISeeSnow centre line. ``x_end``: where the grid ends downstream (default: the
    terrain's last vertex). ``kind``: the terrain's contact rule (``"separable"``: the snow may
    leave the ground). ``active_nodes``: the sparse grid's slots (default 3^dim per particle,
    the most the particles can touch, so that the grid can never be full). ``obstacle``:
    (station x, height), m: a rigid vertical wall of that height above the terrain at the
    station, facing upstream, 2 dx thick, with the terrain's friction μ_w, as ``config.walls[1]``
    (``OBSTACLE``); its impulse (``state.impulse[OBSTACLE]``) gives the force history on it."""
    if snow not in SNOW:
        raise ValueError(f"snow must be one of {tuple(SNOW)}, got {snow!r}")
    for name, value in (("dx", dx), ("thickness", thickness), ("t_end", t_end)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    if not (isinstance(ppc, int) and ppc >= 1):
        raise ValueError(f"ppc must be a positive integer, got {ppc!r}")
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"frames must be a positive integer (the path fields are sampled on them), got {frames!r}")
    if isinstance(terrain, Terrain):
        ground = Terrain(terrain.x, terrain.z, kind=kind, friction="mu_w")
    else:
        path = default_terrain_path() if terrain is None else terrain
        ground = Terrain.from_csv(path, kind=kind, friction="mu_w")
    xv, zv = np.asarray(ground.x), np.asarray(ground.z)
    x0, x1 = float(release[0]), float(release[1])
    if not (xv[0] <= x0 < x1 <= xv[-1]):
        raise ValueError(f"release must be an interval inside the terrain's x range [{xv[0]}, {xv[-1]}], "
                         f"got {release!r}")
    x_end = float(xv[-1]) if x_end is None else float(x_end)
    if not x1 < x_end:
        raise ValueError(f"x_end must lie beyond the release ({x1} m), got {x_end!r}")
    walls = (ground,)
    if obstacle is not None:
        try:
            station, height = (float(v) for v in obstacle)
        except (TypeError, ValueError):
            raise ValueError(f"obstacle must be (station x, height) in metres, got {obstacle!r}") from None
        if not (x1 < station < x_end - 4 * dx):
            raise ValueError(f"obstacle station must lie between the release's end ({x1} m) and x_end - 4 dx "
                             f"({x_end - 4 * dx} m), got {station!r}")
        if not (math.isfinite(height) and height > 0):
            raise ValueError(f"obstacle height must be a positive number of metres, got {height!r}")
        top = float(ground.height(np.array([station]))[0]) + height
        walls += (Wall((station, top), (-1.0, 0.0), "separable", "mu_w", thickness=2 * dx, edge=(0.0, -1.0)),)
    params = Params.create(dtype=dtype, **{**SNOW[snow], "mu_w": mu_w, **param_values})

    # The release slab: a lattice over its bounding box, kept where 0.5 dx < φ < 0.5 dx + thickness.
    margin = 4 * dx
    top = float(np.max(ground.height(np.linspace(x0, x1, 64)))) + thickness * 2.0 + dx
    low = float(np.min(ground.height(np.linspace(x0, x1, 64)))) - dx
    pts, vol = seed_box((x0, low), (x1, top), dx, ppc)
    phi, _ = ground.signed_distance(np.asarray(pts, float).T)
    keep = (phi > 0.5 * dx) & (phi < 0.5 * dx + thickness)
    pts, vol = np.asarray(pts)[keep], np.asarray(vol)[keep]
    if len(pts) == 0:
        raise ValueError("the release holds no particle: dx is too coarse for the thickness")

    z_lo = (float(np.min(zv[(xv >= x0 - margin) & (xv <= x_end)])) if np.any((xv >= x0) & (xv <= x_end))
            else float(zv.min()))
    z_hi = float(pts[:, 1].max()) + 20.0 * dx + 10.0
    origin = (x0 - margin - 2 * dx, z_lo - margin - 2 * dx)
    cells = (math.ceil((x_end - origin[0]) / dx), math.ceil((z_hi - origin[1]) / dx))
    grid = Grid(cells, dx, origin=origin)
    if active_nodes is None:
        active_nodes = 9 * len(pts)
    speed_bound = math.sqrt(2 * 9.81 * max(1.0, float(zv.max() - zv.min())))  # free fall over the drop
    budget = max(step_budget(CriticalState(), params, dx, t_end, extra=frames + 10),
                 int(1.2 * t_end * speed_bound / (0.5 * dx)) + frames + 10)
    config = Config(grid=grid, t_end=t_end, max_steps=budget, material=CriticalState(), walls=walls,
                    transfer=transfer, frame_times=tuple(t_end * (k + 1) / frames for k in range(frames)),
                    active_nodes=active_nodes)
    info = SceneInfo(dim=2, dx=dx, ppc=ppc, sampling="lattice", front0=x1, length=x1 - x0, height=thickness,
                     wall_gap=0.5 * dx, particles_per_cell=float(ppc * ppc))
    return Scene("avalanche", config, init_state(config, pts, vol, dtype=dtype), params, info)
