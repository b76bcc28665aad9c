"""What does each collapse measurement fix? The experiment designer on S4 for all five keys.

    python docs/scripts/what_collapses_tell.py [--cells 8] [--noise 0.01] [--workers 2]

S4 (the cohesive column, L = H = 89 mm) at L/``cells``, at β = 0.25 and the scene's μ1, μ2, I0, ξ,
with two more experiments on the same material: a column twice as tall (aspect ratio 2) and the
same column on a 10° slope. For every candidate set of observations (``calibration.design.design``) the
expected 95 % half-width of β, μ1, μ2, I0 and ξ at ``--noise`` (a fraction of the profile's peak,
of the column length for the front, of the top's height), with the grid's share (1.5 dx). Writes
docs/results/what_collapses_tell.json and docs/figures/what_collapses_tell.png (the data's share
of the regions: at L/8 the grid's share spans the whole valley).
"""

import argparse
import json
import pathlib

import numpy as np

from calibration.batch.workers import Workers
from calibration.design.design import design
from calibration.plots.fits import plot_design
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
L = S4_SIDE
KEYS = ("beta", "mu1", "mu2", "I0", "xi")
VARIANTS = {"tall": {"height": 2 * L, "runout": 0.45}, "slope": {"slope_deg": 10.0, "runout": 0.35}}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--grid-check", type=float, default=1.5)
    parser.add_argument("--variants", type=json.loads, default=VARIANTS,
                        help="the other experiments, as JSON {label: {builder argument: value}} (heights and "
                             "runouts in m); default: a column twice as tall and a 10 degree slope")
    parser.add_argument("--out", default=str(ROOT / "docs/results/what_collapses_tell.json"))
    parser.add_argument("--figure", default=str(ROOT / "docs/figures/what_collapses_tell.png"))
    args = parser.parse_args()
    scene = cohesive_collapse(dx=L / args.cells, t_end=0.5, beta=0.25)
    with Workers(args.workers) as workers:
        result = design(scene, KEYS, {"beta": 0.25}, noise=args.noise, tolerance=0.1, variants=args.variants,
                        grid_ratio=args.grid_check or None, workers=workers)
    out = result.to_json()
    out.update(cells_per_L=args.cells, variants=args.variants)
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1))
    plot_design(result, args.figure, data_only=True,
                title=f"S4 at L/{args.cells}, {100 * args.noise:g} % noise: the data's 95 % regions of (β, μ1)")
    for c in result.candidates:
        rel = ", ".join(f"{k} {100 * r:.3g} %" for k, r in zip(KEYS, c.relative))
        data = ", ".join(f"{100 * d / abs(t):.3g}" for d, t in zip(c.halfwidth_data, result.theta))
        print(f"cost {c.cost:g}  {c.name}: {rel}  (data alone: {data} %)")
    print(result.statement, f"({result.wall_s:.0f} s)")
    print(np.round(result.theta, 4))


if __name__ == "__main__":
    main()
