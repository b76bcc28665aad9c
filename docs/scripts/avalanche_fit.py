"""Calibration on terrain: a smooth runout of the S6 avalanche, its gradient
with respect to β and μ_w through the whole run (release to deposit) against central differences
in float64, and a fit of β to a given runout.

    python docs/scripts/avalanche_fit.py [--dx 2] [--truth 0.1] [--start 0.2 0.03]

The runout is ``jaxmpm.studies.avalanche.smooth_runout`` of the final state (t = 100 s): where a
Gaussian-smoothed deposit, counted from the far end, first covers the ground thicker than 0.1 m,
the ``runout_x`` rule on a smooth field. Its derivative is checked against central differences
at four steps (1e-2 to 1e-5), because the runout is rough at small scales: the steps disagree
among themselves by about 10 %.
The "given runout" is a twin's: the dry snow with β = ``--truth``; each fit starts from one β of
``--start`` and takes safeguarded Newton steps on R(β) − R* (a trust radius, and a step is kept
only if it brings R closer to R*), R'(β) by forward mode (one JVP per trial).
Writes docs/results/avalanche_fit.json and docs/figures/avalanche_fit.png. About 15 minutes at
dx = 2 m on 2 cores.
"""

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxmpm.rollout import make_rollout  # noqa: E402
from jaxmpm.scenes.avalanche import avalanche  # noqa: E402
from jaxmpm.studies.avalanche import smooth_runout  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]


def gradient_check(args, value, jvp, mu_w, r_true):
    """The pathwise derivative at the truth, in both directions, against central differences at
    several steps (the runout is rough at small scales: the steps disagree among themselves)."""
    f64 = jnp.float64
    clock = time.perf_counter()
    check = {"beta": args.truth, "mu_w": float(mu_w), "runout": r_true}
    for name, tangent in (("beta", (1.0, 0.0)), ("mu_w", (0.0, 1.0))):
        _, d = jvp(f64(args.truth), mu_w, f64(tangent[0]), f64(tangent[1]))
        fds = {}
        for h in args.fd_steps:
            up = float(value(f64(args.truth + h * tangent[0]), mu_w + h * tangent[1])[0])
            down = float(value(f64(args.truth - h * tangent[0]), mu_w - h * tangent[1])[0])
            fds[f"{h:g}"] = (up - down) / (2 * h)
        check[f"d_runout_d_{name}"] = {"jvp": float(d), "central_differences": fds,
                                       "fd_range": (min(fds.values()), max(fds.values())),
                                       "jvp_over_fd_mean": float(d) / float(np.mean(list(fds.values())))}
        print(name, check[f"d_runout_d_{name}"], flush=True)
    check["wall_s"] = round(time.perf_counter() - clock, 1)
    return check


def runout_curve(jvp, mu_w):
    """R and the pathwise R' at nine β from 0 to 0.2: the curve the fits walk on."""
    betas = np.linspace(0.0, 0.2, 9)
    pairs = [jvp(jnp.float64(b), mu_w, jnp.float64(1.0), jnp.float64(0.0)) for b in betas]
    curve, slopes = [float(r) for r, _ in pairs], [float(d) for _, d in pairs]
    print("curve", dict(zip(betas.round(3).tolist(), zip(np.round(curve, 2).tolist(), np.round(slopes, 1).tolist()))),
          flush=True)
    return betas, curve, slopes


