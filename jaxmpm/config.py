"""Static configuration: hashable Python. Changing any of it means a new compilation.

``Grid`` is the dense background grid; ``Config`` adds the material model, walls, gravity,
transfer scheme, time-step controls, output times and the step budget.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .boundary import SideWalls, Terrain, Wall
from .materials.base import Material
from .materials.hencky import Hencky

__all__ = ["Grid", "Config", "TRANSFERS"]

TRANSFERS = ("pic", "apic", "aflip")


@dataclasses.dataclass(frozen=True)
class Grid:
    """A dense grid of ``cells`` cells per axis with spacing ``dx``; nodes at origin + i·dx.

    Particles must stay in the interior band [origin + dx/2, origin + (cells - 1/2)·dx) of each
    axis, where their 3-node quadratic stencil lies inside the grid. A ``periodic`` axis has
    ``cells`` nodes that wrap around, and positions wrap into [origin, origin + cells·dx).
    """

    cells: tuple[int, ...]
    dx: float
    origin: tuple[float, ...] | None = None
    periodic: tuple[bool, ...] | None = None

    def __post_init__(self):
        try:
            cells = tuple(int(c) for c in self.cells)
        except (TypeError, ValueError):
            raise ValueError(f"cells must be a sequence of integers, got {self.cells!r}") from None
        if len(cells) not in (2, 3):
            raise ValueError(f"cells must have 2 or 3 entries (the dimension), got {self.cells!r}")
        if any(c < 2 for c in cells) or any(c != c0 for c, c0 in zip(cells, self.cells)):
            raise ValueError(f"cells must be integers >= 2, got {self.cells!r}")
        try:
            dx = float(self.dx)
        except (TypeError, ValueError):
            raise ValueError(f"dx must be a number, got {self.dx!r}") from None
        if not (math.isfinite(dx) and dx > 0):
            raise ValueError(f"dx must be > 0 and finite, got {self.dx!r}")
        origin = (0.0,) * len(cells) if self.origin is None else tuple(float(o) for o in self.origin)
        if len(origin) != len(cells) or not all(math.isfinite(o) for o in origin):
            raise ValueError(f"origin must be {len(cells)} finite numbers, got {self.origin!r}")
        periodic = (False,) * len(cells) if self.periodic is None else tuple(bool(p) for p in self.periodic)
        if len(periodic) != len(cells):
            raise ValueError(f"periodic must have {len(cells)} entries, got {self.periodic!r}")
        if any(p and c < 3 for p, c in zip(periodic, cells)):
            raise ValueError(f"a periodic axis needs at least 3 cells, got cells={cells}")
        object.__setattr__(self, "cells", cells)
        object.__setattr__(self, "dx", dx)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "periodic", periodic)

    @property
    def dim(self) -> int:
        return len(self.cells)

    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(c if p else c + 1 for c, p in zip(self.cells, self.periodic))

    @property
    def n_nodes(self) -> int:
        return int(np.prod(self.nodes))

    @property
    def length(self) -> np.ndarray:
        return np.asarray(self.cells) * self.dx

    def _band(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        origin, periodic = np.asarray(self.origin), np.asarray(self.periodic)
        lower = np.where(periodic, origin, origin + margin * self.dx)
        upper = np.where(periodic, origin + self.length, origin + self.length - margin * self.dx)
        return lower, upper

    @property
    def lower(self) -> np.ndarray:
        """Lowest particle position allowed, per axis."""
        return self._band(0.5)[0]

    @property
    def upper(self) -> np.ndarray:
        """Particle positions must stay strictly below this, per axis."""
        return self._band(0.5)[1]

    @property
    def edge_band(self) -> tuple[np.ndarray, np.ndarray]:
        """Particles outside [lower, upper) of this band are within 1.5 cells of the grid's edge
        (non-periodic axes): the flow has reached the edge of the domain (``state.EDGE``)."""
        return self._band(1.5)

    def outside(self, x) -> np.ndarray:
        """Mask of particles (..., N) that lie outside the allowed band."""
        x = np.asarray(x)
        return np.any((x < self.lower) | (x >= self.upper), axis=-1)

    def node_positions(self) -> np.ndarray:
        """(n_nodes, dim) node coordinates in the flat (row-major) order used by the transfers."""
        axes = [self.origin[a] + self.dx * np.arange(n) for a, n in enumerate(self.nodes)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=-1)


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything static about a run.

    Attributes:
      grid: the background grid.
      t_end: end time (s). Steps after it do nothing.
      max_steps: step budget of the fixed-length scan; the ``BUDGET`` status bit is set if the
        run ends before ``t_end``.
      material: the constitutive model.
      walls: planes, moving plates and terrains (``boundary.Terrain``), applied in order.
      gravity: gravity vector (m/s^2); a slope is a rotated gravity.
      transfer: ``"aflip"`` (AFLIP blend with ``alpha``; alpha = 0 is APIC), ``"apic"`` or
        ``"pic"`` (no affine matrix).
      alpha: FLIP fraction of the AFLIP blend, in [0, 1].
      xpic: 0 (default) or the order m >= 1 of an XPIC(m) filter on the FLIP part of the AFLIP
        update (``transfer.xpic_velocity``): removes the particle-velocity noise the grid cannot
        see, at the cost of m − 1 extra transfers per step.
      cfl, cfl_elastic: time step dt = min(cfl·dx/max|v_p|, cfl_elastic·dx/sqrt(E/ρ)).
      frame_times: output times (s), increasing, in [0, t_end]; steps are clipped to land on them.
      block_size: steps per checkpointed block of the rollout (None: about sqrt(max_steps)).
      active_nodes: None (default): the dense grid. An integer K: a grid only where the material
        is, K slots for the nodes that the particles' stencils touch, found every step
        (``jaxmpm.sparse``); the ``GRID_FULL`` status bit is set when more are touched. The cost
        then follows the particles, not the bounding box.
      rest_speed, rest_duration: a run that stops when the flow stops. None (default): every
        run goes to t_end. A speed (m/s): once every particle has been slower than it for
        ``rest_duration`` seconds of simulated time, the material is at rest and the remaining
        steps do nothing but carry the state to the frame times and t_end (``State.quiet_since``
        records when the quiet began). No particle moved faster than ``rest_speed`` during
        the last ``rest_duration``; one creeping at that speed would have gone on by at most
        ``rest_speed`` × the time skipped.
      side_walls: None (default), or ``boundary.SideWalls``: the friction of a channel's two side
        walls on a 2D run, averaged over its width (2D only).
    """

    grid: Grid
    t_end: float
    max_steps: int
    material: Material = Hencky()
    walls: tuple[Wall | Terrain, ...] = ()
    gravity: tuple[float, ...] | None = None
    transfer: str = "aflip"
    alpha: float = 0.95
    xpic: int = 0
    cfl: float = 0.5
    cfl_elastic: float = 0.5
    frame_times: tuple[float, ...] = ()
    block_size: int | None = None
    active_nodes: int | None = None
    rest_speed: float | None = None
    rest_duration: float = 0.0
    side_walls: SideWalls | None = None

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        if not isinstance(self.grid, Grid):
            raise ValueError(f"grid must be a Grid, got {type(self.grid).__name__}")
        dim = self.grid.dim
        if not isinstance(self.material, Material):
            raise ValueError(f"material must be a Material, got {self.material!r}")
        walls = tuple(self.walls)
        for i, wall in enumerate(walls):
            if not isinstance(wall, (Wall, Terrain)):
                raise ValueError(f"walls[{i}] must be a Wall or a Terrain, got {wall!r}")
            if wall.dim != dim:
                raise ValueError(f"walls[{i}] is {wall.dim}D but the grid is {dim}D")
        set_("walls", walls)
        gravity = (0.0, -9.81, 0.0)[:dim] if dim == 2 else (0.0, 0.0, -9.81)
        gravity = gravity if self.gravity is None else tuple(float(g) for g in self.gravity)
        if len(gravity) != dim or not all(math.isfinite(g) for g in gravity):
            raise ValueError(f"gravity must be {dim} finite numbers, got {self.gravity!r}")
        set_("gravity", gravity)
        if self.transfer not in TRANSFERS:
            raise ValueError(f"transfer must be one of {TRANSFERS}, got {self.transfer!r}")
        if not 0.0 <= float(self.alpha) <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {self.alpha!r}")
        if not (isinstance(self.xpic, int) and 0 <= self.xpic <= 8):
            raise ValueError(f"xpic must be an integer order in [0, 8] (0: off), got {self.xpic!r}")
        for name in ("cfl", "cfl_elastic"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        t_end = float(self.t_end)
        if not (math.isfinite(t_end) and t_end > 0):
            raise ValueError(f"t_end must be > 0 and finite, got {self.t_end!r}")
        set_("t_end", t_end)
        if int(self.max_steps) != self.max_steps or self.max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {self.max_steps!r}")
        set_("max_steps", int(self.max_steps))
        frames = tuple(float(f) for f in self.frame_times)
        if any(not (0.0 <= f <= t_end) for f in frames):
            raise ValueError(f"frame_times must lie in [0, t_end={t_end}], got {self.frame_times!r}")
        if any(b <= a for a, b in zip(frames, frames[1:])):
            raise ValueError(f"frame_times must be strictly increasing, got {self.frame_times!r}")
        set_("frame_times", frames)
        if self.block_size is not None and (int(self.block_size) != self.block_size or self.block_size < 1):
            raise ValueError(f"block_size must be a positive integer or None, got {self.block_size!r}")
        if self.active_nodes is not None:
            if (isinstance(self.active_nodes, bool) or int(self.active_nodes) != self.active_nodes
                    or self.active_nodes < 1):
                raise ValueError(f"active_nodes must be a positive integer or None, got {self.active_nodes!r}")
            set_("active_nodes", int(self.active_nodes))
        if self.rest_speed is not None:
            speed = float(self.rest_speed)
            if not (math.isfinite(speed) and speed > 0):
                raise ValueError(f"rest_speed must be > 0 and finite (m/s) or None, got {self.rest_speed!r}")
            set_("rest_speed", speed)
        duration = float(self.rest_duration)
        if not (math.isfinite(duration) and duration >= 0):
            raise ValueError(f"rest_duration must be >= 0 and finite (s), got {self.rest_duration!r}")
        set_("rest_duration", duration)
        if self.side_walls is not None:
            if not isinstance(self.side_walls, SideWalls):
                raise ValueError(f"side_walls must be a SideWalls or None, got {type(self.side_walls).__name__}")
            if dim != 2:
                raise ValueError("side_walls is the 2D model of a channel's walls; a 3D run has the walls themselves")
        if self.grid.n_nodes >= 2**31 - 1:
            raise ValueError(f"the grid has {self.grid.n_nodes} nodes; node numbers must fit in int32 (< 2**31 - 1)")

    @property
    def reads_mu_w(self) -> bool:
        """Whether a boundary takes its friction from ``Params.mu_w`` (declared ``friction="mu_w"``):
        only then does μ_w change a run."""
        boundaries = tuple(self.walls) + ((self.side_walls,) if self.side_walls is not None else ())
        return any(getattr(b, "friction", None) == "mu_w" for b in boundaries)

    @property
    def dim(self) -> int:
        return self.grid.dim

    @property
    def blocks(self) -> tuple[int, int]:
        """(number of blocks, steps per block); their product is >= max_steps."""
        size = self.block_size or max(1, int(round(math.sqrt(self.max_steps))))
        size = min(size, self.max_steps)
        return -(-self.max_steps // size), size

    @property
    def stop_times(self) -> tuple[float, ...]:
        """Times that steps must land on exactly: the frame times and the end time."""
        return tuple(sorted(set(self.frame_times) | {self.t_end}))

    def to_dict(self) -> dict:
        """A JSON-ready description (for HDF5 attributes and reports)."""

        def plain(obj):
            if dataclasses.is_dataclass(obj):
                return {"type": type(obj).__name__,
                        **{f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
            if isinstance(obj, (tuple, list)):
                return [plain(o) for o in obj]
            if isinstance(obj, float) and not math.isfinite(obj):
                return str(obj)
            return obj

        return plain(self)
