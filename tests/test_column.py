"""The critical-state material in the engine: the S2 column collapses end to end, and its
gradients with respect to the calibration parameters match finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm


@pytest.mark.slow  # 11 s; the column's gradients at t = 0 are tested by default
def test_column_collapses_end_to_end_without_flags():
    """S2 at a coarse dx = 5 mm to t = 0.42 s: no status bits, the deposit is lower and wider
    than the column, symmetric to within one cell, and the flow has come to rest."""
    cfg, s0, params = jm.scenes.gates_collapse(dx=0.005, frames=4)
    result = jm.simulate(cfg, s0, params)
    x0, x = np.asarray(s0.x), np.asarray(result.state.x)
    left = x0[:, 0].min() - x[:, 0].min()
    right = x[:, 0].max() - x0[:, 0].max()
    assert left > 0.03 and right > 0.03  # runout beyond each gate
    assert abs(left - right) < cfg.grid.dx
    assert x[:, 1].max() < x0[:, 1].max() - 0.01
    assert np.max(np.linalg.norm(np.asarray(result.state.v), axis=1)) < 0.05
    assert float(result.state.internal["mu_I"].max()) <= float(params.mu2) + 1e-6


# 40 s: slow-marked to keep the default suite under CI's 15 minutes; the same critical-state gradients
# through a rollout are checked against central differences by tests/test_gradients.py and, on S4, by
# tests/test_calibration.py::test_jacobian_matches_central_differences.
@pytest.mark.slow
def test_column_gradients_match_finite_differences():
    """d(loss)/d(β, μ1, μ2, I0, ξ, p_c0) through ~200 steps of the collapse (float64, plastic
    flow with rate dependence under way), against central differences with relative step 1e-5:
    agreement to 1e-4 relative (measured 1e-9 to 1e-5; the issue asks for 1e-3)."""
    cfg, s0, params = jm.scenes.gates_collapse(dx=0.005, t_end=0.02, beta=0.05, xi=20.0)
    rollout = jm.make_rollout(cfg, observer=None)
    centre = float(jnp.mean(s0.x[:, 0]))

    def loss(p):
        final, _ = rollout(s0, p)
        return 1e3 * jnp.mean((final.x[:, 0] - centre) ** 2) + jnp.mean(final.x[:, 1])

    value = jax.jit(loss)
    grads = jax.jit(jax.grad(loss))(params)
    final, _ = jax.jit(rollout)(s0, params)
    assert 150 < int(final.steps) < 300 and float(final.internal["gamma_dot"].max()) > 1.0
    for key in ("beta", "mu1", "mu2", "I0", "xi", "pc0"):
        v = getattr(params, key)
        h = 1e-5 * v
        fd = (value(params.replace(**{key: v + h})) - value(params.replace(**{key: v - h}))) / (2 * h)
        g = getattr(grads, key)
        assert np.isfinite(g)
        np.testing.assert_allclose(g, fd, rtol=1e-4, err_msg=key)


def test_no_nan_gradient_at_t0_with_critical_state():
    """One step from the stress-free state (F_e = I, zero velocity, β = 0: every particle at
    p̄ = 0, the free-surface limit): every parameter gradient is finite."""
    cfg, s0, params = jm.scenes.gates_collapse(dx=0.01, t_end=0.01)
    step = jm.make_step(cfg)

    def loss(p):
        s = step(s0, p)
        return jnp.sum(s.x**2) + jnp.sum(s.v**2) + 1e-6 * jnp.sum(s.tau**2)

    grads = jax.jit(jax.grad(loss))(params)
    for key, g in grads.to_dict().items():
        assert np.isfinite(g), key
