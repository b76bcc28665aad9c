"""S2 of SCENES.md: a granular column collapsing between two lifted gates."""

from __future__ import annotations

import math

from ..boundary import Wall
from ..config import Config, Grid
from ..materials.critical_state import CriticalState
from ..params import Params
from ..state import init_state, seed_box

__all__ = ["gates_collapse", "S2_PARAMS"]

#: SCENES.md S2 material (other keys take MODEL.md defaults: E = 1e6, nu = 0.3, rho = 1550,
#: rho_s = 2500, mu1 = tan 20.9°, mu2 = tan 32.76°, I0 = 0.279).
S2_PARAMS = {"d": 2e-3, "beta": 0.0, "pc0": 100.0, "xi": 50.0}


def gates_collapse(
    dx: float = 0.0025,
    ppc: int = 2,
    t_end: float = 0.4198,
    frames: int = 0,
    gate_speed: float = 0.45,
    runout: float = 0.09,
    max_steps: int | None = None,
    dtype=None,
    **param_values: float,
):
    """A 0.08 m × 0.05 m column on a no-slip floor between two slip-free gates lifted at
    ``gate_speed`` (SCENES.md S2). The grid spans ``runout`` metres beyond each gate (the flow
    reaches about 0.07 m at t = 0.42 s) and a few cells above the column. Coordinates: column on
    [x_left, x_left + 0.08] × [floor, floor + 0.05]."""
    width, height = 0.08, 0.05
    if not dx > 0:
        raise ValueError(f"dx must be > 0, got {dx!r}")
    params = Params.create(dtype=dtype, **{**S2_PARAMS, **param_values})
    floor = 3 * dx
    x_left = floor + runout
    cells = (math.ceil((2 * x_left + width) / dx), math.ceil((floor + height + 4 * dx) / dx))
    gate = dict(kind="slip-free", velocity=(0.0, gate_speed), edge=(0.0, 1.0), thickness=2 * dx)
    walls = (
        Wall((0.0, floor), (0.0, 1.0), "no-slip"),
        Wall((x_left, floor), (1.0, 0.0), **gate),
        Wall((x_left + width, floor), (-1.0, 0.0), **gate),
    )
    if max_steps is None:
        dt = 0.5 * dx / math.sqrt(float(params.E) / float(params.rho))
        max_steps = int(1.25 * t_end / dt) + frames + 10
    config = Config(
        grid=Grid(cells, dx), t_end=t_end, max_steps=max_steps, walls=walls, material=CriticalState(),
        frame_times=tuple(t_end * (k + 1) / frames for k in range(frames)),
    )
    x, vol = seed_box((x_left, floor), (x_left + width, floor + height), dx, ppc)
    return config, init_state(config, x, vol, dtype=dtype), params
