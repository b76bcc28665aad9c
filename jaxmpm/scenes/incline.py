"""S1 of docs/scenes.md: steady flow down an inclined plane (the Bagnold profile of docs/model.md §6).

A layer of depth h on a rough (no-slip) bed at y = 0, periodic along the slope (x), with gravity
rotated to g = 9.81 (sin θ, -cos θ). The periodic length is a few cells: the steady state is
uniform in x, so nothing is gained by a longer domain. As in the collapses (``collapse.py``),
the layer is raised so that its lowest particle lies half a cell above the bed (no particle's
stencil reaches a node below it); its lower face then stands ``info.wall_gap`` above the bed
(dx/4 for a 2 × 2 lattice), and z = y - wall_gap is the height in the layer.
"""

from __future__ import annotations

import math

from ..boundary import Wall
from ..config import Config, Grid
from ..materials.critical_state import CriticalState
from ..params import Params
from ..sampling import seed_box
from ..state import init_state
from ..step import step_budget
from .base import Scene
from .collapse import G, floor_lift
from .info import SceneInfo

__all__ = ["incline", "S1_DEPTH", "S1_PARAMS", "STEADY_QUANTITIES", "bagnold_velocity", "side_wall_velocity",
           "steady_velocity", "wall_drag"]

#: S1's layer depth h (docs/scenes.md S1), m.
S1_DEPTH = 0.038

#: S1 material: glass beads, β = 0. docs/scenes.md gives no p_c0, ξ: ξ = 50 lets p_c grow by
#: compaction to the critical state under the layer's weight (p_c0 = 100 Pa as S2).
S1_PARAMS = {"rho": 1550.0, "rho_s": 2500.0, "d": 0.7e-3, "beta": 0.0, "pc0": 100.0, "xi": 50.0}


def _steady_flow(params, slope_deg):
    """(a getter of ``params``' floats, θ, tan θ, μ1, μ2) for a steady flow at ``slope_deg``,
    which must lie between atan(μ1) and atan(μ2). ``params``: a Params or a dict of floats."""
    get = (lambda k: float(params[k])) if isinstance(params, dict) else (lambda k: float(getattr(params, k)))
    theta = math.radians(slope_deg)
    tan, mu1, mu2 = math.tan(theta), get("mu1"), get("mu2")
    if not mu1 < tan < mu2:
        raise ValueError(f"slope_deg must lie between atan(mu1) and atan(mu2) for a steady flow, got {slope_deg!r}")
    return get, theta, tan, mu1, mu2


def bagnold_velocity(z, depth, slope_deg, params):
    """docs/model.md §6: v(z) = (2/3) I_θ sqrt(ρ g cos θ / ρ_s) / d (h^{3/2} - (h - z)^{3/2}), with
    I_θ = I0 (tan θ - μ1) / (μ2 - tan θ). ``params`` may be a Params or a dict of floats."""
    get, theta, tan, mu1, mu2 = _steady_flow(params, slope_deg)
    i_theta = get("I0") * (tan - mu1) / (mu2 - tan)
    scale = (2.0 / 3.0) * i_theta * math.sqrt(get("rho") * G * math.cos(theta) / get("rho_s")) / get("d")
    import numpy as np

    z = np.clip(np.asarray(z, float), 0.0, depth)
    return scale * (depth**1.5 - (depth - z) ** 1.5)


#: What ``steady_velocity`` returns: the free surface's velocity, the depth average, or the
#: velocity at a height above the bed (a velocity profile v(z)).
STEADY_QUANTITIES = ("surface", "depth_averaged", "profile")


