"""Sparse grid against dense grid: the sparse grid's cost follows the particles, the
dense grid's follows the bounding box.

An elastic Hencky block (2 x 2 particles per cell, dx = 1/64 m, default parameters) falls half
a cell onto a no-slip floor 4 cells above the bottom of the grid, near the grid's lower-left
corner (it lands after about 130 steps and bounces), for a fixed number of steps (``--steps``,
the same for every case). The run stops long before t_end, so the ``BUDGET`` status bit is
expected; any other bit is reported. 2D, float32, one process; each rollout is compiled ahead
of time (``compile_s``) and then timed over ``--repeat`` calls (median ``run_s``). The sparse
grid is ``Config(active_nodes=9 * n_particles)``: one slot per stencil entry, which cannot
overflow (the script checks that ``GRID_FULL`` stays clear).

1. Fixed particles (4,096), growing box: 64^2 to 1024^2 cells (to 256^2 with ``--quick``).
   The particles, the time step and so the motion are the same in every box.
2. Fixed box (256^2 cells), growing particle count: 1,024 to 65,536 (to 16,384 with ``--quick``).

For each case: grid nodes, slots, particles, steps, compile and run time, particle-steps per
second, status, the number of distinct nodes the stencils touch at the start and the end
(what the slots must hold), and the largest |x_sparse - x_dense| of the final positions (float32
round-off is expected: the sparse transfers are the dense ones renumbered).

    python docs/scripts/sparse_cost.py            # about 4 minutes on 2 idle cores (estimated)
    python docs/scripts/sparse_cost.py --quick    # about 1 minute

writes docs/results/sparse_cost.json and docs/figures/sparse_cost.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import pathlib
import statistics
import time

import jax
import numpy as np

from jaxmpm.boundary import Wall
from jaxmpm.config import Config, Grid
from jaxmpm.params import Params
from jaxmpm.rollout import make_rollout
from jaxmpm.sampling import seed_box
from jaxmpm.state import BUDGET, describe_status, init_state
from jaxmpm.studies.bench import device_name, temp_mb

ROOT = pathlib.Path(__file__).resolve().parents[2]
DX = 1.0 / 64  # a 4,096-particle block is 32 cells (0.5 m) wide
BOXES = (64, 128, 256, 512, 1024)  # sweep 1: cells per axis
PARTICLES = (1_024, 4_096, 16_384, 65_536)  # sweep 2
FIXED_PARTICLES = 4_096  # sweep 1
FIXED_BOX = 256  # sweep 2
SLOTS_PER_PARTICLE = 9  # 3^2 stencil entries per particle: the sparse grid cannot overflow
DESCRIPTION = __doc__.split("\n\n")[0].replace("\n", " ")


def block_scene(cells: int, n_particles: int, steps: int):
    """A square block of about ``n_particles`` particles (2 per cell and axis), 16 cells from
    the left edge and half a cell above a floor 4 cells up, in a ``cells``^2 grid: it lands
    after about 130 steps and bounces."""
    width_cells = max(2, round((n_particles / 4) ** 0.5))
    width = width_cells * DX
    floor = 4 * DX
    lower = (16 * DX, floor + 0.5 * DX)
    upper = (lower[0] + width, lower[1] + width)
    config = Config(
        grid=Grid((cells, cells), DX),
        t_end=10.0,  # never reached: every run is capped at ``steps`` steps
        max_steps=steps,
        walls=(Wall((0.0, floor), (0.0, 1.0), "no-slip"),),
    )
    x, vol = seed_box(lower, upper, DX, 2)
    return config, init_state(config, x, vol, dtype="float32"), Params.create(dtype="float32")


def touched_nodes(x, grid: Grid) -> int:
    """Distinct nodes the particles' quadratic stencils touch (base = floor(x/dx - 1/2))."""
    base = np.floor((np.asarray(x, float) - np.asarray(grid.origin)) / grid.dx - 0.5).astype(np.int64)
    nx, ny = grid.nodes
    offsets = np.arange(3)
    i = (base[:, 0, None, None] + offsets[:, None]).clip(0, nx - 1)
    j = (base[:, 1, None, None] + offsets[None, :]).clip(0, ny - 1)
    return int(np.unique((i * ny + j).reshape(-1)).size)


