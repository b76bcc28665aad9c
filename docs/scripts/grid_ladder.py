"""The grid ladder (``calibration fit --grid-ladder N``) against the default one-step grid term on the
filmed S4 twin of docs/grid_convergence.md: data made at L/64 (36,864 particles, particle seed 11,
profiles at 0.05, 0.1, 0.2 and 0.5 s and the front, 2 % noise; ``five_keys_twin.py data``), fitted
for (β, μ1) with every default at L/16 and with three ladders (docs/grid_term.md, "A ladder of
fits"). Each command runs on two cores (``--workers 2``); an output already in the folder is read,
not run again.

    python docs/scripts/grid_ladder.py [--work /tmp/grid_ladder] [--json docs/results/grid_ladder_s4.json]
        [--figure docs/figures/grid_ladder_s4.png]      # about 17 minutes on two cores
    python docs/scripts/grid_ladder.py --roughness      # and the end points' gradients (3 minutes on one core)

``--roughness`` adds, at the end points of the fits at L/16 and L/24, the loss gradient from the
forward-mode Jacobian beside central differences of the loss at steps of 3e-4 to 1e-2, and how far
the Jacobian's columns are from central differences: whether a fit stopped where the loss's slope
is below its roughness.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

L = 0.089
TRUTH = {"beta": 0.25, "mu1": 0.3818628674187188}  # five_keys_twin.py's column
CASES = {  # name: (the options beyond `fit column.toml --json --workers 2`, what it is)
    "default": ([], "L/16, one-step grid term at 1.5 dx (today's default)"),
    "ladder3_L16": (["--grid-ladder", "3"], "ladder of 3 fits: L/7.1, L/10.7, L/16"),
    "ladder2_L24": (["--dx", repr(L / 24), "--grid-ladder", "2"], "ladder of 2 fits: L/16, L/24"),
    "ladder3_L20": (["--dx", repr(L / 20), "--grid-ladder", "3", "--grid-check", "1.25"],
                    "ladder of 3 fits: L/12.8, L/16, L/20 (ratio 1.25)"),
}


def run(work: pathlib.Path) -> dict:
    if not (work / "column.toml").exists():
        subprocess.run([sys.executable, str(pathlib.Path(__file__).parent / "five_keys_twin.py"), "data", "--only",
                        "column", "--fit", "beta,mu1", "--no-start", "--fit-cells", "16", "--data-cells", "64",
                        "--seed", "11", "--out", str(work)], check=True)
    summary = {}
    for name, (extra, what) in CASES.items():
        out = work / f"{name}.json"
        if not out.exists():
            with open(out, "w") as f:
                subprocess.run([sys.executable, "-m", "calibration", "fit", "column.toml", "--json", "--workers", "2",
                                "--no-progress", *extra], cwd=work, stdout=f, check=False)
        summary[name] = summarise(json.loads(out.read_text()), what, extra)
    return summary


def roughness(work: pathlib.Path, summary: dict) -> dict:
    """The loss gradient at the L/16 and L/24 end points: forward mode against central differences."""
    import numpy as np

    from calibration import Objective
    from jaxmpm import Experiment

    out = {}
    for cells, name in ((16, "default"), (24, "ladder2_L24")):
        objective = Objective.from_experiment(Experiment.from_toml(work / "column.toml").with_options(dx=L / cells))
        theta = np.array([summary[name]["point"][k] for k in objective.keys])
        r, J = (np.asarray(a, float) for a in objective.residuals_and_jacobian(theta)[:2])
        loss = lambda residuals: 0.5 * float(residuals @ residuals)  # noqa: E731
        rows = []
        for h in (1e-2, 3e-3, 1e-3, 3e-4):
            steps = [np.eye(2)[i] * h for i in range(2)]
            plus = [np.asarray(objective.residuals(theta + e)[0], float) for e in steps]
            minus = [np.asarray(objective.residuals(theta - e)[0], float) for e in steps]
            jf = np.stack([(a - b) / (2 * h) for a, b in zip(plus, minus)], 1)
            rows.append({"step": h, "gradient_fd": [(loss(a) - loss(b)) / (2 * h) for a, b in zip(plus, minus)],
                         "jacobian_rel_error": list(np.linalg.norm(jf - J, axis=0) / np.linalg.norm(J, axis=0))})
        out[f"L/{cells}"] = {"theta": dict(zip(objective.keys, theta.tolist())), "gradient_ad": (J.T @ r).tolist(),
                             "central_differences": rows}
    return out


def summarise(d: dict, what: str, extra: list[str]) -> dict:
    """Point, interval, half-widths, whether the truth is inside, cost and the rungs of one fit's JSON."""
    ladder = d.get("ladder")
    point = ladder["point"] if ladder else d["params"]
    ci95 = ladder["ci95"] if ladder else d.get("ci95")
    row = {"what": what, "options": extra, "point": point, "ci95": ci95, "verdict": d["verdict"]["verdict"],
           "wall_s": ladder["wall_s"] if ladder else d["wall_s"]}
    if ci95 is not None:
        row["halfwidth95"] = {k: 0.5 * (hi - lo) for k, (lo, hi) in ci95.items()}
        row["truth_inside"] = {k: bool(lo <= TRUTH[k] <= hi) for k, (lo, hi) in ci95.items()}
    if ladder:
        row.update(rungs=ladder["rungs"], grid=ladder["grid"], statement=ladder["statement"],
                   extrapolated=ladder["extrapolated"])
    else:
        row.update(grid=d.get("grid"), statement=d["statement"])
    return row


