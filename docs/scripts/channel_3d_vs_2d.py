"""3D channel collapses with frictional side walls against 2D with the side-wall term (issue 45).

Each case is one collapse in a channel of width W whose walls have Coulomb friction μ_w, run
four ways with ``python -m jaxmpm run`` as a user would call it:

- ``3d``: the 3D channel (``--dim 3 --width W --side-walls W,MU --ppc 2``), the reference;
- ``3d_coarse``: the same at about 2 dx, to see how far 3D is from converged;
- ``2d``: plane strain with the side-wall term (``--side-walls W,MU``, K = 1);
- ``2d_fine``: the same at dx/2.

Writes docs/results/channel_3d_vs_2d.json (runout, final height, the deposit profiles' RMS
difference to 3D in % of the column's height, each run's time) and, with ``--plot``, the figure
docs/figures/channel_3d_vs_2d.png (2D against 3D, and each run's difference to 3D against its cost).

    python docs/scripts/channel_3d_vs_2d.py [--out DIR] [--only NAME,...] [--plot FIG.png]
    python docs/scripts/channel_3d_vs_2d.py --from-json docs/results/channel_3d_vs_2d.json --plot FIG.png

dx is widened where needed to a whole number of cells across the channel (3D refuses others).
Runs whose JSON is already in DIR are not run again (so an interrupted call resumes); 3D at
dx = 4 mm costs 1 to 10 minutes a run on one core, the whole set about two hours (the S5 cases
of the 10 cm channel 35 minutes of it; 3D at dx/2 for the first case: 16 times its run at dx).
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
    for _w in (0.02, 0.05, 0.1):
        for _mu in (0.2, 0.4):
            CASES[f"S5_a{_a:g}_W{_w * 100:g}cm_mu{_mu:g}"] = (*_s5(_a), _w, _mu)

#: The cases run by default (S4 in a 10 cm channel, 25 cells across: 6 minutes a 3D run on one
#: core; S5 at a = 6 there 8 to 9). The rest of CASES (the 5 cm channel's other S5 cases) are not
#: in docs/validation.md §9.
DEFAULT = ("S4_W2cm_mu0.3", "S4_W2cm_mu0.2", "S4_W2cm_mu0.4", "S5_a2_W2cm_mu0.2", "S5_a2_W2cm_mu0.4",
           "S5_a0.5_W2cm_mu0.2", "S5_a0.5_W2cm_mu0.4", "S5_a6_W2cm_mu0.2", "S5_a6_W2cm_mu0.4",
           "S4_W5cm_mu0.2", "S4_W5cm_mu0.4", "S5_a2_W5cm_mu0.4", "S4_W10cm_mu0.2", "S4_W10cm_mu0.4",
           "S5_a0.5_W10cm_mu0.2", "S5_a0.5_W10cm_mu0.4", "S5_a2_W10cm_mu0.2", "S5_a2_W10cm_mu0.4",
           "S5_a6_W10cm_mu0.2", "S5_a6_W10cm_mu0.4")


def _aligned(dx, w):
    """The smallest spacing >= dx with a whole number of cells across the channel (the 3D walls
    stand on node rows)."""
    return w / max(1, int(w / dx + 1e-9))


def _variants(scene, dx, w, mu, fine=False):
    """(the grid spacing of the 3D and 2D runs, the runs' arguments); ``fine`` adds 3D at dx/2 and
    2D at dx/4."""
    walls = ["--side-walls", f"{w},{mu}"]
    three = ["--dim", "3", "--width", str(w), "--ppc", "2", *walls]
    dx = _aligned(dx, w)
    runs = {"3d": [*scene, "--dx", f"{dx:.12g}", *three],
            "3d_coarse": [*scene, "--dx", f"{_aligned(2 * dx, w):.12g}", *three],
            "2d": [*scene, "--dx", f"{dx:.12g}", *walls], "2d_fine": [*scene, "--dx", f"{dx / 2:.12g}", *walls]}
    if fine:
        runs.update({"3d_fine": [*scene, "--dx", f"{dx / 2:.12g}", *three],
                     "2d_finest": [*scene, "--dx", f"{dx / 4:.12g}", *walls]})
    return dx, runs


def _profile(path):
    rows = [line.strip() for line in open(path) if not line.startswith("#")]
    return np.array([[float(v) for v in r.split(",")] for r in rows[1:]])


def _front_runout(path, H):
    """The runout read from the deposit: the farthest x where the deposit is at least 2 % of H
    deep, minus the column's front at the start (the profile file's ``front0``). The largest
    particle x (the runs' own ``runout``) rests on single particles and moves with dx."""
    header = {k.strip(): v.strip() for k, _, v in (line[1:].partition(":") for line in open(path) if line[0] == "#")}
    front0 = json.loads(header["scene"])["front0"]
    profile = _profile(path)
    deep = profile[profile[:, 1] >= 0.02 * H]
    return float(deep[:, 0].max()) - front0


def _rms(a, b, H):
    xs = np.linspace(-0.01, 1.1 * max(a[:, 0].max(), b[:, 0].max()), 2000)
    diff = np.interp(xs, a[:, 0], a[:, 1], 0.0, 0.0) - np.interp(xs, b[:, 0], b[:, 1], 0.0, 0.0)
    return float(100 * np.sqrt(np.mean(diff**2)) / H)


def run_case(name, folder, dry=False, fine=False):
    scene, dx, H, w, mu = CASES[name]
    rows = {}
    dx, variants = _variants(scene, dx, w, mu, fine)
    for kind, args in variants.items():
        stem = folder / f"{name}_{kind}"
        command = [sys.executable, "-m", "jaxmpm", "run", *args, "--no-progress", "--json",
                   "--profile-csv", f"{stem}.csv"]
        if not pathlib.Path(f"{stem}.json").exists():
            if dry:
                continue
            print(f"running {name} {kind}", file=sys.stderr, flush=True)
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode and '"status"' not in done.stdout:  # not a run that ended with status bits
                raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr}")
            pathlib.Path(f"{stem}.json").write_text(done.stdout)
        run = json.loads(pathlib.Path(f"{stem}.json").read_text())
        rows[kind] = {"command": " ".join(["python", *command[1:-2]]), "runout_m": run["runout"],
                      "y_max_m": run["y_max"], "n_particles": run["n_particles"], "run_s": run["run_s"],
                      "front_runout_m": _front_runout(f"{stem}.csv", H), "status": run["status"],
                      "status_text": run["status_text"], "dx_m": run["dx"],
                      "profile": _profile(f"{stem}.csv")}
    if "3d" in rows:
        ref = rows["3d"]
        for row in rows.values():
            row.update(runout_rel=row["runout_m"] / ref["runout_m"] - 1.0,
                       front_runout_rel=row["front_runout_m"] / ref["front_runout_m"] - 1.0,
                       y_max_rel=row["y_max_m"] / ref["y_max_m"] - 1.0,
                       profile_rms_pct_of_H=_rms(row["profile"], ref["profile"], H))
    for row in rows.values():
        row.pop("profile")
    return {"W_m": w, "wall_friction": mu, "H_m": H, "dx_m": dx, "runs": rows}


