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
import copy
import dataclasses
import json
import math
import os
import pathlib
import sys

from jaxmpm.cli import add_threads_argument
from jaxmpm.precision import use_dtype
from jaxmpm.scenes.collapse import S4_SIDE
from jaxmpm.threads import apply_threads

from .workers import Workers, available_cores

__all__ = ["main", "build_parser"]


def _keys(text: str, option: str = "--fit") -> tuple[str, ...]:
    keys = tuple(k.strip() for k in text.split(",") if k.strip())
    if not keys:
        raise ValueError(f"{option}: expected comma-separated parameter names, got {text!r}")
    return keys


def _pairs(items, option: str) -> dict[str, float]:
    from jaxmpm.cli import parse_set

    out = {}
    for item in items:
        try:
            key, value = parse_set(item)
        except ValueError as err:
            raise ValueError(str(err).replace("--set", option)) from None
        if key in out:
            raise ValueError(f"{option} {key} is given twice; give each key once")
        out[key] = value
    return out


def _load_data(args, experiment=None):
    """The profiles and the front history: --data and --front, else the experiment file's
    [[profile]] and [front] (read with the units they state)."""
    from jaxmpm import describe_status

    from .data import load_front_history, load_measurements, load_profile

    if experiment is not None and not args.data and not args.front:
        profiles, front = load_measurements(experiment, sort=args.sort, clip_noise=args.clip_noise)
        if not profiles and front is None:
            raise ValueError(f"{experiment.path}: lists no measurement ([[profile]] or [front]); give --data or "
                             "--front")
    else:
        profiles = [load_profile(p, units=args.units, dataset=args.dataset, sort=args.sort,
                                 clip_noise=args.clip_noise) for p in args.data]
        front = (load_front_history(args.front, units=args.units, time_units=args.time_units, dataset=args.dataset,
                                    sort=args.sort) if args.front else None)
    if not profiles and front is None:
        raise ValueError("--data (a profile CSV) and/or --front (a front-history CSV) is required")
    for data in [*profiles, front]:
        status = data.meta.get("status") if data is not None else None
        if status not in (None, 0):  # what `python -m jaxmpm run --profile-csv` records of its run
            raise ValueError(f"{data.path}: written by a run that failed (status {status}: "
                             f"{'; '.join(describe_status(int(status)))}); it is not a result of its scene")
    return profiles, front


def _experiments(args) -> list:
    """The experiment files of ``fit``/``sweep`` (positional), with the command line's scene
    options over their values; [] for a named --scene."""
    from jaxmpm.cli import experiment_from_args

    files = list(getattr(args, "experiments", None) or [])
    if files and args.scene:
        raise ValueError(f"give --scene or experiment files, not both (--scene {args.scene}, {files[0]})")
    if not files and not args.scene:
        raise ValueError("the scene is missing: give an experiment file (EXPERIMENT.toml, docs/experiments.md) or "
                         "--scene NAME")
    for file in files:
        if not file.endswith(".toml"):
            raise ValueError(f"{file}: an experiment file ends in .toml")
    if len(files) > 1 and (args.data or args.front):
        raise ValueError("--data and --front apply to one experiment; with several files, each lists its own "
                         "measurements ([[profile]], [front])")
    return [experiment_from_args(args, path=file) for file in files]


def _fit_request(args, experiments):
    """The command line's keys, starting values and noise over the experiment files' [fit] tables."""
    from .options import OptionError, fit_request

    keys = _keys(args.fit) if getattr(args, "fit", None) else None
    try:
        return fit_request(experiments, keys, _pairs(getattr(args, "init", []), "--init"), getattr(args, "noise", None))
    except OptionError as err:
        raise err.as_flag() from None