def figure(summary: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.6))
    for ax, k in zip(axes, TRUTH):
        for i, row in enumerate(summary.values()):
            colour = f"C{i}"
            if "rungs" in row:
                dx = [r["dx"] * 1e3 for r in row["rungs"]]
                ax.plot(dx, [r["theta"][k] for r in row["rungs"]], "o-", color=colour, ms=4, label=row["what"])
                ax.plot([r["dx"] * 1e3 for r in row["rungs"] if r["at_bound"]],
                        [r["theta"][k] for r in row["rungs"] if r["at_bound"]], "x", color="k", ms=8)
                at = dx[-1]
            else:
                at = L / 16 * 1e3
                ax.plot([at], [row["point"][k]], "s", color=colour, label=row["what"])
            if row["ci95"] is not None:
                lo, hi = row["ci95"][k]
                ax.errorbar([at + 0.12 * (i - 1.5)], [row["point"][k]],
                            yerr=[[row["point"][k] - lo], [hi - row["point"][k]]], fmt="none", ecolor=colour,
                            capsize=3)
        ax.axhline(TRUTH[k], color="k", ls="--", lw=1, label="truth (data at L/64)")
        ax.set_xlabel("dx (mm)")
        ax.set_ylabel(k)
    axes[0].legend(fontsize=6.5, loc="upper right")
    fig.suptitle("Filmed S4 twin: fits on ladders of grids (x: ended at a bound; bars: 95 % intervals)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=130)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=pathlib.Path, default=pathlib.Path("/tmp/grid_ladder"))
    parser.add_argument("--json", type=pathlib.Path, default=pathlib.Path("docs/results/grid_ladder_s4.json"))
    parser.add_argument("--figure", type=pathlib.Path, default=pathlib.Path("docs/figures/grid_ladder_s4.png"))
    parser.add_argument("--roughness", action="store_true", help="also the end points' gradients (3 minutes)")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    summary = run(args.work.resolve())
    saved = {"truth": TRUTH, "cases": summary}
    if args.roughness:
        saved["roughness"] = roughness(args.work.resolve(), summary)
    elif args.json.exists():  # keep a roughness measured before
        saved.update({k: v for k, v in json.loads(args.json.read_text()).items() if k == "roughness"})
    args.json.write_text(json.dumps(saved, indent=1) + "\n")
    figure(summary, args.figure)
    print(json.dumps({name: {k: row.get(k) for k in ("point", "halfwidth95", "truth_inside", "wall_s")}
                      for name, row in summary.items()}, indent=1))


if __name__ == "__main__":
    main()
