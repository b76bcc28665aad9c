"""Hencky (logarithmic) hyperelasticity (docs/model.md §1).

With the left stretch b = F_e F_eᵀ, the spatial Hencky strain is ε = ½ log b (= U log Σ Uᵀ for
F_e = U Σ Vᵀ) and the Kirchhoff stress is τ = λ tr(ε) I + 2G ε. ``sym_log`` has a custom
derivative, so gradients are finite at F_e = I and at any repeated stretch.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from ..linalg import planes, sym_log_planes, unplanes
from .base import Material, lame

__all__ = ["Hencky", "hencky_strain", "hencky_stress", "hencky_strain_planes"]


def hencky_strain_planes(F):
    """½ log(F Fᵀ) of a deformation gradient held as planes (``jaxmpm.linalg``)."""
    dim = len(F)
    b = [[sum(F[i][k] * F[j][k] for k in range(dim)) for j in range(dim)] for i in range(dim)]
    for i in range(dim):  # F Fᵀ is symmetric: share the planes
        for j in range(i):
            b[i][j] = b[j][i]
    return [[0.5 * c for c in row] for row in sym_log_planes(b)]


def _stress_planes(F, params):
    G, lam = lame(params)
    eps = hencky_strain_planes(F)
    trace = sum(eps[i][i] for i in range(len(F)))
    return [[(lam * trace if i == j else 0.0) + 2.0 * G * e for j, e in enumerate(row)] for i, row in enumerate(eps)]


def hencky_strain(F):
    """Spatial Hencky strain ½ log(F Fᵀ) of deformation gradients (..., d, d)."""
    return unplanes(hencky_strain_planes(planes(F)))


def hencky_stress(F, params):
    """Kirchhoff stress τ of Hencky elasticity for deformation gradients (..., d, d)."""
    return unplanes(_stress_planes(planes(F), params))


@dataclasses.dataclass(frozen=True)
class Hencky(Material):
    """Purely elastic material: the trial state is the final state."""

    keys: ClassVar[tuple[str, ...]] = ("E", "nu", "rho")

    def init_internal(self, n, dtype):
        return {}

    def update_planes(self, F_trial, internal, params, dt):
        return F_trial, _stress_planes(F_trial, params), internal