def steady_velocity(depth, slope_deg, mu1, mu2, I0, rho, rho_s, d, quantity: str = "surface", side_walls=None,
                    mu_w=None, height=None):
    """The steady flow's velocity at the free surface (``quantity="surface"``), averaged over the
    depth (``"depth_averaged"``) or at the heights ``height`` above the bed (``"profile"``, which
    needs them; 0 <= z <= depth) for a layer of depth ``depth`` at ``slope_deg``. Traceable, on
    arrays that broadcast; NaN where tan θ does not lie strictly between μ1 and μ2 (no steady flow:
    the layer stops, or accelerates), and at a height outside [0, depth].

    Without ``side_walls`` it is Bagnold's (``bagnold_velocity`` at z = h):
    (2/3) I_θ sqrt(ρ g cos θ / ρ_s) h^{3/2} / d at the surface, 3/5 of it averaged over the depth.
    Between ``side_walls`` (a ``jaxmpm.SideWalls``; its friction "mu_w" reads ``mu_w``) it is the
    flow of ``side_wall_velocity`` (docs/model.md §6): μ(I(ζ)) = tan θ − a ζ at the depth ζ, with
    the walls' drag a = μ_w K / W, the flow stopping below ζ* = (tan θ − μ1) / a, so that with
    γ̇ = I(ζ) sqrt(ρ g cos θ ζ / ρ_s) / d and L = min(h, ζ*) the surface moves at ∫_0^L γ̇ dζ and
    the depth average is (1/h) ∫_0^L ζ γ̇ dζ. Both integrals are in closed form (``_wall_integral``),
    exact for a = 0 and finite, with their derivatives, wherever the flow is steady.

    The shear rate depends only on the depth below the surface (the pressure and the walls' drag
    grow with it), so the profile is v(z) = U_s(h) − U_s(h − z), U_s(D) the surface velocity of a
    layer of depth D: 0 at the bed, U_s(h) at the surface, with finite derivatives at both."""
    import jax.numpy as jnp
    from jax import lax

    if quantity not in STEADY_QUANTITIES:
        raise ValueError(f"quantity must be one of {STEADY_QUANTITIES}, got {quantity!r}")
    if (height is None) != (quantity != "profile"):
        raise ValueError("height: the heights z above the bed are given with quantity=\"profile\" and only then, "
                         f"got quantity={quantity!r} and height={'None' if height is None else 'heights'}")
    drag = wall_drag(side_walls, mu_w)
    theta = jnp.deg2rad(slope_deg)
    tan = jnp.tan(theta)
    steady = (mu1 < tan) & (tan < mu2)
    above = jnp.where(steady, tan - mu1, 1.0)  # A = tan θ − μ1 > 0: the surface flows
    below = jnp.where(steady, mu2 - tan, 1.0)  # B = μ2 − tan θ > 0: it does not accelerate
    rate = 2.0 * I0 * jnp.sqrt(rho * G * jnp.cos(theta) / rho_s) / d  # 2 I0 c
    flowing, u = _flowing_depth(depth, above, below, drag)
    if quantity == "profile":
        inside = (height >= 0.0) & (height <= depth)
        lower, u_lower = _flowing_depth(jnp.where(inside, depth - height, 0.0), above, below, drag)  # at D = h − z
        value = (_surface_velocity(flowing, u, above, below, rate)
                 - _surface_velocity(lower, u_lower, above, below, rate, may_be_empty=True))
        # At the bed, or in a static base (L = ζ* both), v = 0 exactly (not an ulp off), its derivatives kept.
        value = jnp.where(lower < flowing, value, value - lax.stop_gradient(value))
        return jnp.where(steady & inside, value, jnp.nan)
    if quantity == "surface":
        value = _surface_velocity(flowing, u, above, below, rate)
    else:  # 2 I0 c L^{5/2} (A/5 − (A + B) u g3(u)) / (B h)
        value = rate / below * flowing**2.5 * (above / 5.0 - (above + below) * u * _wall_integral(u, 3)) / depth
    return jnp.where(steady, value, jnp.nan)


def _flowing_depth(depth, above, below, drag):
    """(L = min(D, ζ*), u = a L / B) of a layer of depth D >= 0 (A = ``above``, B = ``below``, a = ``drag``)."""
    import jax.numpy as jnp

    to_bed = drag * depth < above  # the flow reaches the bed (always without walls)
    flowing = jnp.where(to_bed, depth, above / jnp.where(to_bed, 1.0, drag))  # L = min(h, ζ*)
    return flowing, drag * flowing / below  # a L / B >= 0


def _surface_velocity(flowing, u, above, below, rate, may_be_empty: bool = False):
    """U_s(D) = 2 I0 c L^{3/2} (A/3 − (A + B) u g2(u)) / B of ``steady_velocity`` for a layer of
    depth D >= 0 from its (L, u) (``_flowing_depth``; ``rate`` = 2 I0 c). Where it ``may_be_empty``
    (D = 0: L = 0, U_s = 0), L^{3/2} is taken
    through a double ``where``: its first derivative, 1.5 L^{1/2}, is 0 there either way, but its
    higher ones are infinite, and an infinite factor times a zero tangent is NaN (elsewhere the
    same value as ``L**1.5``)."""
    import jax.numpy as jnp

    if may_be_empty:
        empty = flowing == 0.0
        power = jnp.where(empty, 0.0, jnp.where(empty, 1.0, flowing) ** 1.5)
    else:
        power = flowing**1.5
    return rate / below * power * (above / 3.0 - (above + below) * u * _wall_integral(u, 2))


