r"""Does a fitted μ1 move with the channel's width? docs/results/width_invariance.json and
docs/figures/width_invariance.png (issue 45; the mission's test of a material property).

The "experiment" is the 3D channel: S4's column (β = 0.25, p_c0 = 500 Pa, ξ = 50, μ1 = 0.382)
collapsing between Coulomb side walls (μ_w = 0.3) W = 2, 4 and 10 cm apart (5, 10 and 25 cells), at dx = 4 mm with
2 × 2 × 2 particles a cell; its final deposit h(x) is the data. Each deposit is fitted for μ1
alone (the other keys known) by 2D at the same dx, two ways:

- ``walls``: 2D with the side-wall term of the channel's width and friction (``--side-walls W,0.3``);
- ``plain``: 2D without it, what a fit of a channel experiment did before side walls existed.

Each way is run as a user would (``python -m calibration fit ... --fit mu1 --init mu1=0.45``: the
point, the verdict and its statement) and as a scan of the loss over μ1 (2D runs on ``SCAN``; the
minimum from the parabola through the lowest point and its neighbours), which needs no verdict.
A μ1 that is a property of the material comes back the same at every width. Both models are at
dx = 4 mm, where 3D's own runout is still 8 % from its value at 2 mm (docs/validation.md §9):
this compares the models at one grid.

    python docs/scripts/width_invariance.py [--out DIR]   # about 40 minutes on one core
    python docs/scripts/width_invariance.py --from-json docs/results/width_invariance.json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENE = ["cohesive-collapse", "--set", "beta=0.25", "--set", "pc0=500", "--set", "xi=50", "--dx", "0.004"]
WIDTHS, MU_W, MU1, START = (0.02, 0.04, 0.1), 0.3, 0.3818628674187188, 0.45
#: The μ1 values of the loss scans (μ1 stays below μ2 = 0.643).
SCAN = np.round(np.arange(0.30, 0.635, 0.015), 4)


def _run(command, path: pathlib.Path):
    """``command``'s JSON, kept in ``path`` (an interrupted study resumes)."""
    if not path.exists():
        print("running", " ".join(command[2:]), file=sys.stderr, flush=True)
        path.write_text(subprocess.run([sys.executable, *command], check=True, capture_output=True, text=True).stdout)
    return json.loads(path.read_text())


def scan(csv, width, dx=0.004, values=SCAN) -> dict:
    """The loss against μ1 at ``values`` (2D at ``dx``, side walls ``width`` apart or none) and
    its minimum."""
    import calibration as cal
    from jaxmpm import SideWalls
    from jaxmpm.scenes import build_scene

    walls = None if width is None else SideWalls(width, MU_W)
    scene = build_scene("cohesive-collapse", dx=dx, values={"beta": 0.25, "pc0": 500.0, "xi": 50.0},
                        side_walls=walls)
    objective = cal.Objective(scene, ("mu1",), profile=cal.load_profile(str(csv)))
    values = np.asarray(values, float)
    loss = np.array([objective.loss(np.array([m])) for m in values])
    lowest = int(np.argmin(loss))
    i = int(np.clip(lowest, 1, len(values) - 2))
    a, b, _ = np.polyfit(values[i - 1:i + 2], loss[i - 1:i + 2], 2)
    best = float(-b / (2 * a)) if a > 0 and 0 < lowest < len(values) - 1 else float(values[lowest])
    print(f"scan W={width} dx={dx}: minimum near mu1 = {best:.4f}", file=sys.stderr, flush=True)
    return {"dx": dx, "mu1": values.tolist(), "loss": loss.tolist(), "minimum": best,
            "at_edge": lowest in (0, len(values) - 1)}


def fine(folder: pathlib.Path) -> dict:
    """The 2 cm channel at dx = 2 mm: 3D there (31 minutes on one core) against 2D scans there,
    narrower about each model's minimum at 4 mm."""
    w, walls = 0.02, ["--side-walls", f"0.02,{MU_W}"]
    csv = folder / "W2cm_3d_2mm.csv"
    scene = [*SCENE[:-1], "0.002"]
    three = _run(["-m", "jaxmpm", "run", *scene, "--dim", "3", "--width", str(w), "--ppc", "2", *walls,
                  "--no-progress", "--json", "--profile-csv", str(csv)], folder / "W2cm_3d_2mm.json")
    return {"W_m": w, "dx": 0.002, "3d": {k: three[k] for k in ("runout", "y_max", "n_particles", "run_s", "status")},
            "walls": scan(csv, w, 0.002, np.arange(0.33, 0.425, 0.015)),
            "plain": scan(csv, None, 0.002, np.arange(0.48, 0.605, 0.02))}


