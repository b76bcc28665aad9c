"""The step's speed designs change no result (docs/performance.md), in float64:

- the materialisation points are the identity: the step with them equals the step without them,
  forward and in forward- and reverse-mode derivatives;
- the whole step (planes, materialisation points, Newton stopped at the dtype's resolution)
  equals release 0.2.0's step on S4 (dx = L/6, β = 0.25, p_c0 = 500, ξ = 50) to t = 0.05 s, the
  positions and their derivatives with respect to β and μ1 (tests/data/s4_release_0_2_0.npz,
  written by tests/data/make_release_reference.py with release 0.2.0 on PYTHONPATH).
"""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
import jaxmpm.step
from jaxmpm.scenes import S4_SIDE, cohesive_collapse

jax.config.update("jax_enable_x64", True)
REFERENCE = pathlib.Path(__file__).parent / "data" / "s4_release_0_2_0.npz"


def _scene():
    return cohesive_collapse(beta=0.25, dx=S4_SIDE / 6, pc0=500.0, xi=50.0, dtype="float64", t_end=0.05, rest=False)


def _run(scene):
    rollout = jm.make_rollout(scene.config, observer=None)

    def run(theta):
        final, _ = rollout(scene.state, scene.params.replace(beta=theta[0], mu1=theta[1]))
        return final.x

    return run


@pytest.mark.slow  # 2-3 min compiling four programs (the values come with the JVP)
def test_materialisation_points_are_the_identity(monkeypatch):
    scene = _scene()
    theta = jnp.asarray([0.25, float(scene.params.mu1)])
    results = []
    for barrier in (True, False):
        if not barrier:
            monkeypatch.setattr(jaxmpm.step, "_materialize", lambda tree, token: tree)
        run = _run(scene)
        x, tangent = jax.jit(lambda t, run=run: jax.jvp(run, (t,), (jnp.asarray([1.0, 0.0]),)))(theta)
        grad = jax.jit(jax.grad(lambda t, run=run: jnp.sum(run(t)[:, 0])))(theta)
        results.append((x, tangent, grad))
    (x1, t1, g1), (x2, t2, g2) = results
    np.testing.assert_allclose(x1, x2, rtol=0, atol=1e-13)
    np.testing.assert_allclose(t1, t2, rtol=1e-9, atol=1e-12 * np.abs(t2).max())
    np.testing.assert_allclose(g1, g2, rtol=1e-9)
    assert np.all(np.isfinite(g1)) and np.abs(g1).max() > 0


@pytest.mark.slow  # 16 s; a regression guard of the step against the 0.2.0 release
def test_the_step_equals_release_0_2_0():
    ref = np.load(REFERENCE)
    scene = _scene()
    run = _run(scene)
    theta = jnp.asarray(ref["theta"])
    jvp = jax.jit(lambda t, d: jax.jvp(run, (t,), (d,)))  # one compilation: the values and both directions
    for j, key in enumerate(("dx_dbeta", "dx_dmu1")):
        x, tangent = jvp(theta, jnp.zeros(2).at[j].set(1.0))
        np.testing.assert_allclose(x, ref["x"], rtol=0, atol=1e-10)
        scale = np.abs(ref[key]).max()
        assert scale > 0
        np.testing.assert_allclose(tangent, ref[key], rtol=0, atol=1e-7 * scale, err_msg=key)
