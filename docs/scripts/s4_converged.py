"""Where does the S4 deposit, and the (β, μ1) read from it, stop moving with the grid?

    python docs/scripts/s4_converged.py [--observe final|time-resolved] [--deadline SECONDS] [--out FILE.json]

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

``--observe time-resolved``: the observation is what a filmed collapse gives (the design's
recommended set, docs/what_collapses_tell.md): the profile at t_end × (0.1, 0.2, 0.4) and at the
end, and the front at 20 times; part A then runs only the finest resolution (the data), and part
B's loss is a χ² at 2 % noise: each profile point relative to its profile's peak, each front
position relative to L, one block per observation weighed equally per row. Both modes report,
from the quadratic's curvature, the 95 % half-widths that 2 % noise would give (``interval``), so
that the grid's shift can be set against the statistical interval.

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

from calibration.problem.observe import Observations
from calibration.problem.residuals import model_functions
from jaxmpm.observables import deposit_profile, particle_volumes
from jaxmpm.rollout import make_rollout
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

L = S4_SIDE
TRUTH = (0.25, 0.38)
SLOPE = -1.2  # dμ1/dβ along the valley (docs/twin.md: the fits' pairs lie near this line)
T_END = 0.5
PROFILE_TIMES = (0.05, 0.1, 0.2, T_END)  # t_end × (0.1, 0.2, 0.4) and the end
FRONT_TIMES = np.round(np.linspace(T_END / 20, T_END, 20), 12)  # rounded: a shared time is one frame
NOISE = 0.02  # relative noise for the χ² and the statistical intervals
XS_POINTS = 121  # profile points, 0 to 0.3 m
FRONT_THRESHOLD = 0.001  # m, the same at every resolution (the fit's default follows the particle spacing)


def observations(scene, mode: str):
    """What is observed: the final profile, or profiles at four times and the front at 20."""
    if mode == "final":
        return None
    return Observations(profile_x=(XS,) * len(PROFILE_TIMES), profile_times=PROFILE_TIMES,
                        front_times=FRONT_TIMES, front_points=np.arange(0.0, 0.3, 0.0005),
                        sigma=SIGMA, front_threshold=FRONT_THRESHOLD, mirror=scene.back_face)


def batch_runs(n: int, betas, mu1s, seeds, mode: str = "final"):
    """Observations of S4 at L/n for every (β, μ1, seed) triple, as one vmap batch: ``h`` the
    final profile (``mode`` "final") or every profile then the front, concatenated."""
    scene = cohesive_collapse(dx=L / n, t_end=T_END, beta=TRUTH[0])
    states = [scene.resampled(int(s)) for s in seeds]
    state = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    dtype = scene.state.x.dtype
    params = jax.vmap(lambda b, m: scene.params.replace(beta=b, mu1=m))(
        jnp.asarray(betas, dtype), jnp.asarray(mu1s, dtype))
    observed = observations(scene, mode)
    if observed is None:
        rollout = make_rollout(scene.config, observer=None, checkpoint=False)

        def one(s, p):
            final, _ = rollout(s, p)
            h = deposit_profile(final.x, particle_volumes(final), XS, SIGMA, mirror=scene.back_face)
            return h, final.status, jnp.max(final.x[:, 0]), final.steps
    else:
        config = model_functions(scene.config, observed, ("beta",)).config  # with the observation times
        rollout = make_rollout(config, observer=observed.observer(), checkpoint=False)
        index = [config.frame_times.index(t) for t in observed.profile_times]
        front_index = np.array([config.frame_times.index(float(t)) for t in observed.front_times])

        def one(s, p):
            final, frames = rollout(s, p)
            n_x = XS.size  # the observer evaluates every profile's points at every frame
            h = jnp.concatenate([frames["h"][i, k * n_x:(k + 1) * n_x] for k, i in enumerate(index)]
                                + [frames["front"][front_index]])
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


def quadratic_fit(b, d, loss):
    """A quadratic in (β, δ) fitted by least squares to the points given: its minimiser and its
    Hessian, or None where it has no minimum."""
    A = np.stack([np.ones_like(b), b, d, b * b, b * d, d * d], axis=1)
    c = np.linalg.lstsq(A, loss, rcond=None)[0]
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    g = np.array([c[1], c[2]])
    if np.any(np.linalg.eigvalsh(H) <= 0):
        return None
    bmin, dmin = np.linalg.solve(H, -g)
    return float(bmin), float(dmin), H


def valley_point(b, d, loss):
    """(β, μ1) at the quadratic's minimum of ``loss`` (a χ²) over the lowest points, and the 95 %
    half-widths its curvature gives (covariance 2 H⁻¹ in (β, δ), mapped to (β, μ1))."""
    low = np.argsort(loss)[: max(9, len(b) // 2)]
    fit = quadratic_fit(b[low], d[low], loss[low])
    if fit is None:
        return None
    bmin, dmin, H = fit
    A = np.array([[1.0, 0.0], [SLOPE, 1.0]])
    cov = A @ (2.0 * np.linalg.inv(H)) @ A.T
    half = 1.96 * np.sqrt(np.diag(cov))
    return {"beta": bmin, "mu1": TRUTH[1] + SLOPE * (bmin - TRUTH[0]) + dmin,
            "half_width_beta": float(half[0]), "half_width_mu1": float(half[1])}


def chi2(h, data, mode):
    """χ² at ``NOISE`` of observations ``h`` (..., rows) against ``data`` (rows): profile points
    relative to their profile's peak, front positions relative to L."""
    n_x = XS.size
    if mode == "final":
        scale = np.full(n_x, NOISE * data.max())
    else:
        n_prof = (data.size - 20) // n_x
        scale = np.concatenate([np.full(n_x, NOISE * data[k * n_x:(k + 1) * n_x].max()) for k in range(n_prof)]
                               + [np.full(20, NOISE * L)])
    return np.sum(((h - data) / scale) ** 2, axis=-1)


