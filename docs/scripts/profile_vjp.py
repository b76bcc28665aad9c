"""What a reverse-mode gradient costs, step by step and phase by phase.

The case is ``python -m jaxmpm bench --grad``'s: the 2D Hencky block (2,500 particles, float32),
whose gradient of the final mean height with respect to every parameter costs about 6.4 forward
runs through the checkpointed rollout. With checkpointed blocks the gradient is

    one plain forward pass (storing one carry per block)
  + per block: the forward pass again, now storing the residuals the transposes need
  + per block: the backward pass,

so its cost in forward runs is 1 + (t_forward_with_residuals + t_backward) / t_forward.
This script times the three parts on a 100-step ``lax.scan`` of the step (after 0.1 s of
flow, so the block is in contact with the floor) and the VJP of each phase of the step on its
own (each jitted alone: the shares say where to look, they need not add up).

    python docs/scripts/profile_vjp.py      -> JSON on stdout (docs/results/profile_vjp.json), a minute
"""

import dataclasses
import json

import jax
import jax.numpy as jnp

from jaxmpm.boundary import apply_walls
from jaxmpm.kernels import make_stencil
from jaxmpm.linalg import mm
from jaxmpm.rollout import make_rollout
from jaxmpm.scenes import falling_block
from jaxmpm.step import make_step
from jaxmpm.studies.bench import device_name, median_time
from jaxmpm.transfer import g2p, grid_velocities, p2g


def timed(fn, *args, repeat=20):
    return median_time(fn, *args, repeat=repeat)


def forward_and_vjp(fn, *args):
    """(forward seconds, forward+backward seconds) of ``fn`` at ``args``, cotangent ones."""
    out = jax.jit(fn)(*args)
    ct = jax.tree.map(jnp.ones_like, out)
    fwd = jax.jit(fn)
    both = jax.jit(lambda a, c: jax.vjp(fn, *a)[1](c))
    return timed(fwd, *args), timed(both, args, ct)


def main():
    config, state, params = falling_block(n_particles=2_500, t_end=10.0, max_steps=5_000, dtype="float32")
    warm = make_rollout(dataclasses.replace(config, t_end=0.1, max_steps=2_000, block_size=None), observer=None)
    state = jax.jit(warm)(state, params)[0]
    step = make_step(config)
    n = 100

    def scan(s, p):
        return jax.lax.scan(lambda c, _: (step(c, p), None), s, None, length=n)[0]

    def loss(p):  # the gradient bench --grad takes: with respect to the parameters, through the states
        return jnp.mean(scan(state, p).x[:, -1])

    t_forward = timed(jax.jit(scan), state, params, repeat=10)
    primal, vjp_fn = jax.jit(lambda p: jax.vjp(loss, p))(params)
    one = jnp.ones_like(primal)
    t_residuals = timed(jax.jit(lambda p: jax.vjp(loss, p)), params, repeat=10)
    t_backward = timed(jax.jit(lambda f, c: f(c)), vjp_fn, one, repeat=10)
    t_value_and_grad = timed(jax.jit(jax.grad(loss)), params, repeat=10)

    # Phases of the step, each on its own.
    grid = config.grid
    dt = jnp.asarray(float(state.dt), state.x.dtype)
    node_x = jnp.asarray(grid.node_positions().T, state.x.dtype)
    gravity = jnp.asarray(config.gravity, state.x.dtype)
    stencil = jax.jit(lambda x: make_stencil(x, grid))(state.x)

    def p2g_fn(x, v, C, tau, rho):
        st = make_stencil(x, grid)
        return p2g(st, rho * state.vol0, v, C, state.vol0, tau, grid.n_nodes)

    fields = jax.jit(p2g_fn)(state.x, state.v, state.C, state.tau, params.rho)

    def grid_fn(f):
        v_old, v_new = grid_velocities(f, dt, gravity)
        return v_old, apply_walls(config.walls, v_new, node_x, state.t, dt)

    v_old, v_new = jax.jit(grid_fn)(fields)

    def g2p_fn(x, a, b, v):
        st = make_stencil(x, grid)
        return g2p(st, a, b, v, grid.dx, config.transfer, config.alpha)

    moved = jax.jit(g2p_fn)(state.x, v_old, v_new, state.v)
    F_trial = mm(jnp.eye(2, dtype=state.F.dtype) + dt * moved.grad_v, state.F)

    def material_fn(F, p):
        return config.material.update(F, state.internal, p, dt)

    phases = {
        "stencil": forward_and_vjp(lambda x: make_stencil(x, grid), state.x),
        "p2g (with its stencil)": forward_and_vjp(p2g_fn, state.x, state.v, state.C, state.tau, params.rho),
        "grid_update_and_walls": forward_and_vjp(grid_fn, fields),
        "g2p (with its stencil)": forward_and_vjp(g2p_fn, state.x, v_old, v_new, state.v),
        "material_update": forward_and_vjp(material_fn, F_trial, params),
    }
    del stencil
    per_step = lambda t: round(1e3 * t / n, 4)  # noqa: E731
    out = {
        "case": "bench --grad: 2D Hencky block, float32", "n_particles": state.n_particles,
        "device": device_name(),
        "step_ms": {"forward": per_step(t_forward), "forward_with_residuals": per_step(t_residuals),
                    "backward": per_step(t_backward), "grad_in_one_jit": per_step(t_value_and_grad)},
        "checkpointed_gradient_in_forward_runs": round(1 + (t_residuals + t_backward) / t_forward, 2),
        "one_block_gradient_in_forward_runs": round(t_value_and_grad / t_forward, 2),
        "phases_ms": {k: {"forward": round(1e3 * f, 4), "forward_and_backward": round(1e3 * b, 4),
                          "ratio": round(b / f, 2)} for k, (f, b) in phases.items()},
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
