"""Where does the S4 deposit, and the (β, μ1) read from it, stop moving with the grid? (issue 29)

    python docs/scripts/s4_converged.py [--deadline SECONDS] [--out FILE.json]

Made for one GPU (every case is a `vmap` batch of whole runs); on two CPU cores pass smaller
``--deposit-cells`` and ``--valley-cells``. float32, the scene's jittered 3 × 3 particles per cell.

Part A, the deposit: S4 at the twin's truth (β = 0.25, μ1 = 0.38, the scene's other defaults) at
L/n for each n in ``--deposit-cells``, ``--draws`` particle draws at each (one batch). Each draw's
final profile is smoothed with one kernel for all resolutions (``--sigma``, m), mirrored at the
back wall, so that differences are the model's, not the smoothing's. Reported: the draws' mean
profile, their spread, and the mean's distance to the finest resolution's mean.

Part B, the valley: at L/n for each n in ``--valley-cells``, the loss of the final profile
against the finest mean profile of part A (the data: a twin at the truth, converged as far as this
study can take it), on points along the β–μ1 valley (μ1 = 0.38 − 1.2 (β − 0.25) + δ), with
``--valley-draws`` draws at each point; the loss is the draws' mean squared residual. The minimum
of a quadratic fitted to the lowest points is that resolution's calibrated (β, μ1).

Writes the JSON after every case, so that a run cut short keeps what it finished, and the
figure docs/figures/s4_converged.png (``--plot-only`` redraws it from the JSON).
"""

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.observables import deposit_profile, particle_volumes
from jaxmpm.rollout import make_rollout
from jaxmpm.scenes import cohesive_collapse

L = 0.089
TRUTH = (0.25, 0.38)
SLOPE = -1.2  # dμ1/dβ along the valley (docs/calibration.md: the fits' pairs lie near this line)


def batch_runs(n: int, betas, mu1s, seeds):
    """Final profiles of S4 at L/n for every (β, μ1, seed) triple, as one vmap batch."""
    scene = cohesive_collapse(dx=L / n, t_end=0.5, beta=TRUTH[0])
    states = [scene.resampled(int(s)) for s in seeds]
    state = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    dtype = scene.state.x.dtype
    params = jax.vmap(lambda b, m: scene.params.replace(beta=b, mu1=m))(
        jnp.asarray(betas, dtype), jnp.asarray(mu1s, dtype))
    rollout = make_rollout(scene.config, observer=None, checkpoint=False)

    def one(s, p):
        final, _ = rollout(s, p)
        h = deposit_profile(final.x, particle_volumes(final), XS, SIGMA, mirror=scene.back_face)
        return h, final.status, jnp.max(final.x[:, 0]), final.steps

    run = jax.jit(jax.vmap(one))
    t0 = time.perf_counter()
    compiled = run.lower(state, params).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    h, status, x_max, steps = jax.block_until_ready(compiled(state, params))
    run_s = time.perf_counter() - t0
    return dict(h=np.asarray(h, float), status=np.asarray(status), x_max=np.asarray(x_max, float),
                steps=np.asarray(steps), compile_s=compile_s, run_s=run_s,
                n_particles=int(scene.state.n_particles), max_steps=int(scene.config.max_steps))


def quadratic_minimum(b, d, loss):
    """Minimiser of a quadratic in (β, δ) fitted by least squares to the points given."""
    A = np.stack([np.ones_like(b), b, d, b * b, b * d, d * d], axis=1)
    c = np.linalg.lstsq(A, loss, rcond=None)[0]
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    g = np.array([c[1], c[2]])
    if np.any(np.linalg.eigvalsh(H) <= 0):
        return None
    bmin, dmin = np.linalg.solve(H, -g)
    return float(bmin), float(dmin)


