"""``SceneInfo``: the typed description of a scene's body and set-up, one name per fact for
every scene (``Scene.info``). Facts that do not apply to a scene are None."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

__all__ = ["SceneInfo"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class SceneInfo:
    """Geometry and set-up facts of a scene, in SI units (lengths in metres, angles in degrees).

    The body's extents are the sampled box's, before it was lifted off the floor: it occupies
    x in [front0 - length, front0] (the collapses: [0, L]) and stands ``wall_gap`` above the floor.
    ``to_dict()`` gives the facts that apply (the non-None ones) as plain JSON values; the run's
    HDF5 attributes and profile headers record that."""

    dim: int
    """Spatial dimension, 2 or 3."""
    dx: float
    """Grid spacing, m."""
    ppc: float
    """Particles per cell along each axis, as asked of the sampler (an integer for lattice and
    jitter sampling, a number >= 1 for Poisson-disk sampling)."""
    sampling: str
    """Particle sampling (``jaxmpm.sampling.SAMPLINGS``: ``"lattice"``, ``"jitter"``, ``"poisson"``)."""
    seed: int | None = None
    """Random seed of the sampling; None where the scene's sampling takes none."""
    front0: float
    """Initial x of the body's front (its largest x), m."""
    length: float
    """The body's extent along x, m: the collapse column's L, the incline's (periodic) strip
    length, the elastic block's width."""
    height: float
    """The body's extent normal to the bed (y; the elastic block's vertical axis), m: the collapse
    column's H, the incline's layer depth, the elastic block's height."""
    width: float | None = None
    """Channel width between the side walls in 3D (the walls' z distance), m; None in 2D and
    without a channel."""
    slope_deg: float = 0.0
    """Bed inclination, degrees (0: a flat bed)."""
    wall_gap: float | None = None
    """How far the body was lifted off the floor (its lower face's height above the bed), m."""
    side_gap: float | None = None
    """Gap between the back wall's plane and the body's back face, m; None without a back wall."""
    particles_per_cell: float | None = None
    """Measured mean particles per cell (all axes together); None where not computed."""
    aspect: float | None = None
    """Aspect ratio H/L of the aspect-ratio scene (S5); None for the other scenes."""
    critical_start: bool | None = None
    """Incline only: whether the particles start at the steady flow's critical state; None elsewhere."""

    def __post_init__(self):
        if self.dim not in (2, 3):
            raise ValueError(f"SceneInfo.dim must be 2 or 3, got {self.dim!r}")
        try:
            dx = float(self.dx)
        except (TypeError, ValueError):
            dx = math.nan
        if not (math.isfinite(dx) and dx > 0):
            raise ValueError(f"SceneInfo.dx must be > 0 (m), got {self.dx!r}")

    def to_dict(self) -> dict[str, Any]:
        """The facts that apply (non-None fields), as plain ``int``/``float``/``str``/``bool``."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}


def _plain(value):
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    return str(value)