def _scene_and_objective(args, keys, experiments=()):
    """(scene, objective): the named --scene with --data/--front, or each experiment file with its
    measurements (several: one joint objective, ``CompositeObjective``, fitting the same keys, or
    with ``--shared`` those shared and the others per file, labelled by the file's name; the
    scene returned is the first's)."""

    from jaxmpm.cli import scene_dtype, scene_from_args
    from jaxmpm.scenes import experiments_dtype

    from .data import data_end_time
    from .objective import CompositeObjective, FrontTarget, Objective

    dtype = experiments_dtype(experiments, args.dtype) if experiments else scene_dtype(args)
    use_dtype(dtype)
    members, scenes = [], []
    for experiment in experiments or [None]:
        profiles, front = _load_data(args, experiment)
        options = dict(front_threshold=args.front_threshold, jacobian=getattr(args, "jacobian", "ad"),
                       weighting=args.weighting)
        if experiment is not None:
            member = Objective.from_experiment(
                experiment, keys, profile=profiles or None, front=front,
                weights={"profile": args.weight_profile, "front": args.weight_front},
                front_correlation_time=getattr(args, "front_correlation_time", None), **options)
            members.append(member)
            scenes.append(member.scene)
            continue
        if front is not None and getattr(args, "front_correlation_time", None) is not None:
            front = dataclasses.replace(FrontTarget.of(front), correlation_time=args.front_correlation_time)
        t_end = args.t_end if args.t_end is not None else data_end_time(profiles, front)
        scene = scene_from_args(argparse.Namespace(**{**vars(args), "t_end": t_end}))
        weights = {"profile": 1.0 if args.weight_profile is None else args.weight_profile,
                   "front": 1.0 if args.weight_front is None else args.weight_front}
        members.append(Objective(scene, keys, profile=profiles or None, front=front, weights=weights, **options))
        scenes.append(scene)
    if len(members) == 1:
        return scenes[0], members[0]
    shared = getattr(args, "shared", None)
    if shared is None:
        return scenes[0], CompositeObjective(members)
    labels = [pathlib.Path(e.path).stem if e.path is not None else e.name for e in experiments]
    return scenes[0], CompositeObjective.sharing(members, _keys(shared, "--shared"), labels)


def _objective_from_args(values: dict, keys):
    """The objective that ``python -m calibration`` builds from these parsed options: the
    recipe a cluster worker runs (picklable as a ``functools.partial``)."""
    args = argparse.Namespace(**values)
    return _scene_and_objective(args, keys, _experiments(args))[1]


def _fit_options_of(args, noise=None):
    """The fit's ``FitOptions`` and ``JudgeOptions`` from the flags (``--grid-check 0``: off),
    an error reported under the flag's name (``calibration.options.FLAGS``)."""
    from .options import FitOptions, JudgeOptions, OptionError, cli_steps

    try:
        options = (FitOptions(method=args.method, steps=cli_steps(args.method, args.steps), learning_rate=args.lr)
                   if getattr(args, "command", None) == "fit" else None)
        judge = JudgeOptions(noise=noise, roundoff_samples=getattr(args, "roundoff_samples", 0),
                             sampling_seeds=getattr(args, "sampling_seeds", 0),
                             reference_noise=getattr(args, "reference_noise", 0.01),
                             threshold=getattr(args, "threshold", 0.1),
                             grid_ratio=getattr(args, "grid_check", 0) or None,
                             grid_levels=getattr(args, "grid_levels", 1))
    except OptionError as err:
        raise err.as_flag() from None
    return options, judge


def _emit(obj, compact: bool) -> list[str]:
    """Print ``obj`` as valid JSON (NaN and infinities as null, their paths under "nonfinite");
    return those paths."""
    from jaxmpm.cli import json_safe

    obj, bad = json_safe(obj)
    if bad:
        obj["nonfinite"] = bad
    print(json.dumps(obj, allow_nan=False, default=str, indent=None if compact else 2))
    return bad


def _guard(errors: dict, option: str, write):
    """Run one output step after the work; on failure keep the message (the JSON still prints)."""
    try:
        return write()
    except (OSError, ValueError, RuntimeError, ImportError) as err:
        errors[option] = f"{type(err).__name__}: {err}"
        return None


