"""Command-line helpers shared by ``python -m jaxmpm`` and ``python -m calibration``.

The scene options (``add_scene_arguments``) and the checks made on them before anything is
built; ``--set key=value`` items; the scene or experiment file the options describe
(``scene_from_args``); checks that every output file can be written, made before any work;
and JSON printed strictly (non-finite numbers become null and are listed). Nothing in the core
of ``jaxmpm`` imports this module: it sits with the command lines, on top.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import tempfile
from typing import Any

import jax
import numpy as np

from .params import param_help
from .precision import DTYPES
from .sampling import SAMPLINGS
from .scenes import SCENE_NAMES, build_scene, is_experiment_file
from .threads import THREAD_CHOICES

__all__ = ["OPTION_FIELDS", "add_scene_arguments", "add_threads_argument", "check_figure_file", "check_output_dir",
           "check_output_file", "check_repeated_keys", "check_run_outputs", "check_scene_args", "experiment_from_args",
           "json_safe", "output_writer", "parse_set", "print_json", "scene_dtype", "scene_from_args",
           "side_walls_argument"]


# ---- the scene options -------------------------------------------------------------------------
#: The command line's scene options -> the ``Experiment`` field each sets.
OPTION_FIELDS = {"--dx": "dx", "--ppc": "ppc", "--sampling": "sampling", "--seed": "seed", "--dim": "dim",
                 "--width": "width", "--slope": "slope", "--t-end": "t_end", "--dtype": "dtype", "--frames": "frames",
                 "--side-walls": "side_walls"}


def add_scene_arguments(parser, scene_choices: bool = True) -> None:
    """The scene options shared by ``python -m jaxmpm run`` and ``python -m calibration``:
    SCENE (positional, optional), --set, --dx, --ppc, --sampling, --seed, --dim, --width,
    --side-walls, --slope, --aspect, --t-end, --dtype."""
    if scene_choices:
        parser.add_argument("scene", type=_scene_argument, metavar="SCENE|EXPERIMENT.toml",
                            help=f"a scene ({', '.join(SCENE_NAMES)}) or an experiment file")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help=f"material parameter, in SI units: {param_help()}")
    parser.add_argument("--dx", type=float, default=None, help="grid spacing, m (default: the scene's)")
    parser.add_argument("--ppc", type=float, default=None, help="particles per cell and axis (default: the "
                        "scene's, DEFAULT_PPC; an integer for lattice and jitter sampling)")
    parser.add_argument("--sampling", choices=SAMPLINGS, default=None,
                        help="particle sampling (default: the scene's, DEFAULT_SAMPLING; poisson needs scipy)")
    parser.add_argument("--seed", type=int, default=None, help="random seed of jitter and poisson sampling "
                        "(default: the experiment's, else 0)")
    parser.add_argument("--dim", type=int, default=None, choices=(2, 3), help="2 or 3 (default: the experiment's, "
                        "else 2)")
    parser.add_argument("--width", type=float, default=None, help="channel width for --dim 3, m")
    parser.add_argument("--side-walls", type=side_walls_argument, default=None, metavar="WIDTH,FRICTION[,K]",
                        help="the side walls of a 2D channel: its width (m), the walls' Coulomb friction (a number, "
                             "or mu_w: the parameter, set with --set mu_w=... and fitted with --fit) and the "
                             "lateral pressure ratio K (default 1), e.g. 0.02,0.25 (default: the experiment's, "
                             "else none)")
    parser.add_argument("--slope", type=float, default=None, help="bed angle for slope-collapse, degrees")
    parser.add_argument("--aspect", type=float, default=None, help="aspect ratio H0/L0 for aspect-ratio")
    parser.add_argument("--t-end", type=float, default=None, help="end time, s (default: the scene's)")
    parser.add_argument("--dtype", choices=DTYPES, default=None,
                        help="default: the experiment's, else float32")


def side_walls_argument(text: str):
    """argparse type of ``--side-walls WIDTH,FRICTION[,K]``: a ``jaxmpm.SideWalls`` (width in m)."""
    import argparse

    from .boundary import SideWalls

    parts = [p.strip() for p in str(text).split(",")]
    parameter = len(parts) > 1 and parts[1] == "mu_w"  # the friction is the parameter mu_w (--set/--init/--fit)
    try:
        numbers = [0.0 if parameter and i == 1 else float(p) for i, p in enumerate(parts)]
    except ValueError:
        numbers = []
    if len(numbers) not in (2, 3) or not all(math.isfinite(n) for n in numbers):
        raise argparse.ArgumentTypeError(f"expected WIDTH,FRICTION[,K]: finite numbers, the width in m, the friction "
                                         f"a number or mu_w (e.g. 0.02,0.25 or 0.02,mu_w), got {text!r}")
    width, friction, ratio = numbers[0], numbers[1], (numbers[2] if len(numbers) == 3 else 1.0)
    for name, value, ok, rule in (("width", width, width > 0, "> 0 m"), ("friction", friction, friction >= 0, ">= 0"),
                                  ("K", ratio, ratio >= 0, ">= 0")):
        if not ok:
            raise argparse.ArgumentTypeError(f"the {name} must be {rule}, got {value:g}")
    return SideWalls(width, "mu_w" if parameter else friction, ratio)


#: Scene options that take a number (``add_scene_arguments``): argparse's float() accepts
#: "nan" and "inf", which would otherwise surface as some derived quantity's error.
_SCENE_NUMBERS = ("dx", "ppc", "width", "slope", "aspect", "t_end")


def check_scene_args(args) -> None:
    """Checks on the scene options of ``add_scene_arguments`` that the scene builders cannot
    make with the option's name (shared with ``python -m calibration``): every number finite,
    --width only with --dim 3 (a 2D run has no width: it would be ignored), --set keys once each."""
    for name in _SCENE_NUMBERS:
        value = getattr(args, name, None)
        if value is not None and not math.isfinite(value):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite number, got {value}")
    experiment = is_experiment_file(getattr(args, "scene", None) or "") or bool(getattr(args, "experiments", None))
    if getattr(args, "width", None) is not None and getattr(args, "dim", None) != 3 and not experiment:
        raise ValueError(f"--width applies to --dim 3 (a 3D channel), got --width {args.width} with --dim {args.dim} "
                         "(a 2D channel's walls: --side-walls WIDTH,FRICTION)")
    check_repeated_keys(getattr(args, "set", []), "--set")


def check_repeated_keys(items, option: str) -> None:
    """``key=value`` items (``--set``, ``--init``, ``--over``) must name each key once: a repeated
    key would silently keep only its last value."""
    seen: dict[str, str] = {}
    for item in items:
        key = item.partition("=")[0].strip()
        if key in seen:
            raise ValueError(f"{option} {key} is given twice ({seen[key]!r} and {item!r}); give each key once")
        seen[key] = item


def parse_set(item: str) -> tuple[str, float]:
    """``key=value`` from ``--set`` (value a number)."""
    key, sep, value = item.partition("=")
    if not sep:
        raise ValueError(f"--set expects key=value, got {item!r}")
    try:
        return key.strip(), float(value)
    except ValueError:
        raise ValueError(f"--set {key}: value must be a number, got {value!r}") from None


def experiment_from_args(args, frames: int | None = None, path=None):
    """The experiment file that the command line's SCENE (or ``path``) names, with the scene
    options given on the command line over the file's values (``OPTION_FIELDS``; --set over its
    [material])."""
    from .experiment import Experiment

    if getattr(args, "aspect", None) is not None:
        raise ValueError("--aspect applies to the aspect-ratio scene; an experiment file gives its height and length")
    experiment = Experiment.from_toml(path if path is not None else args.scene)
    options = {field: getattr(args, field, None) for field in OPTION_FIELDS.values() if field != "frames"}
    options["frames"] = frames
    options["dtype"] = args.dtype or experiment.dtype or "float32"  # the command line's default, float32
    values = dict(parse_set(item) for item in getattr(args, "set", []))
    return experiment.with_options(material=values, flags={v: k for k, v in OPTION_FIELDS.items()}, **options)


def scene_dtype(args) -> str:
    """The floating-point type the scene of these options runs in: --dtype, else an experiment
    file's [numerics] dtype, else float32."""
    if getattr(args, "dtype", None):
        return args.dtype
    if is_experiment_file(getattr(args, "scene", "") or ""):
        from .experiment import Experiment

        return Experiment.from_toml(args.scene).dtype or "float32"
    return "float32"


