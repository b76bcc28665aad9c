"""Uncertainty beyond Gauss–Newton: profile likelihoods, the grid posterior and a
held-out prediction, for the S4 twin and for S7 (Bui et al. 2008's aluminium bars).

    python docs/scripts/beyond_gauss_newton.py [s4|s7|both]

S4 twin: dx = L/8, the twin's truth (β = 0.25, μ1 = 0.38), the final profile (t = 0.5 s, 50
points) with 2 % noise; fitted (β, μ1) from 0.9 × the truth; then the profile likelihood of
each, the posterior on a 15 × 15 grid (whitened), and the prediction of what the fit never saw: the
profiles at t = 0.1 and 0.2 s and the front history (noise-free, made at the truth).
S7: dx = H/8, μ1 fitted to the measured surface at x ≤ 0.2 m; the profile likelihood and the
posterior of μ1 (41 points), and the prediction of the held-out toe, x > 0.2 m.
Writes docs/results/beyond_gauss_newton_{s4,s7}.json and docs/figures/*_likelihood.png,
*_heldout.png.
"""

import json
import pathlib
import sys
import time

import numpy as np

from calibration import FrontTarget, Objective, ProfileTarget, fit, load_profile
from calibration.inference.gridpost import grid_posterior, predict_heldout
from calibration.inference.likelihood import profile_likelihood
from calibration.plots.posteriors import plot_heldout, plot_profile_likelihoods
from calibration.studies.twin import FRONT_TIMES
from jaxmpm.scenes import S4_SIDE, aluminium_bars, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS, FIGURES = ROOT / "docs" / "results", ROOT / "docs" / "figures"


def _report(name, result, profiles, posterior, held, extra):
    unc = result.uncertainty
    out = {"fit": {"params": result.theta, "stderr": dict(zip(result.keys, unc.stderr.tolist())),
                   "ci95_gauss_newton": {k: unc.ci95[j].tolist() for j, k in enumerate(result.keys)},
                   "noise": unc.noise, "wall_s": round(result.wall_s, 1)},
           "profile_likelihood": {p.key: p.to_json() for p in profiles}, "posterior": posterior.to_json(),
           "heldout": held.to_json(), **extra}
    (RESULTS / f"beyond_gauss_newton_{name}.json").write_text(json.dumps(out, indent=1))
    for p in profiles:
        print(f"{name} {p.key}: fit {p.theta_hat:.5g}, GN 95 % {np.round(p.gn_ci95, 5).tolist()}, "
              f"profile 95 % {[None if v is None else round(v, 5) for v in p.ci95]}, "
              f"posterior mean {posterior.mean[p.key]:.5g} sd {posterior.sd[p.key]:.3g} "
              f"(GN se {posterior.gn_stderr[p.key]:.3g}), {p.wall_s:.0f} s")
    print(f"{name} held out: rms {held.rms}, inside band {held.inside}")


S4_TRUTH, S4_KEYS = np.array([0.25, 0.38]), ("beta", "mu1")


def s4_twin(cells_per_length):
    """The S4 twin at dx = L / ``cells_per_length``: (scene, points xs, objective of the final
    profile at the truth with 2 % noise, seed 0), the points cut at 1.3 × the deposit's extent."""
    scene = cohesive_collapse(dx=S4_SIDE / cells_per_length, t_end=0.5, beta=0.25)
    xs = np.linspace(0.0, 0.3, 50)
    gen = Objective(scene, S4_KEYS, profile=ProfileTarget(xs, np.ones_like(xs)), check_data=False)
    h = np.asarray(gen.predict(S4_TRUTH)["h"], float)
    keep = xs <= 1.3 * xs[np.flatnonzero(h > 0.01 * h.max())[-1]]
    xs, h = xs[keep], h[keep]
    noisy = h + 0.02 * h.max() * np.random.default_rng(0).standard_normal(h.shape)
    return scene, xs, Objective(scene, S4_KEYS, profile=ProfileTarget(xs, noisy))


