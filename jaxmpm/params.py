"""Material parameters: one table of what each key means, and one pytree of float arrays.

Every parameter of docs/model.md §4 is a leaf of ``Params``, so that ``jax.grad``, ``jax.vmap``
and optax act on them without rebuilding anything. A material uses the leaves it needs
(``Material.keys``) and ignores the rest. Units are SI throughout.

``PARAMS`` is the one table of the keys: each ``ParamSpec`` holds the key's default, its SI unit
and the units a file may give it in, the rule a value must obey, the default bounds of a fit and
a one-line description. ``DEFAULTS``, ``PARAM_KEYS``, ``MATERIAL_KEYS``, the checks of
``validate_params`` and the experiment files' units (``jaxmpm.experiment``) are read from it.
A rule across keys is a ``Relation`` (``RELATIONS``: μ2 >= μ1). The glossary below is the table's
descriptions in short, with the SI units.

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
import types
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Params", "ParamSpec", "PARAMS", "PARAM_KEYS", "MATERIAL_KEYS", "DEFAULTS", "Relation", "RELATIONS", "Rule",
           "LENGTH_UNITS", "PURE_UNITS", "param_help", "param_problem", "validate_params"]

#: Unit names a file may use, with their factors to SI (the SI unit first).
LENGTH_UNITS: Mapping[str, float] = types.MappingProxyType({"m": 1.0, "cm": 1e-2, "mm": 1e-3})
_PRESSURE = types.MappingProxyType({"Pa": 1.0, "kPa": 1e3, "MPa": 1e6})
_DENSITY = types.MappingProxyType({"kg/m^3": 1.0, "kg/m3": 1.0, "g/cm^3": 1e3, "g/cm3": 1e3})
PURE_UNITS: Mapping[str, float] = types.MappingProxyType({"-": 1.0, "": 1.0})


class Rule(NamedTuple):
    """What a value must satisfy: ``test`` (numpy array -> boolean array) and its ``text``."""

    test: Callable[[np.ndarray], Any]
    text: str


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """One parameter key: its default (docs/model.md §4), its SI unit's symbol, the units a file
    may give it in (name -> factor to SI), the rule every value obeys, the default bounds
    (lo, hi) of a fit (None: not fitted by default) and a one-line description."""

    name: str
    default: float
    unit: str
    units: Mapping[str, float]
    rule: Rule
    fit_bounds: tuple[float, float] | None
    description: str


def _spec(name, default, unit, units, rule, fit_bounds, description) -> ParamSpec:
    return ParamSpec(name, float(default), unit, units, rule, fit_bounds, description)


_POSITIVE = Rule(lambda v: v > 0, "> 0")
_NON_NEGATIVE = Rule(lambda v: v >= 0, ">= 0")

#: The parameter table, in the order of ``Params``'s leaves. Defaults: glass beads, the
#: reference code's scene values; fit bounds: wide physical limits, not priors (μ1, μ2, μ_w
#: from tan 3° to tan 63°).
PARAMS: dict[str, ParamSpec] = {s.name: s for s in (
    _spec("E", 1.0e6, "Pa", _PRESSURE, _POSITIVE, (1e4, 1e9), "Young's modulus"),
    _spec("nu", 0.3, "-", PURE_UNITS, Rule(lambda v: (v > -1.0) & (v < 0.5), "in (-1, 0.5)"), (0.0, 0.49),
          "Poisson's ratio"),
    _spec("rho", 1550.0, "kg/m^3", _DENSITY, _POSITIVE, None, "bulk density; a particle's mass is rho V0"),
    _spec("rho_s", 2500.0, "kg/m^3", _DENSITY, _POSITIVE, None, "grain density (enters the inertial number only)"),
    _spec("d", 0.7e-3, "m", LENGTH_UNITS, _POSITIVE, (1e-5, 0.1), "grain diameter"),
    _spec("mu1", math.tan(math.radians(20.9)), "-", PURE_UNITS, _NON_NEGATIVE, (0.05, 2.0),
          "static friction coefficient of the mu(I) law"),
    _spec("mu2", math.tan(math.radians(32.76)), "-", PURE_UNITS, _NON_NEGATIVE, (0.05, 2.0),
          "limiting friction coefficient of the mu(I) law"),
    _spec("I0", 0.279, "-", PURE_UNITS, _POSITIVE, (1e-3, 3.0), "reference inertial number"),
    _spec("beta", 0.0, "-", PURE_UNITS, _NON_NEGATIVE, (0.0, 1.0),
          "cohesion: ratio of tensile to compressive strength"),
    _spec("pc0", 100.0, "Pa", _PRESSURE, _NON_NEGATIVE, (1.0, 1e5), "initial compressive strength p_c"),
    _spec("xi", 0.0, "-", PURE_UNITS, _NON_NEGATIVE, (0.0, 500.0), "hardening rate"),
    _spec("mu_w", 0.0, "-", PURE_UNITS, _NON_NEGATIVE, (0.0, 2.0),
          "Coulomb friction of the walls and terrains declared with friction=\"mu_w\""),
)}


class Relation(NamedTuple):
    """A rule across two keys: ``key`` must be >= ``other``; ``why`` says what ``key`` is."""

    key: str
    other: str
    why: str


#: μ2 is the limiting friction of μ(I) = μ1 + (μ2 - μ1) I/(I0 + I): below μ1 the law would be
#: rate-weakening, which docs/model.md's rheology is not.
RELATIONS: tuple[Relation, ...] = (Relation("mu2", "mu1", "the limiting friction"),)

#: Defaults of docs/model.md §4 (glass beads, the reference code's scene values).
DEFAULTS: dict[str, float] = {k: s.default for k, s in PARAMS.items()}
PARAM_KEYS: tuple[str, ...] = tuple(PARAMS)
#: The keys of the material itself (μ_w belongs to a scene's walls and terrain).
MATERIAL_KEYS: tuple[str, ...] = tuple(k for k in PARAM_KEYS if k != "mu_w")


def param_help() -> str:
    """The keys with their SI units, for a command line's help: ``"E [Pa], nu [-], ..."``."""
    return ", ".join(f"{k} [{s.unit}]" for k, s in PARAMS.items())


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


