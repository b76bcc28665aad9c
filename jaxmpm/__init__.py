"""jaxmpm: a differentiable Material Point Method in JAX for granular flows.

The public surface: static configuration (``Grid``, ``Config``, ``Wall``, materials), the
parameter table (``PARAMS`` of ``ParamSpec``) and pytree (``Params``), the state (``State``,
``init_state``), particle sampling (``seed_box``), the pure step and rollout factories, the public
``simulate`` call, HDF5 output (``io``) and the CSV format (``tables``).
"""

from importlib import metadata as _metadata

from . import io, scenes, tables
from ._version import __version__ as __version__  # the one source of the version (pyproject.toml reads it)
from .boundary import SideWalls, Terrain, Wall
from .config import Config, Grid
from .experiment import Experiment, ExperimentError
from .materials import CriticalState, Hencky, Material, hencky_stress, invariants
from .params import DEFAULTS, MATERIAL_KEYS, PARAM_KEYS, PARAMS, Params, ParamSpec, validate_params
from .rollout import frame_observer, make_rollout
from .sampling import SAMPLINGS, seed_box
from .simulate import Result, SimulationError, compiled_rollout, simulate
from .state import (
    BUDGET,
    EDGE,
    GRID_FULL,
    J_NONPOSITIVE,
    LEFT_GRID,
    NONFINITE,
    State,
    describe_status,
    init_state,
)
from .step import make_step


def _warn_known_bad_jaxlib():
    import warnings

    try:
        version = _metadata.version("jaxlib")
    except _metadata.PackageNotFoundError:
        return
    if version == "0.10.2":
        warnings.warn(
            "jaxlib 0.10.2 miscompiles jaxmpm's step on the CPU under forward-mode Jacobians "
            "(jacfwd in one parameter returns NaN tangents at random; jax-ml/jax#39103 is another "
            "CPU miscompile of that release). Install jax/jaxlib 0.10.1 or a release after 0.10.2.",
            RuntimeWarning, stacklevel=2,
        )


_warn_known_bad_jaxlib()

__all__ = [
    "BUDGET", "Config", "Experiment", "ExperimentError", "CriticalState", "EDGE", "DEFAULTS", "GRID_FULL", "Grid",
    "Hencky", "J_NONPOSITIVE",
    "LEFT_GRID", "Material", "MATERIAL_KEYS", "NONFINITE", "PARAM_KEYS", "PARAMS", "Params", "ParamSpec", "Result",
    "SAMPLINGS",
    "SideWalls", "SimulationError", "State", "Terrain", "Wall",
    "compiled_rollout", "describe_status", "frame_observer", "hencky_stress", "init_state",
    "invariants", "io", "make_rollout", "make_step", "scenes", "seed_box", "simulate", "tables", "validate_params",
]
