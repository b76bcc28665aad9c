"""Walls: planes of any orientation and moving plates, applied to grid velocities (docs/model.md §5).

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

``friction`` is μ_w: a number (static configuration), or the string ``"mu_w"``, which takes it
from the parameter ``Params.mu_w`` so that it can be differentiated and calibrated. The
reference code's names ``"slip-stick"`` and ``"slip-free"`` are
accepted and stored as ``"non-separable"`` and ``"separable"``.

A gate lifted at speed U is ``Wall(point=(x_g, floor), normal=(-1, 0), kind="separable",
velocity=(0, U), edge=(0, 1), thickness=...)``: it extends upwards from its lower edge, which
starts on the floor and rises with it, so material escapes beneath it.

A ``Terrain`` is a ground of any shape (docs/scenes.md S6): the graph z = h(x) of a polyline with
strictly increasing x (distance along the path, elevation), extruded along y in 3D. It acts
through the same contact rules, with its own kind and friction, on the signed distance
φ(p) = (p_z − h(p_x)) n_z and the normal n ∝ (−s(p_x), 1), where s is the slope interpolated
linearly between the vertices' slopes (each vertex takes the mean of its two segments'), so
that the normal is continuous across vertices. The sign of φ is exact (it is the side of the
polyline the point lies on); on a straight stretch φ is the exact distance and n the exact
normal, wherever the vertices fall; near a bend φ is first-order accurate, which is all the
contact test (φ ≤ 0) needs. Beyond the end vertices the end segments are extended.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .linalg import safe_div

__all__ = ["Wall", "Terrain", "SideWalls", "KINDS", "KIND_ALIASES", "apply_walls", "side_wall_friction",
           "friction_value"]

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


def _check_kind(owner, kind):
    kind = KIND_ALIASES.get(kind, kind)
    if kind not in KINDS:
        raise ValueError(f"{owner}.kind must be one of {KINDS} (or the reference code's "
                         f"{tuple(KIND_ALIASES)}), got {kind!r}")
    return kind


def _check_friction(owner, friction):
    if isinstance(friction, str):
        if friction != "mu_w":
            raise ValueError(f"{owner}.friction must be a number >= 0 or the parameter name 'mu_w', got {friction!r}")
        return friction
    try:
        value = float(friction)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.friction must be a number >= 0 or 'mu_w', got {friction!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{owner}.friction must be finite and >= 0, got {friction!r}")
    return value


@dataclasses.dataclass(frozen=True)
class SideWalls:
    """The two side walls of a channel ``width`` apart (m), across a 2D (plane-strain) run.

    Their Coulomb friction ``friction`` (μ_w), averaged over the width, acts on every grid node
    against its velocity with magnitude 2 μ_w K p / W per unit volume: p ≥ 0 is the material's
    pressure at the node, K = ``lateral_pressure_ratio`` the ratio of the walls' normal stress to
    p, W the width. It is applied implicitly (``side_wall_friction``): it can stop a node, never
    reverse it. The plug-flow and K p assumptions, and where they fail: docs/model.md §5.
    ``friction`` is a number, or ``"mu_w"``: the parameter ``Params.mu_w``, so that it can be
    differentiated and fitted (shared with every other boundary declared so)."""

    width: float
    friction: float | str
    lateral_pressure_ratio: float = 1.0

    def __post_init__(self):
        if isinstance(self.friction, str):
            _check_friction("SideWalls", self.friction)
        for name, low, value in (("width", 0.0, self.width), ("friction", None, self.friction),
                                 ("lateral_pressure_ratio", None, self.lateral_pressure_ratio)):
            if name == "friction" and isinstance(value, str):
                continue
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"SideWalls.{name} must be a number, got {value!r}") from None
            if not (math.isfinite(number) and (number > low if low is not None else number >= 0)):
                raise ValueError(f"SideWalls.{name} must be finite and {'> 0' if low is not None else '>= 0'}, "
                                 f"got {value!r}")
            object.__setattr__(self, name, number)


def friction_value(friction, params, dtype, owner: str = "SideWalls"):
    """A boundary's μ_w: its number, or ``params.mu_w`` where it is declared ``"mu_w"`` (an error
    naming ``owner`` without ``params``)."""
    if isinstance(friction, str):
        if params is None:
            raise ValueError(f"{owner} friction 'mu_w' needs the parameters (params=None)")
        return jnp.asarray(params.mu_w, dtype)
    return friction


def side_wall_friction(side: SideWalls, v, pressure, mass, dt, params=None):
    """Node velocities ``v`` (dim, n) after the side walls' friction over ``dt``: |v| <- max(|v| - c,
    0), the direction kept, with c = 2 μ_w K dt P / (W m), P = Σ_p w_ip V_p max(p_p, 0) the node's
    pressure times its volume and m its mass (c = 0 where m = 0); μ_w from ``params`` where the
    walls' friction is ``"mu_w"``. Finite derivatives at v = 0."""
    friction = friction_value(side.friction, params, v.dtype)
    c = (2.0 * friction * side.lateral_pressure_ratio * dt / side.width) * safe_div(pressure, mass)
    speed2 = jnp.sum(v * v, axis=0)
    moving = speed2 > 0
    speed = jnp.sqrt(jnp.where(moving, speed2, 1.0))
    return v * jnp.where(moving & (speed > c), 1.0 - c / speed, 0.0)


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
        setter("kind", _check_kind("Wall", self.kind))
        setter("friction", _check_friction("Wall", self.friction))
        if not self.thickness > 0:
            raise ValueError(f"Wall.thickness must be > 0, got {self.thickness!r}")

    @property
    def dim(self) -> int:
        return len(self.point)

    @property
    def moving(self) -> bool:
        return any(c != 0.0 for c in self.velocity)


