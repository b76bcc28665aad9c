"""Scene builders: each returns a ``Scene`` that unpacks as ``(config, state, params)``."""

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
    "SCENE_NAMES", "add_scene_arguments", "build_scene", "parse_set", "scene_from_args",
    "DEFAULT_PPC", "DEFAULT_SAMPLING", "S1_PARAMS", "bagnold_velocity", "incline", "S2_PARAMS", "S3_PARAMS",
    "S4_PARAMS", "S5_PARAMS", "S7_PARAMS", "Scene", "SceneInfo", "aluminium_bars", "aspect_ratio_collapse",
    "cohesive_collapse",
    "collapse", "falling_block", "gates_collapse", "height_law", "runout_law", "slope_collapse",
]

#: Scene names accepted by ``build_scene`` and the command line.
SCENE_NAMES = ("cohesive-collapse", "gates-collapse", "slope-collapse", "aspect-ratio", "aluminium-bars",
               "elastic-block")


def build_scene(name: str, dx=None, ppc=None, dim=2, width=None, t_end=None, frames=0, slope=None, aspect=None,
                dtype=None, values=None, sampling=None, seed=0):
    """A scene by its command-line name (``SCENE_NAMES``) with the command line's options:
    ``dx``, ``ppc``, ``sampling``, ``t_end`` None take the scene's defaults, ``values`` are
    material parameters."""
    values = dict(values or {})
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
        parser.add_argument("scene", choices=SCENE_NAMES)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    parser.add_argument("--dx", type=float, default=None, help="grid spacing, m (default: the scene's)")
    parser.add_argument("--ppc", type=float, default=None, help="particles per cell and axis (default: the "
                        "scene's, DEFAULT_PPC; an integer for lattice and jitter sampling)")
    parser.add_argument("--sampling", choices=("lattice", "jitter", "poisson"), default=None,
                        help="particle sampling (default: the scene's, DEFAULT_SAMPLING; poisson needs scipy)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of jitter and poisson sampling")
    parser.add_argument("--dim", type=int, default=2, choices=(2, 3))
    parser.add_argument("--width", type=float, default=None, help="channel width for --dim 3, m")
    parser.add_argument("--slope", type=float, default=None, help="bed angle for slope-collapse, degrees")
    parser.add_argument("--aspect", type=float, default=None, help="aspect ratio H0/L0 for aspect-ratio")
    parser.add_argument("--t-end", type=float, default=None, help="end time, s (default: the scene's)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")


def parse_set(item: str) -> tuple[str, float]:
    """``key=value`` from ``--set`` (value a number)."""
    key, sep, value = item.partition("=")
    if not sep:
        raise ValueError(f"--set expects key=value, got {item!r}")
    try:
        return key.strip(), float(value)
    except ValueError:
        raise ValueError(f"--set {key}: value must be a number, got {value!r}") from None


def scene_from_args(args, name: str | None = None, frames: int = 0):
    """Build the scene that ``add_scene_arguments``' options describe."""
    values = dict(parse_set(item) for item in args.set)
    return build_scene(name or args.scene, dx=args.dx, ppc=args.ppc, dim=args.dim, width=args.width,
                       t_end=args.t_end, frames=frames, slope=args.slope, aspect=args.aspect, dtype=args.dtype,
                       values=values, sampling=args.sampling, seed=args.seed)
