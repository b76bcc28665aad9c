"""3D channel collapses with frictional side walls against 2D with the side-wall term (issue 45).

Each case is one collapse in a channel of width W whose walls have Coulomb friction μ_w, run
four ways with ``python -m jaxmpm run`` as a user would call it:

- ``3d``: the 3D channel (``--dim 3 --width W --side-walls W,MU --ppc 2``), the reference;
- ``3d_coarse``: the same at 2 dx, to see how far 3D is from converged;
- ``2d``: plane strain with the side-wall term (``--side-walls W,MU``, K = 1);
- ``2d_fine``: the same at dx/2.

Writes docs/results/channel_3d_vs_2d.json (runout, final height, the deposit profiles' RMS
difference to 3D in % of the column's height, each run's time) and, with ``--plot``, the figure
docs/figures/channel_3d_vs_2d.png (2D against 3D, and each run's difference to 3D against its cost).

    python docs/scripts/channel_3d_vs_2d.py [--out DIR] [--only NAME,...] [--plot FIG.png]

Runs whose JSON is already in DIR are not run again (so an interrupted call resumes); 3D at
dx = 4 mm costs 3 to 17 minutes a run on one core, the whole set about two hours.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

import numpy as np

S4 = ["cohesive-collapse", "--set", "beta=0.25", "--set", "pc0=500", "--set", "xi=50"]
S4_DX, S4_H = 0.004, 0.089
S5_DX, S5_L0 = 0.005, 0.05


def _s5(a):
    return ["aspect-ratio", "--aspect", str(a)], S5_DX, a * S5_L0


#: name -> (scene arguments, dx, column height H, channel width W, wall friction μ_w)
CASES = {}
for _w in (0.02, 0.05, 0.1):
    for _mu in (0.2, 0.3, 0.4):
        CASES[f"S4_W{_w * 100:g}cm_mu{_mu:g}"] = (S4, S4_DX, S4_H, _w, _mu)
for _a in (0.5, 2, 6):
    for _w in (0.02, 0.05):
        for _mu in (0.2, 0.4):
            CASES[f"S5_a{_a:g}_W{_w * 100:g}cm_mu{_mu:g}"] = (*_s5(_a), _w, _mu)

#: The cases run by default, cheapest first (the rest cost more than an afternoon on two cores).
DEFAULT = ("S4_W2cm_mu0.3", "S4_W2cm_mu0.2", "S4_W2cm_mu0.4", "S5_a2_W2cm_mu0.2", "S5_a2_W2cm_mu0.4",
           "S5_a0.5_W2cm_mu0.2", "S5_a0.5_W2cm_mu0.4", "S5_a6_W2cm_mu0.2", "S5_a6_W2cm_mu0.4",
           "S4_W5cm_mu0.2", "S4_W5cm_mu0.4", "S5_a2_W5cm_mu0.4", "S4_W10cm_mu0.4")


def _variants(scene, dx, w, mu):
    walls = ["--side-walls", f"{w},{mu}"]
    three = ["--dim", "3", "--width", str(w), "--ppc", "2", *walls]
    return {"3d": [*scene, "--dx", str(dx), *three], "3d_coarse": [*scene, "--dx", str(2 * dx), *three],
            "2d": [*scene, "--dx", str(dx), *walls], "2d_fine": [*scene, "--dx", str(dx / 2), *walls]}


def _profile(path):
    rows = [line.strip() for line in open(path) if not line.startswith("#")]
    return np.array([[float(v) for v in r.split(",")] for r in rows[1:]])


def _rms(a, b, H):
    xs = np.linspace(-0.01, 1.1 * max(a[:, 0].max(), b[:, 0].max()), 2000)
    diff = np.interp(xs, a[:, 0], a[:, 1], 0.0, 0.0) - np.interp(xs, b[:, 0], b[:, 1], 0.0, 0.0)
    return float(100 * np.sqrt(np.mean(diff**2)) / H)


def run_case(name, folder, dry=False):
    scene, dx, H, w, mu = CASES[name]
    rows = {}
    for kind, args in _variants(scene, dx, w, mu).items():
        stem = folder / f"{name}_{kind}"
        command = [sys.executable, "-m", "jaxmpm", "run", *args, "--no-progress", "--json",
                   "--profile-csv", f"{stem}.csv"]
        if not pathlib.Path(f"{stem}.json").exists():
            if dry:
                continue
            print(f"running {name} {kind}", file=sys.stderr, flush=True)
            out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
            pathlib.Path(f"{stem}.json").write_text(out)
        run = json.loads(pathlib.Path(f"{stem}.json").read_text())
        rows[kind] = {"command": " ".join(["python", *command[1:-2]]), "runout_m": run["runout"],
                      "y_max_m": run["y_max"], "n_particles": run["n_particles"], "run_s": run["run_s"],
                      "status": run["status"], "profile": _profile(f"{stem}.csv")}
    if "3d" in rows:
        ref = rows["3d"]
        for row in rows.values():
            row.update(runout_rel=row["runout_m"] / ref["runout_m"] - 1.0,
                       y_max_rel=row["y_max_m"] / ref["y_max_m"] - 1.0,
                       profile_rms_pct_of_H=_rms(row["profile"], ref["profile"], H))
    for row in rows.values():
        row.pop("profile")
    return {"W_m": w, "wall_friction": mu, "H_m": H, "dx_m": dx, "runs": rows}


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    styles = {"2d": ("o", "C0", "2D + walls, dx"), "2d_fine": ("s", "C1", "2D + walls, dx/2"),
              "3d_coarse": ("^", "C2", "3D, 2 dx")}
    for name, case in results.items():
        runs = case["runs"]
        if "3d" not in runs:
            continue
        ref = runs["3d"]["runout_m"]
        for kind, (marker, color, label) in styles.items():
            if kind in runs:
                ax1.plot(ref / case["H_m"], runs[kind]["runout_m"] / case["H_m"], marker, color=color,
                         label=label if name == next(iter(results)) else None)
                ax2.loglog(runs[kind]["run_s"] / runs["3d"]["run_s"], max(abs(runs[kind]["runout_rel"]), 1e-4),
                           marker, color=color, label=label if name == next(iter(results)) else None)
    lim = ax1.get_xlim()
    ax1.plot(lim, lim, "k-", lw=0.8)
    for f in (0.95, 1.05):
        ax1.plot(lim, [f * v for v in lim], "k:", lw=0.8)
    ax1.set(xlabel="runout / H, 3D with frictional walls (dx)", ylabel="runout / H",
            title="2D with the side-wall term against 3D (dotted: ±5 %)")
    ax1.legend()
    ax2.axhline(0.05, color="k", ls=":", lw=0.8)
    ax2.set(xlabel="cost, fraction of the 3D run's time", ylabel="|runout − 3D runout| / 3D runout",
            title="difference to 3D against cost")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="/tmp/channel_3d_vs_2d")
    parser.add_argument("--only", default=",".join(DEFAULT), help="comma-separated case names")
    parser.add_argument("--collect", action="store_true", help="only assemble the runs already in --out")
    parser.add_argument("--plot", default=None, metavar="FIG.png")
    args = parser.parse_args(argv)
    folder = pathlib.Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    names = [n for n in args.only.split(",") if n]
    unknown = [n for n in names if n not in CASES]
    if unknown:
        parser.error(f"--only: unknown cases {unknown}; known: {sorted(CASES)}")
    results = {name: run_case(name, folder, dry=args.collect) for name in names}
    if args.plot:
        plot(results, args.plot)
    print(json.dumps({"note": "S4: beta 0.25, pc0 500 Pa, xi 50, dx 4 mm; S5: glass beads, L0 5 cm, dx 5 mm; "
                      "3D: 2 x 2 x 2 particles a cell, 2D: the scenes' 3 x 3; side walls K = 1 in 2D",
                      "cases": results}, indent=1))


if __name__ == "__main__":
    main()
