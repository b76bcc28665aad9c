"""The NUTS posterior of the S4 twin's (β, μ1) and of S7's μ1, checked against the
quadrature of ``grid_posterior`` on the same target, with diagnostics and posterior predictives.

    python docs/scripts/nuts_posterior.py [s4|s7|both] [--draws N] [--warmup W]   (needs [bayes])
    python docs/scripts/nuts_posterior.py s7 --resume --draws N [--workers 2]

``--resume`` goes on with the chains stored in docs/results/nuts_{s4,s7}.json for N more draws
each (``nuts_posterior(resume=)``: from their last draws, with their step sizes), in ``--workers``
processes side by side, each pinned to one core with a single-threaded XLA: on two cores one
process per core runs a Jacobian in 1.1 s where one process on both takes 1.7 s (S7 at H/6).

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
import subprocess
import sys
import tempfile
import time

import numpy as np
from beyond_gauss_newton import S4_KEYS, S4_TRUTH, s4_twin  # the same twin (this folder)

from calibration import Objective, ProfileTarget, fit, load_profile
from calibration.inference.gridpost import grid_posterior
from calibration.inference.mcmc import McmcPosterior, nuts_posterior, posterior_predictive
from calibration.plots.posteriors import plot_nuts, plot_posterior_predictive
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


def s4_setup():
    truth, keys = S4_TRUTH, S4_KEYS
    scene, _, objective = s4_twin(6)
    result = fit(objective, dict(zip(keys, 0.9 * truth)), steps=25, noise=0.02)
    extra = {"truth": dict(zip(keys, truth.tolist())), "dx": scene.config.grid.dx, "noise": 0.02,
             "predictive_title": "S4 twin (dx = L/6): 40 NUTS draws against the noisy final profile"}
    return {"objective": objective, "predictive": objective, "result": result, "grid_n": 15, "extra": extra,
            "label": "s4_twin"}


def s7_setup():
    data = load_profile(ROOT / "experiments_data" / "bui2008" / "bui2008_final_surface.csv")
    scene = aluminium_bars(dx=0.1 / 6)
    fitted = data.x <= 0.2
    objective = Objective(scene, ("mu1",), profile=ProfileTarget(data.x[fitted], data.h[fitted], None, str(data.path)))
    everything = Objective(scene, ("mu1",), profile=ProfileTarget(data.x, data.h, None, str(data.path)))
    result = fit(objective, {"mu1": 0.36}, steps=15)
    extra = {"dx": scene.config.grid.dx, "fitted_points": int(fitted.sum()), "split_x": 0.2,
             "predictive_title": "S7 (dx = H/6): 40 NUTS draws; fitted x <= 0.2 m, the toe beyond held out"}
    return {"objective": objective, "predictive": everything, "result": result, "grid_n": 41, "extra": extra,
            "label": "s7"}


SETUPS = {"s4": s4_setup, "s7": s7_setup}


def _stored(name):
    return McmcPosterior.from_json(json.loads((RESULTS / f"nuts_{name}.json").read_text())["nuts"])


def part(name, chains, draws, out):
    """One worker of ``--resume``: the stored chains at positions ``chains`` go on for ``draws``."""
    case = SETUPS[name]()
    stored = _stored(name)
    nuts = nuts_posterior(case["objective"], case["result"], draws=draws, resume=stored.take(chains),
                          seed=stored.seed, progress=True)
    pathlib.Path(out).write_text(json.dumps(nuts.to_json()))


def _resumed(name, draws, workers):
    stored = _stored(name)
    groups = [g.tolist() for g in np.array_split(np.arange(stored.chains), min(workers, stored.chains))]
    env = {**os.environ, "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
    cores = sorted(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory() as tmp:
        outs = [pathlib.Path(tmp) / f"part{i}.json" for i in range(len(groups))]
        procs = [subprocess.Popen([sys.executable, __file__, name, "--draws", str(draws), "--part",
                                   ",".join(map(str, g)), "--out", str(o), "--core", str(cores[i % len(cores)])],
                                  env=env) for i, (g, o) in enumerate(zip(groups, outs))]
        if any(proc.wait() != 0 for proc in procs):
            raise RuntimeError(f"{name}: a worker of --resume failed (its log is above)")
        return McmcPosterior.join([McmcPosterior.from_json(json.loads(o.read_text())) for o in outs])


def run(name, resume=False, workers=1):
    t0 = time.perf_counter()
    if resume:
        nuts = _resumed(name, SETTINGS[name]["draws"], workers)
    case = SETUPS[name]()
    objective, result = case["objective"], case["result"]
    grid = grid_posterior(objective, result, n=case["grid_n"])
    if not resume:
        nuts = nuts_posterior(objective, result, chains=CHAINS, progress=True, **SETTINGS[name])
    extra = {**case["extra"], "wall_s": round(time.perf_counter() - t0, 1)}
    if name == "s7":
        extra["friction_angle_deg"] = {"mean": float(np.degrees(np.arctan(nuts.mean["mu1"]))),
                                       "ci95": [float(np.degrees(np.arctan(v))) for v in nuts.ci95["mu1"]]}
    _finish(name, case["label"], objective, result, grid, nuts, case["predictive"], extra)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("which", nargs="?", default="both", choices=("s4", "s7", "both"))
    parser.add_argument("--draws", type=int, help="draws kept per chain (default: s4 60, s7 50)")
    parser.add_argument("--warmup", type=int, help="step-size adaptation steps per chain (default: s4 25, s7 20)")
    parser.add_argument("--resume", action="store_true", help="extend the stored chains by --draws each")
    parser.add_argument("--workers", type=int, default=1, help="processes for --resume, one core each (default 1)")
    parser.add_argument("--part", help=argparse.SUPPRESS)  # a worker of --resume: chain positions "0,1"
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--core", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.resume and (args.draws is None or args.warmup is not None):
        parser.error("--resume needs --draws (more draws per chain) and takes no --warmup")
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    for name in SETTINGS:
        SETTINGS[name].update({k: v for k, v in (("draws", args.draws), ("warmup", args.warmup)) if v is not None})
    if args.part is not None:
        if args.core is not None:
            os.sched_setaffinity(0, {args.core})
        part(args.which, [int(c) for c in args.part.split(",")], args.draws, args.out)
        sys.exit(0)
    for name in ("s7", "s4"):
        if args.which in (name, "both"):
            run(name, resume=args.resume, workers=args.workers)
