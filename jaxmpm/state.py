"""The simulation state (a pytree of arrays), its status bits, and particle seeding.

Glossary: x positions, v velocities, C the APIC affine matrix, F the elastic deformation
gradient F_e, tau the Kirchhoff stress from the last constitutive update (update-stress-last),
vol0 initial particle volumes V0, internal the material's internal variables, t the time,
steps the number of steps taken, status a bitmask (below), dt the last step size, impulse the
momentum each of the configuration's walls and terrains has received from the material since t = 0
((n_walls, dim), N·s, per unit width in 2D): the force on a wall over an interval is the change of
its impulse over the interval's length, quiet_since the time since which every particle has been
slower than the configuration's rest speed (inf while any is faster, or without a rest speed).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .config import Config
from .sampling import seed_box  # noqa: F401 (re-exported: the public name predates sampling.py)

__all__ = [
    "State",
    "LEFT_GRID",
    "NONFINITE",
    "J_NONPOSITIVE",
    "BUDGET",
    "EDGE",
    "GRID_FULL",
    "STATUS_BITS",
    "describe_status",
    "init_state",
    "seed_box",
]

# Status bits, OR-ed over the run.
LEFT_GRID = 1  # a particle left the grid interior where its stencil fits
NONFINITE = 2  # a non-finite position, velocity or stress appeared
J_NONPOSITIVE = 4  # det(F_e trial) <= 0: a particle was inverted or crushed
BUDGET = 8  # the step budget ran out before t_end
EDGE = 16  # the flow came within 1.5 cells of the grid's edge: the domain is too small
GRID_FULL = 32  # the particles touched more nodes than the sparse grid's active_nodes slots
STATUS_BITS = {
    LEFT_GRID: "a particle left the grid (enlarge the grid or add walls)",
    NONFINITE: "non-finite state (reduce cfl/cfl_elastic or check parameters)",
    J_NONPOSITIVE: "det(F_e) <= 0 (the time step is too large for the deformation)",
    BUDGET: "the step budget max_steps ran out before t_end (raise max_steps)",
    EDGE: "the flow reached the edge of the grid (enlarge the domain)",
    GRID_FULL: "the particles touched more grid nodes than active_nodes holds (raise active_nodes)",
}


def describe_status(status: int) -> list[str]:
    """Plain-language descriptions of the bits set in ``status``."""
    return [text for bit, text in STATUS_BITS.items() if int(status) & bit]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """The particles and the clock, a pytree of arrays that evolves step by step: positions,
    velocities, affine matrices, elastic deformation gradients, Kirchhoff stresses, initial volumes,
    the material's internal variables, time, step, step count, status bits, the walls' impulse and
    the time since which the flow has been at rest (each field as the module's docstring says)."""

    x: Any
    v: Any
    C: Any
    F: Any
    tau: Any
    vol0: Any
    internal: Any
    t: Any
    dt: Any
    steps: Any
    status: Any
    impulse: Any
    quiet_since: Any

    @property
    def n_particles(self) -> int:
        return self.x.shape[-2]

    def replace(self, **values) -> State:
        return dataclasses.replace(self, **values)


def init_state(config: Config, x, vol0, v=None, dtype=None) -> State:
    """A stress-free initial state (F_e = I, C = 0) with validated positions and volumes.

    Raises ``ValueError`` (before any tracing) for an empty scene, wrong shapes, non-finite
    values, non-positive volumes, or particles outside the grid interior.
    """
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.zeros(()).dtype
    x = np.asarray(x, dtype=float)
    dim = config.dim
    if x.ndim != 2 or x.shape[1] != dim:
        raise ValueError(f"x must have shape (n_particles, {dim}), got {x.shape}")
    n = x.shape[0]
    if n == 0:
        raise ValueError("x is empty: the scene has no particles")
    vol0 = np.broadcast_to(np.asarray(vol0, dtype=float), (n,))
    v = np.zeros_like(x) if v is None else np.broadcast_to(np.asarray(v, dtype=float), x.shape)
    for name, arr in (("x", x), ("vol0", vol0), ("v", v)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite; {int(np.sum(~np.isfinite(arr)))} entries are not")
    if np.any(vol0 <= 0):
        raise ValueError(f"vol0 must be > 0, got min {vol0.min()!r}")
    lower, upper = config.grid.lower, config.grid.upper
    outside = config.grid.outside(x)
    if np.any(outside):
        i = int(np.argmax(outside))
        raise ValueError(
            f"x: {int(outside.sum())} particle(s) lie outside the grid interior "
            f"[{lower.tolist()}, {upper.tolist()}) at t = 0, e.g. particle {i} at {x[i].tolist()}"
        )
    eye = np.broadcast_to(np.eye(dim), (n, dim, dim))
    return State(
        x=jnp.asarray(x, dtype),
        v=jnp.asarray(v, dtype),
        C=jnp.zeros((n, dim, dim), dtype),
        F=jnp.asarray(eye, dtype),
        tau=jnp.zeros((n, dim, dim), dtype),
        vol0=jnp.asarray(vol0, dtype),
        internal=config.material.init_internal(n, dtype),
        t=jnp.zeros((), dtype),
        dt=jnp.zeros((), dtype),
        steps=jnp.zeros((), jnp.int32),
        status=jnp.zeros((), jnp.int32),
        impulse=jnp.zeros((len(config.walls), dim), dtype),
        quiet_since=jnp.full((), jnp.inf, dtype),
    )
