"""What ``python -m calibration`` does between parsing and calling the library: the parsed
flags turned into the library's objects (a ``FitSetup``, option objects), a library error about
an option reported under its flag (``as_flag``), and the printing of the JSON. No argparse
namespace goes past this package.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import pathlib
import sys

from jaxmpm import Experiment
from jaxmpm.cli import parse_set, print_json
from jaxmpm.precision import use_dtype
from jaxmpm.scenes import SCENE_NAMES, experiments_dtype, is_experiment_file

from ..batch.workers import available_cores
from ..data.collapse import FrontMeasurement, ProfileMeasurement, read_measurements, with_measurements
from ..data.flow_rule import load_flow_rule
from ..data.incline import InclineExperiment, is_incline_file, load_incline
from ..inference.options import JudgeOptions
from ..optim.options import FitOptions, cli_steps
from ..optim.report import PosteriorOptions
from ..problem.build import FitSetup
from ..problem.options import DataOptions, OptionError

__all__ = [
    "parse_keys", "parse_pairs", "parse_floats", "parse_over", "parse_variants", "design_scene", "design_noise",
    "design_inclines", "worker_count", "fit_options", "data_options", "posterior_options", "fit_request",
    "single_start_reason", "start_count", "fit_meta", "fit_fields", "experiments_of", "setup_of", "coarse_setup",
    "guard", "finish", "FLAGS", "as_flag",
]


# ---- values -------------------------------------------------------------------------------------
def parse_keys(text: str, option: str = "--fit") -> tuple[str, ...]:
    """Comma-separated parameter names; none is an error naming ``option``."""
    keys = tuple(k.strip() for k in text.split(",") if k.strip())
    if not keys:
        raise ValueError(f"{option}: expected comma-separated parameter names, got {text!r}")
    return keys


def parse_pairs(items, option: str) -> dict[str, float]:
    """``KEY=VALUE`` items as {key: value}; a malformed or repeated key is an error naming ``option``."""
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
    collapses = [n for n in SCENE_NAMES if n != "elastic-block"]
    if is_experiment_file(text) or text in collapses:
        return text
    raise argparse.ArgumentTypeError(f"must be a collapse scene ({', '.join(collapses)}) or an experiment file "
                                     f"(.toml), got {text!r}")


def design_noise(args) -> dict[str, float]:
    """``design``'s expected noise by block: --noise, the front's and the top's where given, and
    the inclines' velocities' where given (else each table's stated noise, else the library's 0.02)."""
    noise = {"profile": args.noise, "front": args.noise_front if args.noise_front is not None else args.noise,
             "top": args.noise_top if args.noise_top is not None else args.noise}
    if getattr(args, "noise_velocity", None) is not None:
        noise["velocity"] = args.noise_velocity
    return noise


def design_inclines(files) -> dict:
    """``design --incline FILE`` (repeatable) -> {the file's stem: its flow-rule table, or (table, the
    file's material, its chute's side walls or None) for an incline experiment file}; an unreadable
    file is refused naming the option."""
    out: dict = {}
    for file in files:
        label = pathlib.Path(file).stem
        if label in out:
            raise ValueError(f"--incline: two files are labelled {label!r} (a label is the file's stem); rename one")
        try:
            if is_incline_file(file):
                experiment = load_incline(file)
                out[label] = (load_flow_rule(experiment.table_file), dict(experiment.material), experiment.side_walls)
            else:
                out[label] = load_flow_rule(file)
        except (OSError, ValueError) as err:
            raise ValueError(f"--incline {file}: {err}") from None
    return out


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
        options = (FitOptions(method=args.method, steps=cli_steps(args.method, args.steps, args.lm_jacobian),
                              learning_rate=args.lr, lm_model=args.lm_model, lm_jacobian=args.lm_jacobian,
                              restarts=args.restarts)
                   if getattr(args, "command", None) == "fit" else None)
        judge = JudgeOptions(noise=noise, roundoff_samples=getattr(args, "roundoff_samples", 0),
                             sampling_seeds=getattr(args, "sampling_seeds", 0),
                             reference_noise=getattr(args, "reference_noise", 0.01),
                             threshold=getattr(args, "threshold", 0.1),
                             grid_ratio=getattr(args, "grid_check", 0) or None,
                             grid_levels=getattr(args, "grid_levels", 1), probe=getattr(args, "probe", True))
    except OptionError as err:
        raise as_flag(err) from None
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
        raise as_flag(err) from None


def posterior_options(args) -> PosteriorOptions:
    """The checks of ``posterior`` (``PosteriorOptions``) from the flags (``--grid-check 0``: no
    grid term), an error reported under the flag's name."""
    try:
        return PosteriorOptions(profiles=args.profiles, posterior=args.posterior, nuts=args.nuts, chains=args.chains,
                                emulated=args.emulated, emulator=args.emulator, model_error=args.model_error,
                                prior=parse_priors(args.prior) or None, grid_ratio=args.grid_check or None,
                                grid_levels=args.grid_levels)
    except OptionError as err:
        raise as_flag(err) from None