def param_problem(key: str, value) -> str | None:
    """What is wrong with ``value`` (a number or an array of members) as parameter ``key``
    (``"must be finite, got nan"``, ``"must be > 0, got -1.0"``), or None when every member obeys
    ``PARAMS[key].rule``."""
    try:
        value = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return f"must be a real number, got {value!r}"
    if not np.all(np.isfinite(value)):
        return f"must be finite, got {_show(value)}"
    rule = PARAMS[key].rule
    bad = ~np.asarray(rule.test(value))
    if np.any(bad):
        return f"must be {rule.text}, got {_show(value[bad] if value.ndim else value)}"
    return None


def validate_params(params: Params | Mapping[str, Any]) -> None:
    """Raise ``ValueError`` naming the first parameter that is non-finite or out of range
    (``PARAMS``' rules), then the first broken ``RELATIONS``.

    Works on scalars and on batched leaves (every member is checked). Leaves that are tracers
    are skipped: validation belongs before tracing, at the public entry points.
    """
    get = params.get if isinstance(params, Mapping) else lambda k: getattr(params, k)
    for key in PARAMS:
        value = get(key)
        problem = None if isinstance(value, jax.core.Tracer) else param_problem(key, value)
        if problem is not None:
            raise ValueError(f"{key} {problem}")
    for relation in RELATIONS:
        key, other = _concrete(get(relation.key)), _concrete(get(relation.other))
        if key is None or other is None:
            continue
        key, other = np.broadcast_arrays(key, other)
        bad = key < other
        if np.any(bad):
            raise ValueError(f"{relation.key} ({relation.why}) must be >= {relation.other}, got "
                             f"{relation.other} = {_show(other[bad] if other.ndim else other)} and "
                             f"{relation.key} = {_show(key[bad] if key.ndim else key)}")


def _show(value: np.ndarray) -> str:
    value = np.asarray(value)
    return repr(float(value.reshape(()))) if value.size == 1 else np.array2string(value, threshold=6)
