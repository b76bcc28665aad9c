"""Scene builders: each returns ``(config, state0, params)`` ready for ``simulate``."""

from .collapse import S2_PARAMS, gates_collapse
from .elastic import falling_block

__all__ = ["S2_PARAMS", "falling_block", "gates_collapse"]