def fit_request(args, experiments):
    """The command line's keys, starting values and noise over the experiment files' [fit]
    tables (``calibration.problem.options.fit_request``)."""
    from ..problem.options import fit_request as request

    keys = parse_keys(args.fit) if getattr(args, "fit", None) else None
    try:
        return request(experiments, keys, parse_pairs(getattr(args, "init", []), "--init"),
                       getattr(args, "noise", None))
    except OptionError as err:
        raise as_flag(err) from None


def single_start_reason(args, init=None) -> str | None:
    """Why ``fit`` runs one start (None: a global search is possible)."""
    if args.init:
        return "--init"
    if init:
        return "the experiment file's [fit] init"
    for option, given in (("--resume", args.resume), ("--method adam", args.method == "adam"),
                          ("--jacobian fd", args.jacobian == "fd")):
        if given:
            return option
    return None


def start_count(args, init=None) -> int:
    """The number of starts: --starts, or the search's default when nothing asks for one start.
    More than one start with an option that needs a single one is refused, naming both."""
    single = single_start_reason(args, init)
    if args.starts is None:
        from ..optim.search import DEFAULT_STARTS

        return 1 if single else DEFAULT_STARTS
    if args.starts > 1 and single not in (None, "--init", "the experiment file's [fit] init"):
        what = {"--resume": "continues one start's history",
                "--method adam": "is a single-start optimiser (the search is Levenberg–Marquardt)",
                "--jacobian fd": "is not batched (the search uses forward-mode Jacobians)"}[single]
        raise ValueError(f"--starts {args.starts}: {single} {what}; drop one of them")
    return args.starts


def fit_meta(setup: FitSetup) -> dict:
    """What a fit's file records of the command: its line and the setup its objective was built
    from (``FitSetup.to_json``: ``python -m calibration posterior`` builds it again)."""
    return {"command": "python -m calibration " + " ".join(sys.argv[1:]), "setup": setup.to_json()}


def fit_fields(args, setup: FitSetup, init, found) -> dict:
    """The fields ``fit`` adds to the fit's report (``calibration.optim.report.fit_report``): why
    one start ran (without a search, ``found`` None), the scene, the experiment files and --out."""
    out: dict = {}
    if found is None:
        out["search"] = {"starts": 1, "why": f"a single start ({single_start_reason(args, init) or '--starts 1'})"}
    out["scene"] = setup.experiments[0].name
    if args.experiments:
        out["experiments"] = [str(e.path) for e in setup.experiments]
    if args.out:
        out["out"] = str(args.out)
    return out


def h_stop_tables(setup: FitSetup) -> dict:
    """{file name: (its ``HStopTable``, its material)} of the setup's incline files that name an
    [h_stop] table: read, and refused naming the file, before anything runs."""
    from ..data.flow_rule import load_h_stop

    return {pathlib.Path(e.path).stem if e.path is not None else e.name: (load_h_stop(e.h_stop_file), e.material)
            for e in setup.experiments if isinstance(e, InclineExperiment) and e.h_stop_file is not None}