def s4():
    truth, keys = S4_TRUTH, S4_KEYS
    scene, xs, objective = s4_twin(8)
    t0 = time.perf_counter()
    result = fit(objective, dict(zip(keys, 0.9 * truth)), steps=25, noise=0.02)
    print(f"s4 fit {result.theta} in {result.wall_s:.0f} s", flush=True)
    profiles = [profile_likelihood(objective, result, k, n=9, steps=4) for k in keys]
    print(f"s4 profiles in {sum(p.wall_s for p in profiles):.0f} s", flush=True)
    posterior = grid_posterior(objective, result, n=15)
    print(f"s4 posterior in {posterior.wall_s:.0f} s", flush=True)
    # Held out: the profiles at 0.1 and 0.2 s and the front history, noise-free at the truth.
    times = np.asarray(FRONT_TIMES)
    probe = Objective(scene, keys, profile=[ProfileTarget(xs, np.ones_like(xs), t) for t in (0.1, 0.2)],
                      front=FrontTarget(times, np.full(times.size, 0.1)), check_data=False)
    pred = probe.predict(truth)
    hh = np.asarray(pred["h"], float).reshape(2, xs.size)
    held_obj = Objective(scene, keys, profile=[ProfileTarget(xs, hh[i], t) for i, t in enumerate((0.1, 0.2))],
                         front=FrontTarget(times, np.asarray(pred["front"], float)))
    held = predict_heldout(result, held_obj)
    extra = {"truth": dict(zip(keys, truth.tolist())), "dx": scene.config.grid.dx, "noise": 0.02,
             "heldout_what": "profiles at t = 0.1 and 0.2 s and the front at 10 times (fit: t = 0.5 s only)",
             "wall_s": round(time.perf_counter() - t0, 1)}
    _report("s4", result, profiles, posterior, held, extra)
    plot_profile_likelihoods(profiles, FIGURES / "s4_twin_likelihood.png", truth=dict(zip(keys, truth)),
                             posterior=posterior)
    plot_heldout(held, FIGURES / "s4_twin_heldout.png",
                 title="S4 twin: fitted at t = 0.5 s, predicted at 0.1, 0.2 s and the front")


def s7():
    data = load_profile(ROOT / "experiments_data" / "bui2008" / "bui2008_final_surface.csv")
    scene = aluminium_bars(dx=0.1 / 8)
    fitted, held_out = data.x <= 0.2, data.x > 0.2
    objective = Objective(scene, ("mu1",), profile=ProfileTarget(data.x[fitted], data.h[fitted], None, str(data.path)))
    t0 = time.perf_counter()
    result = fit(objective, {"mu1": 0.36}, steps=15)
    profiles = [profile_likelihood(objective, result, "mu1", n=13)]
    posterior = grid_posterior(objective, result, n=41)
    held_obj = Objective(scene, ("mu1",), profile=ProfileTarget(data.x[held_out], data.h[held_out], None,
                                                                str(data.path)))
    held = predict_heldout(result, held_obj)
    extra = {"dx": scene.config.grid.dx, "fitted_points": int(fitted.sum()), "heldout_points": int(held_out.sum()),
             "heldout_what": "the measured surface beyond x = 0.2 m (the toe), not used in the fit",
             "friction_angle_deg": float(np.degrees(np.arctan(result.theta["mu1"]))),
             "wall_s": round(time.perf_counter() - t0, 1)}
    _report("s7", result, profiles, posterior, held, extra)
    plot_profile_likelihoods(profiles, FIGURES / "s7_likelihood.png", posterior=posterior)
    plot_heldout(held, FIGURES / "s7_heldout.png", title="S7: mu1 fitted on x <= 0.2 m, the toe predicted")


if __name__ == "__main__":
    which = sys.argv[1] if len(sys.argv) > 1 else "both"
    if which in ("s7", "both"):
        s7()
    if which in ("s4", "both"):
        s4()
