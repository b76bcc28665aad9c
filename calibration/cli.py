"""What ``python -m calibration`` does between parsing and calling the library: the parsed
options (an ``argparse.Namespace``) turned into plain values and option objects
(``calibration.options``), every check made before anything compiles, and the printing of the
JSON. A library error about an option is reported under its flag (``OptionError.as_flag``).
Only the command line uses this module."""

from __future__ import annotations

import argparse
import copy
import importlib.util
import math
import os
import pathlib
import sys

from jaxmpm.cli import print_json
from jaxmpm.precision import use_dtype

from .options import DataOptions, FitOptions, JudgeOptions, OptionError, cli_steps
from .workers import available_cores

__all__ = ["check_args", "check_command", "check_options", "check_outputs", "coarse_objective", "data_options",
           "design_noise", "design_scene", "experiment_files", "finish", "fit_fields", "fit_meta",
           "fit_options", "fit_request", "guard", "load_data", "objective_from_args", "parse_floats", "parse_keys",
           "parse_over", "parse_pairs", "parse_variants", "scene_and_objective", "single_start_reason",
           "start_count", "worker_count"]


# ---- values -------------------------------------------------------------------------------------
def parse_keys(text: str, option: str = "--fit") -> tuple[str, ...]:
    """Comma-separated parameter names; none is an error naming ``option``."""
    keys = tuple(k.strip() for k in text.split(",") if k.strip())
    if not keys:
        raise ValueError(f"{option}: expected comma-separated parameter names, got {text!r}")
    return keys


def parse_pairs(items, option: str) -> dict[str, float]:
    """``KEY=VALUE`` items as {key: value}; a malformed or repeated key is an error naming ``option``."""
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


def parse_priors(items) -> dict[str, tuple[float, float]]:
    """``--prior KEY=MEAN:SD`` items as {key: (mean, sd)}: a key measured by another experiment,
    a normal prior in the posteriors. A malformed item, sd <= 0 or a repeated key is an error."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        mean, colon, sd = value.partition(":")
        try:
            pair = (float(mean), float(sd))
        except ValueError:
            pair = None
        if not (sep and colon and key.strip() and pair and all(math.isfinite(v) for v in pair) and pair[1] > 0):
            raise ValueError(f"--prior expects KEY=MEAN:SD with a finite mean and SD > 0, got {item!r}")
        if key.strip() in out:
            raise ValueError(f"--prior {key.strip()} is given twice; give each key once")
        out[key.strip()] = pair
    return out


def parse_floats(text: str, option: str) -> list[float]:
    """Comma-separated numbers."""
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{option} expects comma-separated numbers, got {text!r}") from None


def parse_over(items, lhs: bool = False) -> dict[str, tuple[float, float, int]]:
    """``--over KEY=LO:HI[:N]`` items as {key: (lo, hi, n)} (n 5 where not given; with ``lhs``
    a count is refused)."""
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


def parse_variants(items) -> dict[str, dict[str, float]]:
    """``--variant LABEL:key=value[,key=value...]`` -> {label: {key: value}}."""
    out: dict[str, dict[str, float]] = {}
    for item in items:
        label, sep, rest = item.partition(":")
        if not sep or not label.strip() or not rest.strip():
            raise ValueError(f"--variant expects LABEL:key=value[,key=value...], got {item!r}")
        if label in out:
            raise ValueError(f"--variant: the label {label!r} is given twice")
        out[label.strip()] = parse_pairs([p for p in rest.split(",") if p], f"--variant {label}")
    return out


def design_scene(text: str) -> str:
    """The argument type of ``design --scene``: a collapse scene's name or an experiment file."""
    from jaxmpm.scenes import SCENE_NAMES, is_experiment_file

    collapses = [n for n in SCENE_NAMES if n != "elastic-block"]
    if is_experiment_file(text) or text in collapses:
        return text
    raise argparse.ArgumentTypeError(f"must be a collapse scene ({', '.join(collapses)}) or an experiment file "
                                     f"(.toml), got {text!r}")


def design_noise(args) -> dict[str, float]:
    """``design``'s expected noise by block: --noise, the front's and the top's where given."""
    return {"profile": args.noise, "front": args.noise_front if args.noise_front is not None else args.noise,
            "top": args.noise_top if args.noise_top is not None else args.noise}


def worker_count(args) -> int:
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


# ---- option objects -----------------------------------------------------------------------------
def fit_options(args, noise=None) -> tuple[FitOptions | None, JudgeOptions]:
    """The fit's ``FitOptions`` (``fit`` only, else None) and ``JudgeOptions`` from the flags
    (``--grid-check 0``: off), an error reported under the flag's name (``FLAGS``)."""
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


