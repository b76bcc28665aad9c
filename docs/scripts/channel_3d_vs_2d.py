"""S4 (β = 0.25, p_c0 = 500 Pa, ξ = 50) at dx = 4 mm in a 2 cm channel: 3D with its walls against
2D with the side-wall term, with and without wall friction (μ_w = 0.3). Writes
docs/results/channel_3d_vs_2d.json: runout, final height, the deposit profiles' RMS difference to
3D (% of H) and each run's time.

    python docs/scripts/channel_3d_vs_2d.py [--out DIR]   # about 3 min on one core per 3D run

Each run is ``python -m jaxmpm run`` as a user would call it; ``--from DIR`` assembles the JSON
from the outputs of an earlier call instead of running again.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

import numpy as np

COMMON = ["cohesive-collapse", "--dx", "0.004", "--set", "beta=0.25", "--set", "pc0=500", "--set", "xi=50",
          "--no-progress", "--json"]
RUNS = {
    "3d_frictionless": ["--dim", "3", "--width", "0.02", "--ppc", "2"],
    "3d_mu0.3": ["--dim", "3", "--width", "0.02", "--ppc", "2", "--side-walls", "0.02,0.3"],
    "2d_no_walls": [],
    "2d_mu0.3_K1": ["--side-walls", "0.02,0.3"],
    "2d_mu0.3_K0.7": ["--side-walls", "0.02,0.3,0.7"],
}
H = 0.089  # S4's column height, m


def _profile(path):
    rows = [line.strip() for line in open(path) if not line.startswith("#")]
    a = np.array([[float(v) for v in r.split(",")] for r in rows[1:]])
    xs = np.linspace(-0.01, 0.2, 800)
    return np.interp(xs, a[:, 0], a[:, 1], left=0.0, right=0.0)


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="/tmp/channel_3d_vs_2d")
    parser.add_argument("--from", dest="source", default=None)
    args = parser.parse_args(argv)
    folder = pathlib.Path(args.source or args.out)
    folder.mkdir(parents=True, exist_ok=True)
    results = {}
    for name, extra in RUNS.items():
        command = [sys.executable, "-m", "jaxmpm", "run", *COMMON, *extra, "--profile-csv", str(folder / f"{name}.csv")]
        if args.source is None:
            out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
            (folder / f"{name}.json").write_text(out)
        run = json.loads((folder / f"{name}.json").read_text())
        results[name] = {"command": " ".join(["python", *command[1:]]), "runout_m": run["runout"],
                         "y_max_m": run["y_max"], "n_particles": run["n_particles"], "run_s": run["run_s"],
                         "status": run["status"]}
    for name, row in results.items():
        ref = "3d_mu0.3" if "mu" in name else "3d_frictionless"
        if name.startswith("2d"):
            diff = _profile(folder / f"{name}.csv") - _profile(folder / f"{ref}.csv")
            row.update(against=ref, runout_rel=row["runout_m"] / results[ref]["runout_m"] - 1.0,
                       y_max_rel=row["y_max_m"] / results[ref]["y_max_m"] - 1.0,
                       profile_rms_pct_of_H=float(100 * np.sqrt(np.mean(diff**2)) / H))
    print(json.dumps({"scene": "S4, beta 0.25, pc0 500 Pa, xi 50, dx 4 mm, channel 2 cm (5 cells)",
                      "runs": results}, indent=1))


if __name__ == "__main__":
    main()