def newton(args, jvp, mu_w, r_true, start):
    """A safeguarded Newton iteration on R(β) − R*: the step is the pathwise Newton step cut to a
    trust radius (``--radius``), kept inside β's bounds [0, 0.5], and accepted only if it reduces
    |R − R*| (else the radius becomes half the rejected step); one JVP per trial. Stops at |R − R*| < dx / 20."""
    f64 = jnp.float64
    clock = time.perf_counter()
    beta, radius = f64(start), args.radius
    r, d = (float(v) for v in jvp(beta, mu_w, f64(1.0), f64(0.0)))
    history = [{"beta": float(beta), "runout": r, "residual_m": r - r_true, "d_runout_d_beta": d, "accepted": True}]
    for _ in range(args.steps):
        if abs(r - r_true) < 0.05 * args.dx or d == 0.0:
            break
        step = float(np.clip(-(r - r_true) / d, -radius, radius))
        trial = jnp.clip(beta + step, 0.0, 0.5)
        r_t, d_t = (float(v) for v in jvp(trial, mu_w, f64(1.0), f64(0.0)))
        accepted = abs(r_t - r_true) < abs(r - r_true)
        history.append({"beta": float(trial), "runout": r_t, "residual_m": r_t - r_true, "d_runout_d_beta": d_t,
                        "accepted": accepted, "radius": radius})
        print(start, history[-1], flush=True)
        if accepted:
            beta, r, d, radius = trial, r_t, d_t, min(2 * radius, 0.2)
        else:  # a shorter step next time (shorter than this one, so never the same trial twice)
            radius = 0.5 * min(radius, abs(step))
    fit = {"truth": args.truth, "start": start, "beta": float(beta), "residual_m": r - r_true,
           "converged": abs(r - r_true) < 0.05 * args.dx, "runs": len(history), "iterations": history,
           "wall_s": round(time.perf_counter() - clock, 1)}
    print("fit", {k: v for k, v in fit.items() if k != "iterations"}, flush=True)
    return fit


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dx", type=float, default=2.0)
    parser.add_argument("--truth", type=float, default=0.1, help="the twin's β")
    parser.add_argument("--start", type=float, nargs="+", default=(0.2, 0.03), help="the fits' first β, one fit each")
    parser.add_argument("--steps", type=int, default=10, help="trial steps per fit at most")
    parser.add_argument("--radius", type=float, default=0.05, help="the first trust radius in β")
    parser.add_argument("--fits-only", action="store_true",
                        help="reuse the gradient check and the curve of the saved results; run the fits")
    parser.add_argument("--fd-steps", type=float, nargs="+", default=(1e-2, 1e-3, 1e-4, 1e-5))
    args = parser.parse_args()
    scene = avalanche(dx=args.dx, t_end=100.0, frames=1, dtype=jnp.float64)
    config, state, params = scene
    ground = config.walls[0]
    xs = np.arange(1300.0, float(ground.x[-1]), 0.5 * args.dx)  # the whole path below the release's top
    rollout = jax.jit(make_rollout(config, observer=None))

    def runout(beta, mu_w):
        final = rollout(state, params.replace(beta=beta, mu_w=mu_w))[0]
        return smooth_runout(final.x, final.vol0, ground, xs), final.status

    value = jax.jit(runout)
    jvp = jax.jit(lambda b, m, tb, tm: jax.jvp(lambda b, m: runout(b, m)[0], (b, m), (tb, tm)))
    f64 = jnp.float64
    mu_w = f64(params.mu_w)

    saved = ROOT / "docs/results/avalanche_fit.json"
    r_true = float(value(f64(args.truth), mu_w)[0])
    if args.fits_only:  # the gradient check and the curve from the last full run
        previous = json.loads(saved.read_text())
        check, betas = previous["gradient_check"], np.asarray(previous["runout_vs_beta"]["beta"])
        curve, slopes = previous["runout_vs_beta"]["runout"], previous["runout_vs_beta"]["d_runout_d_beta_jvp"]
        if abs(check["runout"] - r_true) > 1e-6 or check["beta"] != args.truth:
            raise SystemExit("--fits-only: the saved check was made at another truth or by another code")
    else:
        check, (betas, curve, slopes) = gradient_check(args, value, jvp, mu_w, r_true), runout_curve(jvp, mu_w)
    fits = [newton(args, jvp, mu_w, r_true, start) for start in args.start]
    out = {"dx": args.dx, "n_particles": int(state.n_particles), "snow": "dry", "t_end": 100.0,
           "runout": "smooth_runout on x = 1300 m to the terrain's end, threshold 0.1 m, kernel width 2 dx",
           "gradient_check": check,
           "runout_vs_beta": {"beta": betas.tolist(), "runout": curve, "d_runout_d_beta_jvp": slopes,
                              "secant_slopes": (np.diff(curve) / np.diff(betas)).tolist()}, "fits": fits}
    saved.write_text(json.dumps(out, indent=1) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, low) = plt.subplots(2, 1, figsize=(6.5, 7), sharex=True, constrained_layout=True)
    ax.plot(betas, curve, "k.-", label="smooth runout R(β), dry snow")
    ax.axhline(r_true, color="r", ls=":", label=f"given runout (β = {args.truth})")
    for fit, colour in zip(fits, ("b", "g", "m")):
        its = [(h_["beta"], h_["runout"]) for h_ in fit["iterations"] if h_["accepted"]]
        verdict = f"converged to β = {fit['beta']:.4f}" if fit["converged"] else "did not converge"
        ax.plot(*zip(*its), "o--", color=colour, ms=4, label=f"Newton from β = {fit['start']}: {verdict}")
        for k, (b, r) in enumerate(its):
            ax.annotate(str(k), (b, r), textcoords="offset points", xytext=(4, 4), fontsize=7, color=colour)
    ax.set_ylabel("runout (m)")
    ax.set_title(f"S6 avalanche, dx = {args.dx:g} m: a fit of β to a runout", fontsize=10)
    ax.legend(fontsize=8)
    low.semilogy(betas, np.abs(slopes), "ko-", ms=4, label="|dR/dβ|, forward mode (pathwise)")
    mids = 0.5 * (betas[1:] + betas[:-1])
    low.semilogy(mids, np.abs(np.diff(curve) / np.diff(betas)), "rs--", ms=4, label="|secant slope| of the curve above")
    low.set_xlabel("β")
    low.set_ylabel("|dR/dβ| (m)")
    low.legend(fontsize=8)
    fig.savefig(ROOT / "docs/figures/avalanche_fit.png", dpi=120)


if __name__ == "__main__":
    main()
