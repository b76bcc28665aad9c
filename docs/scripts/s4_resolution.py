"""Does the calibrated (β, μ1) of the S4 twin move with the grid?

    python docs/scripts/s4_resolution.py

The data: the final (t = 0.5 s) deposit profile of S4 at the twin's truth (β = 0.25, μ1 = 0.38,
the scene's other defaults) computed at the finest resolution here, dx = L/12 (3 × 3 jittered
particles per cell), noise-free. The fits: (β, μ1) by Levenberg–Marquardt from 0.9 × the truth
at dx = L/6, L/8, L/10 and L/12 (the last must return the truth), with the noise given as 2 % of
the peak, so that each fit's interval is the one a 2 %-noise measurement would give. A
calibrated value that moves with dx by more than that interval is a property of the grid.
Writes docs/results/s4_resolution.json and docs/figures/s4_resolution.png.

    python docs/scripts/s4_resolution.py --reference 24 --fits 8 12 16 20 --ppc-at 12 --ppc 2 4 --tag convergence

is the same study against a finer reference (L/24, 5,184 particles) with fits at four grids and,
at L/12, at 2, 3 and 4 particles per cell and axis (about 40 minutes on 2 cores); it writes
docs/results/s4_convergence.json and docs/figures/s4_convergence.png.
"""

import argparse
import json
import pathlib
import time

import numpy as np

from calibration import Objective, ProfileTarget, fit
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
L = S4_SIDE
TRUTH = np.array([0.25, 0.38])
KEYS = ("beta", "mu1")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--reference", type=int, default=12, help="cells per L of the data")
    parser.add_argument("--fits", type=int, nargs="+", default=[6, 8, 10, 12], help="cells per L of the fits")
    parser.add_argument("--ppc-at", type=int, default=None, help="cells per L of the particles-per-cell series")
    parser.add_argument("--ppc", type=int, nargs="*", default=[], help="other particles per cell and axis there")
    parser.add_argument("--tag", default="resolution")
    args = parser.parse_args()
    ref = cohesive_collapse(dx=L / args.reference, t_end=0.5, beta=0.25)
    default_ppc = ref.info.ppc
    xs = np.linspace(0.0, 0.3, 60)
    gen = Objective(ref, KEYS, profile=ProfileTarget(xs, np.ones_like(xs)), check_data=False)
    h = np.asarray(gen.predict(TRUTH)["h"], float)
    keep = xs <= 1.3 * xs[np.flatnonzero(h > 0.01 * h.max())[-1]]
    data = ProfileTarget(xs[keep], h[keep], 0.5, f"S4 at dx = L/{args.reference}, truth {TRUTH.tolist()}")
    rows = []
    runs = [(n, default_ppc) for n in args.fits] + [(args.ppc_at, p) for p in args.ppc if args.ppc_at]
    for n, ppc in runs:
        t0 = time.perf_counter()
        scene = cohesive_collapse(dx=L / n, ppc=ppc, t_end=0.5, beta=0.25)
        objective = Objective(scene, KEYS, profile=data)
        result = fit(objective, dict(zip(KEYS, 0.9 * TRUTH)), steps=25, noise=0.02, roundoff_samples=4)
        unc = result.uncertainty
        metres = objective.in_metres(result.residuals)["profile"]
        row = {"cells_per_L": n, "ppc": ppc, "dx": L / n, "n_particles": int(scene.state.n_particles),
               "params": result.theta, "verdict": result.verdict.to_dict()["verdict"],
               "verified": result.verdict.verified,
               "reasons": list(result.verdict.reasons), "iterations": result.iterations,
               "stderr": None if unc.withheld else dict(zip(KEYS, unc.stderr.tolist())),
               "corr": float(unc.corr[0, 1]), "profile_rms_m": float(np.sqrt(np.mean(metres ** 2))),
               "error": {k: result.theta[k] - t for k, t in zip(KEYS, TRUTH)},
               "wall_s": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        print(json.dumps({k: row[k] for k in ("cells_per_L", "ppc", "params", "verdict", "stderr", "profile_rms_m",
                                              "wall_s")}), flush=True)
    out = {"truth": dict(zip(KEYS, TRUTH.tolist())), "reference_cells_per_L": args.reference,
           "reference_ppc": default_ppc, "reference_particles": int(ref.state.n_particles),
           "noise_for_intervals": 0.02, "data_points": int(keep.sum()), "fits": rows}
    (ROOT / "docs" / "results" / f"s4_{args.tag}.json").write_text(json.dumps(out, indent=1))
    plot(out, args.tag)


def plot(out, tag):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8.4, 3.2))
    ref_ppc = out.get("reference_ppc")
    for ax, k in zip(axes, KEYS):
        for ppc in sorted({r.get("ppc", ref_ppc) for r in out["fits"]}, key=lambda p: (p != ref_ppc, p)):
            rows = [r for r in out["fits"] if r.get("ppc", ref_ppc) == ppc]
            n = [r["cells_per_L"] for r in rows]
            v = [r["params"][k] for r in rows]
            se = [1.96 * r["stderr"][k] if r["stderr"] else 0.0 for r in rows]
            label = f"fit, {ppc} x {ppc} per cell (95 % at 2 % noise)" if ppc == ref_ppc else f"{ppc} x {ppc} per cell"
            ax.errorbar(n, v, yerr=se, fmt="o-" if ppc == ref_ppc else "s", capsize=3, label=label)
        for r in out["fits"]:
            x, y = r["cells_per_L"], r["params"][k]
            if not r["stderr"]:
                ax.annotate("not a fit", (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.axhline(out["truth"][k], color="k", lw=1, label=f"truth (data at L/{out['reference_cells_per_L']:d})")
        ax.set_xlabel("cells per column length L")
        ax.set_ylabel(k)
        ax.legend(fontsize=7)
    fig.suptitle("S4 twin: the calibrated parameters against the grid", fontsize=10)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "figures" / f"s4_{tag}.png", dpi=120)


if __name__ == "__main__":
    main()