def main():
    global XS, SIGMA
    parser = argparse.ArgumentParser()
    parser.add_argument("--observe", choices=("final", "time-resolved"), default="final")
    parser.add_argument("--deposit-cells", type=int, nargs="+", default=None,
                        help="default 8 … 64 (final), 64 (time-resolved: the data only)")
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--valley-cells", type=int, nargs="+", default=[12, 16, 24, 32, 40, 48])
    parser.add_argument("--valley-draws", type=int, default=2)
    parser.add_argument("--valley-betas", type=int, default=10)
    parser.add_argument("--sigma", type=float, default=0.002, help="profile kernel width (m), all resolutions")
    parser.add_argument("--deadline", type=float, default=1e9, help="skip cases started after this many s")
    parser.add_argument("--out", default=None, help="default docs/results/s4_converged[_time_resolved].json")
    parser.add_argument("--figure", default="docs/figures/s4_converged.png")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from --out")
    args = parser.parse_args()
    suffix = "" if args.observe == "final" else "_time_resolved"
    args.out = args.out or f"docs/results/s4_converged{suffix}.json"
    if args.observe != "final" and args.figure == "docs/figures/s4_converged.png":
        args.figure = "docs/figures/s4_converged_time_resolved.png"
    if args.plot_only:
        plot(json.loads(pathlib.Path(args.out).read_text()), args.figure)
        return
    mode = args.observe
    cells = args.deposit_cells or ([8, 12, 16, 24, 32, 40, 48, 64] if mode == "final" else [64])
    start = time.perf_counter()
    XS = np.linspace(0.0, 0.3, XS_POINTS)
    SIGMA = args.sigma
    out = pathlib.Path(args.out)
    result = {"device": str(jax.devices()[0]), "jax": jax.__version__, "truth": TRUTH, "xs": XS.tolist(),
              "sigma": SIGMA, "observe": mode, "noise": NOISE, "deposit": [], "valley": []}
    if mode != "final":
        result.update(profile_times=list(PROFILE_TIMES), front_times=FRONT_TIMES.tolist(),
                      front_threshold=FRONT_THRESHOLD)

    def save():
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result))

    for n in cells:
        if time.perf_counter() - start > args.deadline:
            result.setdefault("skipped", []).append(f"deposit L/{n}")
            continue
        seeds = np.arange(args.draws)
        r = batch_runs(n, [TRUTH[0]] * len(seeds), [TRUTH[1]] * len(seeds), seeds, mode)
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
        r = batch_runs(n, np.repeat(B, k), np.repeat(M, k), np.tile(np.arange(100, 100 + k), len(B)), mode)
        h = r["h"].reshape(len(B), k, -1)
        draws_chi2 = chi2(h, data, mode)  # (points, draws)
        loss = draws_chi2.mean(axis=1)  # the ensemble of k draws
        best = valley_point(B, D, loss)
        row = {"cells_per_L": n, "n_particles": r["n_particles"], "draws": k, "beta": B.tolist(), "mu1": M.tolist(),
               "loss": loss.tolist(), "loss_draws": draws_chi2.tolist(), "loss_kind": f"chi2 at {NOISE:g} noise",
               "status": r["status"].reshape(len(B), k).tolist(),
               "grid_min": {"beta": float(B[np.argmin(loss)]), "mu1": float(M[np.argmin(loss)]),
                            "chi2": float(loss.min())},
               "quadratic_min": best,
               "single_draw_min": [valley_point(B, D, draws_chi2[:, j]) for j in range(k)],
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


def _save(fig, path):
    import matplotlib.pyplot as plt

    fig.tight_layout()
    pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot(result, path):
    if result.get("observe", "final") != "final":
        return plot_time_resolved(result, path)
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
    _save(fig, path)


def plot_time_resolved(result, path, final_path="docs/results/s4_converged.json"):
    """The filmed collapse's data, and (β, μ1) read from it at each resolution beside those read
    from the final profile alone (``final_path``, where it exists), with 2 %-noise intervals."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = np.asarray(result["xs"]) * 1e3
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    data = np.asarray(result["deposit"][-1]["mean"])
    for k, t in enumerate(result["profile_times"]):
        ax.plot(xs, data[k * xs.size:(k + 1) * xs.size] * 1e3, label=f"t = {t:g} s")
    front = data[-len(result["front_times"]):]
    ax.plot(front * 1e3, np.full(front.size, 1.0), "k|", ms=8, label="front at 20 times")
    ax.set(xlabel="x (mm)", ylabel="h (mm)", xlim=(0, 220),
           title=f"the data: S4 at the truth, L/{result['data_cells_per_L']}, "
                 f"mean of {result['deposit'][-1]['draws']} draws")
    ax.legend(fontsize=8)
    runs = [("profiles in time + front", result)]
    final = pathlib.Path(final_path)
    if final.exists():
        runs.insert(0, ("final profile alone", json.loads(final.read_text())))
    for _, r in runs:
        if r.get("observe") is None:  # written before the χ² losses: its losses are mean squares (m²)
            scale2 = XS_POINTS / (NOISE * max(r["deposit"][-1]["mean"])) ** 2
            for v in r["valley"]:
                b, m = np.asarray(v["beta"]), np.asarray(v["mu1"])
                v["quadratic_min"] = valley_point(b, m - TRUTH[1] - SLOPE * (b - TRUTH[0]),
                                                  np.asarray(v["loss"]) * scale2)
    for ax, key, label in ((axes[1], "beta", "β"), (axes[2], "mu1", "μ1")):
        for j, (name, r) in enumerate(runs):
            rows = [v for v in r["valley"] if v["quadratic_min"] is not None]
            n = np.array([v["cells_per_L"] for v in rows], float) * (1 + 0.03 * (j - 0.5))
            y = [v["quadratic_min"][key] for v in rows]
            err = [v["quadratic_min"].get(f"half_width_{key}", 0.0) for v in rows]
            ax.errorbar(n, y, yerr=err, fmt="o-" if j else "s--", capsize=3,
                        label=f"{name} (L/{r['data_cells_per_L']} data)")
        ax.axhline(result["truth"][0 if key == "beta" else 1], color="k", ls=":", lw=1, label="truth")
        ax.set(xlabel="cells per column length L", ylabel=label,
               title=f"{label} at the loss minimum (bars: 95 % at 2 % noise)")
        ax.legend(fontsize=8)
    _save(fig, path)


if __name__ == "__main__":
    main()
