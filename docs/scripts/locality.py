"""Does particle order matter? Would particles sorted by cell, so that scatters and gathers
touch memory in order, make a step faster?

The state of ``python -m jaxmpm bench --scene column`` (S2, 10,240 particles, float32, the full
model) after 0.02 s of flow is stepped 100 times with its particles in three orders: as seeded
(the lattice, row by row), randomly permuted (the worst case, what a long mixing flow tends
to), and sorted by the cell that holds them (what a periodic sort in the state would restore).
The same for the 3D Hencky block of ``bench --dim 3`` at 32,000 particles. The step is the same
function in each case; only the memory order of the particles differs.

    python docs/scripts/locality.py      -> JSON on stdout (docs/results/locality.json), three minutes
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.kernels import node_strides
from jaxmpm.rollout import make_rollout
from jaxmpm.step import make_step
from jaxmpm.studies.bench import bench_scene, device_name, median_time


def timed(fn, *args, repeat=5):
    return median_time(fn, *args, repeat=repeat)


def permute(state, order):
    """The state with its particle axis permuted (every per-particle leaf has it first)."""
    n = state.n_particles
    return jax.tree.map(lambda a: a[order] if (getattr(a, "ndim", 0) and a.shape[0] == n) else a, state)


def case(scene, dim, warm_t):
    config, state, params = bench_scene(scene, False, dim, "float32")
    warm = make_rollout(dataclasses.replace(config, t_end=warm_t, block_size=None), observer=None)
    state = jax.jit(warm)(state, params)[0]
    step = make_step(config)
    n = 100
    scan = jax.jit(lambda s: jax.lax.scan(lambda c, _: (step(c, params), None), s, None, length=n)[0])
    grid = config.grid
    x = np.asarray(state.x)
    cell = np.floor((x - np.asarray(grid.origin)) / grid.dx).astype(np.int64)
    key = (cell * node_strides(grid.nodes)).sum(axis=1)  # the flat node number of the cell's corner
    orders = {
        "as seeded": np.arange(state.n_particles),
        "random": np.random.default_rng(0).permutation(state.n_particles),
        "sorted by cell": np.argsort(key, kind="stable"),
    }
    ms = {name: round(1e3 * timed(scan, permute(state, jnp.asarray(o))) / n, 4) for name, o in orders.items()}
    return {"n_particles": state.n_particles, "grid_nodes": grid.n_nodes, "step_ms": ms,
            "random_over_sorted": round(ms["random"] / ms["sorted by cell"], 2),
            "seeded_over_sorted": round(ms["as seeded"] / ms["sorted by cell"], 2)}


def main():
    out = {"device": device_name(), "dtype": "float32",
           "column-S2 (2D, full model)": case("column", 2, 0.02),
           "elastic-block (3D)": case("block", 3, 0.05)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
