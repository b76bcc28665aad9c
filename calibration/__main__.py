"""Command line: ``python -m calibration {fit,sweep,twin} ...``.

    python -m calibration fit --scene cohesive-collapse --data deposit.csv --fit beta,mu1 --json
    python -m calibration sweep --scene cohesive-collapse --data deposit.csv --over beta=0.05:0.5:8 \\
        --over mu1=0.3:0.5:8 --plot figs
    python -m calibration twin --quick --noise 0.02 --json
    python -m calibration bench --json

Without --init, ``fit`` is a global search: Levenberg–Marquardt from --starts K (default 8)
space-filling starts in one vmapped batch (``calibration.search``); its JSON lists every distinct
minimum with its loss and whether it lies within the noise of the best, the start the best came
from, and the verdict (``calibration.uncertainty.assess_fit``): a point that is not a verified
minimum, sits at a bound or leaves a misfit well above the noise is "not a fit of the data" and
gets no interval. With --init (or --out, --resume, --method adam, --jacobian fd) one start runs.

``fit``, ``sweep`` and ``twin`` take the scene options of ``python -m jaxmpm run`` (--dx, --ppc,
--t-end, --set key=value, ...). Invalid input exits with status 2 and a message naming the
argument and what was wrong, before anything compiles: options, data (against the scene too),
every swept member, and every output path (--out, --plot). An existing --out is never replaced
without --overwrite; --resume continues only a history made for the same problem. --json output
is valid JSON: a non-finite number is printed as null and its path listed under "nonfinite".
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import sys

from jaxmpm.cli import add_threads_argument, print_json
from jaxmpm.precision import use_dtype
from jaxmpm.scenes.collapse import S4_SIDE
from jaxmpm.threads import apply_threads

from . import cli
from .plots import fit_figures, law_figures, likelihood_figures, sweep_figures, twin_landscape_figure
from .workers import Workers

__all__ = ["main", "build_parser"]


def _fit(args) -> int:
    from .report import fit_report, posterior_checks
    from .search import fit_from_starts

    experiments = cli.experiment_files(args)
    request = cli.fit_request(args, experiments)
    prior = cli.parse_priors(args.prior)
    if prior:
        from .mcmc import gaussian_prior

        try:
            gaussian_prior(request.keys, prior)
        except ValueError as err:
            raise ValueError(f"--{err}") from None
    starts = cli.start_count(args, request.init)
    scene, objective = cli.scene_and_objective(args, request.keys, experiments)
    init = objective.expand(request.init)  # a plain key's start for each experiment's own value
    options, judge = cli.fit_options(args, request.noise)
    coarse = (cli.coarse_objective(args, scene, request.keys, experiments)
              if starts > 1 and args.coarse is not None else None)
    with Workers(cli.worker_count(args)) as workers:
        result, found = fit_from_starts(objective, init, starts=starts, options=options, judge=judge, coarse=coarse,
                                        refine=args.refine, seed=args.search_seed, out=args.out, resume=args.resume,
                                        overwrite=args.overwrite, progress=not args.no_progress,
                                        meta=cli.fit_meta(args, experiments), workers=workers)
        error = cli.posterior_model_error(args, objective, result, workers)
        checks = posterior_checks(objective, result, profiles=args.profiles, posterior=args.posterior, nuts=args.nuts,
                                  chains=args.chains, emulated=args.emulated, emulator=args.emulator, noise=args.noise,
                                  model_error=error if not isinstance(error, str) else None, prior=prior or None,
                                  grid_ratio=args.grid_check or None, grid_levels=args.grid_levels, workers=workers,
                                  progress=not args.json)
        if isinstance(error, str):
            checks.report["model_error_skipped"] = error
    out = {**fit_report(objective, result, found), **cli.fit_fields(args, scene, experiments, init, found)}
    out.update(checks.report)
    errors: dict[str, str] = {}
    if args.plot:
        out["figures"] = cli.guard(errors, "--plot", lambda: fit_figures(args.plot, objective, result))
        if checks.profiles:
            out["figures"] = (out["figures"] or []) + (cli.guard(errors, "--plot", lambda: likelihood_figures(
                args.plot, checks.profiles, posterior=checks.posterior)) or [])
    return cli.finish(out, args, errors)


def _sweep(args) -> int:
    from .sweep import sweep, sweep_points, write_sweep

    keys, thetas = sweep_points(cli.parse_over(args.over, lhs=args.lhs is not None), args.lhs, seed=args.lhs_seed)
    recipe = dict(vars(args))  # the recipe a cluster worker rebuilds the objective from
    scene, objective = cli.scene_and_objective(args, keys, cli.experiment_files(args))
    objective.check_thetas(thetas, "--over")  # every member, before anything compiles
    if args.cluster is not None:
        from .cluster import cluster_sweep, write_cluster_sweep

        clustered = cluster_sweep(functools.partial(cli.objective_from_args, recipe, keys), thetas,
                                  cluster=args.cluster, chunk=args.chunk, retries=args.retries,
                                  progress=not args.no_progress, objective=objective)
        result, out = clustered.sweep, clustered.to_json()
        lost = any(t["lost"] for t in clustered.tasks)
        write = lambda: write_cluster_sweep(args.out, clustered, objective) or True  # noqa: E731
    else:
        result = sweep(objective, thetas, chunk=args.chunk, mode=args.mode, progress=not args.no_progress)
        out, lost = {**result.to_json(), "n_members": result.n}, False
        write = lambda: write_sweep(args.out, result, objective) or True  # noqa: E731
    out.pop("residuals", None)  # per-member residual vectors go to --out, not to the terminal
    out["scene"] = scene.name
    errors: dict[str, str] = {}
    if args.out and cli.guard(errors, "--out", write):
        out["out"] = str(args.out)
    if args.plot:
        out["figures"] = cli.guard(errors, "--plot", lambda: sweep_figures(args.plot, result, keys))
    code = cli.finish(out, args, errors)
    # A task that failed every attempt left members without a result: the sweep did not run
    # in full (its members are in "failed" with the errors), so it does not exit 0.
    return 1 if lost else code


def _twin(args) -> int:
    from .twin import twin, twin_landscape

    use_dtype(args.dtype)
    result = twin(quick=args.quick, noise=args.noise, keys=cli.parse_keys(args.fit), method=args.method,
                  steps=args.steps, seed=args.noise_seed, dx=args.dx, ppc=args.ppc, t_end=args.t_end,
                  values=cli.parse_pairs(args.set, "--set"), dtype=args.dtype or "float32", out=args.out,
                  resume=args.resume, overwrite=args.overwrite, progress=not args.no_progress,
                  reference_noise=args.reference_noise, threshold=args.threshold,
                  roundoff_samples=args.roundoff_samples)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        out["figures"] = cli.guard(errors, "--plot", lambda: fit_figures(args.plot, result.objective, result.fit,
                                                                         prefix="twin", truth=result.truth))
    if args.landscape:
        landscape = twin_landscape(result, args.landscape, progress=not args.no_progress)
        out["landscape"] = landscape.to_json()
        if args.plot:
            out["landscape"]["figure"] = str(twin_landscape_figure(args.plot, landscape))
    return cli.finish(out, args, errors)


def _coverage(args) -> int:
    from .coverage import coverage

    result = coverage(args.seeds, noise=args.noise, keys=cli.parse_keys(args.fit), quick=args.quick,
                      progress=not args.no_progress, dx=args.dx, values=cli.parse_pairs(args.set, "--set"),
                      steps=args.steps)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        from .plots import plot_coverage

        out["figures"] = cli.guard(errors, "--plot", lambda: [str(plot_coverage(
            result, pathlib.Path(args.plot) / "coverage.png"))])
    return cli.finish(out, args, errors)


def _design(args) -> int:
    from jaxmpm.cli import scene_dtype, scene_from_args

    from .design import design

    use_dtype(scene_dtype(args))
    keys, variants = cli.parse_keys(args.fit), cli.parse_variants(args.variant)
    times = cli.parse_floats(args.times, "--times") if args.times else None
    scene = scene_from_args(args)
    with Workers(cli.worker_count(args)) as workers:
        result = design(scene, keys, cli.parse_pairs(args.at, "--at"), noise=cli.design_noise(args),
                        tolerance=args.tolerance, times=times, variants=variants, sampling_seeds=args.sampling_seeds,
                        grid_ratio=args.grid_check or None, workers=workers)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        from .plots import plot_design

        out["figure"] = cli.guard(errors, "--plot", lambda: str(plot_design(result, args.plot)))
    if not args.json:
        print("\n".join(result.lines()))
        return 1 if errors else 0
    return cli.finish(out, args, errors)


def _law(args) -> int:
    from .scaling import fit_runout_law, named_law

    law, label = named_law(args.law, sand=args.sand)
    result = fit_runout_law(cli.parse_floats(args.train, "--train"), cli.parse_floats(args.test, "--test"),
                            cli.parse_keys(args.fit), law=law, label=label, dx=args.dx, ppc=args.ppc,
                            values=cli.parse_pairs(args.set, "--set"), steps=args.steps, out=args.out,
                            overwrite=args.overwrite, progress=not args.no_progress, jacobian=args.jacobian,
                            fd_step=args.fd_step)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        out["figures"] = cli.guard(errors, "--plot", lambda: law_figures(args.plot, result, law))
    return cli.finish(out, args, errors)


def _bench(args) -> int:
    from .bench import bench

    use_dtype(args.dtype)
    kw = {"dx": S4_SIDE / 8, "t_end": 0.2} if args.quick else {"dx": args.dx}
    values = {k: float(v) for k, v in cli.parse_pairs(args.set, "--set").items()}
    result = bench(cli.parse_keys(args.fit), repeat=args.repeat, dtype=args.dtype, values=values, **kw)
    return 1 if print_json(result.to_json(), args.json) else 0


def _common(p, data: bool = True) -> None:
    from jaxmpm.cli import add_scene_arguments
    from jaxmpm.scenes import SCENE_NAMES

    if data:
        p.add_argument("experiments", nargs="*", metavar="EXPERIMENT.toml",
                       help="experiment files (docs/experiments.md): the set-up, its measurements and what to fit; "
                            "several: one material fitted to all of them")
        p.add_argument("--scene", default=None, choices=SCENE_NAMES,
                       help="a named scene the data come from (instead of an experiment file)")
        p.add_argument("--data", action="append", default=[], metavar="FILE.csv",
                       help="a deposit profile (project CSV or WebPlotDigitizer export); repeat for several times")
        p.add_argument("--front", default=None, metavar="FILE.csv", help="a front history (t_s,xf_m)")
        p.add_argument("--front-correlation-time", type=float, default=None, metavar="SECONDS",
                       help="the front's errors are exponentially correlated over this time (FrontTarget."
                            "correlation_time; default: independent). A fit with --front reports the estimate "
                            "from its residuals (front_residual_correlation): refit with it")
        p.add_argument("--units", default=None, choices=("m", "cm", "mm"),
                       help="length units of files that do not state them (WebPlotDigitizer exports)")
        p.add_argument("--time-units", default=None, choices=("s", "ms"), help="time units of a front file")
        p.add_argument("--dataset", default=None, metavar="NAME",
                       help="the dataset to take from multi-dataset WebPlotDigitizer exports (default: the first)")
        p.add_argument("--sort", action="store_true",
                       help="sort points given in WebPlotDigitizer click order by x (or t); duplicates are refused")
        p.add_argument("--clip-noise", action="store_true",
                       help="set heights in [-1e-3 max h, 0) to zero (digitisation noise); lower ones are refused")
        p.add_argument("--weight-profile", type=float, default=None,
                       help="weight of the profile misfit (default: the experiment file's, else 1)")
        p.add_argument("--weight-front", type=float, default=None,
                       help="weight of the front misfit (default: the experiment file's, else 1)")
        p.add_argument("--weighting", choices=("block", "row"), default="block",
                       help="block: each profile and the front history weigh their weight in total, whatever their "
                            "length (the default); row: every point weighs it (the noise-weighted fit, most "
                            "efficient when all points have the same relative noise)")
        p.add_argument("--front-threshold", type=float, default=None,
                       help="height (m) below which the deposit has ended, for the front (default dx/ppc/2)")
    add_scene_arguments(p, scene_choices=False)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _fit_options(p, default_keys: str | None) -> None:
    p.add_argument("--fit", default=default_keys, metavar="KEYS",
                   help="comma-separated parameters to fit, from beta,mu1,mu2,I0,xi (default: the experiment "
                        "file's [fit] keys)")
    p.add_argument("--method", choices=("lm", "adam"), default="lm")
    p.add_argument("--steps", type=int, default=None, help="maximum iterations (default 25 for lm, 150 for adam)")
    p.add_argument("--out", default=None, metavar="FILE.h5", help="history file, written after every iteration")
    p.add_argument("--resume", action="store_true",
                   help="continue the fit stored in --out (it must be a history of the same problem)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out with a new fit")
    p.add_argument("--plot", default=None, metavar="DIR", help="write the figures into DIR")
    p.add_argument("--reference-noise", type=float, default=0.01,
                   help="noise (fraction of the data scale) at which identifiability is judged (default 0.01)")
    p.add_argument("--threshold", type=float, default=0.1,
                   help="a parameter is constrained if its 95%% half-width is below this fraction (default 0.1)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="single-threaded worker processes for the independent runs (the Jacobian's columns, the "
                        "starts, the extra runs of the verdict); default: the number of cores, or $JAXMPM_WORKERS; "
                        "1: everything in this process")
    p.add_argument("--roundoff-samples", type=int, default=8, metavar="N",
                   help="perturbed runs at the end point that measure the run's own round-off scatter, for the "
                        "verdict and the interval (default 8, one forward run each; 0: not measured)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m calibration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    fit = sub.add_parser("fit", help="fit parameters to a measured deposit profile and/or front history")
    _common(fit)
    _fit_options(fit, None)
    fit.add_argument("--init", action="append", default=[], metavar="KEY=VALUE", help="starting value")
    fit.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (in the unconstrained variables)")
    fit.add_argument("--shared", default=None, metavar="KEYS",
                     help="with several experiment files: the fitted keys that are one value for all of them; every "
                          "other fitted key is fitted per file, reported as KEY@FILE (default: all keys shared)")
    fit.add_argument("--jacobian", choices=("ad", "fd"), default="ad",
                     help="LM Jacobian: forward-mode autodiff, or central differences for long violent runs")
    fit.add_argument("--noise", type=float, default=None,
                     help="known noise of the data (fraction of the peak height); default: estimated")
    fit.add_argument("--starts", type=int, default=None, metavar="K",
                     help="global search: Levenberg-Marquardt from K space-filling starts in one batch (default 8 "
                          "without --init, --out, --resume, --method adam or --jacobian fd; else 1)")
    fit.add_argument("--search-seed", type=int, default=0, help="seed of the starts' Sobol design (default 0)")
    fit.add_argument("--coarse", type=float, default=None, metavar="F",
                     help="coarse-to-fine search: the starts run first at F times the grid spacing, then the best "
                          "--refine minima are refined at the requested one (F > 1; needs a search)")
    fit.add_argument("--sampling-seeds", type=int, default=0, metavar="K",
                     help="K other draws of the particles at the end point: the sampling's share of the interval "
                          "(stderr_sampling; one forward run each; default 0: not measured)")
    fit.add_argument("--grid-check", type=float, default=1.5, metavar="RHO",
                     help="the grid's share of the interval: the fit's objective rebuilt at RHO times the grid "
                          "spacing, two particle draws there at the end point (stderr_grid, grid; about two thirds "
                          "of one forward run in 2D; default 1.5; 0: not measured). With --nuts and --emulated also "
                          "the posteriors': the same posterior at RHO x dx (about RHO^-3 of its cost per level in 2D), "
                          "the shift of its mean in ci95_with_grid")
    fit.add_argument("--grid-levels", type=int, default=1, metavar="N",
                     help="coarser grids for the grid term: 1 (RHO x dx; default) or 2 (also RHO^2 x dx, about a "
                          "third of a forward run more in 2D): the order the three grids show, or a wider term "
                          "where they oscillate")
    fit.add_argument("--profiles", type=int, default=0, metavar="N",
                     help="profile likelihood of every fitted key at N values over +-4 standard errors, the others "
                          "refitted at each (calibration.likelihood; default 0: off)")
    fit.add_argument("--posterior", type=int, default=0, metavar="N",
                     help="the posterior of one or two keys (flat prior) by quadrature on an N-point grid per key "
                          "over +-4 standard errors (N^k runs; default 0: off)")
    fit.add_argument("--nuts", type=int, default=0, metavar="N",
                     help="the posterior of every fitted key by NUTS (calibration.mcmc, needs the [bayes] extra): N "
                          "draws per chain after N/2 (at least 20) warm-up steps, with R-hat and ESS (default 0: off)")
    fit.add_argument("--emulated", type=int, default=0, metavar="N",
                     help="the posterior of every fitted key from NUTS on an emulator of the residuals (--emulator), "
                          "corrected by the model's runs at N >= 30 draws (calibration.emulator, needs [bayes]; 3k+1 "
                          "Jacobians and 2k+1 more per re-centring, at most 6, and N runs; also where the verdict "
                          "refuses an interval, with --noise or the estimated noise; default 0: off)")
    fit.add_argument("--emulator", choices=("corrected", "quadratic"), default="corrected",
                     help="--emulated's emulator: a quadratic per residual corrected by a Gaussian process through the "
                          "design points' values and slopes (default), or the quadratic alone "
                          "(calibration.emulator.EMULATORS)")
    fit.add_argument("--model-error", type=int, default=4, metavar="K",
                     help="the model's own error in the likelihood of --profiles, --posterior, --nuts and --emulated: "
                          "K other particle draws and the grid term's coarse runs at the fit's point, added to the "
                          "data's noise by block (calibration.likelihood.model_error; K + 3 forward runs; default 4; "
                          "0: the data's noise alone)")
    fit.add_argument("--prior", action="append", default=[], metavar="KEY=MEAN:SD",
                     help="a key measured by another experiment (an incline's I0): a normal prior in the posteriors "
                          "of --nuts and --emulated, beside the flat one in the bounds; not used by the fit itself "
                          "(repeat for several keys)")
    fit.add_argument("--chains", type=int, default=4, metavar="C",
                     help="NUTS chains, run one after the other (default 4)")
    fit.add_argument("--refine", type=int, default=2, metavar="N",
                     help="coarse minima refined at the requested resolution (default 2; all within the noise of "
                          "the best if more)")

    sweep = sub.add_parser("sweep", help="the loss over a grid or a Latin hypercube of parameters")
    _common(sweep)
    sweep.add_argument("--over", action="append", default=[], metavar="KEY=LO:HI[:N]", help="swept parameter")
    sweep.add_argument("--lhs", type=int, default=None, metavar="N", help="N Latin-hypercube samples instead of a grid")
    sweep.add_argument("--lhs-seed", type=int, default=0, help="seed of the Latin hypercube (--seed seeds "
                       "the particle sampling)")
    sweep.add_argument("--chunk", type=int, default=None, help="members per vmapped chunk (default: by memory)")
    sweep.add_argument("--mode", choices=("auto", "vmap", "shard", "loop"), default="auto")
    sweep.add_argument("--cluster", default=None, metavar="local:N|tcp://HOST:PORT",
                       help="run the chunks as Dask tasks: on N local worker processes, or on the workers of a "
                            "running scheduler (the 'cluster' extra); --chunk is then the members per task")
    sweep.add_argument("--retries", type=int, default=2,
                       help="with --cluster: extra attempts of a task whose worker died or that raised (default 2)")
    sweep.add_argument("--out", default=None, metavar="FILE.h5", help="every member's loss, status and residuals")
    sweep.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    sweep.add_argument("--plot", default=None, metavar="DIR",
                       help="the loss over the swept key, or the landscape over two (a grid, not --lhs)")

    be = sub.add_parser("bench", help="time a forward run, the forward-mode Jacobian and the reverse-mode gradient")
    be.add_argument("--fit", default="beta,mu1,mu2,I0,xi", metavar="KEYS", help="parameters (default all five)")
    be.add_argument("--dx", type=float, default=S4_SIDE / 16, help="grid spacing of the S4 scene, m")
    be.add_argument("--quick", action="store_true", help="dx = L/8 and 0.2 s")
    be.add_argument("--repeat", type=int, default=2)
    be.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene parameter (e.g. --set pc0=500 --set xi=50)")
    be.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    be.add_argument("--json", action="store_true", help="print one line of JSON")

    law = sub.add_parser("law", help="fit the S5 runout-against-aspect-ratio law and predict unused aspect ratios")
    law.add_argument("--fit", default="mu1,mu2", metavar="KEYS", help="parameters to fit (default mu1,mu2)")
    law.add_argument("--train", default="0.5,1,4", help="aspect ratios used in the fit")
    law.add_argument("--test", default="2,8", help="aspect ratios only predicted")
    law.add_argument("--sand", action="store_true", help="the sand law of Lube et al. 2005 instead of glass beads")
    law.add_argument("--law", default=None, metavar="FILE.csv",
                     help="a scaling-law table (a,dL_over_L0), "
                          "e.g. experiments_data/scaling_laws/runout_glass_beads.csv")
    law.add_argument("--dx", type=float, default=None, help="grid spacing, m (default L0/10)")
    law.add_argument("--ppc", type=float, default=None, help="particles per cell and axis (default: the scenes')")
    law.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    law.add_argument("--steps", type=int, default=15)
    law.add_argument("--jacobian", choices=("ad", "fd"), default="fd")
    law.add_argument("--fd-step", type=float, default=0.05, help="relative step of the central differences")
    law.add_argument("--out", default=None, metavar="FILE.h5")
    law.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    law.add_argument("--plot", default=None, metavar="DIR")
    law.add_argument("--no-progress", action="store_true")
    law.add_argument("--json", action="store_true")

    cov = sub.add_parser("coverage", help="twins over many noise seeds: how often the 95 %% intervals hold the truth")
    cov.add_argument("--fit", default="beta,mu1", metavar="KEYS", help="parameters to fit (default beta,mu1)")
    cov.add_argument("--seeds", type=int, default=20, help="noise seeds 0..N-1 (default 20)")
    cov.add_argument("--noise", type=float, default=0.02, help="Gaussian noise, fraction of the peak height")
    cov.add_argument("--quick", action="store_true", help="the twin's coarse grid (dx = L/8), about 25 s a seed")
    cov.add_argument("--dx", type=float, default=None, help="grid spacing, m (default: the twin's)")
    cov.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a true scene parameter")
    cov.add_argument("--steps", type=int, default=None, help="LM iterations per fit (default 25)")
    cov.add_argument("--plot", default=None, metavar="DIR", help="every seed's interval against the truth")
    cov.add_argument("--no-progress", action="store_true")
    cov.add_argument("--json", action="store_true")

    de = sub.add_parser("design", help="which measurements constrain which keys: expected 95 %% half-widths of "
                                       "candidate observation sets before the experiment")
    from jaxmpm.scenes import SCENE_NAMES

    de.add_argument("--scene", required=True, type=cli.design_scene, metavar="SCENE|EXPERIMENT.toml",
                    help="the experiment's set-up: a collapse scene "
                         f"({', '.join(n for n in SCENE_NAMES if n != 'elastic-block')}) or an experiment file")
    _common(de, data=False)
    de.add_argument("--fit", required=True, metavar="KEYS", help="comma-separated keys to calibrate")
    de.add_argument("--at", action="append", default=[], metavar="KEY=VALUE",
                    help="the parameter point (default: the scene's values)")
    de.add_argument("--noise", type=float, default=0.02,
                    help="expected noise, a fraction of the profile's peak (and of the column's length for the "
                         "front, of the top's height for the top) (default 0.02)")
    de.add_argument("--noise-front", type=float, default=None, help="the front's noise, if not --noise")
    de.add_argument("--noise-top", type=float, default=None, help="the top height's noise, if not --noise")
    de.add_argument("--tolerance", type=float, default=0.1,
                    help="the 95 %% half-width every key should reach, a fraction of its value (default 0.1)")
    de.add_argument("--times", default=None, metavar="T1,T2,...",
                    help="profile times during the flow, s (default t_end x 0.1, 0.2, 0.4)")
    de.add_argument("--variant", action="append", default=[], metavar="LABEL:KEY=VALUE[,...]",
                    help="another experiment on the same material: the scene built with these builder arguments "
                         "changed (height, length, slope_deg, front_gate_speed, runout, t_end, ...); repeatable")
    de.add_argument("--sampling-seeds", type=int, default=0, metavar="K",
                    help="K other particle draws per experiment: the sampling's share (default 0: not measured)")
    de.add_argument("--grid-check", type=float, default=1.5, metavar="RHO",
                    help="the grid's share, from each experiment rebuilt at RHO x dx (default 1.5; 0: not measured)")
    de.add_argument("--workers", type=int, default=None, metavar="N",
                    help="single-threaded worker processes for the extra runs (default: the number of cores)")
    de.add_argument("--plot", default=None, metavar="FIG.png", help="the expected 95 %% regions of the first two keys")

    tw = sub.add_parser("twin", help="fit synthetic S4 data made with known parameters")
    _common(tw, data=False)
    _fit_options(tw, "beta,mu1,xi")
    tw.add_argument("--quick", action="store_true", help="a coarse grid (dx = L/8): about three minutes")
    tw.add_argument("--noise", type=float, default=0.0, help="Gaussian noise, fraction of the peak height")
    tw.add_argument("--noise-seed", type=int, default=0, help="seed of the noise")
    tw.add_argument("--landscape", type=int, default=None, metavar="N",
                    help="also sweep the loss on an N × N grid over the first two keys (figure with --plot)")
    for command in sub.choices.values():
        add_threads_argument(command)
    return parser


COMMANDS = {"fit": _fit, "sweep": _sweep, "twin": _twin, "bench": _bench, "law": _law, "coverage": _coverage,
            "design": _design}


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        apply_threads(args.threads)
        cli.check_args(args)
        return COMMANDS[args.command](args)
    except ValueError as err:
        parser.exit(2, f"python -m calibration {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
