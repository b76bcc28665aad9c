"""The emulated posterior (``calibration.inference.emulator``) against the model's own: the S4 twin's
(β, μ1) at dx = L/6, where NUTS on the model (docs/results/nuts_s4.json, 7,490 Jacobians) and the
grid quadrature are stored, and the five keys of the three filmed collapses (docs/five_keys/).

    python docs/scripts/emulated_posterior.py s4 [--workers 2]       (needs [bayes])
    python docs/scripts/emulated_posterior.py five [--workers 2] [--coarsen R] [--model-error] [--checks N]
        [--draws N] [--target-accept A] [--emulator corrected] [--i0-measured REL] [--grid-levels L] [--tag T]
    python docs/scripts/emulated_posterior.py error [--workers 2]      (the five keys' model error)
    python docs/scripts/emulated_posterior.py shape [--workers 2]      (its grid term: rows or one shape)
    python docs/scripts/emulated_posterior.py linear [--workers 2]     (the posterior's grid term linearised)
    python docs/scripts/emulated_posterior.py regrid [--result NAME]   (a stored result's grid reading again)

Writes docs/results/emulated_{s4,five}.json and docs/figures/emulated_{s4,five}.png (``--coarsen R``:
``five_coarse{R}``; ``--model-error``: ``five_model_error``, the likelihood's σ by block the data's 2 %
and the model's own error there, ``calibration.inference.likelihood.model_error``, in quadrature).
"""

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from beyond_gauss_newton import S4_KEYS, S4_TRUTH, s4_twin  # noqa: E402  (this folder)

from calibration import fit  # noqa: E402
from calibration.batch.workers import Workers  # noqa: E402
from calibration.inference.emulator import emulated_posterior  # noqa: E402
from calibration.inference.likelihood import model_error  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS, FIGURES = ROOT / "docs" / "results", ROOT / "docs" / "figures"


def s4(workers, args):
    _, _, objective = s4_twin(6)
    t0 = time.perf_counter()
    result = fit(objective, dict(zip(S4_KEYS, 0.9 * S4_TRUTH)), steps=25, noise=0.02)
    fit_s = time.perf_counter() - t0
    print(f"fit {result.theta} in {fit_s:.0f} s", flush=True)
    post = emulated_posterior(objective, result, checks=args.checks, emulator=args.emulator, workers=workers,
                              progress=True)
    stored = json.loads((RESULTS / "nuts_s4.json").read_text())
    out = {"case": "S4 twin (beta, mu1) at dx = L/6: final profile, 2 % noise",
           "truth": dict(zip(S4_KEYS, S4_TRUTH.tolist())), "fit": result.theta, "fit_wall_s": round(fit_s, 1),
           "emulated": post.to_json(),
           "model_nuts": {k: stored["nuts"][k] for k in ("mean", "sd", "ci95", "rhat", "ess_bulk",
                                                         "gradient_evaluations", "wall_s")},
           "grid_quadrature": {k: stored["grid_posterior"][k] for k in ("mean", "sd", "ci95", "wall_s")}}
    return out, post


FIVE = ("beta", "mu1", "mu2", "I0", "xi")
FIVE_TRUTH = {"beta": 0.25, "mu1": 0.3818628674187188, "mu2": 0.6434683848584607, "I0": 0.279, "xi": 50.0}
FIVE_FILES = [ROOT / "docs" / "five_keys" / f"{name}.toml" for name in ("column", "slope20", "tall_slope20")]


