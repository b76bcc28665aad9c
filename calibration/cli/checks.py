"""Every check of the parsed options made before anything is read or compiles.
"""

from __future__ import annotations

import importlib.util
import math
import pathlib

from jaxmpm.cli import check_output_dir, check_output_file, check_scene_args

from .args import data_options, fit_options, parse_keys, parse_over, parse_pairs, posterior_options, start_count

__all__ = ["check_args", "check_options", "check_command", "check_outputs"]


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
            stray = sorted(set(shared) - set(parse_keys(args.fit))) if args.fit else []
            if stray:
                raise ValueError(f"--shared {','.join(stray)}: not among the fitted keys (--fit {args.fit})")
        starts = start_count(args)  # --starts against the options that need a single start
        if args.coarse is not None:
            if not (math.isfinite(args.coarse) and args.coarse > 1):
                raise ValueError(f"--coarse must be a finite factor > 1 of the grid spacing, got {args.coarse}")
            if starts < 2:
                raise ValueError("--coarse is a stage of the global search: it needs two starts or more (the "
                                 "default without --init; with --init give --starts K)")
        if args.refine < 1:
            raise ValueError(f"--refine must be an integer >= 1, got {args.refine}")
        if args.grid_ladder is not None:
            _check_ladder(args)


def _check_ladder(args) -> None:
    """--grid-ladder N against the options it replaces or cannot continue."""
    from ..optim.ladder import LADDER_RUNGS

    if args.grid_ladder not in LADDER_RUNGS:
        raise ValueError(f"--grid-ladder must be one of {', '.join(map(str, LADDER_RUNGS))} (grids, the fit's "
                         f"included), got {args.grid_ladder}")
    for option, given, why in (
            ("--coarse", args.coarse is not None, "the ladder's coarsest rung is where the starts run"),
            ("--grid-check 0", not args.grid_check, "the ladder's coarser grids are RHO x dx (--grid-check RHO)"),
            ("--grid-levels 2", args.grid_levels != 1, "the ladder's rungs are its grids"),
            ("--resume", args.resume, "a ladder starts from its coarsest rung")):
        if given:
            raise ValueError(f"--grid-ladder {args.grid_ladder} with {option}: {why}; drop one of them")


def check_command(args) -> None:
    """Each command's own checks (``posterior``, ``sweep``, ``twin``, ``coverage`` and ``design``)."""
    command = getattr(args, "command", None)
    if command == "posterior":
        _check_posterior(args)
    elif command == "sweep":
        keys = tuple(parse_over(args.over, lhs=args.lhs is not None))
        if args.plot and args.lhs:
            raise ValueError("--plot draws the loss over a grid; a Latin hypercube (--lhs) is none: drop one of them")
        if args.plot and len(keys) > 2:
            raise ValueError(f"--plot draws the loss over one or two swept keys, got {len(keys)} ({', '.join(keys)})")
        if args.cluster is not None:
            from ..batch.cluster import parse_cluster

            parse_cluster(args.cluster)  # a clear error before any worker starts
            if args.mode != "auto":
                raise ValueError(f"--mode {args.mode}: with --cluster every task is one vmapped chunk; drop --mode")
            if args.retries < 0:
                raise ValueError(f"--retries must be >= 0, got {args.retries}")
    elif command == "twin":
        if (args.slope is not None or args.aspect is not None or args.dim not in (None, 2) or args.width is not None
                or getattr(args, "side_walls", None) is not None):
            raise ValueError("twin is the 2D S4 cohesive collapse: --slope, --aspect, --dim, --width and --side-walls "
                             "do not apply")
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


def _check_posterior(args) -> None:
    """``posterior``: the checks asked for (``PosteriorOptions``), their extra's packages, the fit's file."""
    from ..optim.history import read_history

    options = posterior_options(args)
    if not options.any:
        raise ValueError("posterior: ask for a check: --profiles, --posterior, --nuts or --emulated")
    missing = [m for m in ("blackjax", "arviz_stats") if importlib.util.find_spec(m) is None]
    for flag in ("nuts", "emulated"):
        if getattr(options, flag) and missing:
            raise ValueError(f"--{flag} needs {missing[0]}: pip install 'jaxmpm[bayes]'")
    try:
        read_history(args.fit_file)
    except ValueError as err:
        raise ValueError(f"FIT.h5: {err}") from None


def check_outputs(args) -> None:
    """Every output path is checked before the data are read or anything compiles: a file for
    --out (which must exist for --resume, and must not, unless --overwrite, otherwise), a folder
    for --plot. Nothing is created here."""
    out = getattr(args, "out", None)
    resume, overwrite = getattr(args, "resume", False), getattr(args, "overwrite", False)
    if out:
        check_output_file(out, "--out")
        path = pathlib.Path(out)
        if resume and overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        if resume:
            from ..optim.history import read_history

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
