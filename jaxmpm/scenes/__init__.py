"""Scene builders: each returns a ``Scene`` that unpacks as ``(config, state, params)``."""

import math

from .collapse import (
    DEFAULT_PPC,
    DEFAULT_SAMPLING,
    S2_PARAMS,
    S3_PARAMS,
    S4_PARAMS,
    S5_PARAMS,
    S7_PARAMS,
    Scene,
    aluminium_bars,
    aspect_ratio_collapse,
    cohesive_collapse,
    collapse,
    gates_collapse,
    height_law,
    runout_law,
    slope_collapse,
)
from .elastic import falling_block
from .incline import S1_PARAMS, bagnold_velocity, incline
from .info import SceneInfo

__all__ = [
    "SCENE_NAMES", "is_experiment_file", "experiment_from_args", "scene_dtype", "experiments_dtype", "OPTION_FIELDS",
    "add_scene_arguments", "build_scene", "check_repeated_keys", "check_scene_args", "parse_set", "scene_from_args",
    "DEFAULT_PPC", "DEFAULT_SAMPLING", "S1_PARAMS", "bagnold_velocity", "incline", "S2_PARAMS", "S3_PARAMS",
    "S4_PARAMS", "S5_PARAMS", "S7_PARAMS", "Scene", "SceneInfo", "aluminium_bars", "aspect_ratio_collapse",
    "cohesive_collapse",
    "collapse", "falling_block", "gates_collapse", "height_law", "runout_law", "slope_collapse",
]

#: Scene names accepted by ``build_scene`` and the command line.
SCENE_NAMES = ("cohesive-collapse", "gates-collapse", "slope-collapse", "aspect-ratio", "aluminium-bars",
               "elastic-block")


#: The command line's scene options -> the ``Experiment`` field each sets.
OPTION_FIELDS = {"--dx": "dx", "--ppc": "ppc", "--sampling": "sampling", "--seed": "seed", "--dim": "dim",
                 "--width": "width", "--slope": "slope", "--t-end": "t_end", "--dtype": "dtype", "--frames": "frames"}


def is_experiment_file(scene: str) -> bool:
    """Whether a command line's SCENE names an experiment file (``*.toml``) rather than a scene."""
    return str(scene).endswith(".toml")


def build_scene(name: str, dx=None, ppc=None, dim=None, width=None, t_end=None, frames=0, slope=None, aspect=None,
                dtype=None, values=None, sampling=None, seed=None):
    """A scene by its command-line name (``SCENE_NAMES``) with the command line's options:
    ``dx``, ``ppc``, ``sampling``, ``t_end`` None take the scene's defaults, ``values`` are
    material parameters. The collapses with one geometry (cohesive-collapse, gates-collapse,
    aluminium-bars) are built from their shipped experiment files
    (``jaxmpm.experiment.SHIPPED_EXPERIMENTS``), as a user's file would be; slope-collapse and
    aspect-ratio, families over the slope and the aspect ratio, from their builders (their
    files describe the default member)."""
    values = dict(values or {})
    dim = 2 if dim is None else dim
    seed = 0 if seed is None else seed
    if name in ("cohesive-collapse", "gates-collapse", "aluminium-bars"):
        from ..experiment import shipped_experiment

        if slope is not None or aspect is not None:
            raise ValueError(f"--{'slope' if slope is not None else 'aspect'} applies to "
                             f"{'slope-collapse' if slope is not None else 'aspect-ratio'}, not {name}")
        if dim == 3 and width is None:
            raise ValueError("width (the channel width, m) is required when dim=3")
        options = dict(dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames, dtype=dtype,
                       sampling=sampling, seed=seed)
        flags = {field: field for field in options}
        return shipped_experiment(name).with_options(material=values, flags=flags, **options).scene()
    common = dict(ppc=ppc, dim=dim, width=width, frames=frames, dtype=dtype, sampling=sampling, seed=seed, **values)
    if t_end is not None:
        common["t_end"] = t_end
    if dx is not None:
        common["dx"] = dx
    if name != "slope-collapse" and slope is not None:
        raise ValueError(f"--slope applies to slope-collapse, not {name}")
    if name != "aspect-ratio" and aspect is not None:
        raise ValueError(f"--aspect applies to aspect-ratio, not {name}")
    if name == "cohesive-collapse":
        return cohesive_collapse(**common)
    if name == "gates-collapse":
        return gates_collapse(**common)
    if name == "slope-collapse":
        return slope_collapse(10.0 if slope is None else slope, **common)
    if name == "aspect-ratio":
        return aspect_ratio_collapse(1.0 if aspect is None else aspect, **common)
    if name == "aluminium-bars":
        return aluminium_bars(**common)
    if name == "elastic-block":
        if dim != 2 or width is not None:
            raise ValueError("elastic-block is 2D")
        if sampling not in (None, "lattice") or ppc not in (None, 2):
            raise ValueError("elastic-block is sampled on a 2 x 2 lattice (--ppc and --sampling do not apply)")
        return falling_block(n_particles=2_500, t_end=0.39 if t_end is None else t_end, frames=frames, dtype=dtype,
                             **values)
    raise ValueError(f"scene must be one of {SCENE_NAMES}, got {name!r}")