def five(workers, args):
    """The five keys from the three filmed collapses (docs/five_keys/, files at L/12, data made at
    L/18 with 2 % noise), centred where the four-key fit stopped (docs/results/five_keys_fit_L12.json)
    with I0 at the files' start; ``--coarsen R``: the same on a grid R times coarser (the grid term)."""
    import numpy as np

    from calibration import CompositeObjective, Objective
    from calibration.inference.emulator import log_uniform
    from calibration.inference.gridpost import weighted_quantile
    from calibration.inference.surrogates import psis
    from jaxmpm import Experiment

    objective = CompositeObjective([Objective.from_experiment(Experiment.from_toml(f), FIVE) for f in FIVE_FILES])
    if args.coarsen != 1.0:
        objective = objective.coarsened(args.coarsen)
    four = json.loads((RESULTS / "five_keys_fit_L12.json").read_text())["params"]
    centre = {**four, "I0": 0.4}
    noise, error = 0.02, None
    if args.model_error:
        error = model_error(objective, centre, workers=workers)
        noise = error.noise(0.02)
        print("model error by block", error.total(), flush=True)
    prior = None
    if args.i0_measured:  # an incline's I0 to a relative sd, the measurement drawn about the truth (seeded)
        measured = FIVE_TRUTH["I0"] * (1.0 + args.i0_measured * np.random.default_rng(args.i0_seed).standard_normal())
        prior = {"I0": (measured, args.i0_measured * measured)}
        print("I0 measured elsewhere:", prior, flush=True)
    post = emulated_posterior(objective, centre, noise=noise, checks=args.checks, emulator=args.emulator,
                              draws=args.draws, target_accept=args.target_accept, prior=prior,
                              grid_ratio=1.5 if args.grid_levels else None, grid_levels=max(args.grid_levels, 1),
                              workers=workers, progress=True)
    truth_chi2 = post.chi2_at(objective, FIVE_TRUTH)
    joint = {"truth_chi2": truth_chi2, "truth_level": post.credible_level(truth_chi2),
             "check_chi2_quantiles": dict(zip(("5%", "50%", "95%"), map(float, weighted_quantile(
                 post.check_chi2, np.exp(psis(post.checks[1])[0]), [0.05, 0.5, 0.95]))))}
    print("the truth in the joint credible regions:", joint, flush=True)
    # I0 spans three decades of its box: the same checks under a log-uniform prior on it.
    log_prior = log_uniform(post.keys, "I0")
    under_log = {**post.reweighted(log_prior), "truth_level": post.credible_level(truth_chi2, log_prior)}
    under_log["truth_inside_ci95"] = {k: bool(under_log["ci95"][k][0] <= FIVE_TRUTH[k] <= under_log["ci95"][k][1])
                                      for k in FIVE}
    print("with a log-uniform prior on I0:", under_log, flush=True)
    out = {"case": f"five keys, three filmed collapses at dx = L/{0.089 / objective.dx:.0f} (data L/18, 2 % noise)",
           "dx": objective.dx, "coarsen": args.coarsen, "truth": FIVE_TRUTH, "centre": centre, "noise": noise,
           "data_noise": 0.02, "model_error": None if error is None else error.to_dict(), "emulated": post.to_json(),
           "truth_inside_ci95": {k: bool(post.ci95[k][0] <= FIVE_TRUTH[k] <= post.ci95[k][1]) for k in FIVE},
           "truth_joint": joint, "log_uniform_I0": under_log, "prior": prior,
           "truth_inside_ci95_with_grid": None if post.grid is None else {
               k: bool(post.ci95_with_grid[k][0] <= FIVE_TRUTH[k] <= post.ci95_with_grid[k][1]) for k in FIVE},
           "box": dict(zip(FIVE, zip(map(float, objective.bounds.lower), map(float, objective.bounds.upper))))}
    return out, post


def error(workers, args):
    """The model error of the five-key objective (``calibration.inference.likelihood.model_error``) at the
    posterior's centre, against what it is meant to hold: the residuals at the truth, where the
    twin's data (L/18, another draw, 2 % noise) and the L/12 model differ by noise, draw and grid."""
    import numpy as np

    from calibration import CompositeObjective, Objective
    from jaxmpm import Experiment

    objective = CompositeObjective([Objective.from_experiment(Experiment.from_toml(f), FIVE) for f in FIVE_FILES])
    centre = {**json.loads((RESULTS / "five_keys_fit_L12.json").read_text())["params"], "I0": 0.4}
    found = model_error(objective, centre, workers=workers)
    r, _ = objective.residuals(np.array([FIVE_TRUTH[k] for k in objective.keys]))
    e = np.asarray(r, float) / np.asarray(objective.row_scale, float)
    at_truth = {b: float(np.sqrt(np.mean(e[sl] ** 2))) for b, sl in objective.blocks.items()}
    for b in objective.blocks:
        print(f"{b:14s} draw {found.draw[b]:.4f} grid {found.grid[b]:.4f} rms at truth {at_truth[b]:.4f}")
    return {"case": "the five-key objective's model error at the posterior's centre (dx = L/12)",
            "centre": centre, "truth": FIVE_TRUTH, "data_noise": 0.02, "model_error": found.to_dict(),
            "residual_rms_at_truth": at_truth}, None