def h_stop_fields(tables: dict, params) -> dict:
    """The ``h_stop`` blocks (``calibration.studies.flow_rule.h_stop_report``) of ``tables``
    (``h_stop_tables``) by file name, each at its incline's μ1 in ``params`` (the fitted values by
    name: its own "mu1@NAME", or "mu1"), else its material's; {} without tables."""
    from ..problem.flow_rule import flow_rule_material
    from ..studies.flow_rule import h_stop_report

    blocks = {}
    for label, (table, material) in tables.items():
        name = next((k for k in (f"mu1@{label}", "mu1") if k in params), None)
        mu1 = params[name] if name is not None else flow_rule_material(material)["mu1"]
        blocks[label] = h_stop_report(table, mu1, fitted=name is not None)
    return {"h_stop": blocks} if blocks else {}


# ---- the setup ---------------------------------------------------------------------------------
def experiments_of(args) -> list[Experiment | InclineExperiment]:
    """The experiments of ``fit``/``sweep``: each experiment file (positional) with the command
    line's scene options over its values, or the named --scene as an experiment; --data and
    --front are the measurements of the one experiment (replacing a file's). An incline file
    (``[experiment] kind = "incline"``) is read as it is (``load_incline``): the scene options
    apply to the collapses only, and --data and --front to none."""
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
    if not files:
        return [_scene_experiment(args)]
    inclines = {file for file in files if is_incline_file(file)}
    if inclines and (args.data or args.front):
        raise ValueError(f"{'--data' if args.data else '--front'} applies to a collapse; {min(inclines)} is an "
                         "incline file, whose measurements are its [flow_rule] table")
    experiments = [load_incline(file) if file in inclines else experiment_from_args(args, path=file)
                   for file in files]
    if args.data or args.front:
        return [_with_data(experiments[0], args)]
    for e in experiments:
        listed = None if isinstance(e, InclineExperiment) else read_measurements(e)
        if listed is not None and not listed.profiles and listed.front is None:
            raise ValueError(f"{e.path}: lists no measurement ([[profile]] or [front]); give --data or --front")
    return experiments


def _with_data(experiment: Experiment, args, **changes) -> Experiment:
    """``experiment`` measured by --data and --front (read with --units, --dataset, --time-units),
    its other measurements (``fit``) as ``changes`` say."""
    filed = read_measurements(experiment).front
    kept = filed.correlation_time if filed is not None else None
    front = (FrontMeasurement(pathlib.Path(args.front), args.units, args.time_units, kept) if args.front else None)
    profiles = tuple(ProfileMeasurement(pathlib.Path(p), units=args.units, dataset=args.dataset) for p in args.data)
    return with_measurements(experiment, profiles=profiles, front=front, **changes)


def _scene_experiment(args) -> Experiment:
    """The named --scene (``jaxmpm.scenes.named_experiment``, with the scene options) measured by
    --data and --front and run to --t-end, else to the data's last time, else the scene's; in
    --dtype, else the file's, else float32 (the command line's default)."""
    from jaxmpm.scenes import named_experiment

    from ..data.measurements import data_end_time, load_data

    if not args.data and not args.front:
        raise ValueError("--data (a profile CSV) and/or --front (a front-history CSV) is required")
    t_end = args.t_end
    if t_end is None:
        t_end = data_end_time(*load_data(args.data, args.front, units=args.units, time_units=args.time_units,
                                         dataset=args.dataset, sort=args.sort, clip_noise=args.clip_noise))
    experiment = named_experiment(args.scene, dx=args.dx, ppc=args.ppc, dim=args.dim, width=args.width, t_end=t_end,
                                  slope=args.slope, aspect=args.aspect, dtype=args.dtype,
                                  values=parse_pairs(args.set, "--set"), sampling=args.sampling, seed=args.seed,
                                  side_walls=getattr(args, "side_walls", None))
    return _with_data(experiment.replace(dtype=experiment.dtype or "float32"), args, fit=None)


