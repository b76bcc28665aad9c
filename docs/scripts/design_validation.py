"""Does the experiment designer tell the truth?

    python docs/scripts/design_validation.py [--seeds 10] [--cells 8] [--workers 2]

A twin: S4 at L/``cells`` (float32, the scene's jittered particles), truth β = 0.25, μ1 = 0.38,
ξ = 50, noise 1 % of each profile's peak and of the column length for the front. ``design`` ranks
the candidate observation sets and recommends the cheapest that constrains every key to 10 %. Then,
for the final profile alone and for the recommended set, ``--seeds`` noisy data sets are made
(Gaussian noise added to the model's own observations at the truth) and fitted from the truth
(LM, 20 iterations at most; the same grid and particles as the data, so that only the noise
moves the answer). The spread of the fitted values is compared with the designer's expected
standard errors (the library's fit, which weighs each block as a whole: the sandwich; and the
noise-weighted bound beside it), and the figure draws the fits over the expected 95 % ellipses.
``--reuse-fits`` redoes the design and the comparison from the fits stored in the JSON.
Writes docs/results/design_validation.json and docs/figures/design_validation.png.
"""

import argparse
import json
import pathlib
import time

import numpy as np

from calibration import FrontTarget, Objective, ProfileTarget, fit
from calibration.batch.workers import Workers
from calibration.design.design import design
from calibration.inference.noise import Z95
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
L = S4_SIDE
TRUTH = {"beta": 0.25, "mu1": 0.38, "xi": 50.0}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default=str(ROOT / "docs/results/design_validation.json"))
    parser.add_argument("--figure", default=str(ROOT / "docs/figures/design_validation.png"))
    parser.add_argument("--plot-only", action="store_true")
    parser.add_argument("--reuse-fits", action="store_true",
                        help="redo the design and the comparison with the fits stored in --out (same settings)")
    parser.add_argument("--add-set", default=None, metavar="NAME",
                        help="with --reuse-fits: fit this candidate set too and add it to the stored fits")
    args = parser.parse_args()
    if args.plot_only:
        plot(json.loads(pathlib.Path(args.out).read_text()), args.figure)
        return
    keys = tuple(TRUTH)
    scene = cohesive_collapse(dx=L / args.cells, t_end=0.5, **TRUTH)
    clock = time.perf_counter()
    with Workers(args.workers) as workers:
        planned = design(scene, keys, TRUTH, noise=args.noise, tolerance=0.1, workers=workers)
    design_s = time.perf_counter() - clock
    by_name = {c.name: c for c in planned.candidates}
    chosen = ["final profile", planned.recommended.name if planned.recommended else "profiles in time + front"]
    # The noise-free observations of every kind, from the designer's own objective layout.
    t_end = float(scene.config.t_end)
    times = [t_end * f for f in (0.1, 0.2, 0.4)] + [t_end]
    grid = scene.config.grid
    xs = np.linspace(0.0, 0.9 * (grid.origin[0] + grid.cells[0] * grid.dx), 60)
    front_times = np.linspace(t_end / 20, t_end, 20)
    top_x = 0.1 * L
    gen = Objective(scene, keys, profile=[ProfileTarget(xs, np.ones_like(xs), t) for t in times]
                    + [ProfileTarget(np.array([top_x]), np.ones(1), float(t)) for t in front_times],
                    front=FrontTarget(front_times, np.ones(front_times.size)), check_data=False)
    pred = gen.predict(np.array([TRUTH[k] for k in keys]))
    h = np.asarray(pred["h"], float)
    profiles = [h[i * xs.size:(i + 1) * xs.size] for i in range(len(times))]
    tops = h[len(times) * xs.size:]
    front = np.asarray(pred["front"], float)
    rows, to_fit = [], chosen
    if args.reuse_fits:
        rows = json.loads(pathlib.Path(args.out).read_text())["fits"]
        chosen = list(dict.fromkeys(r["set"] for r in rows))
        to_fit = [args.add_set] if args.add_set and args.add_set not in chosen else []
        chosen += to_fit
    for name in to_fit:
        parts = {kind for _, kind in by_name[name].parts}
        for seed in range(args.seeds):
            rng = np.random.default_rng(seed)
            targets, front_target = [], None
            use = (range(len(times)) if "profiles" in parts else [len(times) - 1])
            for i in use:
                noisy = profiles[i] + args.noise * profiles[i].max() * rng.standard_normal(xs.size)
                targets.append(ProfileTarget(xs, noisy, times[i], f"seed {seed} profile at {times[i]:g} s"))
            if "top" in parts:
                for t, top in zip(front_times, tops):
                    noisy = np.array([top * (1 + args.noise * rng.standard_normal())])
                    targets.append(ProfileTarget(np.array([top_x]), noisy, float(t)))
            if "front" in parts:
                front_target = FrontTarget(front_times, front + args.noise * L * rng.standard_normal(front.size))
            objective = Objective(scene, keys, profile=targets, front=front_target, check_data=False)
            t0 = time.perf_counter()
            with Workers(args.workers) as workers:
                result = fit(objective, TRUTH, steps=20, roundoff_samples=0, uncertainty=False, workers=workers)
            rows.append({"set": name, "seed": seed, "theta": result.theta, "converged": result.converged,
                         "message": result.message, "wall_s": round(time.perf_counter() - t0, 1)})
            print(json.dumps(rows[-1]), flush=True)
    summary = []
    for name in chosen:
        fitted = np.array([[r["theta"][k] for k in keys] for r in rows if r["set"] == name])
        expected = by_name[name].halfwidth_data / Z95
        spread = fitted.std(axis=0, ddof=1)
        bound = by_name[name].halfwidth_weighted / Z95
        summary.append({"set": name, "fits": len(fitted), "spread": dict(zip(keys, spread.tolist())),
                        "expected_stderr": dict(zip(keys, expected.tolist())),
                        "noise_weighted_stderr": dict(zip(keys, bound.tolist())),
                        "ratio": dict(zip(keys, (spread / expected).tolist())),
                        "mean_minus_truth": dict(zip(keys, (fitted.mean(axis=0)
                                                             - np.array([TRUTH[k] for k in keys])).tolist()))})
    out = {"truth": TRUTH, "cells_per_L": args.cells, "noise": args.noise, "seeds": args.seeds,
           "design": planned.to_json(), "design_s": round(design_s, 1), "fits": rows, "summary": summary,
           "covariances": {name: by_name[name].cov.tolist() for name in chosen}}
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1))
    plot(out, args.figure)


