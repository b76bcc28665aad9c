"""Scene builders: each returns a ``Scene`` that unpacks as ``(config, state, params)``."""

from .collapse import (
    S2_PARAMS, S3_PARAMS, S4_PARAMS, S5_PARAMS, Scene, aspect_ratio_collapse, cohesive_collapse, collapse,
    gates_collapse, height_law, runout_law, slope_collapse,
)
from .elastic import falling_block
from .incline import S1_PARAMS, bagnold_velocity, incline

__all__ = [
    "S1_PARAMS", "bagnold_velocity", "incline", "S2_PARAMS", "S3_PARAMS", "S4_PARAMS", "S5_PARAMS", "Scene", "aspect_ratio_collapse", "cohesive_collapse",
    "collapse", "falling_block", "gates_collapse", "height_law", "runout_law", "slope_collapse",
]