def setup_of(args, keys) -> FitSetup:
    """The ``FitSetup`` of ``fit`` and ``sweep``: the experiments (``experiments_of``) fitting
    ``keys``, read and weighed as the flags say, several sharing --shared (labelled by their files'
    names); its float type (the collapses', or --dtype) is enabled here, before anything is built."""
    experiments = experiments_of(args)
    dtype = experiments_dtype([e for e in experiments if not isinstance(e, InclineExperiment)], args.dtype)
    use_dtype(dtype)
    shared = getattr(args, "shared", None)
    labels = tuple(pathlib.Path(e.path).stem if e.path is not None else e.name for e in experiments)
    return FitSetup(tuple(experiments), tuple(keys), data_options(args),
                    parse_keys(shared, "--shared") if shared else None, labels if shared else None, args.sort,
                    args.clip_noise, dtype)


def coarse_setup(setup: FitSetup, factor: float) -> FitSetup:
    """The coarse stage's setup of ``fit --coarse F``: the same data on F times the grid spacing
    (one experiment)."""
    if len(setup.experiments) > 1:
        raise ValueError("--coarse takes one experiment (its dx); fit several without it")
    (experiment,) = setup.experiments
    if isinstance(experiment, InclineExperiment):
        raise ValueError(f"--coarse: {experiment.path} is an incline (a closed form), which has no grid to coarsen")
    dx = experiment.builder_arguments()["dx"] * factor
    return dataclasses.replace(setup, experiments=(experiment.replace(dx=dx),))


def guard(errors: dict, option: str, write):
    """Run one output step after the work; on any failure (a full disk, a missing extra, or a
    defect in a figure) keep the message under ``option`` in ``errors`` and return None: the
    work is done, and its JSON still prints (the exit status says the output failed)."""
    try:
        return write()
    except Exception as err:  # noqa: BLE001 - nothing an output step raises may lose a finished fit
        errors[option] = f"{type(err).__name__}: {err}"
        return None


def finish(out: dict, args, errors: dict) -> int:
    """Print ``out`` (with the output steps' ``errors``, if any); the exit status: 1 if a number
    was not finite or an output failed, else 0."""
    if errors:
        out["output_errors"] = errors
    bad = print_json(out, args.json)
    return 1 if (bad or errors) else 0


#: Library field -> command-line flag (None: the command line does not set it).
FLAGS: dict[str, str | None] = {
    "method": "--method", "steps": "--steps", "learning_rate": "--lr", "clip": None, "grad_mode": None,
    "xtol": None, "ftol": None, "stat_tol": None, "max_rejections": None, "lm_model": "--lm-model",
    "lm_jacobian": "--lm-jacobian", "restarts": "--restarts", "noise": "--noise", "uncertainty": None,
    "roundoff_samples": "--roundoff-samples",
    "sampling_seeds": "--sampling-seeds", "reference_noise": "--reference-noise", "threshold": "--threshold",
    "grid_ratio": "--grid-check", "grid_draws": None, "grid_levels": "--grid-levels", "probe": "--probe",
    "keys": "--fit",     "init": "--init", "weighting": "--weighting", "weight_profile": "--weight-profile",
    "weight_front": "--weight-front", "front_threshold": "--front-threshold",
    "front_correlation_time": "--front-correlation-time", "jacobian": "--jacobian", "profiles": "--profiles",
    "posterior": "--posterior", "nuts": "--nuts", "chains": "--chains", "emulated": "--emulated",
    "emulator": "--emulator", "model_error": "--model-error", "prior": "--prior",
}


def as_flag(err: OptionError) -> ValueError:
    """An option object's error under the command-line flag's name (``FLAGS``; the field's own name
    where no flag sets it)."""
    return ValueError(f"{FLAGS.get(err.field) or err.field} {err.what}")