@dataclasses.dataclass(frozen=True)
class Terrain:
    """A frictional ground of any shape: the graph of the polyline (``x``, ``z``), x strictly
    increasing, extruded along y when ``dim`` = 3. Contact, kinds and friction as for ``Wall``
    (default ``"non-separable"``: the snow slides on the ground and never leaves it; use
    ``"separable"`` to let it take off). See the module docstring for φ and the normal."""

    x: tuple[float, ...]
    z: tuple[float, ...]
    kind: str = "non-separable"
    friction: float | str = 0.0
    dim: int = 2
    thickness: float = math.inf

    def __post_init__(self):
        setter = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        x, z = _as_floats("Terrain.x", self.x), _as_floats("Terrain.z", self.z)
        if len(x) != len(z):
            raise ValueError(f"Terrain.x and Terrain.z must have the same length, got {len(x)} and {len(z)}")
        if len(x) < 2:
            raise ValueError(f"Terrain needs at least 2 vertices, got {len(x)}")
        bad = [i for i in range(len(x) - 1) if not x[i + 1] > x[i]]
        if bad:
            i = bad[0]
            raise ValueError(f"Terrain.x must increase strictly (the terrain is the graph z = h(x)), "
                             f"got x[{i}] = {x[i]!r} and x[{i + 1}] = {x[i + 1]!r}")
        setter("x", x)
        setter("z", z)
        setter("kind", _check_kind("Terrain", self.kind))
        setter("friction", _check_friction("Terrain", self.friction))
        if self.dim not in (2, 3):
            raise ValueError(f"Terrain.dim must be 2 or 3, got {self.dim!r}")
        if not self.thickness > 0:
            raise ValueError(f"Terrain.thickness must be > 0, got {self.thickness!r}")

    @classmethod
    def from_csv(cls, path, **kwargs) -> Terrain:
        """A terrain from a CSV of ``x_m, z_m`` rows (the project's table format: ``#`` header
        lines, then the column names)."""
        from .tables import read_columns

        _, columns = read_columns(path, required=("x_m", "z_m"))
        return cls(tuple(columns["x_m"]), tuple(columns["z_m"]), **kwargs)

    @property
    def moving(self) -> bool:
        return False

    def height(self, x):
        """h(x), the polyline's elevation (end segments extended), for numpy or JAX arrays."""
        return self._evaluate(x)[0]

    def _evaluate(self, px):
        xp = jnp if isinstance(px, jax.Array) else np
        px = px if xp is jnp else np.asarray(px, float)
        xv, zv = xp.asarray(self.x, px.dtype), xp.asarray(self.z, px.dtype)
        seg = (zv[1:] - zv[:-1]) / (xv[1:] - xv[:-1])
        vertex = xp.concatenate([seg[:1], 0.5 * (seg[1:] + seg[:-1]), seg[-1:]])
        k = xp.clip(xp.searchsorted(xv, px, side="right") - 1, 0, len(self.x) - 2)
        t = (px - xv[k]) / (xv[k + 1] - xv[k])
        h = zv[k] + t * (zv[k + 1] - zv[k])
        tc = xp.clip(t, 0.0, 1.0)
        return h, vertex[k] + tc * (vertex[k + 1] - vertex[k])

    def signed_distance(self, p):
        """(φ, n) at points ``p`` (dim, n): φ > 0 above the ground, n the unit normal, (dim, n).
        A jax array gives jax arrays (traced inside the step); anything else numpy, in float64
        (for scene set-up, before tracing)."""
        xp = jnp if isinstance(p, jax.Array) else np
        p = p if xp is jnp else np.asarray(p, float)
        h, s = self._evaluate(p[0])
        inv = jax.lax.rsqrt(1.0 + s * s) if xp is jnp else 1.0 / np.sqrt(1.0 + s * s)
        comps = [-s * inv] + [xp.zeros_like(s)] * (p.shape[0] - 2) + [inv]
        return (p[-1] - h) * inv, xp.stack(comps)