def run_case(cells: int, n_particles: int, steps: int, sparse: bool, repeat: int):
    config, state, params = block_scene(cells, n_particles, steps)
    if sparse:
        config = dataclasses.replace(config, active_nodes=SLOTS_PER_PARTICLE * state.n_particles)
    rollout = jax.jit(make_rollout(config, observer=None))
    start = time.perf_counter()
    compiled = rollout.lower(state, params).compile()
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        final, _ = jax.block_until_ready(compiled(state, params))
        times.append(time.perf_counter() - start)
    run_s = statistics.median(times)
    n, n_steps, status = state.n_particles, int(final.steps), int(final.status)
    row = {
        "grid": "sparse" if sparse else "dense",
        "cells": [cells, cells],
        "grid_nodes": config.grid.n_nodes,
        "active_nodes": config.active_nodes,
        "n_particles": n,
        "n_steps": n_steps,
        "compile_s": round(compile_s, 3),
        "run_s": round(run_s, 4),
        "run_s_all": [round(t, 4) for t in times],
        "ms_per_step": round(1e3 * run_s / n_steps, 4),
        "particle_steps_per_s": round(n * n_steps / run_s),
        "xla_temp_mb": temp_mb(compiled),
        "status": status,
        "status_unexpected": describe_status(status & ~BUDGET),
        "touched_nodes_start": touched_nodes(state.x, config.grid),
        "touched_nodes_end": touched_nodes(final.x, config.grid),
    }
    return row, np.asarray(final.x)


def print_row(sweep: str, row: dict) -> None:
    slots = "-" if row["active_nodes"] is None else f"{row['active_nodes']:d}"
    flag = "" if not row["status_unexpected"] else "  STATUS: " + "; ".join(row["status_unexpected"])
    diff = row.get("max_abs_dx_vs_dense")
    diff = "" if diff is None else f"  |dx| {diff:.1e} m"
    print(f"{sweep} {row['grid']:6s} {row['cells'][0]:>4d}^2 nodes={row['grid_nodes']:>8d} slots={slots:>7s} "
          f"n={row['n_particles']:>6d} steps={row['n_steps']:>4d} compile {row['compile_s']:6.2f} s  "
          f"run {row['run_s']:7.3f} s  {row['ms_per_step']:7.3f} ms/step  "
          f"{row['particle_steps_per_s'] / 1e6:5.2f} M/s  status {row['status']}  "
          f"touched {row['touched_nodes_start']}->{row['touched_nodes_end']}{diff}{flag}", flush=True)


def run_pair(sweep: str, cells: int, n: int, steps: int, repeat: int, cache: dict) -> list[dict]:
    """Dense and sparse at one size; the sparse row records its distance to the dense one."""
    key = (cells, n)
    if key not in cache:
        dense, x_dense = run_case(cells, n, steps, False, repeat)
        sparse, x_sparse = run_case(cells, n, steps, True, repeat)
        sparse["max_abs_dx_vs_dense"] = float(np.max(np.abs(x_sparse - x_dense)))
        cache[key] = (dense, sparse, x_dense)
    dense, sparse, _ = cache[key]
    for row in (dense, sparse):
        print_row(sweep, row)
    return [dense, sparse]


