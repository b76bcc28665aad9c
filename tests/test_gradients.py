"""Gradients: finite everywhere (F_e = I, repeated stretches, zero velocity) and equal to
finite differences, from the small-matrix kernels up to a whole rollout. Float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxmpm as jm
from jaxmpm.linalg import eigh_sym, sym_exp, sym_log
from jaxmpm.materials import hencky_stress


def _spd(dim, seed, repeated=False):
    rng = np.random.default_rng(seed)
    if repeated:
        return jnp.eye(dim) * 1.3
    a = rng.normal(size=(dim, dim)) * 0.3
    return jnp.asarray(np.eye(dim) + a @ a.T)


@pytest.mark.parametrize("dim", [2, 3])
def test_sym_functions_match_eigendecomposition(dim):
    a = _spd(dim, 0)
    lam, q = np.linalg.eigh(np.asarray(a))
    np.testing.assert_allclose(sym_log(a), q @ np.diag(np.log(lam)) @ q.T, atol=1e-13)
    np.testing.assert_allclose(sym_exp(a), q @ np.diag(np.exp(lam)) @ q.T, rtol=1e-13, atol=1e-13)
    lam2, q2 = eigh_sym(a)
    np.testing.assert_allclose(np.sort(lam2), lam, rtol=1e-13)
    np.testing.assert_allclose(q2 @ jnp.diag(lam2) @ q2.T, a, atol=1e-13)


# 3D: 15 s each, slow-marked to keep the default suite under CI's 15 minutes (3D values are checked
# against the eigendecomposition by default; 2D gradients run by default).
@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])
@pytest.mark.parametrize("repeated", [False, True])
def test_sym_function_gradients(dim, repeated):
    a = _spd(dim, 1, repeated)
    for fn in (sym_log, sym_exp):
        # fn bound as a default: both closures are used within this iteration
        check_grads(jax.jit(lambda a, fn=fn: fn(jm.linalg.sym(a))), (a,), order=1, modes=("fwd", "rev"))
        g = jax.jit(jax.grad(lambda a, fn=fn: jnp.sum(fn(a) ** 2)))(a)
        assert np.all(np.isfinite(g))
    # Nearly repeated eigenvalues: the divided differences switch branch smoothly.
    near = jnp.diag(jnp.asarray([1.0, 1.0 + 1e-9, 1.0 - 2e-9][:dim]))
    check_grads(jax.jit(lambda a: sym_log(jm.linalg.sym(a))), (near,), order=1, modes=("fwd", "rev"))


# 3D: 11 s on a core, slow-marked (2D runs by default; 3D Hencky stresses are checked against the
# eigendecomposition by default).
@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_hencky_stress_gradients(dim):
    params = jm.Params.create(E=2e6, nu=0.27)
    eye = jnp.eye(dim)
    rng = np.random.default_rng(2)
    F = jnp.asarray(np.eye(dim) + 0.1 * rng.normal(size=(dim, dim)))
    stress = jax.jit(lambda F, E, nu: hencky_stress(F, params.replace(E=E, nu=nu)))  # compiled once for all points
    for point in (eye, F, 1.1 * eye):
        check_grads(stress, (point, params.E, params.nu), order=1, modes=("fwd", "rev"), eps=1e-6)
    # Small strain: Hencky reduces to linear elasticity.
    G, lam = params.E / (2 * (1 + params.nu)), params.E * params.nu / ((1 + params.nu) * (1 - 2 * params.nu))
    eps = 1e-7 * jnp.asarray(rng.normal(size=(dim, dim)))
    eps = 0.5 * (eps + eps.T)
    tau = hencky_stress(eye + eps, params)
    np.testing.assert_allclose(tau, lam * jnp.trace(eps) * eye + 2 * G * eps, rtol=1e-5, atol=1e-8)


def _small_scene(t_end=0.08, frames=()):
    dx = 0.05
    cfg = jm.Config(grid=jm.Grid((20, 16), dx), t_end=t_end, max_steps=400,
                    walls=(jm.Wall((0, 0.1), (0, 1)), jm.Wall((0.1, 0), (1, 0), "non-separable", 0.3)),
                    frame_times=frames)
    x, vol = jm.seed_box((0.1, 0.1), (0.45, 0.4), dx, 2)
    rng = np.random.default_rng(5)
    v = 0.05 * rng.normal(size=x.shape) + np.array([-0.5, -0.3])  # pushes into both walls
    return cfg, jm.init_state(cfg, x, vol, v=v)


def test_no_nan_gradient_at_t0():
    """One step from the stress-free state (F_e = I, tau = 0): every gradient is finite."""
    cfg, s0 = _small_scene()
    s0 = s0.replace(v=jnp.zeros_like(s0.v))  # zero velocity too: the CFL term is inactive
    step = jm.make_step(cfg)
    params = jm.Params.create()

    def loss(params, x, v, F):
        s = step(s0.replace(x=x, v=v, F=F), params)
        return jnp.sum(s.x**2) + jnp.sum(s.v**2) + 1e-6 * jnp.sum(s.tau**2) + jnp.sum(s.C**2)

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(params, s0.x, s0.v, s0.F)
    for leaf in jax.tree.leaves(grads):
        assert np.all(np.isfinite(leaf))


# 13 s; the kernels' and the return map's gradients against finite differences stay in the default suite
@pytest.mark.slow
def test_rollout_gradient_matches_finite_differences():
    """d(final mean position)/dE, dnu, drho through ~60 adaptive steps with walls and friction,
    against central differences with a relative step of 1e-6 (agreement to 1e-5 relative)."""
    cfg, s0 = _small_scene()
    rollout = jm.make_rollout(cfg, observer=None)
    params = jm.Params.create(E=5e5)

    def loss(params):
        final, _ = rollout(s0, params)
        return jnp.mean(final.x[:, 0]) + 2.0 * jnp.mean(final.x[:, 1])

    grads = jax.jit(jax.grad(loss))(params)
    f = jax.jit(loss)
    steps = int(jax.jit(rollout)(s0, params)[0].steps)
    assert steps > 40
    for key in ("E", "nu", "rho"):
        value = getattr(params, key)
        h = 1e-6 * value
        fd = (f(params.replace(**{key: value + h})) - f(params.replace(**{key: value - h}))) / (2 * h)
        np.testing.assert_allclose(getattr(grads, key), fd, rtol=1e-5, err_msg=key)


@pytest.mark.slow  # 25 s; the checkpointed rollout's gradient is checked against differences by default
def test_checkpointed_and_plain_rollouts_agree():
    cfg, s0 = _small_scene(frames=(0.01, 0.02))
    params = jm.Params.create()

    def loss(params, checkpoint):
        final, frames = jm.make_rollout(cfg, checkpoint=checkpoint)(s0, params)
        return jnp.sum(final.x**2) + jnp.sum(frames["q"])

    g1 = jax.jit(jax.grad(loss), static_argnums=1)(params, True)
    g2 = jax.jit(jax.grad(loss), static_argnums=1)(params, False)
    for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g2)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-30)


@pytest.mark.slow  # 15 s; float32 Jacobians are used by default in tests/test_search.py's round-off test
def test_float32_forward_jacobian_is_finite_and_matches_jvp():
    """The forward-mode Jacobian in one parameter (jacfwd: vmap of jvp with a batch of one, as
    the S5 law fit of μ1 alone uses it) through 20 float32 rollout steps of the tall S5 column:
    every leaf of the final state is finite and equals a single jvp. jaxlib 0.10.2 miscompiles
    this on the CPU (about 74,000 NaN tangents, at random; hence its exclusion in pyproject.toml)."""
    import dataclasses

    from jaxmpm.scenes import aspect_ratio_collapse

    scene = aspect_ratio_collapse(4.0, L0=0.05, dtype="float32")
    rollout = jm.make_rollout(dataclasses.replace(scene.config, max_steps=20), observer=None)

    def run(theta):
        final, _ = rollout(scene.state, scene.params.replace(mu1=theta[0]))
        return final.x, final.v, final.F, final.tau, final.internal

    theta = jnp.asarray([0.38], jnp.float32)
    jac = jax.jit(jax.jacfwd(run))(theta)
    tangent = jax.jit(lambda t: jax.jvp(run, (t,), (jnp.ones_like(t),))[1])(theta)
    for leaf in jax.tree.leaves(jac):
        assert np.all(np.isfinite(leaf))
    # The dynamic state (the reported I and μ(I) are ill-conditioned in float32 where p̄ -> 0).
    for column, single in zip(jac[:4], tangent[:4]):
        single = np.asarray(single)
        # Two compiled programs in float32: agreement to 1e-3 of the leaf's largest tangent.
        np.testing.assert_allclose(np.asarray(column)[..., 0], single, rtol=0, atol=1e-3 * np.abs(single).max())
    assert np.abs(np.asarray(jac[0])).max() > 0


# float32, where the smallest normal number is reached first, by default; float64 (9 s) in the slow set.
@pytest.mark.parametrize("dtype", ["float32", pytest.param("float64", marks=pytest.mark.slow)])
def test_coulomb_wall_and_time_step_tangents_finite_at_tiny_speeds(dtype):
    """Stuck nodes with |v_t| near the smallest normal number and a body almost at rest give
    finite forward and reverse derivatives (max(0, ·) of an overflowing ratio made 0 · inf)."""
    from jaxmpm.boundary import apply_walls
    from jaxmpm.step import time_step

    dt_ = jnp.dtype(dtype)
    tiny = float(jnp.finfo(dt_).tiny)
    wall = jm.Wall(point=(0.0, 0.0), normal=(0.0, 1.0), kind="non-separable", friction=0.4)
    v = jnp.asarray([[tiny, 1e3 * tiny, 1e-10, 1e-3, 0.0], [-1e-3, -1e-3, -1.0, -1e-4, 0.0]], dt_)
    node_x = jnp.zeros((2, 5), dt_)

    def walls(scale):
        return jnp.sum(apply_walls((wall,), scale * v, node_x, 0.0, 1e-4) ** 2)

    assert np.isfinite(jax.grad(walls)(jnp.asarray(1.0, dt_)))
    assert np.isfinite(jax.jvp(walls, (jnp.asarray(1.0, dt_),), (jnp.asarray(1.0, dt_),))[1])

    cfg, s0 = _small_scene()
    def dt_of(scale):
        s = s0.replace(v=(scale * 1e-14) * jnp.ones_like(s0.v))
        return time_step(cfg, s, jm.Params.create())

    assert np.isfinite(jax.grad(dt_of)(1.0))
    assert np.isfinite(jax.jvp(dt_of, (1.0,), (1.0,))[1])
