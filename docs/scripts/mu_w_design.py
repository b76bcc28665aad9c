"""Can a collapse fit find the side walls' friction μ_w beside the material?

    taskset -c 1 python docs/scripts/mu_w_design.py [--cells 8] [--noise 0.01]

S4 (the cohesive column, L = H = 89 mm, β = 0.25, p_c0 = 500 Pa, ξ = 50) at L/``cells`` in a 2D
channel whose walls' friction is the parameter μ_w = 0.3 (``jaxmpm.SideWalls(width, "mu_w")``,
K = 1), W = 2 cm, and the same column in channels 5 cm and 10 cm wide. ``calibration.design.design``
gives the expected 95 % half-widths of (β, μ1, μ_w) at ``--noise`` on every observation, for one
channel's observations and for two or three widths together, the correlation of μ1 with μ_w, and
(β, μ1)'s half-widths from the same sets with μ_w known (measured apart, by a tilting test).
Writes docs/results/mu_w_design.json.
"""

import argparse
import json
import pathlib
import time

import numpy as np

from calibration.design.design import design
from jaxmpm import SideWalls
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
KEYS = ("beta", "mu1", "mu_w")
WIDTHS = {"main": 0.02, "w5": 0.05, "w10": 0.10}


def sets():
    one = [(f"{kind} at W = {100 * WIDTHS['main']:g} cm", (("main", kind),)) for kind in ("final", "profiles")]
    one.append(("profiles in time + front at W = 2 cm", (("main", "profiles"), ("main", "front"))))
    two = [("final profiles at W = 2 and 5 cm", (("main", "final"), ("w5", "final"))),
           ("final profiles at W = 2 and 10 cm", (("main", "final"), ("w10", "final"))),
           ("final profiles at W = 2, 5 and 10 cm", (("main", "final"), ("w5", "final"), ("w10", "final"))),
           ("profiles in time + front at W = 2 and 10 cm",
            (("main", "profiles"), ("main", "front"), ("w10", "profiles"), ("w10", "front")))]
    return one + two


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--noise", type=float, default=0.01)
    args = parser.parse_args()
    clock = time.perf_counter()
    scene = cohesive_collapse(dx=S4_SIDE / args.cells, t_end=0.5, beta=0.25, pc0=500.0, xi=50.0, mu_w=0.3,
                              side_walls=SideWalls(WIDTHS["main"], "mu_w"))
    variants = {label: {"side_walls": SideWalls(w, "mu_w")} for label, w in WIDTHS.items() if label != "main"}
    result = design(scene, KEYS, noise=args.noise, variants=variants, sets=sets())
    out = result.to_json()
    i, j = KEYS.index("mu1"), KEYS.index("mu_w")
    out["correlation_mu1_mu_w"] = {c.name: float(c.cov_data[i, j] / np.sqrt(c.cov_data[i, i] * c.cov_data[j, j]))
                                   for c in result.candidates}
    fixed = design(scene, KEYS[:2], noise=args.noise, variants=variants, sets=sets())  # μ_w known (measured apart)
    out["mu_w_fixed"] = {c.name: dict(zip(KEYS[:2], map(float, c.relative))) for c in fixed.candidates}
    out["settings"] = {"dx": S4_SIDE / args.cells, "t_end": 0.5, "beta": 0.25, "pc0": 500.0, "xi": 50.0,
                       "mu_w": 0.3, "K": 1.0, "widths_m": WIDTHS, "noise": args.noise, "grid_share": "not measured"}
    out["script_wall_s"] = round(time.perf_counter() - clock, 1)
    path = ROOT / "docs" / "results" / "mu_w_design.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print("\n".join(result.lines()))
    print(json.dumps({"correlation": out["correlation_mu1_mu_w"], "mu_w_fixed": out["mu_w_fixed"]}, indent=1))


if __name__ == "__main__":
    main()
