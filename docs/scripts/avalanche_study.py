"""The S6 avalanche against resolution and against the snow (issue 13, item 6).

    python docs/scripts/avalanche_study.py [--quick]

Runs ``jaxmpm.scenes.avalanche`` on the shipped ISeeSnow CoulombOnly centre line (μ_w = 0.4) at
dx = 2, 1 and 0.5 m with dry snow, then at dx = 1 m (2 m with --quick) with wet snow and with the
dry snow's μ1 at tan 15° and tan 25°, and prints one JSON line per run: runout_x, the front's
largest speed, the peak pressure, the particles, steps and wall time. Writes
docs/results/avalanche_study.json and the figure and GIF of the default run (dry, dx = 1 m):
docs/figures/avalanche.png, docs/figures/avalanche.gif.
"""

import argparse
import json
import math
import pathlib
import time

import numpy as np

import jaxmpm as jm
from jaxmpm.avalanche import path_fields
from jaxmpm.plots import animate_avalanche, plot_avalanche
from jaxmpm.scenes.avalanche import avalanche

ROOT = pathlib.Path(__file__).resolve().parents[2]


def run(dx, snow="dry", t_end=100.0, **values):
    scene = avalanche(dx=dx, snow=snow, t_end=t_end, frames=int(t_end), **values)
    config, state, params = scene
    t0 = time.perf_counter()
    result = jm.simulate(config, state, params, observer=lambda s, p: {"x": s.x, "v": s.v}, throw=False, timed=True)
    wall = time.perf_counter() - t0
    fields = path_fields(config.walls[0], result.frames["x"], result.frames["v"], state.vol0,
                         np.asarray(config.frame_times), float(params.rho), dx)
    row = {"dx": dx, "snow": snow, **{k: float(v) for k, v in values.items()}, "mu1": float(params.mu1),
           "beta": float(params.beta), "n_particles": int(state.n_particles), "n_steps": int(result.state.steps),
           "status": result.status, **fields.summary(), "compile_s": round(result.compile_s, 2),
           "run_s": round(result.run_s, 2), "wall_s": round(wall, 1)}
    print(json.dumps(row), flush=True)
    return row, fields, params


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    rows = []
    grids = (2.0, 1.0) if args.quick else (2.0, 1.0, 0.5)
    for dx in grids:
        row, fields, params = run(dx)
        rows.append(row)
        if dx == 1.0:
            plot_avalanche(fields, ROOT / "docs/figures/avalanche.png",
                           title="S6 avalanche (ISeeSnow CoulombOnly terrain), dry snow, dx = 1 m, mu_w = 0.4")
            animate_avalanche(fields, ROOT / "docs/figures/avalanche.gif", fps=8)
    base = 2.0 if args.quick else 1.0
    rows.append(run(base, snow="wet")[0])
    for angle in (15.0, 25.0):
        rows.append(run(base, mu1=math.tan(math.radians(angle)))[0])
    (ROOT / "docs/results/avalanche_study.json").write_text(json.dumps({"runs": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
