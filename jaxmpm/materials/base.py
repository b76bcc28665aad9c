"""The interface every material implements, and stress invariants shared by all of them.

A material is a small frozen dataclass (static configuration: hashable, part of ``Config``).
Its methods are pure functions of arrays; parameters come in as a ``Params`` pytree, of which it
reads the leaves its ``keys`` name (the rest, e.g. μ_w of the walls, are not its own).
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import jax.numpy as jnp

from ..linalg import planes, safe_sqrt, trace, unplanes

__all__ = ["Material", "invariants", "lame", "P_WAVE_RATIO_MAX"]

#: The largest c_p / sqrt(E/ρ) = sqrt((1 − ν) / ((1 + ν)(1 − 2ν))) for which the time step keeps
#: the reference code's rule dt = cfl_e dx / sqrt(E/ρ) (1.16 at ν = 0.3; 1.2 at ν = 0.322).
P_WAVE_RATIO_MAX = 1.2


def lame(params):
    """Shear modulus G and Lamé's first parameter λ from E and ν (docs/model.md §1)."""
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
    """Constitutive update of the elastic deformation gradient and Kirchhoff stress.

    A material implements ``update_planes``, on matrices held as planes (lists of (N,) arrays,
    ``jaxmpm.linalg``), which the time step calls; ``update`` is the same on (N, d, d) arrays.
    ``keys``: the parameters (``jaxmpm.params.PARAMS``) its update and ``wave_speed`` read."""

    keys: ClassVar[tuple[str, ...]] = ()

    @abc.abstractmethod
    def init_internal(self, n: int, dtype) -> dict[str, Any]:
        """Internal variables of ``n`` stress-free particles, as a dict of (n,) arrays."""

    @abc.abstractmethod
    def update_planes(self, F_trial, internal, params, dt):
        """(F_e, τ, internal) after the step, from the trial elastic deformation gradient; F and τ
        as planes [[(N,) arrays]]."""

    def update(self, F_trial, internal, params, dt):
        """(F_e, τ, internal) after the step, from the trial elastic deformation gradient (N, d, d)."""
        F, tau, internal = self.update_planes(planes(F_trial), internal, params, dt)
        return unplanes(F), unplanes(tau), internal

    def wave_speed(self, params):
        """Elastic wave speed c of the time-step bound cfl_e·dx/c.

        docs/model.md §5 and the reference code use c = sqrt(E/ρ). That is below the P-wave speed
        c_p = sqrt((λ + 2G)/ρ) (by 1.16 at ν = 0.3, by 13 at ν = 0.499), so as ν -> 0.5 the
        P-wave Courant number cfl_e·c_p/c grows without bound and the run goes unstable while no
        status bit fires. Here c = max(sqrt(E/ρ), c_p / P_WAVE_RATIO_MAX): the reference rule
        wherever c_p <= 1.2 sqrt(E/ρ), that is for −0.45 <= ν <= 0.322 (the same steps as the
        reference code, and no kink of dt(ν) near the default ν = 0.3, so d/dν stays smooth),
        and outside it a bound that keeps the P-wave Courant number at 1.2 cfl_e (0.6)."""
        G, lam = lame(params)
        c_e = jnp.sqrt(params.E / params.rho)
        c_p = jnp.sqrt((lam + 2.0 * G) / params.rho)
        return jnp.maximum(c_e, c_p / P_WAVE_RATIO_MAX)