def plot(results, path):
    """Left: 2D with the side-wall term against 3D at the same dx, every case. Right: for the
    first case, the runout of each model at every spacing it was run at against its run time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    markers = {"S4": "o", "S5_a0.5": "s", "S5_a2": "^", "S5_a6": "D"}
    for name, case in results.items():
        runs = case["runs"]
        if "3d" not in runs:
            continue
        scene = next(k for k in sorted(markers, key=len, reverse=True) if name.startswith(k))
        color = {0.2: "C0", 0.3: "C2", 0.4: "C3"}.get(case["wall_friction"], "k")
        ax1.plot(runs["3d"]["front_runout_m"] / case["H_m"], runs["2d"]["front_runout_m"] / case["H_m"],
                 markers[scene], color=color, mfc=color if case["W_m"] <= 0.02 else "none", ms=7)
        spacings = [k for k in ("3d_coarse", "3d", "3d_fine", "2d", "2d_fine", "2d_finest") if k in runs]
        if name == next(iter(results)):  # the first case, at every spacing it was run at
            for model, color2 in (("3d", "C3"), ("2d", "C0")):
                kinds = [k for k in spacings if k.startswith(model)]
                ax2.semilogx([runs[k]["run_s"] for k in kinds], [runs[k]["front_runout_m"] * 1000 for k in kinds],
                             "o-", color=color2, label=f"{model.upper()}, {name.replace('_', ' ')}")
                for k in kinds:
                    where = (runs[k]["run_s"], runs[k]["front_runout_m"] * 1000)
                    ax2.annotate(f"{runs[k]['dx_m'] * 1000:.3g} mm", where, textcoords="offset points", xytext=(4, 4),
                                 fontsize=8)
    lim = ax1.get_xlim()
    ax1.plot(lim, lim, "k-", lw=0.8)
    for f in (0.95, 1.05):
        ax1.plot(lim, [f * v for v in lim], "k:", lw=0.8)
    for scene, marker in markers.items():
        ax1.plot([], [], marker, color="gray", label=scene.replace("_", " a=").replace("a=a", "a="))
    for mu, color in ((0.2, "C0"), (0.3, "C2"), (0.4, "C3")):
        ax1.plot([], [], "-", color=color, label=f"μ_w = {mu}")
    ax1.set(xlabel="runout / H, 3D with frictional walls", ylabel="runout / H, 2D with the side-wall term (K = 1)",
            title="2D against 3D at the same dx (dotted ±5 %; hollow: W ≥ 5 cm)")
    ax1.legend(fontsize=8)
    ax2.set(xlabel="run time, one core (s)", ylabel="runout read from the deposit (mm)",
            title="runout against cost as dx is refined")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _pct(v) -> str:
    return f"{100 * v:+.1f} %"


def _against(runs, kind) -> str:
    """The runout of ``kind`` against 3D's; a failed run says so (its status bits), not a runout."""
    if kind not in runs:
        return ""
    run = runs[kind]
    return _pct(run["front_runout_rel"]) if not run["status"] else f"failed: status {run['status']}"