def plot(out, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(out["truth"])
    truth = np.array([out["truth"][k] for k in keys])
    pairs = [(0, 1), (0, 2)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    t = np.linspace(0, 2 * np.pi, 200)
    circle = np.stack([np.cos(t), np.sin(t)])
    for ax, (i, j) in zip(axes, pairs):
        for c, s in enumerate(out["summary"]):
            cov = np.asarray(out["covariances"][s["set"]])[np.ix_([i, j], [i, j])]
            evals, evecs = np.linalg.eigh(cov)
            xy = (evecs * np.sqrt(np.maximum(evals, 0))) @ circle * np.sqrt(5.991) + truth[[i, j], None]
            ax.plot(xy[0], xy[1], color=f"C{c}", label=f"{s['set']}: expected 95 %")
            pts = np.array([[r["theta"][keys[i]], r["theta"][keys[j]]] for r in out["fits"] if r["set"] == s["set"]])
            ax.plot(pts[:, 0], pts[:, 1], "o", color=f"C{c}", ms=4, alpha=0.8, label=f"{s['set']}: fits")
        ax.plot(*truth[[i, j]], "k+", ms=12)
        ax.set(xlabel=keys[i], ylabel=keys[j])
    axes[0].legend(fontsize=7)
    fig.suptitle(f"S4 twin at L/{out['cells_per_L']}, {100 * out['noise']:g} % noise: {out['seeds']} noise seeds "
                 "per set against the designer's ellipses")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
