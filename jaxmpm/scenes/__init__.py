"""Scene builders: each returns a ``Scene`` that unpacks as ``(config, state, params)``."""

from .collapse import (
    DEFAULT_PPC,
    DEFAULT_SAMPLING,
    S2_HEIGHT,
    S2_LENGTH,
    S2_PARAMS,
    S3_HEIGHT,
    S3_LENGTH,
    S3_PARAMS,
    S4_PARAMS,
    S4_SIDE,
    S5_LENGTH,
    S5_PARAMS,
    S7_HEIGHT,
    S7_LENGTH,
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
from .incline import S1_DEPTH, S1_PARAMS, bagnold_velocity, incline
from .info import SceneInfo

__all__ = [
    "SCENE_NAMES", "is_experiment_file", "experiments_dtype", "build_scene",
    "DEFAULT_PPC", "DEFAULT_SAMPLING", "S1_DEPTH", "S1_PARAMS", "bagnold_velocity", "incline", "S2_HEIGHT",
    "S2_LENGTH", "S2_PARAMS", "S3_HEIGHT", "S3_LENGTH", "S3_PARAMS", "S4_PARAMS", "S4_SIDE", "S5_LENGTH", "S5_PARAMS",
    "S7_HEIGHT", "S7_LENGTH", "S7_PARAMS", "Scene", "SceneInfo", "aluminium_bars", "aspect_ratio_collapse",
    "cohesive_collapse",
    "collapse", "falling_block", "gates_collapse", "height_law", "runout_law", "slope_collapse",
]

#: Scene names accepted by ``build_scene`` and the command line.
SCENE_NAMES = ("cohesive-collapse", "gates-collapse", "slope-collapse", "aspect-ratio", "aluminium-bars",
               "elastic-block")


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