def wall_drag(side_walls, mu_w=None):
    """The side walls' drag a = μ_w K / W (1/m) of ``steady_velocity``: 0.0 without ``side_walls``;
    ``mu_w`` (traceable) where their friction is the parameter "mu_w"."""
    if side_walls is None:
        return 0.0
    friction = side_walls.friction
    if isinstance(friction, str):
        if mu_w is None:
            raise ValueError("mu_w: the side walls' friction is the parameter mu_w (friction=\"mu_w\"); give its value")
        friction = mu_w
    return friction * side_walls.lateral_pressure_ratio / side_walls.width


#: Below this u = a L / B, ``_wall_integral`` sums its series (60 terms: the first left out is
#: below 0.5^60 / 125 < 1e-20); above it, the arctan form's cancellation costs at most ~3 digits.
_SERIES_BELOW = 0.5


def _wall_integral(u, k: int):
    """g_k(u) = ∫_0^1 t^{2k} / (1 + u t²) dt (u >= 0, k = 2 or 3): the series Σ_j (−u)^j / (2j + 2k + 1)
    for small u, else g_1 = (X − atan X) / X³ (X = √u) and g_{k+1} = (1/(2k + 1) − g_k) / u. Each
    branch sees only arguments it is accurate on (the double ``where``: finite derivatives)."""
    import jax.numpy as jnp

    small = u < _SERIES_BELOW
    us = jnp.where(small, u, 0.0)
    series = 0.0
    for j in reversed(range(60)):
        series = 1.0 / (2 * j + 2 * k + 1) - us * series
    ul = jnp.where(small, 1.0, u)
    x = jnp.sqrt(ul)
    closed = (x - jnp.arctan(x)) / (x * ul)
    for m in range(1, k):
        closed = (1.0 / (2 * m + 1) - closed) / ul
    return jnp.where(small, series, closed)


def side_wall_velocity(z, depth, slope_deg, params, side_walls, points: int = 4001):
    """The steady flow between side walls (docs/model.md §6): at depth ζ below the surface the
    walls take 2 μ_w K p ζ / W of the shear stress, so μ(I(ζ)) = tan θ − μ_w K ζ / W, the flow
    stops below ζ* = W (tan θ − μ1) / (μ_w K), and v(z) integrates γ̇ = I(ζ) sqrt(p / ρ_s) / d
    (p = ρ g cos θ ζ) up from the no-slip bed. Returns (v at the heights ``z`` above the bed, ζ*
    (inf without friction)). ``params``: as for ``bagnold_velocity``."""
    import numpy as np

    get, theta, tan, mu1, mu2 = _steady_flow(params, slope_deg)
    drag = wall_drag(side_walls, get("mu_w") if side_walls.friction == "mu_w" else None)
    stop = (tan - mu1) / drag if drag > 0 else math.inf
    height = np.linspace(0.0, depth, points)
    zeta = depth - height
    mu = np.maximum(tan - drag * zeta, mu1)
    rate = (get("I0") * (mu - mu1) / (mu2 - mu)
            * np.sqrt(get("rho") * G * math.cos(theta) * zeta / get("rho_s")) / get("d"))
    v = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(height))])
    return np.interp(np.clip(np.asarray(z, float), 0.0, depth), height, v), stop


