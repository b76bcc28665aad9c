"""Scene builders: each returns a ``Scene`` that unpacks as ``(config, state, params)``.

The named collapses S2–S5 and S7 are their shipped experiment files (``named``: ``named_experiment``
and the builders read them), built by the common builder ``collapse``; the incline (S1), the
elastic block and the avalanche are built in Python. The constants S2_LENGTH, ..., S7_PARAMS are
read from the files when first asked for."""

from .base import Scene
from .collapse import (
    DEFAULT_PPC,
    DEFAULT_SAMPLING,
    aspect_column,
    collapse,
    height_law,
    runout_law,
)
from .elastic import falling_block
from .incline import S1_DEPTH, S1_PARAMS, bagnold_velocity, incline
from .info import SceneInfo
from .named import (
    CONSTANTS,
    aluminium_bars,
    aspect_member,
    aspect_ratio_collapse,
    cohesive_collapse,
    gates_collapse,
    named_experiment,
    slope_collapse,
    slope_member,
)

__all__ = [
    "SCENE_NAMES", "is_experiment_file", "experiments_dtype", "build_scene", "named_experiment", "slope_member",
    "aspect_member", "DEFAULT_PPC", "DEFAULT_SAMPLING", "S1_DEPTH", "S1_PARAMS", "bagnold_velocity", "incline",
    "S2_HEIGHT", "S2_LENGTH", "S3_HEIGHT", "S3_LENGTH", "S4_SIDE", "S5_LENGTH", "S7_HEIGHT", "S7_LENGTH", "S7_PARAMS",
    "Scene", "SceneInfo", "aluminium_bars", "aspect_column", "aspect_ratio_collapse", "cohesive_collapse", "collapse",
    "falling_block", "gates_collapse", "height_law", "runout_law", "slope_collapse",
]

# The named scenes' dimensions and S7's material: their shipped files' values, given by
# __getattr__ below (jaxmpm.scenes.named reads them when first asked for); annotated here so that
# readers and tools see the names.
#: S2's column length, m (``S2_gates_collapse.toml`` [geometry] length).
S2_LENGTH: float
#: S2's column height, m.
S2_HEIGHT: float
#: S3's column length, m (``S3_slope_collapse.toml``).
S3_LENGTH: float
#: S3's column height, m.
S3_HEIGHT: float
#: S4's column: a square of this side, m (``S4_cohesive_collapse.toml``).
S4_SIDE: float
#: S5's column length L0, m (``S5_aspect_ratio.toml``; the height is a L0).
S5_LENGTH: float
#: S7's column length, m (``S7_aluminium_bars.toml``).
S7_LENGTH: float
#: S7's column height, m.
S7_HEIGHT: float
#: S7's material (``S7_aluminium_bars.toml`` [material], every value with its source there).
S7_PARAMS: dict[str, float]

#: Scene names accepted by ``build_scene`` and the command line.
SCENE_NAMES = ("cohesive-collapse", "gates-collapse", "slope-collapse", "aspect-ratio", "aluminium-bars",
               "elastic-block")


def __getattr__(name: str):
    # The named scenes' dimensions and S7's material, read from their shipped files on first use
    # (jaxmpm.scenes.named).
    if name in CONSTANTS:
        from . import named

        return getattr(named, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def is_experiment_file(scene: str) -> bool:
    """Whether a command line's SCENE names an experiment file (``*.toml``) rather than a scene."""
    return str(scene).endswith(".toml")


def build_scene(name: str, dx=None, ppc=None, dim=None, width=None, t_end=None, frames=0, slope=None, aspect=None,
                dtype=None, values=None, sampling=None, seed=None, side_walls=None):
    """A scene by its command-line name (``SCENE_NAMES``) with the command line's options:
    ``dx``, ``ppc``, ``sampling``, ``t_end`` None take the scene's defaults, ``values`` are
    material parameters, ``side_walls`` a 2D collapse's channel walls (``jaxmpm.SideWalls``). The
    collapses are their shipped experiment files with these options over them
    (``named_experiment(...).scene()``), as a user's file would be; elastic-block, not a collapse,
    is ``falling_block`` (it takes no side walls)."""
    if name not in SCENE_NAMES:
        raise ValueError(f"scene must be one of {SCENE_NAMES}, got {name!r}")
    if name != "elastic-block":
        return named_experiment(name, dx=dx, ppc=ppc, dim=dim, width=width, t_end=t_end, frames=frames, slope=slope,
                                aspect=aspect, dtype=dtype, values=values, sampling=sampling, seed=seed,
                                side_walls=side_walls).scene()
    if side_walls is not None:
        raise ValueError(f"--side-walls applies to the collapses, not {name} (a block falling in the open)")
    for option, value in (("slope", slope), ("aspect", aspect)):
        if value is not None:
            raise ValueError(f"--{option} applies to {'slope-collapse' if option == 'slope' else 'aspect-ratio'}, "
                             f"not {name}")
    if dim not in (None, 2) or width is not None:
        raise ValueError("elastic-block is 2D")
    if sampling not in (None, "lattice") or ppc not in (None, 2):
        raise ValueError("elastic-block is sampled on a 2 x 2 lattice (--ppc and --sampling do not apply)")
    return falling_block(n_particles=2_500, t_end=0.39 if t_end is None else t_end, frames=frames, dtype=dtype,
                         **dict(values or {}))


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
