"""Where one step of the full model goes: the S2 column of ``python -m jaxmpm bench
--scene column`` (10,240 particles, float32, critical-state μ(I), AFLIP), each phase of the step
jitted on its own and timed on the column's state after 0.02 s of flow, beside the whole step
in a ``lax.scan``. A phase jitted alone loses its fusion with its neighbours, so the parts need
not add up to the whole; their shares say where to look.

    python docs/scripts/profile_step.py [--iterations N ...]   -> JSON on stdout

``--iterations`` times the return map and the step with other Newton iteration counts, and
reports the largest |g| / p_c,n of the return's scalar solve (g = y along the return path) in
float32 with each.
"""

import argparse
import dataclasses
import json

import jax
import jax.numpy as jnp

from jaxmpm.boundary import apply_walls
from jaxmpm.kernels import make_stencil
from jaxmpm.linalg import mm
from jaxmpm.materials.critical_state import bulk_modulus, return_map, surface_residual
from jaxmpm.materials.hencky import hencky_strain
from jaxmpm.rollout import make_rollout
from jaxmpm.step import make_step, time_step
from jaxmpm.studies.bench import bench_scene, device_name, median_time
from jaxmpm.transfer import g2p, grid_velocities, p2g


def timed(fn, *args, repeat=30):
    return median_time(fn, *args, repeat=repeat)


def whole_step(config, state, params, n, repeat):
    """Seconds per step of ``n`` steps from ``state`` in one compiled scan (median of ``repeat``)."""
    step = make_step(config)
    scan = jax.jit(lambda s: jax.lax.scan(lambda c, _: (step(c, params), None), s, None, length=n)[0])
    return timed(scan, state, repeat=repeat) / n


def transfer_phases(config, state, params, dt):
    """The step's transfer phases at ``state`` as jitted functions, each with what the next one
    reads: (stencil_fn, stencil, p2g_fn, fields, grid_fn, v_old, v_new); ``grid_fn`` applies
    the walls as the step does (with the parameters and the nodes' mass) and returns their
    impulse too, so that nothing it computes is dropped from the timing."""
    grid = config.grid
    stencil_fn = jax.jit(lambda x: make_stencil(x, grid))
    stencil = stencil_fn(state.x)
    mass = params.rho * state.vol0
    p2g_fn = jax.jit(lambda st, v, C, tau: p2g(st, mass, v, C, state.vol0, tau, grid.n_nodes))
    fields = p2g_fn(stencil, state.v, state.C, state.tau)
    node_x = jnp.asarray(grid.node_positions().T, state.x.dtype)
    gravity = jnp.asarray(config.gravity, state.x.dtype)

    def grid_update(f):
        v_old, v_new = grid_velocities(f, dt, gravity)
        return v_old, apply_walls(config.walls, v_new, node_x, state.t, dt, params, mass=f.mass)

    grid_fn = jax.jit(grid_update)
    v_old, (v_new, _) = grid_fn(fields)
    return stencil_fn, stencil, p2g_fn, fields, grid_fn, v_old, v_new


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--iterations", type=int, nargs="*", default=[])
    parser.add_argument("--particles", type=int, default=None, help="override the column's 10,240 particles")
    args = parser.parse_args()
    config, state, params = bench_scene("column", False, 2, "float32", args.particles)
    grid = config.grid
    warm = make_rollout(dataclasses.replace(config, t_end=0.02), observer=None)
    state = jax.jit(warm)(state, params)[0]
    dt = jnp.asarray(float(state.dt), state.x.dtype)
    whole = whole_step(config, state, params, n=100, repeat=5)
    stencil_fn, stencil, p2g_fn, fields, grid_fn, v_old, v_new = transfer_phases(config, state, params, dt)
    alpha = 0.0 if config.transfer == "apic" else config.alpha
    g2p_fn = jax.jit(lambda st, a, b, v: g2p(st, a, b, v, grid.dx, config.transfer, alpha))
    moved = g2p_fn(stencil, v_old, v_new, state.v)
    F_trial = jax.jit(lambda g, F: mm(jnp.eye(2, dtype=F.dtype) + dt * g, F))(moved.grad_v, state.F)
    material = config.material
    update_fn = jax.jit(lambda F, internal: material.update(F, internal, params, dt))
    hencky_fn = jax.jit(hencky_strain)
    strain = hencky_fn(F_trial)
    rmap_fn = jax.jit(lambda e, ev: return_map(e, ev, params, dt, material.iterations))
    dt_fn = jax.jit(lambda s: time_step(config, s, params))
    parts = {
        "stencil": timed(stencil_fn, state.x),
        "p2g": timed(p2g_fn, stencil, state.v, state.C, state.tau),
        "grid_update_and_walls": timed(grid_fn, fields),
        "g2p": timed(g2p_fn, stencil, v_old, v_new, state.v),
        "material_update": timed(update_fn, F_trial, state.internal),
        "  of which hencky_log": timed(hencky_fn, F_trial),
        "  of which return_map": timed(rmap_fn, strain, state.internal["eps_v_p"]),
        "time_step": timed(dt_fn, state),
    }
    out = {"scene": "column-S2", "n_particles": state.n_particles, "device": device_name(), "dtype": "float32",
           "iterations": material.iterations, "whole_step_ms": round(1e3 * whole, 3),
           "parts_ms": {k: round(1e3 * v, 3) for k, v in parts.items()},
           "parts_share_of_whole": {k: round(v / whole, 3) for k, v in parts.items()},
           "plastic_fraction": float(jnp.mean(rmap_fn(strain, state.internal["eps_v_p"])[2]["plastic"]))}

    def surface_error(iterations):
        """max |g(ε)| / p_c,n over plastic lanes: the residual of the scalar solve the return map's
        Newton iterations zero (g = y along the return path), with the final implicit step."""
        _, _, o = jax.jit(lambda e, ev: return_map(e, ev, params, dt, iterations))(strain, state.internal["eps_v_p"])
        G, K = bulk_modulus(params, 2)
        e_v = strain[:, 0, 0] + strain[:, 1, 1]
        dev = strain - (e_v / 2)[:, None, None] * jnp.eye(2, dtype=strain.dtype)
        q_tr = 2.0 * G * jnp.sqrt(0.5 * jnp.sum(dev * dev, axis=(-2, -1)))
        pc_n = params.pc0 * jnp.exp(-params.xi * state.internal["eps_v_p"])
        g = surface_residual(o["deps_v_p"], -K * e_v, q_tr, pc_n, params, K, G)
        return float(jnp.max(jnp.where(o["plastic"] > 0, jnp.abs(g) / pc_n, 0.0)))

    sweep = {}
    for it in sorted(set(args.iterations) | {material.iterations}):
        rm = jax.jit(lambda e, ev, it=it: return_map(e, ev, params, dt, it))
        config_it = dataclasses.replace(config, material=dataclasses.replace(material, iterations=it))
        sweep[it] = {"return_map_ms": round(1e3 * timed(rm, strain, state.internal["eps_v_p"]), 3),
                     "whole_step_ms": round(1e3 * whole_step(config_it, state, params, n=100, repeat=5), 3),
                     "max_rel_surface_residual": surface_error(it)}
    out["iterations_sweep"] = sweep
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
