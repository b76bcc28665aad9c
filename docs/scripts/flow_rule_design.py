"""Which slopes of a flow-rule table fix μ1, μ2 and I0: the 95 % half-widths of a fit of noise-free
twin tables (S1's glass beads, four thicknesses of 10-40 mm at each slope) with 1 % noise on each
velocity, for several sets of slopes (docs/incline_fits.md).

    python docs/scripts/flow_rule_design.py [--json docs/results/flow_rule_design.json]
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from calibration.data.flow_rule import FlowRuleTable
from calibration.studies.flow_rule import fit_flow_rule
from jaxmpm.params import DEFAULTS
from jaxmpm.precision import x64
from jaxmpm.scenes import S1_PARAMS
from jaxmpm.scenes.incline import steady_velocity

MATERIAL = {**DEFAULTS, **S1_PARAMS}
THICKNESSES = (0.01, 0.02, 0.03, 0.04)
DESIGNS = {
    "S1's slopes: 22, 24, 26, 28°": (22.0, 24.0, 26.0, 28.0),
    "22-30° every 2°": (22.0, 24.0, 26.0, 28.0, 30.0),
    "22-32° every 2°": (22.0, 24.0, 26.0, 28.0, 30.0, 32.0),
    "near θ1: 21.5-23°": (21.5, 22.0, 22.5, 23.0),
    "near θ2: 29-32°": (29.0, 30.0, 31.0, 32.0),
}


def design(slopes) -> dict:
    slope, h = (a.ravel() for a in np.meshgrid(slopes, THICKNESSES, indexing="ij"))
    p = MATERIAL
    with x64():
        u = np.asarray(steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"],
                                       "depth_averaged"))
    table = FlowRuleTable(slope, h, u, "depth_averaged", "noise-free twin", False, noise=0.01)
    start = {"mu1": 0.9 * math.tan(math.radians(min(slopes))), "mu2": 1.1 * math.tan(math.radians(max(slopes))),
             "I0": 0.5}
    result = fit_flow_rule(table, init=start, values={k: p[k] for k in ("rho", "rho_s", "d")})
    unc = result.uncertainty
    keys = list(result.keys)
    return {"slopes_deg": list(slopes), "rows": table.n, "message": result.message,
            "recovered_rel_error": {k: result.theta[k] / p[k] - 1 for k in keys},
            "halfwidth95_percent": {k: 100 * 1.96 * float(s) / p[k] for k, s in zip(keys, unc.stderr)},
            "corr_mu2_I0": float(unc.corr[1, 2]), "corr_mu1_mu2": float(unc.corr[0, 1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    out = {"material": {k: MATERIAL[k] for k in ("rho", "rho_s", "d", "mu1", "mu2", "I0")},
           "thicknesses_m": list(THICKNESSES), "noise": 0.01,
           "designs": {name: design(slopes) for name, slopes in DESIGNS.items()}}
    for name, row in out["designs"].items():
        hw = row["halfwidth95_percent"]
        print(f"{name:26s} mu1 ±{hw['mu1']:.2f} %  mu2 ±{hw['mu2']:.2f} %  I0 ±{hw['I0']:.1f} %  "
              f"corr(mu2, I0) {row['corr_mu2_I0']:+.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
