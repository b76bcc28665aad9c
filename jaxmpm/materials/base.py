"""The interface every material implements, and stress invariants shared by all of them.

A material is a small frozen dataclass (static configuration: hashable, part of ``Config``).
Its methods are pure functions of arrays; parameters come in as a ``Params`` pytree.
"""

from __future__ import annotations

import abc
from typing import Any

import jax.numpy as jnp

from ..linalg import safe_sqrt, trace

__all__ = ["Material", "invariants", "lame"]


def lame(params):
    """Shear modulus G and Lamé's first parameter λ from E and ν (MODEL.md §1)."""
    G = params.E / (2.0 * (1.0 + params.nu))
    lam = params.E * params.nu / ((1.0 + params.nu) * (1.0 - 2.0 * params.nu))
    return G, lam


def invariants(tau):
    """Pressure p = -tr(τ)/dim (compression positive) and q = sqrt(½ s:s) of stresses (..., d, d)."""
    dim = tau.shape[-1]
    p = -trace(tau) / dim
    s = tau + p[..., None, None] * jnp.eye(dim, dtype=tau.dtype)
    q = safe_sqrt(0.5 * jnp.sum(s * s, axis=(-2, -1)))
    return p, q


class Material(abc.ABC):
    """Constitutive update of the elastic deformation gradient and Kirchhoff stress."""

    @abc.abstractmethod
    def init_internal(self, n: int, dtype) -> dict[str, Any]:
        """Internal variables of ``n`` stress-free particles, as a dict of (n,) arrays."""

    @abc.abstractmethod
    def update(self, F_trial, internal, params, dt):
        """(F_e, τ, internal) after the step, from the trial elastic deformation gradient."""

    def wave_speed(self, params):
        """Elastic wave speed used by the time-step bound cfl_e·dx/c (MODEL.md §5: sqrt(E/ρ))."""
        return jnp.sqrt(params.E / params.rho)
