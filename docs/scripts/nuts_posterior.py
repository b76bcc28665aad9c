"""The NUTS posterior (issue 11) of the S4 twin's (β, μ1) and of S7's μ1, checked against the
quadrature of ``grid_posterior`` on the same target, with diagnostics and posterior predictives.

    python docs/scripts/nuts_posterior.py [s4|s7|both] [--draws N] [--warmup W]   (needs [bayes])

Resolutions cheap enough to sample on two CPU cores: S4 at dx = L/6 (the twin of
``beyond_gauss_newton.py``: truth β = 0.25, μ1 = 0.38, final profile, 2 % noise), S7 at dx = H/6
(μ1 fitted on the measured surface at x <= 0.2 m; the toe beyond is the held-out part of the
posterior predictive). Writes docs/results/nuts_{s4,s7}.json and docs/figures/{s4_twin,s7}_nuts.png,
{s4_twin,s7}_predictive.png; the posterior objects are pickled to $NUTS_PICKLE_DIR when set.
"""

import argparse
import json
import os
import pathlib
import pickle
import time

import numpy as np
from beyond_gauss_newton import S4_KEYS, S4_TRUTH, s4_twin  # the same twin (this folder)

from calibration import Objective, ProfileTarget, fit, load_profile
from calibration.likelihood import grid_posterior
from calibration.mcmc import nuts_posterior, posterior_predictive
from calibration.plots import plot_nuts, plot_posterior_predictive
from jaxmpm.scenes import aluminium_bars

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS, FIGURES = ROOT / "docs" / "results", ROOT / "docs" / "figures"
CHAINS = 4
SETTINGS = {"s4": {"warmup": 25, "draws": 60}, "s7": {"warmup": 20, "draws": 50}}


def _finish(name, label, objective, result, grid, nuts, predictive_objective, extra):
    predictive = posterior_predictive(predictive_objective, nuts, n=40)
    out = {"fit": {"params": result.theta, "stderr": dict(zip(result.keys, result.uncertainty.stderr.tolist())),
                   "noise": result.uncertainty.noise, "wall_s": round(result.wall_s, 1)},
           "nuts": nuts.to_json(), "grid_posterior": grid.to_json(),
           "nuts_sd_over_grid_sd": {k: nuts.sd[k] / grid.sd[k] for k in nuts.keys},
           "nuts_mean_minus_grid_mean_in_grid_sd": {k: (nuts.mean[k] - grid.mean[k]) / grid.sd[k] for k in nuts.keys},
           **extra}
    (RESULTS / f"nuts_{name}.json").write_text(json.dumps(out, indent=1))
    if os.environ.get("NUTS_PICKLE_DIR"):
        with open(pathlib.Path(os.environ["NUTS_PICKLE_DIR"]) / f"{name}.pkl", "wb") as fh:
            pickle.dump({"nuts": nuts, "grid": grid, "predictive": predictive, "extra": extra}, fh)
    for k in nuts.keys:
        print(f"{name} {k}: NUTS {nuts.mean[k]:.5g} ± {nuts.sd[k]:.3g} (R-hat {nuts.rhat[k]:.3f}, ESS bulk "
              f"{nuts.ess_bulk[k]:.0f}), grid {grid.mean[k]:.5g} ± {grid.sd[k]:.3g}, GN se {nuts.gn_stderr[k]:.3g}")
    print(f"{name}: divergences {nuts.divergences}, steps/draw {nuts.steps}, {nuts.wall_s:.0f} s", flush=True)
    plot_nuts(nuts, FIGURES / f"{label}_nuts.png", grid=grid, truth=extra.get("truth"))
    plot_posterior_predictive(predictive, FIGURES / f"{label}_predictive.png", title=extra["predictive_title"],
                              split=extra.get("split_x"))


def s4():
    truth, keys = S4_TRUTH, S4_KEYS
    scene, _, objective = s4_twin(6)
    t0 = time.perf_counter()
    result = fit(objective, dict(zip(keys, 0.9 * truth)), steps=25, noise=0.02)
    grid = grid_posterior(objective, result, n=15)
    nuts = nuts_posterior(objective, result, chains=CHAINS, progress=True, **SETTINGS["s4"])
    extra = {"truth": dict(zip(keys, truth.tolist())), "dx": scene.config.grid.dx, "noise": 0.02,
             "predictive_title": "S4 twin (dx = L/6): 40 NUTS draws against the noisy final profile",
             "wall_s": round(time.perf_counter() - t0, 1)}
    _finish("s4", "s4_twin", objective, result, grid, nuts, objective, extra)


def s7():
    data = load_profile(ROOT / "experiments_data" / "bui2008" / "bui2008_final_surface.csv")
    scene = aluminium_bars(dx=0.1 / 6)
    fitted = data.x <= 0.2
    objective = Objective(scene, ("mu1",), profile=ProfileTarget(data.x[fitted], data.h[fitted], None, str(data.path)))
    everything = Objective(scene, ("mu1",), profile=ProfileTarget(data.x, data.h, None, str(data.path)))
    t0 = time.perf_counter()
    result = fit(objective, {"mu1": 0.36}, steps=15)
    grid = grid_posterior(objective, result, n=41)
    nuts = nuts_posterior(objective, result, chains=CHAINS, progress=True, **SETTINGS["s7"])
    extra = {"dx": scene.config.grid.dx, "fitted_points": int(fitted.sum()), "split_x": 0.2,
             "friction_angle_deg": {"mean": float(np.degrees(np.arctan(nuts.mean["mu1"]))),
                                    "ci95": [float(np.degrees(np.arctan(v))) for v in nuts.ci95["mu1"]]},
             "predictive_title": "S7 (dx = H/6): 40 NUTS draws; fitted x <= 0.2 m, the toe beyond held out",
             "wall_s": round(time.perf_counter() - t0, 1)}
    _finish("s7", "s7", objective, result, grid, nuts, everything, extra)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("which", nargs="?", default="both", choices=("s4", "s7", "both"))
    parser.add_argument("--draws", type=int, help="draws kept per chain (default: s4 60, s7 50)")
    parser.add_argument("--warmup", type=int, help="step-size adaptation steps per chain (default: s4 25, s7 20)")
    args = parser.parse_args()
    for name in SETTINGS:
        SETTINGS[name].update({k: v for k, v in (("draws", args.draws), ("warmup", args.warmup)) if v is not None})
    which = args.which
    if which in ("s7", "both"):
        s7()
    if which in ("s4", "both"):
        s4()
