"""One pure explicit MPM step, built once from static configuration (docs/model.md §5).

``make_step(config)`` returns ``step(state, params) -> state``:

1. dt = min(cfl·dx/max|v_p|, cfl_e·dx/c), clipped so the step lands exactly on the next frame
   time or the end time; after t_end the step returns the state unchanged;
2. APIC P2G of mass, momentum and internal force (stress from the previous step: USL);
3. grid update with gravity, then the walls (each one's impulse from the material accumulates
   in ``state.impulse``);
4. G2P (PIC/APIC/AFLIP), positions advected with the PIC velocity;
5. F_e,trial = (I + dt ∇v) F_e and the material update (new F_e, τ, internal variables);
6. status bits: particle left the grid, non-finite state, det F_e,trial <= 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import sparse
from . import state as st
from .boundary import apply_walls
from .config import Config
from .kernels import make_stencil
from .linalg import det, mm
from .transfer import g2p, grid_velocities, p2g, xpic_velocity

__all__ = ["make_step", "time_step", "step_budget"]


def time_step(config: Config, state, params):
    """The adaptive step size before clipping to output times (docs/model.md §5)."""
    dx = config.grid.dx
    speed2 = jnp.max(jnp.sum(state.v * state.v, axis=-1))
    dt_e = config.cfl_elastic * dx / config.material.wave_speed(params)
    binds = (config.cfl * dx / dt_e) ** 2
    dt_v = config.cfl * dx * jax.lax.rsqrt(jnp.maximum(speed2, binds))
    return jnp.where(speed2 > binds, jnp.minimum(dt_v, dt_e), dt_e)


def step_budget(material, params, dx: float, t_end: float, cfl_elastic: float = 0.5, margin: float = 1.25,
                extra: int = 10) -> int:
    """A step budget (``Config.max_steps``) for a run to ``t_end`` whose time step the elastic
    bound sets (flow speeds far below the wave speed): ``margin`` × t_end / dt_e + ``extra``.
    ``params`` must hold concrete values (this runs in Python, before tracing)."""
    dt = cfl_elastic * dx / float(material.wave_speed(params))
    return int(margin * t_end / dt) + int(extra)


def make_step(config: Config):
    """Build ``step(state, params) -> state`` for this static configuration."""
    grid = config.grid
    dim, dx = grid.dim, grid.dx
    alpha = 0.0 if config.transfer == "apic" else config.alpha
    sparse_grid = config.active_nodes is not None
    node_x_np = None if sparse_grid else grid.node_positions().T
    stops_np = np.asarray(config.stop_times)
    lower_np, upper_np = grid.lower, grid.upper
    edge_lo_np, edge_hi_np = grid.edge_band
    periodic = np.asarray(grid.periodic)

    def advance(state, params, dt, t_new):
        dtype = state.x.dtype
        stencil = make_stencil(state.x, grid)
        if sparse_grid:
            slots, keys, touched = sparse.activate(stencil.index, config.active_nodes, grid.n_nodes,
                                                   consecutive_rows=not grid.periodic[-1])
            stencil = stencil._replace(index=slots)
            node_x = sparse.slot_positions(keys, grid, dtype)
            n_grid = config.active_nodes
        else:
            node_x, n_grid, touched = jnp.asarray(node_x_np, dtype), grid.n_nodes, 0
        stencil = jax.lax.optimization_barrier(stencil)
        mass = params.rho * state.vol0
        fields = p2g(stencil, mass, state.v, state.C, state.vol0, state.tau, n_grid)
        v_old, v_new = grid_velocities(fields, dt, jnp.asarray(config.gravity, dtype))
        v_new, impulse = apply_walls(config.walls, v_new, node_x, state.t, dt, params, mass=fields.mass)
        v_flip = state.v
        if config.xpic and config.transfer == "aflip" and alpha != 0.0:
            v_flip = xpic_velocity(stencil, mass, fields.mass, state.v, config.xpic)
        moved = g2p(stencil, v_old, v_new, v_flip, dx, config.transfer, alpha)
        x = state.x + dt * moved.v_pic
        if periodic.any():  # wrap positions on periodic axes
            origin, length = jnp.asarray(grid.origin, dtype), jnp.asarray(grid.length, dtype)
            x = jnp.where(periodic, origin + jnp.mod(x - origin, length), x)
        F_trial = mm(jnp.eye(dim, dtype=dtype) + dt * moved.grad_v, state.F)
        F, tau, internal = config.material.update(F_trial, state.internal, params, dt)

        left = jnp.any((x < jnp.asarray(lower_np, dtype)) | (x >= jnp.asarray(upper_np, dtype)))
        edge = jnp.any((x < jnp.asarray(edge_lo_np, dtype)) | (x >= jnp.asarray(edge_hi_np, dtype)))
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(moved.v)) & jnp.all(jnp.isfinite(tau))
        inverted = jnp.any(det(F_trial) <= 0)
        flags = (
            jnp.where(left, st.LEFT_GRID, 0)
            | jnp.where(edge, st.EDGE, 0)
            | jnp.where(finite, 0, st.NONFINITE)
            | jnp.where(inverted, st.J_NONPOSITIVE, 0)
            | jnp.where(touched > n_grid, st.GRID_FULL, 0)
        )
        return state.replace(
            x=x, v=moved.v, C=moved.C, F=F, tau=tau, internal=internal,
            t=t_new, dt=dt, steps=state.steps + 1, status=state.status | flags, impulse=state.impulse + impulse,
        )

    def step(state, params):
        t = state.t
        stops = jnp.asarray(stops_np, t.dtype)
        next_stop = jnp.min(jnp.where(stops > t, stops, jnp.inf))
        dt = time_step(config, state, params)
        lands = t + dt >= next_stop
        dt = jnp.where(lands, next_stop - t, dt)
        t_new = jnp.where(lands, next_stop, t + dt)
        active = t < config.t_end
        return jax.lax.cond(active, lambda s: advance(s, params, dt, t_new), lambda s: s, state)

    return step
