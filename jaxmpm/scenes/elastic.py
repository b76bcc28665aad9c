"""An elastic block falling onto a no-slip floor and bouncing: the engine's smoke and speed test."""

from __future__ import annotations

import math

from ..boundary import Wall
from ..config import Config, Grid
from ..materials.hencky import Hencky
from ..params import Params
from ..sampling import seed_box
from ..state import init_state
from ..step import step_budget
from .base import Scene
from .info import SceneInfo

__all__ = ["falling_block"]


def falling_block(
    n_particles: int = 10_000,
    dim: int = 2,
    t_end: float = 0.39,
    max_steps: int | None = None,
    frames: int = 0,
    transfer: str = "aflip",
    dtype=None,
    **param_values: float,
):
    """A square (cube) Hencky-elastic block of about ``n_particles`` particles, 2 per cell and axis,
    released 0.1 block-widths above a no-slip floor, in a grid that just holds its bounce.

    The block is 0.5 m wide; dx follows from ``n_particles``. With the default E = 1e6 Pa and
    ρ = 1550 kg/m³ the elastic time step bound sets dt, and t_end = 0.39 s takes about 2,000 steps
    at 10,000 particles. ``frames`` evenly spaced output times are recorded (0: none).
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    if not n_particles >= 2**dim:
        raise ValueError(f"n_particles must be >= {2**dim}, got {n_particles!r}")
    width = 0.5
    cells_across = max(2, round((n_particles / 2**dim) ** (1.0 / dim)))
    dx = width / cells_across
    floor = 4 * dx
    lift = 0.1 * width
    span = 2 * width  # room for lateral spreading and the bounce
    cells = [math.ceil(span / dx)] * (dim - 1) + [math.ceil((floor + lift + 1.6 * width) / dx)]
    grid = Grid(tuple(cells), dx)
    lower = [0.5 * (span - width)] * (dim - 1) + [floor + lift]
    upper = [lo + width for lo in lower]
    up = (0.0,) * (dim - 1) + (1.0,)
    point = (0.0,) * (dim - 1) + (floor,)
    if max_steps is None:
        max_steps = step_budget(Hencky(), Params.create(**param_values), dx, t_end, margin=1.2)
    config = Config(
        grid=grid,
        t_end=t_end,
        max_steps=max_steps,
        walls=(Wall(point, up, "no-slip"),),
        transfer=transfer,
        frame_times=tuple(t_end * (k + 1) / frames for k in range(frames)),
    )
    x, vol = seed_box(lower, upper, dx, 2)
    state = init_state(config, x, vol, dtype=dtype)
    info = SceneInfo(dim=dim, dx=dx, ppc=2, sampling="lattice", front0=float(upper[0]), length=width,
                     height=width, wall_gap=lift)
    return Scene("elastic-block", config, state, Params.create(dtype=dtype, **param_values), info)