def markdown(results) -> str:
    """One row a case: 3D's runout (read from the deposit) and final height, 2D's differences at
    the same dx and at dx/2, 3D's at about 2 dx, the deposits' RMS difference and the costs."""
    lines = ["| case | dx | W / H | 3D runout, final height (mm) | 2D + walls: runout, height, deposit RMS (% of H) | "
             "2D at dx/2: runout against 3D at dx | 3D at about 2 dx: runout against 3D at dx | "
             "run time 3D / 2D (s) |", "|" + "---|" * 8]
    for name, case in results.items():
        runs = case["runs"]
        if "3d" not in runs:
            continue
        three, two = runs["3d"], runs["2d"]
        lines.append(f"| {name.replace('_', ' ')} | {case['dx_m'] * 1000:.3g} mm | {case['W_m'] / case['H_m']:.2g} | "
                     f"{three['front_runout_m'] * 1000:.1f}, {three['y_max_m'] * 1000:.1f} | "
                     f"{_pct(two['front_runout_rel'])}, {_pct(two['y_max_rel'])}, {two['profile_rms_pct_of_H']:.1f} | "
                     f"{_against(runs, '2d_fine')} | {_against(runs, '3d_coarse')} | "
                     f"{three['run_s']:.0f} / {two['run_s']:.1f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="/tmp/channel_3d_vs_2d")
    parser.add_argument("--only", default=",".join(DEFAULT), help="comma-separated case names")
    parser.add_argument("--collect", action="store_true", help="only assemble the runs already in --out")
    parser.add_argument("--fine", default="S4_W2cm_mu0.3", help="cases also run at 3D dx/2 and 2D dx/4 "
                        "(3D at dx/2 costs 16 times 3D at dx: 40 minutes for S4 in a 2 cm channel)")
    parser.add_argument("--plot", default=None, metavar="FIG.png")
    parser.add_argument("--markdown", action="store_true", help="print the table of docs/validation.md §9 instead")
    parser.add_argument("--from-json", default=None, metavar="FILE",
                        help="the figure and table from a results file (docs/results/channel_3d_vs_2d.json), no runs")
    args = parser.parse_args(argv)
    if args.from_json:
        results = json.loads(pathlib.Path(args.from_json).read_text())["cases"]
        if args.plot:
            plot(results, args.plot)
        print(markdown(results))
        return
    folder = pathlib.Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    names = [n for n in args.only.split(",") if n]
    unknown = [n for n in names if n not in CASES]
    if unknown:
        parser.error(f"--only: unknown cases {unknown}; known: {sorted(CASES)}")
    fine = set(args.fine.split(","))
    results = {name: run_case(name, folder, dry=args.collect, fine=name in fine) for name in names}
    if args.plot:
        plot(results, args.plot)
    if args.markdown:
        print(markdown(results))
        return
    print(json.dumps({"note": "S4: beta 0.25, pc0 500 Pa, xi 50, dx 4 mm; S5: glass beads, L0 5 cm, dx 5 mm; "
                      "3D: 2 x 2 x 2 particles a cell, 2D: the scenes' 3 x 3; side walls K = 1 in 2D",
                      "cases": results}, indent=1))


if __name__ == "__main__":
    main()