def shape(workers, args):
    """The grid term as independent rows or as one shape per block (covariance σ² I + g gᵀ), at
    the five-key twin's truth: the linearised fit from the truth's residuals in each form's sd."""
    import numpy as np

    from calibration import CompositeObjective, Objective, uncertainty
    from jaxmpm import Experiment

    objective = CompositeObjective([Objective.from_experiment(Experiment.from_toml(f), FIVE) for f in FIVE_FILES])
    keys = list(objective.keys)
    theta = np.array([FIVE_TRUTH[k] for k in keys])
    r, J, pred = objective.residuals_and_jacobian(theta)
    fine = uncertainty.clean_runs([(r, pred)]) + uncertainty.redrawn_residuals(objective, theta, 4, workers)
    _, coarse = uncertainty.coarse_residuals(objective, theta, 1.5, 2, workers)
    s = np.asarray(objective.row_scale, float)
    e, Je = np.asarray(r, float) / s, np.asarray(J, float) / s[:, None]
    F, C = np.stack(fine) / s, np.stack(coarse) / s
    var, diff = np.var(F, axis=0, ddof=1), F.mean(axis=0) - C.mean(axis=0)
    factor = 1.5 - 1.0  # ratio^p - 1, p = 1
    forms, correlation = {}, {}
    for form in ("data", "rows", "shape", "rows+shape"):
        cov = np.zeros((e.size, e.size))
        for b, sl in objective.blocks.items():
            v = float(np.mean(var[sl]))
            grid = np.sqrt(max(float(np.mean(diff[sl] ** 2)) - v * (1 / len(F) + 1 / len(C)), 0.0)) / factor
            g = diff[sl] / factor
            g = g * grid / np.sqrt(np.mean(g**2)) if np.any(g) else g
            correlation[b] = float(np.corrcoef(g, e[sl])[0, 1])
            n = sl.stop - sl.start
            base = 0.02**2 + (v if form != "data" else 0.0)
            cov[sl, sl] = np.eye(n) * (base + (grid**2 if "rows" in form else 0.0))
            if "shape" in form:
                cov[sl, sl] += np.outer(g, g)
        inv = np.linalg.inv(cov)
        c = np.linalg.inv(Je.T @ inv @ Je)
        sd = np.sqrt(np.diag(c))
        lands = -c @ Je.T @ inv @ e
        forms[form] = {"chi2_at_truth": float(e @ inv @ e), "rows": int(e.size), "sd": dict(zip(keys, sd.tolist())),
                       "lands_sd": dict(zip(keys, (lands / sd).tolist()))}
        print(form, forms[form], flush=True)
    return {"case": "the grid term's form at the five-key twin's truth (L/12, data L/18, 2 % noise)",
            "truth": FIVE_TRUTH, "forms": forms, "shape_vs_truth_error_correlation": correlation}, None


def linear(workers, args):
    """The grid term of the five-key posterior (I0 measured) linearised, as a fit's: the
    Gauss–Newton shift −(Jᵀ W J + P)⁻¹ Jᵀ W (r(1.5 dx) − r(dx)) at the L/12 posterior's mean (and
    at the truth), with the posterior's noise W and the I0 prior's precision P, against the shift
    of the posterior's mean that the same posterior at L/8 shows (stored results: with the same
    noise, the grid term's run; with the L/8 model's own error as noise, ``--coarsen 1.5``)."""
    import numpy as np

    from calibration import CompositeObjective, Objective
    from calibration.inference.nuts import row_weights
    from calibration.inference.scatter import coarse_residuals
    from jaxmpm import Experiment

    fine = json.loads((RESULTS / "emulated_five_model_error_corrected_i0_measured.json").read_text())
    coarse = json.loads((RESULTS / "emulated_five_coarse1.5_model_error_corrected_i0_measured.json").read_text())
    objective = CompositeObjective([Objective.from_experiment(Experiment.from_toml(f), FIVE) for f in FIVE_FILES])
    weights = row_weights(objective, fine["noise"])
    precision = np.zeros((len(FIVE), len(FIVE)))
    precision[FIVE.index("I0"), FIVE.index("I0")] = fine["prior"]["I0"][1] ** -2
    grid = json.loads((RESULTS / "emulated_five_model_error_corrected_i0_measured_grid.json").read_text())
    out = {"case": "the five-key posterior's grid term (L/12, I0 measured): linearised against the posterior at L/8",
           "posterior_mean_shift_same_noise": grid["emulated"]["grid"]["shift"],
           "posterior_mean_shift_own_noise": {k: coarse["emulated"]["mean"][k] - fine["emulated"]["mean"][k]
                                              for k in FIVE},
           "truth_minus_posterior_mean": {k: FIVE_TRUTH[k] - fine["emulated"]["mean"][k] for k in FIVE},
           "posterior_sd": fine["emulated"]["sd"]}
    for label, point in (("at_posterior_mean", fine["emulated"]["mean"]), ("at_truth", FIVE_TRUTH)):
        theta = np.array([point[k] for k in FIVE])
        t0 = time.perf_counter()
        r, J, _ = objective.residuals_and_jacobian(theta)
        r, J = np.asarray(r, float), np.asarray(J, float)
        _, kept = coarse_residuals(objective, theta, 1.5, 2, workers)
        change = np.mean(kept, axis=0) - r
        shift = -np.linalg.solve(J.T @ (weights[:, None] * J) + precision, J.T @ (weights * change))
        out[f"linearised_{label}"] = {"shift": dict(zip(FIVE, shift.tolist())), "wall_s": time.perf_counter() - t0}
        print(label, out[f"linearised_{label}"], flush=True)
    print("posterior mean shift", out["posterior_mean_shift_same_noise"])
    return out, None