def plot(results: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.3), constrained_layout=True)
    styles = {"dense": dict(marker="o", ls="-", color="C0"), "sparse": dict(marker="s", ls="--", color="C3")}
    for ax, sweep, xkey in ((ax1, "fixed_particles", "grid_nodes"), (ax2, "fixed_box", "n_particles")):
        rows = results[sweep]["rows"]
        for kind, style in styles.items():
            sel = [r for r in rows if r["grid"] == kind]
            label = "dense grid" if kind == "dense" else f"sparse grid ({SLOTS_PER_PARTICLE} slots per particle)"
            ax.loglog([r[xkey] for r in sel], [r["ms_per_step"] for r in sel], label=label, **style)
        for axis, fmt in ((ax.xaxis, "{:,.0f}"), (ax.yaxis, "{:g}")):  # plain numbers
            # 1-2-5 ticks, but decades only along a node axis that spans three of them (labels collide)
            decades = axis is ax.xaxis and xkey == "grid_nodes"
            axis.set_major_locator(LogLocator(subs=(1.0,) if decades else (1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _, fmt=fmt: fmt.format(v)))
            axis.set_minor_formatter(NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        ax.set_ylabel("run time per step (ms)")
        ax.legend(fontsize=8)
    steps = results["n_steps"]
    ax1.set_xlabel("grid nodes of the bounding box")
    sweep1 = results["fixed_particles"]
    ax1.set_title(f"fixed particles ({sweep1['n_particles']:,}), growing box "
                  f"({sweep1['cells'][0]}$^2$ to {sweep1['cells'][-1]}$^2$ cells)", fontsize=9)
    ax2.set_xlabel("particles")
    ax2.set_title(f"fixed box ({FIXED_BOX}$^2$ cells, {results['fixed_box']['rows'][0]['grid_nodes']:,} nodes), "
                  "growing particle count", fontsize=9)
    for ax, sweep, xkey in ((ax1, "fixed_particles", "cells"), (ax2, "fixed_box", "n_particles")):
        for r in results[sweep]["rows"]:
            if r["grid"] == "dense":
                text = f"{r['cells'][0]}$^2$" if xkey == "cells" else f"{r['n_particles']:,}"
                ax.annotate(text, (r["grid_nodes"] if xkey == "cells" else r["n_particles"], r["ms_per_step"]),
                            textcoords="offset points", xytext=(-4, 7), fontsize=7, color="C0", ha="right")
    fig.suptitle(f"Dense against sparse grid: 2D elastic block, float32, {steps} steps per case, {results['device']}",
                 fontsize=10)
    fig.savefig(path, dpi=130)


def main() -> None:
    parser = argparse.ArgumentParser(description=DESCRIPTION)
    parser.add_argument("--quick", action="store_true", help="boxes to 256^2, particles to 16,384, 200 steps")
    parser.add_argument("--steps", type=int, default=None, help="steps per case (default 300, 200 with --quick)")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per case (median)")
    parser.add_argument("--out", type=pathlib.Path, default=ROOT / "docs/results/sparse_cost.json")
    parser.add_argument("--figure", type=pathlib.Path, default=ROOT / "docs/figures/sparse_cost.png")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from the saved JSON")
    args = parser.parse_args()
    if args.plot_only:
        plot(json.loads(args.out.read_text()), args.figure)
        return
    steps = args.steps or (200 if args.quick else 300)
    boxes = BOXES[:3] if args.quick else BOXES
    particles = PARTICLES[:3] if args.quick else PARTICLES
    clock = time.perf_counter()
    cache: dict = {}
    fixed_particles = [row for cells in boxes
                       for row in run_pair("1", cells, FIXED_PARTICLES, steps, args.repeat, cache)]
    # The motion is the same in every box of sweep 1: the final positions should agree across boxes too.
    x_ref = cache[(boxes[0], FIXED_PARTICLES)][2]
    spread = max(float(np.max(np.abs(cache[(c, FIXED_PARTICLES)][2] - x_ref))) for c in boxes)
    print(f"sweep 1: largest |x_dense(box) - x_dense({boxes[0]}^2)| over the boxes: {spread:.1e} m", flush=True)
    fixed_box = [row for n in particles for row in run_pair("2", FIXED_BOX, n, steps, args.repeat, cache)]
    rows = fixed_particles + fixed_box
    unexpected = [f"{r['grid']} {r['cells'][0]}^2 n={r['n_particles']}: {r['status_unexpected']}"
                  for r in rows if r["status_unexpected"]]
    results = {
        "description": DESCRIPTION,
        "date": datetime.date.today().isoformat(),
        "device": device_name(),
        "jax": jax.__version__,
        "dtype": "float32",
        "dim": 2,
        "dx": DX,
        "material": "Hencky (default parameters)",
        "n_steps": steps,
        "repeat": args.repeat,
        "quick": args.quick,
        "slots_per_particle": SLOTS_PER_PARTICLE,
        "fixed_particles": {"n_particles": fixed_particles[0]["n_particles"], "cells": list(boxes),
                            "max_abs_dx_dense_across_boxes": spread, "rows": fixed_particles},
        "fixed_box": {"cells": FIXED_BOX, "n_particles": [r["n_particles"] for r in fixed_box[::2]], "rows": fixed_box},
        "max_abs_dx_sparse_vs_dense": max(r["max_abs_dx_vs_dense"] for r in rows if r["grid"] == "sparse"),
        "unexpected_status": unexpected,
        "wall_s": round(time.perf_counter() - clock, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    plot(results, args.figure)
    print(f"largest |x_sparse - x_dense|: {results['max_abs_dx_sparse_vs_dense']:.1e} m; "
          f"unexpected status: {unexpected or 'none'}; {results['wall_s']} s")
    print(f"wrote {args.out} and {args.figure}")


if __name__ == "__main__":
    main()
