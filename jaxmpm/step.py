"""One pure explicit MPM step, built once from static configuration (docs/model.md §5).

``make_step(config)`` returns ``step(state, params) -> state``:

1. dt = min(cfl·dx/max|v_p|, cfl_e·dx/c), clipped so the step lands exactly on the next frame
   time or the end time; after t_end, or past ``max_steps`` steps, the step returns the state
   unchanged, and once the material is at rest (``Config.rest_speed``) it only moves the time
   on to the next stop;
2. APIC P2G of mass, momentum and internal force (stress from the previous step: USL);
3. grid update with gravity, the side walls' friction of a 2D channel (``Config.side_walls``),
   then the walls (each one's impulse from the material accumulates in ``state.impulse``);
4. G2P (PIC/APIC/AFLIP), positions advected with the PIC velocity;
5. F_e,trial = (I + dt ∇v) F_e and the material update (new F_e, τ, internal variables);
6. status bits: particle left the grid, non-finite state, det F_e,trial <= 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from . import sparse
from . import state as st
from .boundary import apply_walls, side_wall_friction
from .config import Config
from .kernels import make_stencil
from .linalg import det_planes, mm_planes, planes, unplanes
from .transfer import g2p_planes, grid_velocities, p2g, xpic_velocity

__all__ = ["make_step", "time_step", "step_budget"]


def time_step(config: Config, state, params, speed2=None):
    """The adaptive step size before clipping to output times (docs/model.md §5). ``speed2``:
    the largest squared particle speed, if the caller has it."""
    dx = config.grid.dx
    if speed2 is None:
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


def _materialize(tree, token):
    """``tree`` unchanged, computed once. XLA's CPU compiler drops ``optimization_barrier``
    before it fuses, and it fuses a cheap producer into every consumer, recomputing it there (the
    stencil's weights in each of the five P2G channels and the gathers, the grid velocities in
    each gathered element, the whole material update in each component of the stacked stress).
    A conditional on ``token`` (``_always_true``), which XLA cannot know to be true, forces its
    operand to be computed once and stored: measured on the S4 step, the materialisation points
    below save about a third of a step (docs/performance.md)."""
    return jax.lax.cond(token, lambda t: t, lambda t: jax.tree.map(jnp.zeros_like, t), tree)


@custom_vmap
def _always_true(steps):
    """``steps >= 0``: true, but not a constant XLA could fold. Under ``vmap`` it stays one
    unbatched boolean (the rule below): a batched token would turn every ``_materialize`` into a
    select (and the step's ``cond`` on t < t_end batches its operands whenever its predicate is
    batched), and then XLA recomputes the whole material update in each component of the stacked
    state; a vmapped S4 Jacobian took 85 s instead of 0.9 s. It takes an integer, so no
    derivative ever passes through it."""
    return steps >= 0


@_always_true.def_vmap
def _always_true_batched(axis_size, in_batched, steps):
    return jnp.all(steps >= 0), False


def _stencil_and_nodes(x, config: Config, node_x_np):
    """(the particles' stencil, the positions of the grid's nodes (of its active slots on a
    sparse grid), the number of nodes or slots, the number of nodes touched (0 on a dense
    grid))."""
    grid = config.grid
    stencil = make_stencil(x, grid)
    if config.active_nodes is None:
        return stencil, jnp.asarray(node_x_np, x.dtype), grid.n_nodes, 0
    slots, keys, touched = sparse.activate(stencil.index, config.active_nodes, grid.n_nodes,
                                           consecutive_rows=not grid.periodic[-1])
    return stencil._replace(index=slots), sparse.slot_positions(keys, grid, x.dtype), config.active_nodes, touched


def _status_flags(x, v, tau, F_trial, touched, n_grid, bounds):
    """The status bits a step sets (``jaxmpm.state``): a particle outside the grid's interior
    (``x``, per axis) or within its edge band, a non-finite position, velocity or stress, an
    inverted trial deformation, more nodes touched than a sparse grid's slots. ``bounds``:
    (lower, upper, edge band's lower, edge band's upper), per axis."""
    lower, upper, edge_lo, edge_hi = bounds
    left = edge = finite = None
    for a in range(len(x)):
        out_a = (x[a] < lower[a]) | (x[a] >= upper[a])
        edge_a = (x[a] < edge_lo[a]) | (x[a] >= edge_hi[a])
        finite_a = jnp.isfinite(x[a]) & jnp.isfinite(v[a])
        left, edge = (out_a, edge_a) if left is None else (left | out_a, edge | edge_a)
        finite = finite_a if finite is None else finite & finite_a
    for row in tau:
        for t in row:
            finite = finite & jnp.isfinite(t)
    return (
        jnp.where(jnp.any(left), st.LEFT_GRID, 0)
        | jnp.where(jnp.any(edge), st.EDGE, 0)
        | jnp.where(jnp.all(finite), 0, st.NONFINITE)
        | jnp.where(jnp.any(det_planes(F_trial) <= 0), st.J_NONPOSITIVE, 0)
        | jnp.where(touched > n_grid, st.GRID_FULL, 0)
    )


def make_step(config: Config):
    """Build ``step(state, params) -> state`` for this static configuration."""
    grid = config.grid
    dim, dx = grid.dim, grid.dx
    alpha = 0.0 if config.transfer == "apic" else config.alpha
    node_x_np = None if config.active_nodes is not None else grid.node_positions().T
    stops_np = np.asarray(config.stop_times)
    # Python floats (weakly typed): the bounds take the particles' dtype.
    bounds = (grid.lower.tolist(), grid.upper.tolist(), *(b.tolist() for b in grid.edge_band))
    origin, length, periodic = grid.origin, grid.length.tolist(), grid.periodic

    def advance(state, params, dt, t_new):
        dtype = state.x.dtype
        token = _always_true(state.steps)
        stencil, node_x, n_grid, touched = _stencil_and_nodes(state.x, config, node_x_np)
        stencil = _materialize(stencil, token)
        mass = params.rho * state.vol0
        v = list(jnp.unstack(state.v, axis=-1))  # unstack: its transpose is a stack (linalg.planes)
        F = planes(state.F)
        tau = planes(state.tau)
        pressure = None
        if config.side_walls is not None:  # V_p max(p_p, 0), p = -tr(τ)/dim (Kirchhoff: V0 τ = V σ)
            pressure = state.vol0 * jnp.maximum(-sum(tau[a][a] for a in range(dim)) / dim, 0.0)
        fields = p2g(stencil, mass, v, planes(state.C), state.vol0, tau, n_grid, pressure)
        v_old, v_new = grid_velocities(fields, dt, jnp.asarray(config.gravity, dtype))
        if config.side_walls is not None:
            v_new = side_wall_friction(config.side_walls, v_new, fields.pressure, fields.mass, dt, params)
        v_new, impulse = apply_walls(config.walls, v_new, node_x, state.t, dt, params, mass=fields.mass)
        v_flip = v
        if config.xpic and config.transfer == "aflip" and alpha != 0.0:
            v_flip = list(xpic_velocity(stencil, mass, fields.mass, state.v, config.xpic).T)
        v_old, v_new = _materialize((v_old, v_new), token)
        moved = _materialize(g2p_planes(stencil, v_old, v_new, v_flip, dx, config.transfer, alpha), token)
        x = [x_a + dt * moved.v_pic[a] for a, x_a in enumerate(jnp.unstack(state.x, axis=-1))]
        for a in range(dim):
            if periodic[a]:  # wrap positions on periodic axes
                x[a] = origin[a] + jnp.mod(x[a] - origin[a], length[a])
        grad_v_F = mm_planes(moved.grad_v, F)
        F_trial = [[F[a][b] + dt * grad_v_F[a][b] for b in range(dim)] for a in range(dim)]
        F, tau, internal = config.material.update_planes(F_trial, state.internal, params, dt)
        F, tau = _materialize((F, tau), token)
        flags = _status_flags(x, moved.v, tau, F_trial, touched, n_grid, bounds)
        return state.replace(
            x=jnp.stack(x, -1), v=jnp.stack(moved.v, -1), C=unplanes(moved.C), F=unplanes(F), tau=unplanes(tau),
            internal=internal, t=t_new, dt=dt, steps=state.steps + 1, status=state.status | flags,
            impulse=state.impulse + impulse,
        )

    def step(state, params):
        t = state.t
        stops = jnp.asarray(stops_np, t.dtype)
        next_stop = jnp.min(jnp.where(stops > t, stops, jnp.inf))
        speed2 = jnp.max(jnp.sum(state.v * state.v, axis=-1))
        dt = time_step(config, state, params, speed2)
        lands = t + dt >= next_stop
        dt = jnp.where(lands, next_stop - t, dt)
        t_new = jnp.where(lands, next_stop, t + dt)
        # A step beyond the budget (the rollout's last block runs past max_steps) does nothing.
        in_budget = state.steps < config.max_steps
        running = (t < config.t_end) & in_budget
        active = running
        if config.rest_speed is not None:
            # The material is at rest once every particle has stayed slower than rest_speed for
            # rest_duration; from then on a step only carries the state to the next stop time.
            quiet = speed2 < config.rest_speed**2
            quiet_since = jnp.where(quiet, jnp.minimum(state.quiet_since, t), jnp.inf)
            state = state.replace(quiet_since=jnp.where(in_budget, quiet_since, state.quiet_since))
            active &= t - state.quiet_since < config.rest_duration

        def idle(s):  # at rest before t_end: jump to the next stop (a frame or t_end); else nothing
            return s.replace(t=jnp.where(running, next_stop, t))

        # No jax.checkpoint inside the step's cond: rematerialising ``advance`` there made the
        # critical-state model's backward pass 3.6 times slower, recomputing the return map's
        # Newton solves (docs/performance.md, "Reverse mode"). The rollout checkpoints whole steps
        # and blocks instead (jaxmpm.rollout._scan_steps).
        return jax.lax.cond(active, lambda s: advance(s, params, dt, t_new), idle, state)

    return step