def _single_start_reason(args, init=None) -> str | None:
    """Why ``fit`` runs one start (None: a global search is possible)."""
    if args.init:
        return "--init"
    if init:
        return "the experiment file's [fit] init"
    for option, given in (("--out", args.out), ("--resume", args.resume), ("--method adam", args.method == "adam"),
                          ("--jacobian fd", args.jacobian == "fd")):
        if given:
            return option
    return None


def _starts(args, init=None) -> int:
    """The number of starts: --starts, or the search's default when nothing asks for one start.
    More than one start with an option that needs a single one is refused, naming both."""
    single = _single_start_reason(args, init)
    if args.starts is None:
        from .search import DEFAULT_STARTS

        return 1 if single else DEFAULT_STARTS
    if args.starts > 1 and single not in (None, "--init", "the experiment file's [fit] init"):
        what = {"--out": "keeps the resumable history of one start", "--resume": "continues one start's history",
                "--method adam": "is a single-start optimiser (the search is Levenberg–Marquardt)",
                "--jacobian fd": "is not batched (the search uses forward-mode Jacobians)"}[single]
        raise ValueError(f"--starts {args.starts}: {single} {what}; drop one of them")
    return args.starts


def _workers(args) -> int:
    """--workers, else $JAXMPM_WORKERS, else every core this process may use."""
    if args.workers is not None:
        if args.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {args.workers}")
        return args.workers
    env = os.environ.get("JAXMPM_WORKERS")
    if env:
        if not env.isdigit() or int(env) < 1:
            raise ValueError(f"$JAXMPM_WORKERS must be an integer >= 1, got {env!r}")
        return int(env)
    return available_cores()


def _fit(args) -> int:
    from .fit import fit
    from .report import fit_report

    experiments = _experiments(args)
    request = _fit_request(args, experiments)
    keys, init, noise = request.keys, request.init, request.noise
    starts = _starts(args, init)
    scene, objective = _scene_and_objective(args, keys, experiments)
    if getattr(objective, "shared", None) is not None:
        init = objective.expand(init)  # a plain key's start for each experiment's own value
    options, judge = _fit_options_of(args, noise)
    found = None
    with Workers(_workers(args)) as workers:
        if starts > 1:
            from .search import search

            if args.coarse is not None:
                from .search import coarse_to_fine

                coarse_args = copy.copy(args)
                coarse_args.dx = scene.config.grid.dx * args.coarse
                if len(experiments) > 1:
                    raise ValueError("--coarse takes one experiment (its dx); fit several without it")
                _, coarse = _scene_and_objective(coarse_args, keys, _experiments(coarse_args))
                found = coarse_to_fine(objective, coarse, starts, refine=args.refine, seed=args.search_seed,
                                       init=init or None, steps=options.steps, progress=not args.no_progress,
                                       workers=workers, **judge.kwargs())
            else:
                found = search(objective, starts, seed=args.search_seed, init=init or None, steps=options.steps,
                               progress=not args.no_progress, workers=workers, **judge.kwargs())
            result = found.best
        else:
            result = fit(objective, init, options=options, judge=judge, out=args.out, resume=args.resume,
                         overwrite=args.overwrite, progress=not args.no_progress,
                         meta={"command": "python -m calibration " + " ".join(sys.argv[1:]),
                               "data": args.data, "front": args.front,
                               "experiments": [e.to_toml() for e in experiments]},
                         workers=workers)
    out = fit_report(objective, result, found)
    if found is None:
        reason = _single_start_reason(args, init)
        out["search"] = {"starts": 1, "why": f"a single start ({reason or '--starts 1'})"}
    out["scene"] = scene.name
    if experiments:
        out["experiments"] = [str(e.path) for e in experiments]
    if args.out:
        out["out"] = str(args.out)
    errors: dict[str, str] = {}
    profiles, posterior = _beyond_gauss_newton(args, objective, result, out)
    if args.plot:
        out["figures"] = _guard(errors, "--plot", lambda: _plots(args.plot, objective, result, prefix="fit"))
        if profiles:
            from .plots import plot_profile_likelihoods

            path = pathlib.Path(args.plot) / "fit_likelihood.png"
            out["figures"] = (out["figures"] or []) + (_guard(errors, "--plot", lambda: [str(
                plot_profile_likelihoods(profiles, path, posterior=posterior))]) or [])
    return _finish(out, args, errors)


