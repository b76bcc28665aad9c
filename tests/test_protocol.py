"""The objective protocol (calibration.problem.protocol): both objectives implement all of it, every
consumer relies on it instead of probing, and compiled batches are kept by content."""

import inspect
import pathlib
import re
import typing

import numpy as np
import pytest

import calibration
from calibration import CompositeObjective, FrontTarget, Objective, ObjectiveLike, ProfileTarget, ResidualModel
from calibration.problem.cache import BATCHES, CompileCache, content_key
from jaxmpm import scenes

#: The modules that take an objective (``__main__``, the command line, is not a consumer's library).
#: The consumers: every module of calibration outside calibration/problem/ (which implements the protocol).
ROOT = pathlib.Path(__file__).resolve().parents[1]
CONSUMERS = tuple(sorted(str(p.relative_to(ROOT / "calibration").with_suffix("")) for p in (ROOT / "calibration").rglob(
    "*.py") if "problem" not in p.parts))


def _objective(profile_h=1.0):
    scene = scenes.cohesive_collapse(dx=0.089 / 4, t_end=0.05, beta=0.25)
    x = np.linspace(0.0, 0.16, 9)
    return Objective(scene, ("beta", "mu1"), profile=ProfileTarget(x, profile_h * np.ones_like(x)),
                     front=FrontTarget(np.array([0.025, 0.05]), np.array([0.1, 0.11])), check_data=False)


def _members(protocol) -> dict[str, str]:
    """Every member the protocol declares, by kind: "method", "property" or "attribute"."""
    out = {}
    for klass in protocol.__mro__:
        if klass in (typing.Protocol, typing.Generic, object):
            continue
        for name in getattr(klass, "__annotations__", {}):
            out.setdefault(name, "attribute")
        for name, value in vars(klass).items():
            if name.startswith("_"):
                continue
            if isinstance(value, property):
                out.setdefault(name, "property")
            elif inspect.isfunction(value):
                out.setdefault(name, "method")
    return out


@pytest.fixture(scope="module")
def objectives():
    one = _objective()
    return one, CompositeObjective([one, _objective(1.1)])


def test_both_objectives_implement_every_member_of_the_protocol(objectives):
    members = _members(ObjectiveLike)
    assert set(_members(ResidualModel)) <= set(members)
    assert {"keys", "bounds", "residual_fn", "residuals_and_jacobian_z", "check_thetas", "fingerprint",
            "parts", "batched_jacobian_z"} <= set(members)
    for objective in objectives:
        assert isinstance(objective, ObjectiveLike) and isinstance(objective, ResidualModel)
        for name, kind in members.items():
            value = getattr(objective, name)  # raises if missing
            if kind == "method":
                assert callable(value), (type(objective).__name__, name)
            else:
                assert not inspect.ismethod(value), (type(objective).__name__, name)
    one, both = objectives
    assert one.parts[0][0] is one and both.parts[0][0] is one
    assert one.jacobian == "ad" and both.jacobian == "ad"
    assert one.sampling_seed == one.scene.info.seed and both.sampling_seed is None


def test_expand_spreads_plain_keys_and_refuses_strays(objectives):
    """Starting values by plain key: an objective takes its own keys as they are, and neither kind
    accepts a key it does not fit (the command line calls ``expand`` on every objective)."""
    one, both = objectives
    assert one.expand({"beta": 0.2}) == {"beta": 0.2} and both.expand({"mu1": 0.4}) == {"mu1": 0.4}
    for objective in objectives:
        with pytest.raises(ValueError, match="'xi' is not fitted"):
            objective.expand({"xi": 30.0})


def test_the_consumers_probe_no_objective():
    root = pathlib.Path(calibration.__file__).parent
    probe = re.compile(r"\b(getattr|hasattr)\(\s*(objective|coarse|obj|member|m)\b")
    assert "optim/fit" in CONSUMERS and "inference/verdict" in CONSUMERS
    for name in CONSUMERS:
        source = (root / f"{name}.py").read_text()
        assert not probe.findall(source), f"calibration/{name}.py probes an objective: {probe.findall(source)}"


@pytest.mark.slow  # 27 s; the z-space Jacobians drive every fit of the default suite
def test_z_space_evaluation_returns_both_jacobians_from_one_trace(objectives):
    one, _ = objectives
    z = np.asarray(one.bounds.to_unconstrained(np.array([0.3, 0.4])))
    r, Jz, J, _ = one.residuals_and_jacobian_z(z)
    dtheta_dz = np.asarray(one.bounds.jacobian_diag(z))
    np.testing.assert_allclose(np.asarray(J) * dtheta_dz[None, :], np.asarray(Jz), rtol=1e-12, atol=1e-15)
    r_b, Jz_b, J_b, _ = one.batched_jacobian_z()(z[None])
    np.testing.assert_allclose(np.asarray(J_b[0]), np.asarray(J), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(np.asarray(r_b[0]), np.asarray(r), rtol=1e-12, atol=1e-15)


def test_compiled_batches_are_kept_by_content_not_identity(objectives):
    _, both = objectives
    again = CompositeObjective([_objective(), _objective(1.1)])  # equal content, other objects
    assert again is not both and content_key(again) == content_key(both)
    assert again.batched_jacobian_z() is both.batched_jacobian_z()
    other = CompositeObjective([_objective(), _objective(1.2)])  # other data: another entry
    assert content_key(other) != content_key(both)
    assert ("search", content_key(both)) in BATCHES

    cache, built = CompileCache(2), []
    build = lambda: built.append(1) or len(built)  # noqa: E731
    assert cache.get("a", build) == 1 and cache.get("a", build) == 1  # a hit builds nothing
    cache.get("b", build)
    cache.get("c", build)  # beyond the size: "a", the least recently used, goes
    assert "a" not in cache and len(cache) == 2
    assert cache.get(None, build) == 4 and len(cache) == 2  # no content key: built, never kept
