"""The one parameter table (``jaxmpm.params.PARAMS``): the names the rest of the code reads are
derived from it unchanged, its rules are the ones ``validate_params`` applies, its fit bounds are
calibration's defaults, and every material declares the keys it reads (and reads no other)."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.params import DEFAULTS, MATERIAL_KEYS, PARAM_KEYS, PARAMS, RELATIONS, param_help, validate_params

# The values every caller relied on before the table existed (docs/model.md §4).
BEFORE = {"E": 1.0e6, "nu": 0.3, "rho": 1550.0, "rho_s": 2500.0, "d": 0.7e-3, "mu1": math.tan(math.radians(20.9)),
          "mu2": math.tan(math.radians(32.76)), "I0": 0.279, "beta": 0.0, "pc0": 100.0, "xi": 0.0, "mu_w": 0.0}


def test_the_derived_names_keep_their_values_and_order():
    assert DEFAULTS == BEFORE and list(DEFAULTS) == list(BEFORE)
    assert PARAM_KEYS == tuple(BEFORE) == tuple(PARAMS)
    assert MATERIAL_KEYS == tuple(k for k in BEFORE if k != "mu_w")
    assert tuple(f.name for f in dataclasses.fields(jm.Params)) == PARAM_KEYS  # the pytree's leaves, in order
    assert jm.PARAMS is PARAMS and jm.ParamSpec is type(PARAMS["E"]) and {"PARAMS", "ParamSpec"} <= set(jm.__all__)


@pytest.mark.parametrize("key", PARAM_KEYS)
def test_each_entry_is_complete(key):
    spec = PARAMS[key]
    assert spec.name == key and spec.default == DEFAULTS[key]
    assert spec.units[spec.unit] == 1.0 and next(iter(spec.units)) == spec.unit  # the SI unit first
    assert spec.unit in ("Pa", "-", "kg/m^3", "m")
    assert spec.description and "\n" not in spec.description
    assert spec.rule.test(np.asarray(spec.default))  # the default obeys its own rule
    if spec.fit_bounds is not None:
        lo, hi = spec.fit_bounds
        assert lo < hi and spec.rule.test(np.asarray(hi))
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.default = 1.0
    with pytest.raises(TypeError):
        spec.units["furlong"] = 201.168  # the unit tables are read-only too



def test_the_glossary_names_each_key_with_its_unit():
    """The module's glossary (what a reader of params.py sees first) agrees with the table."""
    import jaxmpm.params

    glossary = jaxmpm.params.__doc__.split("Glossary\n--------\n")[1].splitlines()
    rows = {}
    for line in glossary:
        names, _, text = line.partition("  ")
        for name in names.split(", ") if names.strip() else ():
            rows[name.strip()] = text
    assert list(rows) == list(PARAM_KEYS)
    for key, text in rows.items():
        assert f"[{PARAMS[key].unit}]" in text, (key, text)

def test_fit_bounds_are_calibrations_defaults():
    from calibration import DEFAULT_BOUNDS

    assert DEFAULT_BOUNDS == {k: s.fit_bounds for k, s in PARAMS.items() if s.fit_bounds is not None}
    assert PARAMS["rho"].fit_bounds is None and PARAMS["rho_s"].fit_bounds is None


def test_param_help_lists_every_key_with_its_unit():
    text = param_help()
    assert text.startswith("E [Pa], nu [-], rho [kg/m^3], rho_s [kg/m^3], d [m], mu1 [-]")
    assert [item.split(" [")[0] for item in text.split(", ")] == list(PARAM_KEYS)


@pytest.mark.parametrize("key, value, message", [
    ("E", -1.0, "E must be > 0, got -1.0"),
    ("nu", 0.5, "nu must be in (-1, 0.5), got 0.5"),
    ("rho", 0.0, "rho must be > 0, got 0.0"),
    ("d", float("nan"), "d must be finite, got nan"),
    ("beta", -0.1, "beta must be >= 0, got -0.1"),
    ("mu_w", -0.2, "mu_w must be >= 0, got -0.2"),
])
def test_validate_params_applies_the_tables_rules(key, value, message):
    with pytest.raises(ValueError) as err:
        validate_params({**DEFAULTS, key: value})
    assert str(err.value) == message


def test_the_relation_mu2_at_least_mu1():
    assert RELATIONS[0][:2] == ("mu2", "mu1")
    with pytest.raises(ValueError, match=r"^mu2 \(the limiting friction\) must be >= mu1, got mu1 = 0.5 and mu2 = "
                                         r"0.4$"):
        validate_params({**DEFAULTS, "mu1": 0.5, "mu2": 0.4})
    # Batched leaves: the failing members are shown.
    with pytest.raises(ValueError, match=r"got mu1 = \[0.5 0.6\] and mu2 = \[0.4 0.4\]$"):
        validate_params({**DEFAULTS, "mu1": np.array([0.3, 0.5, 0.6]), "mu2": 0.4})
    validate_params({**DEFAULTS, "mu1": 0.4, "mu2": 0.4})


# -- each material declares the keys it reads -----------------------------------------------------------

def _read_keys(material, F_trial, dt=1e-4) -> set[str]:
    """The parameters that the update and the wave speed of ``material`` depend on: the leaves
    with a non-zero derivative of a sum of all they return (a leaf never read has exactly 0)."""
    params = jm.Params.create(dtype=jnp.float64, beta=0.3, xi=5.0, pc0=2000.0, mu_w=0.4)
    internal = material.init_internal(F_trial.shape[0], jnp.float64)

    def total(p):
        F, tau, out = material.update(F_trial, internal, p, dt)
        leaves = [F, tau, *out.values(), material.wave_speed(p)]
        return sum(jnp.sum(jnp.square(leaf)) for leaf in leaves)

    grads = jax.grad(total)(params)
    values = {k: float(getattr(grads, k)) for k in PARAM_KEYS}
    assert all(math.isfinite(v) for v in values.values()), values
    return {k for k, v in values.items() if v != 0.0}


def _trial_states(dim=2):
    """A compressed column sheared fast (plastic, flowing) beside a gently compressed one."""
    sheared = np.eye(dim) * 0.995
    sheared[0, 1] = 0.05
    return jnp.asarray(np.stack([sheared, np.eye(dim) * 0.9999]))


@pytest.mark.parametrize("material", [jm.Hencky(), jm.CriticalState()], ids=lambda m: type(m).__name__)
def test_materials_declare_the_keys_they_read(material):
    keys = type(material).keys
    assert keys and len(set(keys)) == len(keys) and set(keys) <= set(PARAM_KEYS)
    assert set(keys) == _read_keys(material, _trial_states())


def test_declared_keys():
    assert jm.Hencky.keys == ("E", "nu", "rho")
    assert set(jm.CriticalState.keys) == set(MATERIAL_KEYS)  # every key but the walls' mu_w
    assert jm.Material.keys == ()