def study(folder: pathlib.Path) -> dict:
    out = {"note": __doc__.split("\n\n")[1], "truth": {"mu1": MU1}, "mu_w": MU_W, "start": {"mu1": START}, "cases": {}}
    for w in WIDTHS:
        walls = ["--side-walls", f"{w},{MU_W}"]
        csv = folder / f"W{w * 100:g}cm_3d.csv"
        three = _run(["-m", "jaxmpm", "run", *SCENE, "--dim", "3", "--width", str(w), "--ppc", "2", *walls,
                      "--no-progress", "--json", "--profile-csv", str(csv)], folder / f"W{w * 100:g}cm_3d.json")
        case = {"3d": {k: three[k] for k in ("runout", "y_max", "n_particles", "run_s", "status")}}
        for model, extra in (("walls", walls), ("plain", [])):
            fit = _run(["-m", "calibration", "fit", "--scene", *SCENE, *extra, "--data", str(csv), "--fit", "mu1",
                        "--init", f"mu1={START}", "--workers", "1", "--no-progress", "--json"],
                       folder / f"W{w * 100:g}cm_fit_{model}.json")
            case[model] = {"fit": {"mu1": fit["params"]["mu1"], "ci95": fit.get("ci95", {}).get("mu1"),
                                   "verdict": fit["verdict"]["verdict"], "statement": fit["statement"],
                                   "iterations": fit["iterations"], "wall_s": fit["wall_s"],
                                   "residual_rms_m": fit["residual_rms_m"]},
                           "scan": scan(csv, w if model == "walls" else None)}
        out["cases"][f"{w * 100:g} cm"] = case
    return out


def plot(out: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.3))
    widths = [float(name.split()[0]) for name in out["cases"]]
    styles = {"walls": ("C0", "2D with the side-wall term"), "plain": ("C3", "2D without side walls")}
    for (name, case), ls in zip(out["cases"].items(), ("-", "--", ":")):
        for model, (color, label) in styles.items():
            s = case[model]["scan"]
            loss = np.asarray(s["loss"])
            ax1.semilogy(s["mu1"], loss, ls, color=color, label=f"{label}, W = {name}")
    ax1.axvline(out["truth"]["mu1"], color="k", lw=0.8)
    ax1.set(xlabel="μ1", ylabel="loss (sum of squared residuals)", title="the loss against μ1, each width")
    ax1.legend(fontsize=7)
    for model, (color, label) in styles.items():
        ax2.plot(widths, [c[model]["scan"]["minimum"] for c in out["cases"].values()], "o-", color=color,
                 label=f"{label}: the scan's minimum")
        ax2.plot(widths, [c[model]["fit"]["mu1"] for c in out["cases"].values()], "x", color=color, ms=9,
                 label=f"{label}: calibration fit's point")
    fine = out.get("fine")
    if fine:
        for model, (color, label) in styles.items():
            ax2.plot([fine["W_m"] * 100], [fine[model]["minimum"]], "s", color=color, mfc="none", ms=9,
                     label=f"{label}: the scan's minimum, 2D and 3D at 2 mm")
    ax2.axhline(out["truth"]["mu1"], color="k", lw=0.8, ls="--", label="the 3D material's μ1")
    ax2.set(xscale="log", xlabel="channel width W (cm)", ylabel="fitted μ1",
            title=f"μ1 fitted to 3D deposits (μ_w = {out['mu_w']}, dx = 4 mm)")
    ax2.set_xticks(widths, [f"{w:g}" for w in widths])
    ax2.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax2.set_ylim(0.34, 0.62)
    ax2.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="/tmp/width_invariance")
    parser.add_argument("--from-json", default=None, metavar="FILE")
    parser.add_argument("--fine", action="store_true", help="only the 2 cm channel at dx = 2 mm: "
                        "docs/results/width_invariance_fine.json")
    args = parser.parse_args(argv)
    if args.fine:
        folder = pathlib.Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        result = fine(folder)
        (ROOT / "docs" / "results" / "width_invariance_fine.json").write_text(json.dumps(result, indent=1))
        print(json.dumps({k: result[k]["minimum"] for k in ("walls", "plain")}))
        return
    if args.from_json:
        out = json.loads(pathlib.Path(args.from_json).read_text())
        fine_json = ROOT / "docs" / "results" / "width_invariance_fine.json"
        if fine_json.exists():
            out["fine"] = json.loads(fine_json.read_text())
    else:
        folder = pathlib.Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        out = study(folder)
        (ROOT / "docs" / "results" / "width_invariance.json").write_text(json.dumps(out, indent=1))
    plot(out, ROOT / "docs" / "figures" / "width_invariance.png")
    for name, case in out["cases"].items():
        print(name, f"3D runout {case['3d']['runout'] * 1000:.1f} mm;",
              *(f"{m}: scan {case[m]['scan']['minimum']:.4f}, fit {case[m]['fit']['mu1']:.4f} "
                f"({case[m]['fit']['verdict']});" for m in ("walls", "plain")))


if __name__ == "__main__":
    main()