def main():
    global XS, SIGMA
    parser = argparse.ArgumentParser()
    parser.add_argument("--deposit-cells", type=int, nargs="+", default=[8, 12, 16, 24, 32, 40, 48, 64])
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--valley-cells", type=int, nargs="+", default=[12, 16, 24, 32, 40, 48])
    parser.add_argument("--valley-draws", type=int, default=2)
    parser.add_argument("--valley-betas", type=int, default=10)
    parser.add_argument("--sigma", type=float, default=0.002, help="profile kernel width (m), all resolutions")
    parser.add_argument("--deadline", type=float, default=1e9, help="skip cases started after this many s")
    parser.add_argument("--out", default="docs/results/s4_converged.json")
    parser.add_argument("--figure", default="docs/figures/s4_converged.png")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from --out")
    args = parser.parse_args()
    if args.plot_only:
        plot(json.loads(pathlib.Path(args.out).read_text()), args.figure)
        return
    start = time.perf_counter()
    XS = np.linspace(0.0, 0.3, 121)
    SIGMA = args.sigma
    out = pathlib.Path(args.out)
    result = {"device": str(jax.devices()[0]), "jax": jax.__version__, "truth": TRUTH, "xs": XS.tolist(),
              "sigma": SIGMA, "deposit": [], "valley": []}

    def save():
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result))

    for n in args.deposit_cells:
        if time.perf_counter() - start > args.deadline:
            result.setdefault("skipped", []).append(f"deposit L/{n}")
            continue
        seeds = np.arange(args.draws)
        r = batch_runs(n, [TRUTH[0]] * len(seeds), [TRUTH[1]] * len(seeds), seeds)
        result["deposit"].append({
            "cells_per_L": n, "n_particles": r["n_particles"], "draws": len(seeds),
            "mean": r["h"].mean(0).tolist(), "spread": r["h"].std(0, ddof=1).tolist(),
            "runout": (r["x_max"] - L).tolist(), "status": r["status"].tolist(), "steps": r["steps"].tolist(),
            "max_steps": r["max_steps"], "compile_s": round(r["compile_s"], 2), "run_s": round(r["run_s"], 2)})
        print(json.dumps({k: v for k, v in result["deposit"][-1].items() if k not in ("mean", "spread")}),
              flush=True)
        save()
    data = np.asarray(result["deposit"][-1]["mean"])
    result["data_cells_per_L"] = result["deposit"][-1]["cells_per_L"]
    betas = np.linspace(0.1, 0.45, args.valley_betas)  # μ1 stays below μ2 = 0.643
    deltas = np.array([-0.04, 0.0, 0.04])
    B, D = [a.ravel() for a in np.meshgrid(betas, deltas, indexing="ij")]
    M = TRUTH[1] + SLOPE * (B - TRUTH[0]) + D
    for n in args.valley_cells:
        if time.perf_counter() - start > args.deadline:
            result.setdefault("skipped", []).append(f"valley L/{n}")
            continue
        k = args.valley_draws
        r = batch_runs(n, np.repeat(B, k), np.repeat(M, k), np.tile(np.arange(100, 100 + k), len(B)))
        h = r["h"].reshape(len(B), k, -1)
        loss = np.mean((h - data) ** 2, axis=(1, 2))
        low = np.argsort(loss)[: max(9, len(B) // 2)]
        best = quadratic_minimum(B[low], D[low], loss[low])
        row = {"cells_per_L": n, "n_particles": r["n_particles"], "draws": k, "beta": B.tolist(), "mu1": M.tolist(),
               "loss": loss.tolist(), "status": r["status"].reshape(len(B), k).tolist(),
               "grid_min": {"beta": float(B[np.argmin(loss)]), "mu1": float(M[np.argmin(loss)]),
                            "rms_m": float(np.sqrt(loss.min()))},
               "quadratic_min": None if best is None else {
                   "beta": best[0], "mu1": TRUTH[1] + SLOPE * (best[0] - TRUTH[0]) + best[1]},
               "compile_s": round(r["compile_s"], 2), "run_s": round(r["run_s"], 2)}
        result["valley"].append(row)
        print(json.dumps({k_: row[k_] for k_ in ("cells_per_L", "n_particles", "grid_min", "quadratic_min",
                                                  "compile_s", "run_s")}), flush=True)
        save()
    result["wall_s"] = round(time.perf_counter() - start, 1)
    save()
    plot(result, args.figure)


def deposit_errors(result):
    """Per resolution: the RMS distance (m) of the draws' mean profile to the finest one's, the
    standard error of that distance's two means, and the RMS spread of one draw."""
    finest = result["deposit"][-1]
    ref, ref_spread = np.asarray(finest["mean"]), np.asarray(finest["spread"])
    rows = []
    for d in result["deposit"]:
        mean, spread = np.asarray(d["mean"]), np.asarray(d["spread"])
        se = np.sqrt(np.mean(spread ** 2 / d["draws"] + ref_spread ** 2 / finest["draws"]))
        rows.append({"cells_per_L": d["cells_per_L"], "rms_to_finest": float(np.sqrt(np.mean((mean - ref) ** 2))),
                     "standard_error": float(se), "draw_spread": float(np.sqrt(np.mean(spread ** 2)))})
    return rows


def plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = np.asarray(result["xs"])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    cmap = plt.get_cmap("viridis")
    deposits = result["deposit"]
    for i, d in enumerate(deposits):
        ax.plot(xs * 1e3, np.asarray(d["mean"]) * 1e3, color=cmap(i / max(1, len(deposits) - 1)),
                label=f"L/{d['cells_per_L']}")
    ax.set(xlabel="x (mm)", ylabel="h (mm)", xlim=(100, 210), ylim=(0, 40),
           title=f"S4 at the truth: mean deposit of {deposits[0]['draws']} particle draws")
    ax.legend(fontsize=8, ncol=2)
    ax = axes[1]
    errors = deposit_errors(result)[:-1]
    n = [e["cells_per_L"] for e in errors]
    ax.loglog(n, [e["rms_to_finest"] * 1e3 for e in errors], "o-", label="mean profile − finest mean (RMS)")
    ax.loglog(n, [e["standard_error"] * 1e3 for e in errors], "s--", label="its standard error (the draws)")
    ax.loglog(n, [e["draw_spread"] * 1e3 for e in errors], "^:", label="one draw's spread (RMS)")
    ax.set(xlabel="cells per column length L", ylabel="mm",
           title=f"distance to L/{deposits[-1]['cells_per_L']}")
    ax.set_xticks(n, [str(k) for k in n])
    ax.set_yticks([0.3, 0.5, 1.0, 2.0, 4.0], ["0.3", "0.5", "1", "2", "4"])
    ax.minorticks_off()
    ax.legend(fontsize=8)
    ax = axes[2]
    valley = [v for v in result["valley"] if v["quadratic_min"] is not None]
    n = [v["cells_per_L"] for v in valley]
    ax.plot(n, [v["quadratic_min"]["beta"] for v in valley], "o-", label="β")
    ax.plot(n, [v["quadratic_min"]["mu1"] for v in valley], "s-", label="μ1")
    ax.axhline(result["truth"][0], color="C0", ls=":", lw=1)
    ax.axhline(result["truth"][1], color="C1", ls=":", lw=1)
    ax.set(xlabel="cells per column length L", ylabel="value at the loss minimum",
           title=f"(β, μ1) read from the L/{result['data_cells_per_L']} deposit (dotted: truth)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