def add_scene_arguments(parser, scene_choices: bool = True) -> None:
    """The scene options shared by ``python -m jaxmpm run`` and ``python -m calibration``:
    SCENE (positional, optional), --set, --dx, --ppc, --sampling, --seed, --dim, --width, --slope,
    --aspect, --t-end, --dtype."""
    if scene_choices:
        parser.add_argument("scene", type=_scene_argument, metavar="SCENE|EXPERIMENT.toml",
                            help=f"a scene ({', '.join(SCENE_NAMES)}) or an experiment file")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    parser.add_argument("--dx", type=float, default=None, help="grid spacing, m (default: the scene's)")
    parser.add_argument("--ppc", type=float, default=None, help="particles per cell and axis (default: the "
                        "scene's, DEFAULT_PPC; an integer for lattice and jitter sampling)")
    parser.add_argument("--sampling", choices=("lattice", "jitter", "poisson"), default=None,
                        help="particle sampling (default: the scene's, DEFAULT_SAMPLING; poisson needs scipy)")
    parser.add_argument("--seed", type=int, default=None, help="random seed of jitter and poisson sampling "
                        "(default: the experiment's, else 0)")
    parser.add_argument("--dim", type=int, default=None, choices=(2, 3), help="2 or 3 (default: the experiment's, "
                        "else 2)")
    parser.add_argument("--width", type=float, default=None, help="channel width for --dim 3, m")
    parser.add_argument("--slope", type=float, default=None, help="bed angle for slope-collapse, degrees")
    parser.add_argument("--aspect", type=float, default=None, help="aspect ratio H0/L0 for aspect-ratio")
    parser.add_argument("--t-end", type=float, default=None, help="end time, s (default: the scene's)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default=None,
                        help="default: the experiment's, else float32")


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
        raise ValueError(f"--width applies to --dim 3 (a 3D channel), got --width {args.width} with --dim {args.dim}")
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
    from ..experiment import Experiment

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
        from ..experiment import Experiment

        return Experiment.from_toml(args.scene).dtype or "float32"
    return "float32"


def experiments_dtype(experiments, dtype: str | None = None) -> str:
    """The one floating-point type that ``experiments`` (``jaxmpm.Experiment``) run in together:
    ``dtype`` if given, else their files' (float32 where a file states none); files that
    disagree must be overruled."""
    if dtype:
        return dtype
    dtypes = sorted({e.dtype or "float32" for e in experiments})
    if len(dtypes) > 1:
        raise ValueError(f"the experiment files run in different dtypes ({dtypes}); give --dtype")
    return dtypes[0] if dtypes else "float32"


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
                       dtype=args.dtype or "float32",
                       values=values, sampling=args.sampling, seed=args.seed)


def _scene_argument(text: str) -> str:
    """argparse type of SCENE: a scene name or an experiment file."""
    import argparse

    if text in SCENE_NAMES or is_experiment_file(text):
        return text
    raise argparse.ArgumentTypeError(f"must be one of {', '.join(SCENE_NAMES)} or an experiment file (.toml), "
                                     f"got {text!r}")