def scene_from_args(args, name: str | None = None, frames: int = 0):
    """Build the scene that ``add_scene_arguments``' options describe: a named scene, or the
    experiment file that SCENE names (``experiment_from_args``)."""
    name = name or args.scene
    if is_experiment_file(name):
        return experiment_from_args(args, frames).scene()
    values = dict(parse_set(item) for item in args.set)
    frames = 0 if frames is None else frames
    return build_scene(name or args.scene, dx=args.dx, ppc=args.ppc, dim=args.dim, width=args.width,
                       t_end=args.t_end, frames=frames, slope=args.slope, aspect=args.aspect,
                       dtype=args.dtype or "float32", values=values, sampling=args.sampling, seed=args.seed,
                       side_walls=getattr(args, "side_walls", None))


def _scene_argument(text: str) -> str:
    """argparse type of SCENE: a scene name or an experiment file."""
    import argparse

    if text in SCENE_NAMES or is_experiment_file(text):
        return text
    raise argparse.ArgumentTypeError(f"must be one of {', '.join(SCENE_NAMES)} or an experiment file (.toml), "
                                     f"got {text!r}")


def add_threads_argument(parser) -> None:
    """The command lines' ``--threads {1,all}`` (default 1: the process on one core), applied by
    ``jaxmpm.threads.apply_threads``."""
    parser.add_argument("--threads", choices=THREAD_CHOICES, default=None,
                        help="XLA's CPU threads: 1 (the default: the process on one core, faster below "
                             "about 1e5 particles, docs/performance.md) or all (XLA's own pool on every core)")


