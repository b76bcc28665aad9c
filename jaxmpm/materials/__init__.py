"""Materials: small final classes behind the ``Material`` interface."""

from .base import Material, invariants, lame
from .hencky import Hencky, hencky_strain, hencky_stress

__all__ = ["Material", "Hencky", "invariants", "lame", "hencky_strain", "hencky_stress"]
