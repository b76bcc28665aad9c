r"""Levenberg–Marquardt with each trial's exact Jacobian against LM with Broyden's updates of the
Jacobian (one forward run a trial), from the two coarse minima of the S4 fit at dx = 4 mm
(issue 44, item 3): docs/results/broyden_lm_4mm.json, "lm_from_the_coarse_minima".

This is the rule of ``calibration.optim.lm`` with ``jacobian="broyden"`` as first measured: the
exact Jacobian at the start, Broyden's update after each trial whose run succeeds, the exact one
again after a rejected step or a claimed stop on an estimate; Gauss–Newton's model, one start on
one core, to a loss of 1e-10 (the twin is noise-free) or LM's stop:

    python -m jaxmpm run cohesive-collapse --dx 0.004 --set pc0=500 --set xi=50 --set beta=0.3 \
        --set mu1=0.55 --profile-csv twin4mm.csv
    taskset -c 0 python docs/scripts/broyden_lm.py twin4mm.csv start0 out_start0.json &
    taskset -c 1 python docs/scripts/broyden_lm.py twin4mm.csv start1 out_start1.json   # 8 minutes
    python docs/scripts/broyden_lm.py --plot      # docs/figures/broyden_lm_4mm.png from the results
"""

import json
import pathlib
import sys
import time

import jax.numpy as jnp
import numpy as np

import calibration as cal
from calibration.optim.lm import LAM0, LMOptions, broyden_update, judge, propose
from jaxmpm.scenes import build_scene

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results" / "broyden_lm_4mm.json"

#: The two coarse minima (8 mm) the fine stage starts from (docs/results/fit_4mm_2026-12-06.json).
STARTS = {"start0": (0.5437837839126587, 0.3526687026023865), "start1": (0.40797165036201477, 0.39925453066825867)}
STEPS, LOSS_DONE = 40, 1e-10


def lm(objective, start, broyden):
    """LM from ``start``: one record per iteration, with the Jacobians and residual runs so far."""
    bounds = objective.bounds
    counts = {"jacobians": 0, "residual_runs": 0}

    def theta(z):
        return np.asarray(bounds.to_physical(jnp.asarray(z)), float)

    def jacobian(z):
        counts["jacobians"] += 1
        r, Jz, _, pred = objective.residuals_and_jacobian_z(jnp.asarray(z, objective.dtype))
        return np.asarray(r, float), np.asarray(Jz, float), int(pred["status"])

    def residuals(z):
        counts["residual_runs"] += 1
        r, pred = objective.residuals(theta(z))
        return np.asarray(r, float), int(np.asarray(pred["status"]))

    clock = time.perf_counter()
    z = np.asarray(bounds.to_unconstrained(np.array(start)), float)
    r, Jz, _ = jacobian(z)
    fresh, lam, rejections, log = True, LAM0, 0, []
    for it in range(STEPS):
        delta, promised = propose(r[None], Jz[None], np.array([lam]))
        delta = delta[0]
        if broyden:
            (r_t, status), Jz_t = residuals(z + delta), None
        else:
            r_t, Jz_t, status = jacobian(z + delta)
        accepted, lam_, rej_, done, _ = judge(
            np.array([r @ r]), theta(z)[None], np.array([r_t @ r_t]), theta(z + delta)[None], np.array([status == 0]),
            promised, np.array([lam]), np.array([rejections]), r.size, LMOptions(model="gauss-newton"))
        lam, rejections, refreshed = float(lam_[0]), int(rej_[0]), False
        if broyden:
            if status == 0 and np.all(np.isfinite(r_t)):
                Jz, fresh = broyden_update(Jz[None], delta[None], r[None], r_t[None])[0], False
            if accepted[0]:
                z, r = z + delta, r_t
            if (not accepted[0] or done[0]) and not fresh:  # the exact Jacobian before a rejection or a stop counts
                (r, Jz, _), fresh, refreshed, done = jacobian(z), True, True, np.array([False])
        elif accepted[0]:
            z, r, Jz = z + delta, r_t, Jz_t
        log.append({"iteration": it + 1, "loss": float(r @ r), "accepted": bool(accepted[0]), "lam": lam,
                    "refreshed": refreshed, "theta": theta(z).tolist(), "wall_s": time.perf_counter() - clock,
                    **counts})
        print(json.dumps(log[-1]), flush=True)
        if r @ r < LOSS_DONE or done[0]:
            break
    return log


def main(twin_csv, name, out):
    scene = build_scene("cohesive-collapse", dx=0.004, values={"pc0": 500.0, "xi": 50.0})
    objective = cal.Objective(scene, ("beta", "mu1"), profile=cal.load_profile(twin_csv))
    clock = time.perf_counter()  # compile both paths first, so that the walls compare runs
    objective.residuals(np.array(STARTS[name]))
    first_residuals = time.perf_counter() - clock
    objective.residuals_and_jacobian_z(jnp.zeros(2, objective.dtype))
    result = {"compile_and_first_run_s": {"residuals": first_residuals,
                                          "jacobian": time.perf_counter() - clock - first_residuals}, "runs": {}}
    for broyden in (True, False):
        log = lm(objective, STARTS[name], broyden)
        result["runs"]["broyden" if broyden else "exact"] = {
            "start": STARTS[name], "iterations": len(log), "wall_s": log[-1]["wall_s"], "final_loss": log[-1]["loss"],
            "final_theta": log[-1]["theta"], "log": log}
    with open(out, "w") as f:
        json.dump(result, f, indent=1)


def plot(path=ROOT / "docs" / "figures" / "broyden_lm_4mm.png") -> None:
    """The loss against the wall time of each start's two runs (RESULTS)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = json.loads(RESULTS.read_text())["lm_from_the_coarse_minima"]["runs"]
    fig, axes = plt.subplots(1, len(runs), figsize=(9, 3.6), sharey=True)
    for ax, result in zip(axes, runs.values()):
        for kind, color in (("exact", "C0"), ("broyden", "C3")):
            run = result["runs"][kind]
            log = run["log"]
            wall = [0.0] + [r["wall_s"] for r in log]
            loss = [None] + [r["loss"] for r in log]
            theta = run["final_theta"]
            end = "the truth" if run["final_loss"] < 1e-9 else f"({theta[0]:.3f}, {theta[1]:.3f})"
            ax.semilogy(wall[1:], loss[1:], "o-", ms=3, color=color,
                        label=f"{kind}: {len(log)} it, {log[-1]['jacobians']} Jacobians, {run['wall_s']:.0f} s, {end}")
            fresh = [r["wall_s"] for r in log if r.get("refreshed")]
            ax.semilogy(fresh, [r["loss"] for r in log if r.get("refreshed")], "s", mfc="none", color=color, ms=7)
        start = result["runs"]["exact"]["start"]
        ax.set(title=f"from the coarse minimum ({start[0]:.3f}, {start[1]:.3f})", xlabel="wall time on one core (s)")
        ax.legend(fontsize=7, loc="best")
    axes[0].set_ylabel("loss (accepted point)")
    fig.suptitle("S4 at dx = 4 mm, noise-free twin at (0.3, 0.55): LM's Jacobian exact or by Broyden's updates "
                 "(squares: the exact one again)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    if sys.argv[1:] == ["--plot"]:
        plot()
    else:
        main(*sys.argv[1:])