# ---- outputs, checked before any work ------------------------------------------------------------
def _probe_writable(folder: pathlib.Path, option: str, shown: str) -> None:
    """Create and remove a temporary file in ``folder``: the one test of writability that also
    holds for root and for read-only file systems (``os.access`` answers yes to root)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".jaxmpm-write-check-")
    except OSError as err:
        raise ValueError(f"{option} {shown}: cannot write in the folder {str(folder)!r} "
                         f"({err.strerror or err})") from None
    os.close(fd)
    os.unlink(tmp)


def check_output_file(path, option: str, suffixes: tuple[str, ...] | None = None) -> pathlib.Path:
    """Check, before any work, that ``path`` can be written as a file; return it as a Path.

    Raises ``ValueError`` naming ``option`` (e.g. ``"--out"``) when the path is empty, is a
    folder, lies in a folder that does not exist (or is a file), cannot be written there, names
    an existing file that is read-only, or (with ``suffixes``) does not end in one of them.
    Nothing is left behind: writability is probed with a temporary file that is removed at once.
    """
    text = os.fspath(path)
    if not text:
        raise ValueError(f"{option}: the file name is empty")
    path = pathlib.Path(text)
    shown = repr(text)
    if path.is_dir():
        raise ValueError(f"{option} {shown} is a folder; give a file name")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {shown}: the file name must end in one of {', '.join(suffixes)}")
    parent = path.parent
    if not parent.exists():
        raise ValueError(f"{option} {shown}: the folder {str(parent)!r} does not exist")
    if not parent.is_dir():
        raise ValueError(f"{option} {shown}: {str(parent)!r} is a file, not a folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"{option} {shown} exists and is read-only")
    _probe_writable(parent, option, shown)
    return path


def check_output_dir(path, option: str) -> pathlib.Path:
    """Check, before any work, that figures can be written into the folder ``path`` (which is
    created only when they are). Raises ``ValueError`` naming ``option`` when the path is a file,
    when a folder above it is a file, or when the nearest existing folder is not writable."""
    text = os.fspath(path)
    if not text:
        raise ValueError(f"{option}: the folder name is empty")
    path = pathlib.Path(text)
    shown = repr(text)
    existing = path
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if not existing.is_dir():
        what = "is a file" if existing == path else f"lies under {str(existing)!r}, which is a file"
        raise ValueError(f"{option} {shown} {what}; give a folder")
    _probe_writable(existing, option, shown)
    return path


def json_safe(obj) -> tuple[Any, list[str]]:
    """``obj`` with every non-finite float (NaN, ±inf) replaced by None, and the paths of the
    replaced values ("stderr.beta", "loss[3]"), so that ``json.dumps(..., allow_nan=False)``
    gives valid JSON and the caller can report what was not finite. Numpy and JAX arrays and
    scalars become lists and Python numbers."""
    bad: list[str] = []

    def walk(value, where):
        if isinstance(value, dict):
            return {str(k): walk(v, f"{where}.{k}" if where else str(k)) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [walk(v, f"{where}[{i}]") for i, v in enumerate(value)]
        if isinstance(value, (np.ndarray, jax.Array)):
            return walk(np.asarray(value).tolist(), where)
        if isinstance(value, (np.bool_, bool)):
            return bool(value)
        if isinstance(value, np.integer):
            return int(value)
        if isinstance(value, (float, np.floating)):
            if math.isfinite(value):
                return float(value)
            bad.append(where or "value")
            return None
        return value

    return walk(obj, ""), bad


def print_json(summary: dict, compact: bool) -> list[str]:
    """Print ``summary`` as valid JSON: non-finite numbers become null and their paths are listed
    under ``"nonfinite"``; any other object that JSON cannot hold (a path) as its text. Returns that
    list (empty when every number was finite)."""
    summary, bad = json_safe(summary)
    if bad:
        summary["nonfinite"] = bad
    print(json.dumps(summary, allow_nan=False, default=str, indent=None if compact else 2))
    return bad


def check_figure_file(path, option: str):
    """A figure file: matplotlib installed, a format it writes, a place it can be written."""
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        raise ValueError(f"{option} needs matplotlib: pip install 'jaxmpm[plot]'")
    from matplotlib.figure import Figure

    kinds = tuple("." + k for k in Figure().canvas.get_supported_filetypes())
    return check_output_file(path, option, suffixes=kinds)


def check_run_outputs(args, frames: int) -> None:
    """Every output of ``python -m jaxmpm run`` (--out, --ply, --profile-csv, --plot, --gif) is
    checked before the scene is built or anything compiles; no two name the same file."""
    import importlib.util

    named = [(opt, getattr(args, attr)) for opt, attr in
             (("--out", "out"), ("--profile-csv", "profile_csv"), ("--plot", "plot"), ("--gif", "gif"))
             if getattr(args, attr)]
    if args.out:
        check_output_file(args.out, "--out")
    if getattr(args, "ply", None):
        check_output_dir(args.ply, "--ply")
    if args.profile_csv:
        check_output_file(args.profile_csv, "--profile-csv")
    if args.plot:
        check_figure_file(args.plot, "--plot")
    if args.gif:
        if importlib.util.find_spec("matplotlib") is None:
            raise ValueError("--gif needs matplotlib: pip install 'jaxmpm[plot]'")
        if importlib.util.find_spec("PIL") is None:
            raise ValueError("--gif needs Pillow: pip install pillow")
        if frames < 1:
            raise ValueError(f"--gif animates the frames: --frames must be >= 1, got {frames}")
        check_output_file(args.gif, "--gif", suffixes=(".gif",))
    seen: dict[str, str] = {}
    for option, path in named:
        key = os.path.realpath(path)
        if key in seen:
            raise ValueError(f"{seen[key]} and {option} name the same file {path!r}")
        seen[key] = option


def output_writer(errors: dict):
    """``output(option, write)``: call ``write()``; on an I/O failure record it in ``errors``
    under ``option`` and return None, so that the other outputs and the summary still appear."""

    def output(option, write):
        try:
            return write()
        except (OSError, ValueError, RuntimeError) as err:
            errors[option] = f"{type(err).__name__}: {err}"
            return None

    return output