def _as_floats(name, value):
    try:
        out = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of numbers, got {value!r}") from None
    if not all(math.isfinite(c) for c in out):
        raise ValueError(f"{name} must be finite")
    return out


def _coulomb(vt, vn, friction):
    """|v_t| <- max(0, |v_t| - μ_w |v_n|) along v_t's own direction.

    Written with selects, not max(0, ·) of a ratio: JAX differentiates max by multiplying with
    a 0/1 mask, so a ratio whose derivative overflows where |v_t| -> 0 (stuck nodes) would turn
    0 · inf into a NaN tangent. Here a stuck node's tangent is exactly 0 and the ratio is only
    formed where |v_t| > (smallest normal)^(1/4), where its derivative is finite."""
    if isinstance(friction, float) and friction == 0.0:
        return vt
    vt2 = jnp.sum(vt * vt, axis=0, keepdims=True)
    limit = friction * jnp.abs(vn)
    slides = vt2 > limit * limit
    safe = slides & (vt2 > jnp.sqrt(jnp.finfo(vt.dtype).tiny))
    scale = 1.0 - limit * jax.lax.rsqrt(jnp.where(safe, vt2, 1.0))
    return vt * jnp.where(safe, scale, jnp.where(slides, 1.0, 0.0))


def _contact_velocity(wall, v_rel, normal, friction):
    """Relative velocity (dim, n_nodes) after the contact rule, for nodes in contact."""
    if wall.kind == "no-slip":
        return jnp.zeros_like(v_rel)
    vn = jnp.sum(v_rel * normal, axis=0, keepdims=True)
    vt = _coulomb(v_rel - vn * normal, vn, friction)
    if wall.kind == "non-separable":
        return vt
    return jnp.where(vn < 0, vt, v_rel)  # separable


def apply_walls(walls, v, node_x, t, dt, params=None, mass=None):
    """Apply every wall and terrain in order to grid velocities ``v`` (dim, n_nodes) at nodes
    ``node_x`` (dim, n_nodes), at time ``t`` for a step of ``dt``. ``params`` supplies μ_w to
    the boundaries declared with ``friction="mu_w"``.

    With the node masses ``mass`` (n_nodes,), also return the impulse each boundary received
    from the material in this step, (n_walls, dim): Σ_nodes m (v before − v after that
    boundary), so that the force on it is impulse / dt (docs/model.md §5: the walls act on the
    grid velocities, and this is the momentum they remove)."""
    impulses = []
    for wall in walls:
        friction = friction_value(wall.friction, params, v.dtype, type(wall).__name__)
        after = _apply_wall(wall, v, node_x, t, dt, friction)
        if mass is not None:
            impulses.append(jnp.sum(mass * (v - after), axis=1))
        v = after
    if mass is None:
        return v
    impulse = jnp.stack(impulses) if impulses else jnp.zeros((0, v.shape[0]), v.dtype)
    return v, impulse


def _apply_wall(wall, v, node_x, t, dt, friction):
    """The grid velocities (dim, n_nodes) after one wall's or terrain's contact rule."""
    if isinstance(wall, Terrain):
        signed, normal = wall.signed_distance(node_x + dt * v)
        contact = signed <= 0
        if math.isfinite(wall.thickness):
            contact &= signed > -wall.thickness
        return jnp.where(contact, _contact_velocity(wall, v, normal, friction), v)
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
    return jnp.where(contact, _contact_velocity(wall, v - wall_v, normal, friction) + wall_v, v)
