"""Materials: small final classes behind the ``Material`` interface."""

from .base import Material, invariants, lame
from .critical_state import CriticalState, mu_of_I, return_invariants, return_map, yield_function
from .hencky import Hencky, hencky_strain, hencky_stress

__all__ = [
    "CriticalState", "Hencky", "Material", "hencky_strain", "hencky_stress", "invariants", "lame",
    "mu_of_I", "return_invariants", "return_map", "yield_function",
]
