"""Where a 3D step goes, against 2D at the same particle count.

The case is the Hencky block of ``python -m jaxmpm bench --dim 2|3`` (float32, AFLIP), after
0.05 s of flight, each phase of the step jitted on its own and timed beside the whole step in a
``lax.scan`` (as ``profile_step.py`` does for the 2D column). A phase jitted alone loses its
fusion with its neighbours, so the parts need not add up to the whole; their ratios 3D/2D say
where a 3D particle's extra cost is.

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
        taskset -c 1 python docs/scripts/profile_3d.py [--particles N]   -> JSON on stdout
"""

import argparse
import dataclasses
import json

import jax
import jax.numpy as jnp
from profile_step import timed, transfer_phases, whole_step  # the same phases, beside this script

from jaxmpm.linalg import eigh_sym, mm, planes, sym_log, unplanes
from jaxmpm.rollout import make_rollout
from jaxmpm.scenes import falling_block
from jaxmpm.studies.bench import device_name
from jaxmpm.transfer import g2p_planes


def profile(dim, n_particles, repeat):
    config, state, params = falling_block(n_particles=n_particles, dim=dim, t_end=10.0, max_steps=100_000,
                                          dtype="float32")
    warm = make_rollout(dataclasses.replace(config, t_end=0.05, block_size=None), observer=None)
    state = jax.jit(warm)(state, params)[0]
    grid = config.grid
    dt = jnp.asarray(float(state.dt), state.x.dtype)
    whole = whole_step(config, state, params, n=50, repeat=max(3, repeat // 5))
    stencil_fn, stencil, p2g_fn, fields, grid_fn, v_old, v_new = transfer_phases(config, state, params, dt)
    # planes in and out, as inside the step (stacking (N, d, d) arrays costs more than the phase)
    vp = [state.v[:, a] for a in range(dim)]
    g2p_fn = jax.jit(lambda st, a, b, v: g2p_planes(st, a, b, v, grid.dx, config.transfer, config.alpha))
    moved = g2p_fn(stencil, v_old, v_new, vp)
    F_trial = jax.jit(lambda g, F: mm(jnp.eye(dim, dtype=F.dtype) + dt * g, F))(unplanes(moved.grad_v), state.F)
    Fp = planes(F_trial)
    stress_fn = jax.jit(lambda F: config.material.update_planes(F, state.internal, params, dt)[1])
    b = jax.jit(lambda F: mm(F, jnp.swapaxes(F, -1, -2)))(F_trial)
    parts = {
        "stencil": timed(stencil_fn, state.x, repeat=repeat),
        "p2g": timed(p2g_fn, stencil, state.v, state.C, state.tau, repeat=repeat),
        "grid_update_and_walls": timed(grid_fn, fields, repeat=repeat),
        "g2p": timed(g2p_fn, stencil, v_old, v_new, vp, repeat=repeat),
        "material (hencky stress)": timed(stress_fn, Fp, repeat=repeat),
        "  of which sym_log(F F^T)": timed(jax.jit(sym_log), b, repeat=repeat),
        "  of which eigh": timed(jax.jit(lambda a: eigh_sym(a)), b, repeat=repeat),
    }
    return {"dim": dim, "n_particles": state.n_particles, "grid_nodes": grid.n_nodes,
            "whole_step_ms": round(1e3 * whole, 4),
            "parts_ms": {k: round(1e3 * v, 4) for k, v in parts.items()},
            "whole_us_per_particle": round(1e6 * whole / state.n_particles, 4)}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--repeat", type=int, default=30)
    args = parser.parse_args()
    two, three = profile(2, args.particles, args.repeat), profile(3, args.particles, args.repeat)
    ratio = {k: round(three["parts_ms"][k] / two["parts_ms"][k], 2) for k in two["parts_ms"]}
    ratio["whole_step"] = round(three["whole_step_ms"] / two["whole_step_ms"], 2)
    per_particle = round(three["whole_us_per_particle"] / two["whole_us_per_particle"], 2)
    out = {"case": "Hencky block, float32, AFLIP, one thread", "device": device_name(), "2d": two, "3d": three,
           "ratio_3d_over_2d": ratio, "per_particle_ratio_3d_over_2d": per_particle}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