def regrid(workers, args):
    """The grid reading of a stored five-key result (``--result NAME``: docs/results/emulated_NAME.json)
    made again by the library from its stored posteriors' means, intervals and sds (no model run):
    for a result written before a change to how the index is read (``three_grid_index`` measuring
    the shifts in the posterior's sds). Rewrites the result's grid fields and its figure."""
    import dataclasses
    import types
    from typing import Any

    from calibration.inference.gridterm import GridTerm, with_grid_term
    from calibration.plots.posteriors import plot_grid_term

    @dataclasses.dataclass(frozen=True)
    class Stored(GridTerm):
        keys: tuple
        mean: dict
        sd: dict
        ci95: dict
        grid: Any = None
        ci95_with_grid: Any = None
        grid_posteriors: tuple = ()
        grid_note: str = ""

    path = RESULTS / f"emulated_{args.result}.json"
    out = json.loads(path.read_text())
    em, keys = out["emulated"], tuple(out["emulated"]["keys"])
    posts = em["grid"]["posteriors"]
    fine = Stored(keys, em["mean"], em["sd"], {k: tuple(v) for k, v in em["ci95"].items()})
    box = types.SimpleNamespace(lower=[out["box"][k][0] for k in keys], upper=[out["box"][k][1] for k in keys])
    objective = types.SimpleNamespace(dx=em["grid"]["dx"], bounds=box)
    coarse = [types.SimpleNamespace(dx=p["dx"], record=p) for p in posts]
    head = ("dx", "mean", "sd", "ci95", "converged", "wall_s")

    def reading(levels):
        return with_grid_term(fine, objective, levels, em["grid"]["ratio"],
                              lambda obj: types.SimpleNamespace(**{k: obj.record[k] for k in head}, record=obj.record),
                              lambda other: {k: v for k, v in other.record.items() if k not in head})

    def inside(found):
        return {k: bool(found.ci95_with_grid[k][0] <= FIVE_TRUTH[k] <= found.ci95_with_grid[k][1]) for k in keys}

    found = reading(coarse)
    wall = em["grid"]["wall_s"]
    em.update(found.grid_json())
    em["grid"]["wall_s"] = wall
    out["truth_inside_ci95_with_grid"] = inside(found)
    if len(coarse) == 2:  # the default reading, one coarser grid (fit's --grid-levels 1), from the same runs
        two = reading(coarse[:1])
        out["two_grid_reading"] = {**two.grid_json(), "truth_inside_ci95_with_grid": inside(two)}
        del out["two_grid_reading"]["grid"]["posteriors"]
        print("two grids:", two.grid_statement, "inside:", inside(two))
        plot_grid_term(two, FIGURES / f"emulated_{args.result}_grid_term_two.png", truth=out["truth"],
                       title=out["case"] + ": the grid term from 1.5 dx")
    out["grid_reading"] = ("made again from the stored posteriors by `python docs/scripts/emulated_posterior.py "
                           f"regrid --result {args.result}` (three_grid_index measuring the shifts in the posterior's "
                           "sds; the runs' wall time kept)")
    path.write_text(json.dumps(out, indent=1))
    plot_grid_term(found, FIGURES / f"emulated_{args.result}_grid_term.png", truth=out["truth"], title=out["case"])
    print(found.grid_statement)
    print("with the grid term:", found.ci95_with_grid, "inside:", out["truth_inside_ci95_with_grid"])
    return None, None


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("which", choices=("s4", "five", "error", "shape", "linear", "regrid"))
    parser.add_argument("--result", default="five_model_error_corrected_i0_measured_grid",
                        help="regrid: the stored result docs/results/emulated_RESULT.json")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--checks", type=int, default=200)
    parser.add_argument("--draws", type=int, default=1000, help="the emulator's NUTS draws per chain (4 chains)")
    parser.add_argument("--target-accept", type=float, default=0.8, help="the emulator's NUTS acceptance target")
    parser.add_argument("--i0-measured", type=float, default=0.0, metavar="REL",
                        help="five: I0 measured by another experiment to this relative sd, a normal prior centred on a "
                             "seeded draw about the truth (default 0: none)")
    parser.add_argument("--i0-seed", type=int, default=0, help="the draw of that measurement")
    parser.add_argument("--tag", default="", help="appended to the result's and figure's names")
    parser.add_argument("--coarsen", type=float, default=1.0, help="five: a grid this many times coarser")
    parser.add_argument("--grid-levels", type=int, default=0, choices=(0, 1, 2),
                        help="five: the posterior's grid term, the same posterior at 1.5 x dx (1) and 2.25 x dx (2) "
                             "(emulated_posterior's grid_ratio; default 0: not measured)")
    parser.add_argument("--emulator", default="quadratic", choices=("quadratic", "corrected"),
                        help="the emulator (calibration.inference.surrogates.EMULATORS)")
    parser.add_argument("--model-error", action="store_true",
                        help="five: the model's own error (particle draws, grid) beside the data's noise")
    args = parser.parse_args()
    with Workers(args.workers) as workers:
        out, post = {"s4": s4, "five": five, "error": error, "shape": shape, "linear": linear,
                     "regrid": regrid}[args.which](
            workers if args.workers > 1 else None, args)
    if args.which == "regrid":
        return
    if post is None:
        name = {"error": "model_error_five", "shape": "model_error_shape_five",
                "linear": "grid_term_linearised_five"}[args.which]
        (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=1))
        return
    name = args.which if args.coarsen == 1.0 else f"{args.which}_coarse{args.coarsen:g}"
    name += "_model_error" if args.model_error else ""
    name += "" if args.emulator == "quadratic" else f"_{args.emulator}"
    name += f"_{args.tag}" if args.tag else ""
    (RESULTS / f"emulated_{name}.json").write_text(json.dumps(out, indent=1))
    from calibration.plots.posteriors import plot_emulated

    reference = None
    if args.which == "s4":
        reference = {label: {k: (out[name]["mean"][k], out[name]["sd"][k]) for k in post.keys}
                     for label, name in (("NUTS on the model", "model_nuts"), ("grid quadrature", "grid_quadrature"))}
    plot_emulated(post, FIGURES / f"emulated_{name}.png", truth=out["truth"], reference=reference,
                  title=out["case"])
    for k in post.keys:
        print(f"{k}: emulated+IS {post.mean[k]:.5g} ± {post.sd[k]:.3g} {post.ci95[k]}; chains R-hat "
              f"{post.emulated.rhat[k]:.4f} ESS {post.emulated.ess_bulk[k]:.0f}")
    if post.grid is not None:
        from calibration.plots.posteriors import plot_grid_term

        plot_grid_term(post, FIGURES / f"emulated_{name}_grid_term.png", truth=out["truth"], title=out["case"])
        print(post.grid_statement)
        print("with the grid term:", post.ci95_with_grid, "inside:", out.get("truth_inside_ci95_with_grid"))
    print(f"pareto k {post.pareto_k:.3f}, IS ESS {post.ess_importance:.0f}, failed {post.failed_checks}, "
          f"jacobians {post.jacobians}, runs {post.runs}, {post.wall_s:.0f} s; rounds {post.rounds}")


if __name__ == "__main__":
    main()