def data_options(args) -> DataOptions:
    """How the objective reads and weighs the data (``DataOptions``) from the flags, an error
    reported under the flag's name."""
    try:
        return DataOptions(weighting=getattr(args, "weighting", "block"),
                           weight_profile=getattr(args, "weight_profile", None),
                           weight_front=getattr(args, "weight_front", None),
                           front_threshold=getattr(args, "front_threshold", None),
                           front_correlation_time=getattr(args, "front_correlation_time", None),
                           jacobian=getattr(args, "jacobian", "ad"))
    except OptionError as err:
        raise err.as_flag() from None


def fit_request(args, experiments):
    """The command line's keys, starting values and noise over the experiment files' [fit]
    tables (``calibration.options.fit_request``)."""
    from .options import fit_request as request

    keys = parse_keys(args.fit) if getattr(args, "fit", None) else None
    try:
        return request(experiments, keys, parse_pairs(getattr(args, "init", []), "--init"),
                       getattr(args, "noise", None))
    except OptionError as err:
        raise err.as_flag() from None


def single_start_reason(args, init=None) -> str | None:
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


def start_count(args, init=None) -> int:
    """The number of starts: --starts, or the search's default when nothing asks for one start.
    More than one start with an option that needs a single one is refused, naming both."""
    single = single_start_reason(args, init)
    if args.starts is None:
        from .search import DEFAULT_STARTS

        return 1 if single else DEFAULT_STARTS
    if args.starts > 1 and single not in (None, "--init", "the experiment file's [fit] init"):
        what = {"--out": "keeps the resumable history of one start", "--resume": "continues one start's history",
                "--method adam": "is a single-start optimiser (the search is Levenberg–Marquardt)",
                "--jacobian fd": "is not batched (the search uses forward-mode Jacobians)"}[single]
        raise ValueError(f"--starts {args.starts}: {single} {what}; drop one of them")
    return args.starts


def fit_meta(args, experiments) -> dict:
    """What a fit's history file records of the command: its line, its data files and the
    experiment files it ran, as they ran."""
    return {"command": "python -m calibration " + " ".join(sys.argv[1:]), "data": args.data, "front": args.front,
            "experiments": [e.to_toml() for e in experiments]}


def fit_fields(args, scene, experiments, init, found) -> dict:
    """The fields ``fit`` adds to the fit's report (``calibration.report.fit_report``): why
    one start ran (without a search, ``found`` None), the scene, the experiment files and --out."""
    out: dict = {}
    if found is None:
        out["search"] = {"starts": 1, "why": f"a single start ({single_start_reason(args, init) or '--starts 1'})"}
    out["scene"] = scene.name
    if experiments:
        out["experiments"] = [str(e.path) for e in experiments]
    if args.out:
        out["out"] = str(args.out)
    return out


# ---- the objective ------------------------------------------------------------------------------
def experiment_files(args) -> list:
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


def load_data(args, experiment=None):
    """The profiles and the front history: --data and --front, else the experiment file's
    [[profile]] and [front] (read with the units they state)."""
    from . import data

    if experiment is not None and not args.data and not args.front:
        profiles, front = data.load_measurements(experiment, sort=args.sort, clip_noise=args.clip_noise)
        if not profiles and front is None:
            raise ValueError(f"{experiment.path}: lists no measurement ([[profile]] or [front]); give --data or "
                             "--front")
        data.check_run_status([*profiles, front])
    else:
        profiles, front = data.load_data(args.data, args.front, units=args.units, time_units=args.time_units,
                                    dataset=args.dataset, sort=args.sort, clip_noise=args.clip_noise)
    if not profiles and front is None:
        raise ValueError("--data (a profile CSV) and/or --front (a front-history CSV) is required")
    return profiles, front


def scene_and_objective(args, keys, experiments=()):
    """(scene, objective): the named --scene with --data/--front (run to --t-end, else to the
    data's last time), or each experiment file with its measurements (several: one joint
    objective, with --shared labelled by the files' names; the scene returned is the first's);
    ``calibration.problem.objective_of``."""
    from jaxmpm.cli import scene_dtype, scene_from_args
    from jaxmpm.scenes import experiments_dtype

    from .data import data_end_time
    from .objective import CompositeObjective
    from .problem import objective_of

    use_dtype(experiments_dtype(experiments, args.dtype) if experiments else scene_dtype(args))
    options = data_options(args)
    if experiments:
        sources, data = list(experiments), [load_data(args, e) for e in experiments]
    else:
        profiles, front = load_data(args)
        t_end = args.t_end if args.t_end is not None else data_end_time(profiles, front)
        sources, data = [scene_from_args(argparse.Namespace(**{**vars(args), "t_end": t_end}))], [(profiles, front)]
    shared = getattr(args, "shared", None)
    labels = [pathlib.Path(e.path).stem if e.path is not None else e.name for e in experiments]
    objective = objective_of(sources, keys, data, options, shared=parse_keys(shared, "--shared") if shared else None,
                             labels=labels)
    first = objective.members[0] if isinstance(objective, CompositeObjective) else objective
    return first.scene, objective