def _beyond_gauss_newton(args, objective, result, out):
    """--profiles N and --posterior N on the fit's point: the JSON blocks "profile_likelihood"
    and "posterior"; skipped, with the reason, where the point has no interval to scan around."""
    if not (args.profiles or args.posterior or args.nuts):
        return [], None
    if result.uncertainty is None or result.uncertainty.withheld:
        out["profile_likelihood_skipped"] = "the point is not a fit of the data: no interval to scan around"
        return [], None
    if args.nuts:
        from .mcmc import nuts_posterior

        nuts = nuts_posterior(objective, result, chains=args.chains, warmup=max(20, args.nuts // 2),
                              draws=args.nuts, noise=args.noise, progress=not args.json)
        out["nuts"] = {k: v for k, v in nuts.to_json().items() if k != "draws"}
    from .likelihood import grid_posterior, profile_likelihood

    profiles = [profile_likelihood(objective, result, k, n=args.profiles, noise=args.noise) for k in result.keys
                ] if args.profiles else []
    if profiles:
        out["profile_likelihood"] = {p.key: p.to_json() for p in profiles}
    posterior = None
    if args.posterior:
        if len(result.keys) > 2:
            out["posterior_skipped"] = f"{len(result.keys)} keys: the grid posterior is for one or two"
        else:
            posterior = grid_posterior(objective, result, n=args.posterior, noise=args.noise)
            out["posterior"] = posterior.to_json()
    return profiles, posterior


def _finish(out, args, errors) -> int:
    if errors:
        out["output_errors"] = errors
    bad = _emit(out, args.json)
    return 1 if (bad or errors) else 0


def _plots(directory, objective, result, prefix: str, truth=None, initial=None):
    from .plots import plot_fit, plot_history

    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    figs = [plot_fit(objective, result, d / f"{prefix}_profiles.png", initial_prediction=initial),
            plot_history(result.history, result.keys, d / f"{prefix}_history.png", truth=truth)]
    return [str(f) for f in figs]


def _parse_over(items, lhs: bool = False) -> dict[str, tuple[float, float, int]]:
    out = {}
    for item in items:
        key, sep, rng = item.partition("=")
        key = key.strip()
        parts = rng.split(":")
        if not sep or len(parts) not in (2, 3):
            raise ValueError(f"--over expects key=lo:hi[:n], got {item!r}")
        try:
            lo, hi = float(parts[0]), float(parts[1])
            n = int(parts[2]) if len(parts) == 3 else 5
        except ValueError:
            raise ValueError(f"--over {key}: lo, hi must be numbers and n an integer, got {rng!r}") from None
        if key in out:
            raise ValueError(f"--over {key} is given twice ({key}={':'.join(map(str, out[key]))} and {item!r}); "
                             "give each swept key once")
        if lhs and len(parts) == 3:
            raise ValueError(f"--over {item!r}: a count n does not apply with --lhs (which draws --lhs N points)")
        out[key] = (lo, hi, n)
    if not out:
        raise ValueError("--over key=lo:hi[:n] is required (once per swept parameter)")
    return out


def _sweep(args) -> int:
    from .sweep import grid_points, latin_hypercube, sweep, write_sweep

    over = _parse_over(args.over, lhs=args.lhs is not None)
    keys = tuple(over)
    if args.plot and args.lhs:
        raise ValueError("--plot draws the loss over a grid; a Latin hypercube (--lhs) is none: drop one of them")
    if args.plot and len(keys) > 2:
        raise ValueError(f"--plot draws the loss over one or two swept keys, got {len(keys)} ({', '.join(keys)})")
    ranges = {k: (lo, hi) for k, (lo, hi, _) in over.items()}
    if args.lhs:
        keys, thetas = latin_hypercube(ranges, args.lhs, seed=args.lhs_seed)
    else:
        keys, thetas = grid_points(ranges, {k: n for k, (_, _, n) in over.items()})
    if args.cluster is not None:
        from .cluster import parse_cluster

        parse_cluster(args.cluster)  # a clear error before any worker starts
        if args.mode != "auto":
            raise ValueError(f"--mode {args.mode}: with --cluster every task is one vmapped chunk; drop --mode")
        if args.retries < 0:
            raise ValueError(f"--retries must be >= 0, got {args.retries}")
    recipe = dict(vars(args))  # the recipe a cluster worker rebuilds the objective from
    scene, objective = _scene_and_objective(args, keys, _experiments(args))
    objective.check_thetas(thetas, "--over")  # every member, before anything compiles
    if args.cluster is not None:
        import functools

        from .cluster import cluster_sweep, write_cluster_sweep

        clustered = cluster_sweep(functools.partial(_objective_from_args, recipe, keys), thetas,
                                  cluster=args.cluster, chunk=args.chunk, retries=args.retries,
                                  progress=not args.no_progress, objective=objective)
        result = clustered.sweep
        out = clustered.to_json()
        lost = [t["index"] for t in clustered.tasks if t["lost"]]
        write = lambda: write_cluster_sweep(args.out, clustered, objective) or True  # noqa: E731
    else:
        result = sweep(objective, thetas, chunk=args.chunk, mode=args.mode, progress=not args.no_progress)
        out = result.to_json()
        out["n_members"] = result.n
        write = lambda: write_sweep(args.out, result, objective) or True  # noqa: E731
        lost = []
    out.pop("residuals", None)  # per-member residual vectors go to --out, not to the terminal
    out["scene"] = scene.name
    errors: dict[str, str] = {}
    if args.out and _guard(errors, "--out", write):
        out["out"] = str(args.out)
    if args.plot:
        out["figures"] = _guard(errors, "--plot", lambda: _sweep_plot(args.plot, result, keys))
    code = _finish(out, args, errors)
    # A task that failed every attempt left members without a result: the sweep did not run
    # in full (its members are in "failed" with the errors), so it does not exit 0.
    return 1 if lost else code


def _sweep_plot(directory, result, keys) -> list[str]:
    import numpy as np

    from .plots import plot_landscape, plot_loss_curve

    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    best = result.best() if result.ok.any() else None
    if len(keys) == 1:
        return [str(plot_loss_curve(result.thetas[:, 0], result.loss, keys[0], d / "loss.png",
                                    best=best[keys[0]] if best else None))]
    xs, ys, loss = result.landscape(keys[0], keys[1])
    failed = list(result.failed)
    fx = np.asarray(result.thetas)[failed, 0] if failed else np.zeros(0)
    fy = np.asarray(result.thetas)[failed, 1] if failed else np.zeros(0)
    marks = {"lowest": (best[keys[0]], best[keys[1]])} if best else None
    return [str(plot_landscape(xs, ys, loss, keys[0], keys[1], d / "landscape.png", marks=marks, failed=(fx, fy)))]


def _twin(args) -> int:
    from .twin import twin, twin_landscape

    use_dtype(args.dtype)
    if args.slope is not None or args.aspect is not None or args.dim not in (None, 2) or args.width is not None:
        raise ValueError("twin is the 2D S4 cohesive collapse: --slope, --aspect, --dim and --width do not apply")
    if args.sampling is not None or args.seed not in (None, 0):
        raise ValueError("twin uses the S4 scene's default particle sampling: --sampling and --seed do not apply "
                         "(--noise-seed seeds the noise)")
    keys = _keys(args.fit)
    if args.landscape and len(keys) < 2:
        raise ValueError("--landscape needs at least two fitted keys")
    result = twin(quick=args.quick, noise=args.noise, keys=keys, method=args.method, steps=args.steps,
                  seed=args.noise_seed, dx=args.dx, ppc=args.ppc, t_end=args.t_end, values=_pairs(args.set, "--set"),
                  dtype=args.dtype or "float32", out=args.out, resume=args.resume, overwrite=args.overwrite,
                  progress=not args.no_progress, reference_noise=args.reference_noise, threshold=args.threshold,
                  roundoff_samples=args.roundoff_samples)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        out["figures"] = _guard(errors, "--plot", lambda: _plots(args.plot, result.objective, result.fit,
                                                                 prefix="twin", truth=result.truth))
    if args.landscape:
        landscape = twin_landscape(result, args.landscape, progress=not args.no_progress)
        out["landscape"] = landscape.to_json()
        if args.plot:
            out["landscape"]["figure"] = str(_twin_landscape_plot(args.plot, landscape))
    return _finish(out, args, errors)


def _twin_landscape_plot(directory, landscape):
    from .plots import plot_landscape

    kx, ky = landscape.keys
    xs, ys, loss = landscape.grid()
    return plot_landscape(xs, ys, loss, kx, ky, pathlib.Path(directory) / "twin_landscape.png",
                          marks=landscape.marks, title=f"twin loss over ({kx}, {ky}), others at truth")


def _coverage(args) -> int:
    from .coverage import coverage

    if not 0 < args.noise < 1:
        raise ValueError(f"--noise must be in (0, 1): coverage needs noisy data, got {args.noise}")
    if args.seeds < 2:
        raise ValueError(f"--seeds must be >= 2, got {args.seeds}")
    result = coverage(args.seeds, noise=args.noise, keys=_keys(args.fit), quick=args.quick,
                      progress=not args.no_progress, dx=args.dx, values=_pairs(args.set, "--set"), steps=args.steps)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        from .plots import plot_coverage

        out["figures"] = _guard(errors, "--plot", lambda: [str(plot_coverage(
            result, pathlib.Path(args.plot) / "coverage.png"))])
    return _finish(out, args, errors)


def _variants(items) -> dict[str, dict[str, float]]:
    """``--variant LABEL:key=value[,key=value...]`` -> {label: {key: value}}."""
    out: dict[str, dict[str, float]] = {}
    for item in items:
        label, sep, rest = item.partition(":")
        if not sep or not label.strip() or not rest.strip():
            raise ValueError(f"--variant expects LABEL:key=value[,key=value...], got {item!r}")
        if label in out:
            raise ValueError(f"--variant: the label {label!r} is given twice")
        out[label.strip()] = _pairs([p for p in rest.split(",") if p], f"--variant {label}")
    return out


def _design(args) -> int:
    from jaxmpm.cli import scene_dtype, scene_from_args

    from .design import design

    use_dtype(scene_dtype(args))
    keys = _keys(args.fit)
    if args.plot and len(keys) < 2:
        raise ValueError("--plot draws the first two keys' regions: give at least two keys in --fit")
    variants = _variants(args.variant)
    noise = {"profile": args.noise, "front": args.noise_front if args.noise_front is not None else args.noise,
             "top": args.noise_top if args.noise_top is not None else args.noise}
    times = _floats(args.times, "--times") if args.times else None
    scene = scene_from_args(args)
    with Workers(_workers(args)) as workers:
        result = design(scene, keys, _pairs(args.at, "--at"), noise=noise, tolerance=args.tolerance, times=times,
                        variants=variants, sampling_seeds=args.sampling_seeds, grid_ratio=args.grid_check or None,
                        workers=workers)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        from .plots import plot_design

        out["figure"] = _guard(errors, "--plot", lambda: str(plot_design(result, args.plot)))
    if not args.json:
        for c in result.candidates:
            widths = ", ".join(f"{k} ±{100 * r:.3g} % (data alone ±{100 * d / max(abs(t), 1e-12):.3g} %, "
                               f"noise-weighted ±{100 * b / max(abs(t), 1e-12):.3g} %)"
                               for k, r, d, b, t in zip(result.keys, c.relative, c.halfwidth_data,
                                                        c.halfwidth_weighted, result.theta))
            print(f"{'*' if c is result.recommended else ' '} cost {c.cost:g}  {c.name}: {widths}")
        print(result.statement)
        for note in result.notes:
            print(f"note: {note}")
    return _finish(out, args, errors) if args.json else (1 if errors else 0)


def _design_scene(text: str) -> str:
    from jaxmpm.scenes import SCENE_NAMES, is_experiment_file

    collapses = [n for n in SCENE_NAMES if n != "elastic-block"]
    if is_experiment_file(text) or text in collapses:
        return text
    raise argparse.ArgumentTypeError(f"must be a collapse scene ({', '.join(collapses)}) or an experiment file "
                                     f"(.toml), got {text!r}")


def _floats(text: str, option: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{option} expects comma-separated numbers, got {text!r}") from None


def _law(args) -> int:
    import functools

    from jaxmpm.scenes import runout_law

    from .scaling import fit_runout_law

    if args.law:
        from .data import load_scaling_law
        from .scaling import law_from_table

        table = load_scaling_law(args.law)
        law = law_from_table(table)
        label = f"{table.experiment} ({'secondary' if table.secondary else 'primary'}: {table.source})"
    else:
        law = functools.partial(runout_law, sand=True) if args.sand else runout_law
        label = ("sand (Lube et al. 2005" if args.sand else "glass beads (Lajeunesse et al. 2005") + ", secondary)"
    result = fit_runout_law(_floats(args.train, "--train"), _floats(args.test, "--test"), _keys(args.fit), law=law,
                            label=label, dx=args.dx, ppc=args.ppc, values=_pairs(args.set, "--set"), steps=args.steps,
                            out=args.out, overwrite=args.overwrite, progress=not args.no_progress,
                            jacobian=args.jacobian, fd_step=args.fd_step)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        from .plots import plot_history, plot_runout_law

        def figures():
            d = pathlib.Path(args.plot)
            d.mkdir(parents=True, exist_ok=True)
            return [str(plot_runout_law(out["cases"], d / "law_runout.png", law=law, title=result.law)),
                    str(plot_history(result.fit.history, result.fit.keys, d / "law_history.png"))]

        out["figures"] = _guard(errors, "--plot", figures)
    return _finish(out, args, errors)


def _bench(args) -> int:
    from .bench import bench

    use_dtype(args.dtype)
    kw = {"dx": S4_SIDE / 8, "t_end": 0.2} if args.quick else {"dx": args.dx}
    values = {k: float(v) for k, v in _pairs(args.set, "--set").items()}
    result = bench(_keys(args.fit), repeat=args.repeat, dtype=args.dtype, values=values, **kw)
    return 1 if _emit(result.to_json(), args.json) else 0


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
                          "of one forward run in 2D; default 1.5; 0: not measured)")
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

    de.add_argument("--scene", required=True, type=_design_scene, metavar="SCENE|EXPERIMENT.toml",
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


def _check_options(args) -> None:
    """Checks the library would make later, or with its own argument names."""
    from jaxmpm.cli import check_scene_args

    if hasattr(args, "sampling"):  # the scene options of add_scene_arguments
        check_scene_args(args)
    if getattr(args, "front_correlation_time", None) is not None and not args.front:
        raise ValueError("--front-correlation-time needs --front (the front history whose errors it describes)")
    for name in ("fd_step", "front_threshold", "front_correlation_time"):
        value = getattr(args, name, None)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite number > 0, got {value}")
    if hasattr(args, "weight_profile"):
        for option, weight, given, what in (("--weight-profile", args.weight_profile, bool(args.data), "--data"),
                                            ("--weight-front", args.weight_front, bool(args.front), "--front")):
            if weight is None:
                continue
            if not (math.isfinite(weight) and weight >= 0):
                raise ValueError(f"{option} must be a finite number >= 0, got {weight}")
            if given and weight == 0:
                raise ValueError(f"{option} 0 gives the {what} data no weight: their residuals would all be zero and "
                                 f"their uncertainty undefined; leave out {what} instead")
    _fit_options_of(args)  # the fit's and the verdict's options, checked by the library's option objects
    for option in ("init", "set"):
        if hasattr(args, option):
            _pairs(getattr(args, option), f"--{option}")  # malformed or repeated keys
    if getattr(args, "command", None) == "fit":
        if args.shared is not None:
            shared = _keys(args.shared, "--shared")
            if len(args.experiments) < 2:
                raise ValueError("--shared needs two experiment files or more (the keys they share)")
            if args.fit and sorted(set(shared) - set(_keys(args.fit))):
                raise ValueError(f"--shared {','.join(sorted(set(shared) - set(_keys(args.fit))))}: not among the "
                                 f"fitted keys (--fit {args.fit})")
        starts = _starts(args)  # --starts against the options that need a single start
        if args.coarse is not None:
            if not (math.isfinite(args.coarse) and args.coarse > 1):
                raise ValueError(f"--coarse must be a finite factor > 1 of the grid spacing, got {args.coarse}")
            if starts < 2:
                raise ValueError("--coarse is a stage of the global search: it needs two starts or more (the "
                                 "default without --init; with --init give --starts K)")
        if args.refine < 1:
            raise ValueError(f"--refine must be an integer >= 1, got {args.refine}")


def _check_outputs(args) -> None:
    """Every output path is checked before the data are read or anything compiles: a file for
    --out (which must exist for --resume, and must not, unless --overwrite, otherwise), a folder
    for --plot. Nothing is created here."""
    import importlib.util

    from jaxmpm.cli import check_output_dir, check_output_file

    out = getattr(args, "out", None)
    resume, overwrite = getattr(args, "resume", False), getattr(args, "overwrite", False)
    if out:
        check_output_file(out, "--out")
        path = pathlib.Path(out)
        if resume and overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        if resume:
            from .fit import read_history

            if not path.exists():
                raise ValueError(f"--resume: --out {out!r} does not exist, so there is nothing to resume (check the "
                                 "name; without --resume a new fit starts)")
            try:
                read_history(path)
            except ValueError as err:
                raise ValueError(f"--resume: {err}") from None
        elif path.exists() and not overwrite:
            hint = "--resume to continue the fit it holds, or " if hasattr(args, "resume") else ""
            raise ValueError(f"--out {out!r} exists: pass {hint}--overwrite to replace it")
    elif overwrite:
        raise ValueError("--overwrite needs --out")
    plot = getattr(args, "plot", None)
    if plot:
        if importlib.util.find_spec("matplotlib") is None:
            raise ValueError("--plot needs matplotlib: pip install 'jaxmpm[plot]'")
        check_output_dir(plot, "--plot")


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        apply_threads(args.threads)
        for name in ("steps", "chunk", "lhs", "starts"):
            value = getattr(args, name, None)
            if value is not None and value < 1:
                raise ValueError(f"--{name} must be >= 1, got {value}")
        for name in ("profiles", "posterior"):
            value = getattr(args, name, 0)
            if value and value < 3:
                raise ValueError(f"--{name} must be 0 (off) or >= 3, got {value}")
        if getattr(args, "nuts", 0) and args.nuts < 4:
            raise ValueError(f"--nuts must be 0 (off) or >= 4 draws per chain, got {args.nuts}")
        if getattr(args, "chains", 1) < 1:
            raise ValueError(f"--chains must be >= 1, got {args.chains}")
        if getattr(args, "nuts", 0):
            import importlib.util

            if importlib.util.find_spec("blackjax") is None:
                raise ValueError("--nuts needs blackjax: pip install 'jaxmpm[bayes]'")
        for name in ("noise",):
            value = getattr(args, name, None)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        if getattr(args, "search_seed", 0) < 0:
            raise ValueError(f"--search-seed must be >= 0, got {args.search_seed}")
        if getattr(args, "resume", False) and not args.out:
            raise ValueError("--resume needs --out (the history file to continue)")
        _check_options(args)
        _check_outputs(args)
        commands = {"fit": _fit, "sweep": _sweep, "twin": _twin, "bench": _bench, "law": _law, "coverage": _coverage,
                    "design": _design}
        return commands[args.command](args)
    except ValueError as err:
        parser.exit(2, f"python -m calibration {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
