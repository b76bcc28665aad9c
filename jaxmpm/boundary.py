"""Walls: planes of any orientation and moving plates, applied to grid velocities (MODEL.md §5).

A ``Wall`` is static configuration (hashable). Its surface passes through ``point + velocity·t``
with unit ``normal`` pointing from the wall into the material. A grid node is in contact when
its predicted position x_i + dt v_i lies on or behind the surface, within ``thickness`` of it,
and, for a plate with a lower ``edge``, on the plate's side of that edge. In contact, the node
velocity relative to the wall, v_rel = v - v_wall = v_n n + v_t (v_n < 0: moving into the wall),
becomes, by the wall's ``kind`` (the reference code's three types):

- ``"no-slip"``: 0, the node takes the wall's velocity;
- ``"non-separable"`` (the reference code's *slip-stick*): on every contact node the normal part
  is removed and the tangential part gets Coulomb friction, |v_t| <- max(0, |v_t| - μ_w |v_n|).
  Material slides along the wall but never leaves it. Friction is charged on every contact
  node, whatever the sign of v_n, as the reference code does on its plates (its general objects
  charge it only where v_n < 0);
- ``"separable"`` (the reference code's *slip-free*): only where v_n < 0 (pressed against the
  wall), the normal part is removed and the same Coulomb friction applies with the wall's own
  μ_w (0 by default: a frictionless gate); elsewhere the node is left alone, so material can
  separate from the wall.

``friction`` is μ_w. The reference code's names ``"slip-stick"`` and ``"slip-free"`` are
accepted and stored as ``"non-separable"`` and ``"separable"``.

A gate lifted at speed U is ``Wall(point=(x_g, floor), normal=(-1, 0), kind="separable",
velocity=(0, U), edge=(0, 1), thickness=...)``: it extends upwards from its lower edge, which
starts on the floor and rises with it, so material escapes beneath it.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

__all__ = ["Wall", "KINDS", "KIND_ALIASES", "apply_walls"]

KINDS = ("no-slip", "non-separable", "separable")
#: The reference code's names for the same types.
KIND_ALIASES = {"slip-stick": "non-separable", "slip-free": "separable"}


def _as_vector(name, value, dim=None):
    try:
        vec = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of numbers, got {value!r}") from None
    if len(vec) not in (2, 3) or (dim is not None and len(vec) != dim):
        want = dim if dim is not None else "2 or 3"
        raise ValueError(f"{name} must have {want} components, got {value!r}")
    if not all(math.isfinite(c) for c in vec):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return vec


def _unit(name, value, dim):
    vec = _as_vector(name, value, dim)
    norm = math.sqrt(sum(c * c for c in vec))
    if norm == 0:
        raise ValueError(f"{name} must be a non-zero vector, got {value!r}")
    return tuple(c / norm for c in vec)


@dataclasses.dataclass(frozen=True)
class Wall:
    """A plane or a moving plate. See the module docstring for the contact rules."""

    point: tuple[float, ...]
    normal: tuple[float, ...]
    kind: str = "no-slip"
    friction: float = 0.0
    velocity: tuple[float, ...] | None = None
    thickness: float = math.inf
    edge: tuple[float, ...] | None = None

    def __post_init__(self):
        point = _as_vector("Wall.point", self.point)
        dim = len(point)
        setter = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        setter("point", point)
        setter("normal", _unit("Wall.normal", self.normal, dim))
        velocity = (0.0,) * dim if self.velocity is None else self.velocity
        setter("velocity", _as_vector("Wall.velocity", velocity, dim))
        if self.edge is not None:
            setter("edge", _unit("Wall.edge", self.edge, dim))
        kind = KIND_ALIASES.get(self.kind, self.kind)
        if kind not in KINDS:
            raise ValueError(f"Wall.kind must be one of {KINDS} (or the reference code's "
                             f"{tuple(KIND_ALIASES)}), got {self.kind!r}")
        setter("kind", kind)
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"Wall.friction must be finite and >= 0, got {self.friction!r}")
        if not self.thickness > 0:
            raise ValueError(f"Wall.thickness must be > 0, got {self.thickness!r}")

    @property
    def dim(self) -> int:
        return len(self.point)

    @property
    def moving(self) -> bool:
        return any(c != 0.0 for c in self.velocity)


def _coulomb(vt, vn, friction):
    """|v_t| <- max(0, |v_t| - μ_w |v_n|) along v_t's own direction.

    Written with selects, not max(0, ·) of a ratio: JAX differentiates max by multiplying with
    a 0/1 mask, so a ratio whose derivative overflows where |v_t| -> 0 (stuck nodes) would turn
    0 · inf into a NaN tangent. Here a stuck node's tangent is exactly 0 and the ratio is only
    formed where |v_t| > (smallest normal)^(1/4), where its derivative is finite."""
    if friction == 0.0:
        return vt
    vt2 = jnp.sum(vt * vt, axis=0, keepdims=True)
    limit = friction * jnp.abs(vn)
    slides = vt2 > limit * limit
    safe = slides & (vt2 > jnp.sqrt(jnp.finfo(vt.dtype).tiny))
    scale = 1.0 - limit * jax.lax.rsqrt(jnp.where(safe, vt2, 1.0))
    return vt * jnp.where(safe, scale, jnp.where(slides, 1.0, 0.0))


def _contact_velocity(wall: Wall, v_rel, normal):
    """Relative velocity (dim, n_nodes) after the contact rule, for nodes in contact."""
    if wall.kind == "no-slip":
        return jnp.zeros_like(v_rel)
    vn = jnp.sum(v_rel * normal, axis=0, keepdims=True)
    vt = _coulomb(v_rel - vn * normal, vn, wall.friction)
    if wall.kind == "non-separable":
        return vt
    return jnp.where(vn < 0, vt, v_rel)  # separable


def apply_walls(walls, v, node_x, t, dt):
    """Apply every wall in order to grid velocities ``v`` (dim, n_nodes) at nodes ``node_x``
    (dim, n_nodes), at time ``t`` for a step of ``dt``."""
    for wall in walls:
        dtype = v.dtype
        normal = jnp.asarray(wall.normal, dtype)[:, None]
        wall_v = jnp.asarray(wall.velocity, dtype)[:, None]
        point = jnp.asarray(wall.point, dtype)[:, None] + (t * wall_v if wall.moving else 0.0)
        signed = jnp.sum((node_x + dt * v - point) * normal, axis=0)
        contact = signed <= 0
        if math.isfinite(wall.thickness):
            contact &= signed > -wall.thickness
        if wall.edge is not None:
            edge = jnp.asarray(wall.edge, dtype)[:, None]
            contact &= jnp.sum((node_x - point) * edge, axis=0) >= 0
        v = jnp.where(contact, _contact_velocity(wall, v - wall_v, normal) + wall_v, v)
    return v