def incline(slope_deg: float = 24.0, dx: float | None = None, ppc: int = 2, depth: float = S1_DEPTH,
            length_cells: int = 4, t_end: float = 2.0, frames: int = 0, max_steps: int | None = None,
            start_from_analytic: bool = True, critical_start: bool = False, transfer: str = "aflip",
            alpha: float = 0.95, dtype=None, sampling: str = "lattice", seed: int = 0,
            wall_gap: float | None = None, side_walls=None, **param_values) -> Scene:
    """S1 at ``slope_deg`` with layer ``depth`` (default 0.038 m) and grid spacing ``dx``
    (default depth/16), periodic over ``length_cells`` cells along the slope.

    The approach to the steady state from rest is slow: near it the relaxation time is
    v/(g cos θ μ'(I) I), 2 s at 22° and 11 s at 28°. With ``start_from_analytic`` (default) the
    layer starts with the Bagnold velocity profile of docs/model.md §6 and the run shows whether the
    scheme holds it, which is the question the validation asks.

    ``critical_start``: start every particle at the critical state of the steady flow (p_c = 2p
    at the lithostatic pressure, the state docs/model.md §6's solution assumes). Without it p_c = p_c0
    everywhere, and near the free surface, where p ≪ p_c0, the material is overconsolidated:
    it is stronger than μ(I) p there and shears only as dilation softens it. The offset lives in
    ε_v^p, so ``particle_volumes`` counts it as a plastic volume change: divide by
    exp(ε_v^p(t = 0)) for volumes relative to the start. ``start_from_analytic=False`` starts
    from rest (the approach to the steady state, ``validate bagnold --from-rest``). ``side_walls``
    (``jaxmpm.SideWalls``): the chute's walls (docs/model.md §6, ``side_wall_velocity``)."""
    dx = dx if dx is not None else depth / 16
    if wall_gap is not None and not (isinstance(wall_gap, (int, float)) and math.isfinite(wall_gap)
                                     and 0.0 <= wall_gap <= 2.0 * dx):
        raise ValueError(f"wall_gap must be in [0, 2 dx] (m), got {wall_gap!r}")
    for name, value in (("dx", dx), ("depth", depth), ("t_end", t_end)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be > 0, got {value!r}")
    if not (isinstance(length_cells, int) and length_cells >= 3):
        raise ValueError(f"length_cells must be an integer >= 3, got {length_cells!r}")
    params = Params.create(dtype=dtype, **{**S1_PARAMS, **param_values})
    theta = math.radians(slope_deg)
    margin = 3 * dx
    grid = Grid((length_cells, math.ceil((1.3 * depth + 2 * dx + 2 * margin) / dx)), dx, origin=(0.0, -margin),
                periodic=(True, False))
    if max_steps is None:
        max_steps = step_budget(CriticalState(), params, dx, t_end, margin=1.1, extra=frames + 10)
    config = Config(
        grid=grid, t_end=t_end, max_steps=max_steps, material=CriticalState(),
        walls=(Wall((0.0, 0.0), (0.0, 1.0), "no-slip"),), gravity=(G * math.sin(theta), -G * math.cos(theta)),
        transfer=transfer, alpha=alpha,
        frame_times=tuple(t_end * (k + 1) / frames for k in range(frames)), side_walls=side_walls,
    )
    x, vol = seed_box((0.0, 0.0), (length_cells * dx, depth), dx, ppc, sampling=sampling, seed=seed)
    z = x[:, 1].copy()
    gap = floor_lift(z, dx, wall_gap)
    x[:, 1] += gap
    v = None
    if start_from_analytic:
        vx = (bagnold_velocity(z, depth, slope_deg, params) if side_walls is None
              else side_wall_velocity(z, depth, slope_deg, params, side_walls)[0])
        v = [[u, 0.0] for u in vx]
    info = SceneInfo(dim=2, dx=dx, ppc=ppc, sampling=sampling, seed=seed, front0=float(length_cells * dx),
                     length=length_cells * dx, height=depth, slope_deg=slope_deg, wall_gap=gap,
                     critical_start=bool(critical_start))
    state = init_state(config, x, vol, v=v, dtype=dtype)
    if critical_start:
        state = _at_critical_state(state, z, depth, theta, params)
    return Scene("incline", config, state, params, info)


def _at_critical_state(state, y, depth, theta, params):
    """Set each particle's p_c to the critical state of the steady flow: the apex of the ellipse
    at the lithostatic pressure p(y) = ρ g cos θ (h − y), p_c = 2 p / (1 − β), through the
    plastic volumetric strain ε_v^p = −ln(p_c / p_c0) / ξ (docs/model.md §2's hardening law)."""
    import numpy as np

    get = lambda k: float(getattr(params, k))  # noqa: E731
    if get("xi") <= 0:
        raise ValueError("critical_start needs xi > 0 (p_c is set through the hardening law)")
    p = get("rho") * G * math.cos(theta) * np.maximum(depth - np.asarray(y, float), 0.0)
    pc = np.maximum(2.0 * p / (1.0 - get("beta")), 1e-6 * get("pc0"))
    eps = -np.log(pc / get("pc0")) / get("xi")
    internal = dict(state.internal)
    internal["eps_v_p"] = internal["eps_v_p"] + np.asarray(eps, internal["eps_v_p"].dtype)
    return state.replace(internal=internal)