def posterior_model_error(args, objective, result, workers):
    """The model's own error at the fit's point for the posterior checks' likelihood
    (``calibration.likelihood.model_error`` with ``--model-error`` draws, on the grid
    ``--grid-check`` times coarser, 1.5 where that is off): None where no check is asked for or
    ``--model-error 0``; the reason, a string, where it cannot be measured (the JSON says so)."""
    from .likelihood import model_error
    from .uncertainty import GRID_RATIO

    if not (args.model_error and (args.profiles or args.posterior or args.nuts or args.emulated)):
        return None
    try:
        return model_error(objective, result.theta, draws=args.model_error, ratio=args.grid_check or GRID_RATIO,
                           workers=workers)
    except ValueError as err:
        return str(err)


def coarse_objective(args, scene, keys, experiments):
    """The coarse stage's objective of ``fit --coarse F``: the same data on F times the grid
    spacing of ``scene`` (one experiment)."""
    if len(experiments) > 1:
        raise ValueError("--coarse takes one experiment (its dx); fit several without it")
    coarse = copy.copy(args)
    coarse.dx = scene.config.grid.dx * args.coarse
    return scene_and_objective(coarse, keys, experiment_files(coarse))[1]


def objective_from_args(values: dict, keys):
    """The objective that ``python -m calibration`` builds from these parsed options (``vars``
    of the Namespace): the recipe a cluster worker runs (picklable as a ``functools.partial``)."""
    args = argparse.Namespace(**values)
    return scene_and_objective(args, keys, experiment_files(args))[1]


# ---- checks before the work ---------------------------------------------------------------------
def check_args(args) -> None:
    """Every check of the parsed options made before anything is read or compiles: counts and
    ranges, the options the library would check later or under its own names
    (``check_options``), the output paths (``check_outputs``) and each command's own
    (``check_command``)."""
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
    if getattr(args, "emulated", 0) and args.emulated < 30:
        raise ValueError(f"--emulated must be 0 (off) or >= 30 checked draws, got {args.emulated}")
    if getattr(args, "emulated", 0) and getattr(args, "chains", 4) < 2:
        raise ValueError(f"--chains must be >= 2 with --emulated (R-hat compares chains), got {args.chains}")
    if getattr(args, "chains", 1) < 1:
        raise ValueError(f"--chains must be >= 1, got {args.chains}")
    if getattr(args, "prior", None):
        parse_priors(args.prior)
        if not (args.nuts or args.emulated):
            raise ValueError("--prior enters the posteriors of --nuts and --emulated (not the fit): give one of them")
    draws = getattr(args, "model_error", 0)
    if draws < 0 or draws == 1:
        raise ValueError(f"--model-error must be 0 (off) or >= 2 particle draws, got {args.model_error}")
    for flag in ("nuts", "emulated"):
        if getattr(args, flag, 0) and importlib.util.find_spec("blackjax") is None:
            raise ValueError(f"--{flag} needs blackjax: pip install 'jaxmpm[bayes]'")
    noise = getattr(args, "noise", None)
    if noise is not None and not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"--noise must be >= 0, got {noise}")
    if getattr(args, "search_seed", 0) < 0:
        raise ValueError(f"--search-seed must be >= 0, got {args.search_seed}")
    if getattr(args, "resume", False) and not args.out:
        raise ValueError("--resume needs --out (the history file to continue)")
    check_options(args)
    check_outputs(args)
    check_command(args)


