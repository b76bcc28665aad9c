"""Collapses and inclines in one design: which mix of experiments fixes all five keys?

    taskset -c 1 python docs/scripts/mixed_design.py [--cells 8] [--noise 0.01] [--workers 1]

S4 (the cohesive column, L = H = 89 mm, p_c0 = 500 Pa, ξ = 50) at L/``cells`` with β = 0.25 and
the scene's μ1, μ2, I0, with the two other collapses of docs/what_collapses_tell.md (a column twice
as tall, the same column on a 10° slope) and two incline plans on the same material: the shipped
twin flow-rule table (experiments_data/synthetic/flow_rule_twin.csv, slopes 22–28°) and a plan
over 22–32° (every 2°, the same four thicknesses). A design uses a table's slopes, thicknesses and
quantity, not its velocities (the model's at θ are the data). ``calibration.design.design`` ranks
every candidate set by cost, at ``--noise`` on every observation (the velocities included), with
the grid's share (1.5 dx) for the collapses. Writes docs/results/mixed_design.json: the
``DesignResult`` JSON, the settings, the recommendation on the data's share alone, and the wall
time.
"""

import argparse
import json
import pathlib
import time

import numpy as np

from calibration.batch.workers import Workers
from calibration.data.flow_rule import FlowRuleTable, load_flow_rule
from calibration.design.design import design
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
L = S4_SIDE
KEYS = ("beta", "mu1", "mu2", "I0", "xi")
VARIANTS = {"tall": {"height": 2 * L, "runout": 0.45}, "slope": {"slope_deg": 10.0, "runout": 0.35}}
THICKNESSES = (0.01, 0.02, 0.03, 0.04)
WIDE_SLOPES = (22.0, 24.0, 26.0, 28.0, 30.0, 32.0)


def wide_plan() -> FlowRuleTable:
    """Slopes 22–32° every 2°, four thicknesses each; the velocity column is a placeholder (1 m/s):
    a design reads a table's plan, not its velocities."""
    slope, h = np.meshgrid(WIDE_SLOPES, THICKNESSES, indexing="ij")
    return FlowRuleTable(slope.ravel(), h.ravel(), np.ones(slope.size), "depth_averaged",
                         "docs/scripts/mixed_design.py: a plan, not a measurement", secondary=False,
                         experiment="incline plan 22-32 deg")


def recommended_on_data(result, tolerance):
    """The cheapest candidate whose data's half-widths alone (no grid share) meet ``tolerance``."""
    theta = np.abs(result.theta)
    return next((c for c in result.candidates if np.all(c.halfwidth_data / theta <= tolerance)), None)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--tolerance", type=float, default=0.1)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--grid-check", type=float, default=1.5)
    parser.add_argument("--out", default=str(ROOT / "docs/results/mixed_design.json"))
    args = parser.parse_args()
    clock = time.perf_counter()
    scene = cohesive_collapse(dx=L / args.cells, t_end=0.5, beta=0.25, pc0=500.0, xi=50.0)
    inclines = {"twin_22_28": load_flow_rule(ROOT / "experiments_data/synthetic/flow_rule_twin.csv"),
                "plan_22_32": wide_plan()}
    with Workers(args.workers) as workers:
        result = design(scene, KEYS, {"beta": 0.25}, noise=args.noise, tolerance=args.tolerance, variants=VARIANTS,
                        inclines=inclines, grid_ratio=args.grid_check or None, workers=workers)
    wall = time.perf_counter() - clock
    on_data = recommended_on_data(result, args.tolerance)
    out = result.to_json()
    out.update(settings={"scene": "S4 cohesive_collapse", "cells_per_L": args.cells, "dx": L / args.cells,
                         "t_end": 0.5, "beta": 0.25, "pc0": 500.0, "xi": 50.0, "noise": args.noise,
                         "tolerance": args.tolerance, "grid_ratio": args.grid_check or None, "workers": args.workers,
                         "variants": VARIANTS,
                         "inclines": {label: {"slopes_deg": t.slopes.tolist(), "thicknesses_m": np.unique(t.h).tolist(),
                                              "quantity": t.quantity, "rows": t.n} for label, t in inclines.items()}},
               recommended_on_data_alone=None if on_data is None else {"name": on_data.name, "cost": on_data.cost},
               script_wall_s=round(wall, 1))
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    for c in result.candidates:
        data = ", ".join(f"{k} {100 * d / abs(t):.3g} %" for k, d, t in zip(KEYS, c.halfwidth_data, result.theta))
        total = ", ".join(f"{100 * r:.3g}" for r in c.relative)
        print(f"cost {c.cost:g}  {c.name}: {data}  (with the grid's share: {total} %)")
    print(result.statement)
    print("on the data's share alone:", None if on_data is None else f"{on_data.name} (cost {on_data.cost:g})",
          f"({wall:.0f} s)")


if __name__ == "__main__":
    main()
