"""Does a collapse in a channel move as a plug across the width? (the side-wall term's assumption,
docs/model.md §5). Runs S4 (β = 0.25, p_c0 = 500 Pa, ξ = 50) in 3D between frictional walls and
compares, frame by frame, the mean downstream speed of the moving particles in the outer fifths
of the width (next to the walls) with that of the middle fifth.

    python docs/scripts/channel_plug_flow.py [--width 0.05] [--friction 0.4] [--cells 6]

Prints JSON: per frame, the moving particles and the ratio v_wall / v_centre (1 for a plug).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile

import h5py
import numpy as np


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--width", type=float, default=0.05, help="channel width, m")
    parser.add_argument("--friction", type=float, default=0.4, help="the walls' Coulomb friction")
    parser.add_argument("--cells", type=int, default=6, help="cells across the width (dx = width / cells)")
    parser.add_argument("--frames", type=int, default=10)
    args = parser.parse_args(argv)
    dx = args.width / args.cells
    with tempfile.TemporaryDirectory() as tmp:
        out = f"{tmp}/run.h5"
        command = [sys.executable, "-m", "jaxmpm", "run", "cohesive-collapse", "--set", "beta=0.25", "--set", "pc0=500",
                   "--set", "xi=50", "--dim", "3", "--width", str(args.width), "--dx", f"{dx:.12g}", "--ppc", "2",
                   "--side-walls", f"{args.width},{args.friction}", "--frames", str(args.frames), "--out", out,
                   "--no-progress", "--json"]
        run = json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout)
        rows = []
        with h5py.File(out) as f:
            for name in sorted(f["frames"]):
                x, v = f["frames"][name]["x"][:], f["frames"][name]["v"][:]
                across = np.abs(x[:, 2] / args.width - 0.5)  # 0 in the middle, 0.5 at a wall
                moving = np.abs(v[:, 0]) > 0.02  # m/s
                wall, centre = moving & (across > 0.3), moving & (across < 0.1)
                if wall.sum() < 20 or centre.sum() < 20:
                    rows.append({"frame": name, "moving": int(moving.sum())})
                    continue
                rows.append({"frame": name, "moving": int(moving.sum()),
                             "v_wall_over_v_centre": float(np.mean(v[wall, 0]) / np.mean(v[centre, 0]))})
    print(json.dumps({"command": " ".join(["python", *command[1:]]), "runout_m": run["runout"],
                      "run_s": run["run_s"], "frames": rows}, indent=1))


if __name__ == "__main__":
    main()
