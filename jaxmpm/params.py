"""Material parameters: one pytree of float arrays.

Every parameter of docs/model.md §4 is a leaf, so that ``jax.grad``, ``jax.vmap`` and optax act on
them without rebuilding anything. A material uses the leaves it needs and ignores the rest.
Units are SI throughout.

Glossary
--------
E, nu      Young's modulus [Pa] and Poisson's ratio [-]
rho        bulk density [kg/m^3]; particle mass is rho * V0
rho_s      grain density [kg/m^3] (enters the inertial number only)
d          grain diameter [m]
mu1, mu2   static and limiting friction coefficients of the mu(I) law [-]
I0         reference inertial number [-]
beta       cohesion: ratio of tensile to compressive strength [-]
pc0        initial compressive strength p_c [Pa]
xi         hardening rate [-]
mu_w       Coulomb friction of the walls and terrains declared with ``friction="mu_w"`` [-]
           (a parameter, so that it can be differentiated and calibrated; 0 by default)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Params", "PARAM_KEYS", "MATERIAL_KEYS", "DEFAULTS", "validate_params"]

#: Defaults of docs/model.md §4 (glass beads, the reference code's scene values).
DEFAULTS: dict[str, float] = {
    "E": 1.0e6,
    "nu": 0.3,
    "rho": 1550.0,
    "rho_s": 2500.0,
    "d": 0.7e-3,
    "mu1": math.tan(math.radians(20.9)),
    "mu2": math.tan(math.radians(32.76)),
    "I0": 0.279,
    "beta": 0.0,
    "pc0": 100.0,
    "xi": 0.0,
    "mu_w": 0.0,
}
PARAM_KEYS: tuple[str, ...] = tuple(DEFAULTS)
#: The keys of the material itself (μ_w belongs to a scene's walls and terrain).
MATERIAL_KEYS: tuple[str, ...] = tuple(k for k in PARAM_KEYS if k != "mu_w")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Params:
    """Material parameters (see the module glossary). All fields are float arrays."""

    E: Any
    nu: Any
    rho: Any
    rho_s: Any
    d: Any
    mu1: Any
    mu2: Any
    I0: Any
    beta: Any
    pc0: Any
    xi: Any
    mu_w: Any

    @classmethod
    def create(cls, dtype=None, **values: float) -> Params:
        """Defaults of docs/model.md §4 overridden by ``values``, validated, as arrays of ``dtype``.

        ``dtype`` defaults to JAX's default float type (float32 unless x64 is enabled).
        """
        unknown = sorted(set(values) - set(PARAM_KEYS))
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {unknown}; valid keys are {list(PARAM_KEYS)}"
            )
        merged = {**DEFAULTS, **values}
        for key, value in merged.items():
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"{key} must be a real number, got {value!r}") from None
            merged[key] = arr
        validate_params(merged)
        dtype = jnp.dtype(dtype) if dtype is not None else jnp.zeros(()).dtype
        return cls(**{k: jnp.asarray(v, dtype=dtype) for k, v in merged.items()})

    def replace(self, **values) -> Params:
        """A copy with some leaves replaced (no validation: this is used inside traced code)."""
        return dataclasses.replace(self, **values)

    def to_dict(self) -> dict[str, Any]:
        """Leaves by key, as numpy arrays (or Python floats for scalars)."""
        out = {}
        for key in PARAM_KEYS:
            arr = np.asarray(getattr(self, key))
            out[key] = float(arr) if arr.ndim == 0 else arr
        return out


def _concrete(value) -> np.ndarray | None:
    """The value as a numpy array, or None when it is a tracer (inside jit/vmap/grad)."""
    if isinstance(value, jax.core.Tracer):
        return None
    return np.asarray(value, dtype=float)


# (key, test, what the test requires) for the checks a material-independent caller can make.
_RULES: tuple[tuple[str, Any, str], ...] = (
    ("E", lambda v: v > 0, "> 0"),
    ("nu", lambda v: (v > -1.0) & (v < 0.5), "in (-1, 0.5)"),
    ("rho", lambda v: v > 0, "> 0"),
    ("rho_s", lambda v: v > 0, "> 0"),
    ("d", lambda v: v > 0, "> 0"),
    ("mu1", lambda v: v >= 0, ">= 0"),
    ("mu2", lambda v: v >= 0, ">= 0"),
    ("I0", lambda v: v > 0, "> 0"),
    ("beta", lambda v: v >= 0, ">= 0"),
    ("pc0", lambda v: v >= 0, ">= 0"),
    ("xi", lambda v: v >= 0, ">= 0"),
    ("mu_w", lambda v: v >= 0, ">= 0"),
)


def validate_params(params: Params | Mapping[str, Any]) -> None:
    """Raise ``ValueError`` naming the first parameter that is non-finite or out of range.

    Works on scalars and on batched leaves (every member is checked). Leaves that are tracers
    are skipped: validation belongs before tracing, at the public entry points.
    """
    get = params.get if isinstance(params, Mapping) else lambda k: getattr(params, k)
    for key, rule, requirement in _RULES:
        value = _concrete(get(key))
        if value is None:
            continue
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{key} must be finite, got {_show(value)}")
        bad = ~np.asarray(rule(value))
        if np.any(bad):
            raise ValueError(f"{key} must be {requirement}, got {_show(value[bad] if value.ndim else value)}")
    # μ2 is the limiting friction of μ(I) = μ1 + (μ2 - μ1) I/(I0 + I): below μ1 the law would be
    # rate-weakening, which docs/model.md's rheology is not.
    mu1, mu2 = _concrete(get("mu1")), _concrete(get("mu2"))
    if mu1 is not None and mu2 is not None:
        mu1, mu2 = np.broadcast_arrays(mu1, mu2)
        bad = mu2 < mu1
        if np.any(bad):
            raise ValueError("mu2 (the limiting friction) must be >= mu1, got "
                             f"mu1 = {_show(mu1[bad] if mu1.ndim else mu1)} and "
                             f"mu2 = {_show(mu2[bad] if mu2.ndim else mu2)}")


def _show(value: np.ndarray) -> str:
    value = np.asarray(value)
    return repr(float(value.reshape(()))) if value.size == 1 else np.array2string(value, threshold=6)
