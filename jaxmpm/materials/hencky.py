"""Hencky (logarithmic) hyperelasticity (docs/model.md §1).

With the left stretch b = F_e F_eᵀ, the spatial Hencky strain is ε = ½ log b (= U log Σ Uᵀ for
F_e = U Σ Vᵀ) and the Kirchhoff stress is τ = λ tr(ε) I + 2G ε. ``sym_log`` has a custom
derivative, so gradients are finite at F_e = I and at any repeated stretch.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from ..linalg import mm, mt, sym_log, trace
from .base import Material, lame

__all__ = ["Hencky", "hencky_strain", "hencky_stress"]


def hencky_strain(F):
    """Spatial Hencky strain ½ log(F Fᵀ) of deformation gradients (..., d, d)."""
    return 0.5 * sym_log(mm(F, mt(F)))


def hencky_stress(F, params):
    """Kirchhoff stress τ of Hencky elasticity for deformation gradients (..., d, d)."""
    G, lam = lame(params)
    eps = hencky_strain(F)
    eye = jnp.eye(F.shape[-1], dtype=F.dtype)
    return lam * trace(eps)[..., None, None] * eye + 2.0 * G * eps


@dataclasses.dataclass(frozen=True)
class Hencky(Material):
    """Purely elastic material: the trial state is the final state."""

    def init_internal(self, n, dtype):
        return {}

    def update(self, F_trial, internal, params, dt):
        return F_trial, hencky_stress(F_trial, params), internal