def check_options(args) -> None:
    """Checks the library would make later, or with its own argument names."""
    from jaxmpm.cli import check_scene_args

    if hasattr(args, "sampling"):  # the scene options of add_scene_arguments
        check_scene_args(args)
    if getattr(args, "front_correlation_time", None) is not None and not args.front:
        raise ValueError("--front-correlation-time needs --front (the front history whose errors it describes)")
    fd_step = getattr(args, "fd_step", None)
    if fd_step is not None and not (math.isfinite(fd_step) and fd_step > 0):
        raise ValueError(f"--fd-step must be a finite number > 0, got {fd_step}")
    if hasattr(args, "weight_profile"):
        options = data_options(args)  # weights, front threshold and correlation time
        for option, weight, given, what in (("--weight-profile", options.weight_profile, bool(args.data), "--data"),
                                            ("--weight-front", options.weight_front, bool(args.front), "--front")):
            if given and weight == 0:
                raise ValueError(f"{option} 0 gives the {what} data no weight: their residuals would all be zero and "
                                 f"their uncertainty undefined; leave out {what} instead")
    fit_options(args)  # the fit's and the verdict's options, checked by the library's option objects
    for option in ("init", "set"):
        if hasattr(args, option):
            parse_pairs(getattr(args, option), f"--{option}")  # malformed or repeated keys
    if getattr(args, "command", None) == "fit":
        if args.shared is not None:
            shared = parse_keys(args.shared, "--shared")
            if len(args.experiments) < 2:
                raise ValueError("--shared needs two experiment files or more (the keys they share)")
            if args.fit and sorted(set(shared) - set(parse_keys(args.fit))):
                raise ValueError(f"--shared {','.join(sorted(set(shared) - set(parse_keys(args.fit))))}: not among "
                                 f"the fitted keys (--fit {args.fit})")
        starts = start_count(args)  # --starts against the options that need a single start
        if args.coarse is not None:
            if not (math.isfinite(args.coarse) and args.coarse > 1):
                raise ValueError(f"--coarse must be a finite factor > 1 of the grid spacing, got {args.coarse}")
            if starts < 2:
                raise ValueError("--coarse is a stage of the global search: it needs two starts or more (the "
                                 "default without --init; with --init give --starts K)")
        if args.refine < 1:
            raise ValueError(f"--refine must be an integer >= 1, got {args.refine}")


def check_command(args) -> None:
    """Each command's own checks: ``sweep``'s --over items, a figure only of one or two keys on
    a grid, and --cluster's options; ``twin``'s scene options (the S4 scene's own); ``coverage``'s
    noise and seeds; ``design``'s figure of two keys."""
    command = getattr(args, "command", None)
    if command == "sweep":
        keys = tuple(parse_over(args.over, lhs=args.lhs is not None))
        if args.plot and args.lhs:
            raise ValueError("--plot draws the loss over a grid; a Latin hypercube (--lhs) is none: drop one of them")
        if args.plot and len(keys) > 2:
            raise ValueError(f"--plot draws the loss over one or two swept keys, got {len(keys)} ({', '.join(keys)})")
        if args.cluster is not None:
            from .cluster import parse_cluster

            parse_cluster(args.cluster)  # a clear error before any worker starts
            if args.mode != "auto":
                raise ValueError(f"--mode {args.mode}: with --cluster every task is one vmapped chunk; drop --mode")
            if args.retries < 0:
                raise ValueError(f"--retries must be >= 0, got {args.retries}")
    elif command == "twin":
        if args.slope is not None or args.aspect is not None or args.dim not in (None, 2) or args.width is not None:
            raise ValueError("twin is the 2D S4 cohesive collapse: --slope, --aspect, --dim and --width do not apply")
        if args.sampling is not None or args.seed not in (None, 0):
            raise ValueError("twin uses the S4 scene's default particle sampling: --sampling and --seed do not apply "
                             "(--noise-seed seeds the noise)")
        if args.landscape and len(parse_keys(args.fit)) < 2:
            raise ValueError("--landscape needs at least two fitted keys")
    elif command == "coverage":
        if not 0 < args.noise < 1:
            raise ValueError(f"--noise must be in (0, 1): coverage needs noisy data, got {args.noise}")
        if args.seeds < 2:
            raise ValueError(f"--seeds must be >= 2, got {args.seeds}")
    elif command == "design" and args.plot and len(parse_keys(args.fit)) < 2:
        raise ValueError("--plot draws the first two keys' regions: give at least two keys in --fit")


def check_outputs(args) -> None:
    """Every output path is checked before the data are read or anything compiles: a file for
    --out (which must exist for --resume, and must not, unless --overwrite, otherwise), a folder
    for --plot. Nothing is created here."""
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


# ---- output -------------------------------------------------------------------------------------
def guard(errors: dict, option: str, write):
    """Run one output step after the work; on failure keep the message under ``option`` in
    ``errors`` (the JSON still prints) and return None."""
    try:
        return write()
    except (OSError, ValueError, RuntimeError, ImportError) as err:
        errors[option] = f"{type(err).__name__}: {err}"
        return None


def finish(out: dict, args, errors: dict) -> int:
    """Print ``out`` (with the output steps' ``errors``, if any); the exit status: 1 if a number
    was not finite or an output failed, else 0."""
    if errors:
        out["output_errors"] = errors
    bad = print_json(out, args.json)
    return 1 if (bad or errors) else 0
