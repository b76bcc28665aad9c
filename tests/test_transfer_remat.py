"""The transfers under ``jax.checkpoint`` (``jaxmpm.transfer``, "Reverse mode"): their values
and forward-mode derivatives are the plain bodies', bit for bit, and their reverse-mode
derivatives equal the plain bodies' to round-off (float64); a critical-state run's gradient
equals the plain transfers' to 1e-10 and central differences to 1e-6; and a step's VJP stores
the transfers' inputs, not their per-particle products."""

import contextlib
import io

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.ad_checkpoint import print_saved_residuals

import jaxmpm as jm
from jaxmpm import transfer
from jaxmpm.kernels import make_stencil

jax.config.update("jax_enable_x64", True)


def _use_plain_transfers(patch):
    """The step's transfers without ``jax.checkpoint`` (what the engine ran before)."""
    patch.setattr(transfer, "_p2g_remat", transfer._p2g)
    patch.setattr(transfer, "_g2p_remat", transfer._g2p_planes)


def _sum_sin(tree):
    return sum(jnp.sum(jnp.sin(x) * x) for x in jax.tree.leaves(tree))


def _inputs(dim, n=40, seed=0):
    rng = np.random.default_rng(seed)
    grid = jm.Grid((10,) * dim, 0.1, origin=(-0.3,) * dim)
    x = jnp.asarray(rng.uniform(-0.1, 0.55, (n, dim)))
    normal = lambda *shape: jnp.asarray(rng.normal(size=shape))  # noqa: E731
    particles = dict(mass=1.0 + jnp.abs(normal(n)), v=normal(n, dim), C=normal(n, dim, dim),
                     vol0=0.5 + jnp.abs(normal(n)), tau=normal(n, dim, dim), pressure=jnp.abs(normal(n)))
    nodes = dict(v_old=normal(dim, grid.n_nodes), v_new=normal(dim, grid.n_nodes),
                 v_p=list(jnp.unstack(normal(n, dim), axis=-1)))
    return grid, x, particles, nodes


def _check_same(fn, plain, args, jvp=True):
    """Values and (``jvp``) JVPs bit for bit; VJPs (through every argument) to round-off. The JVP's
    program gives the values too, so a body compiles two programs, not three."""
    if jvp:
        _check_same_jvp(fn, plain, args)
    else:
        for a, b in zip(jax.tree.leaves(jax.jit(fn)(*args)), jax.tree.leaves(jax.jit(plain)(*args))):
            np.testing.assert_array_equal(a, b)
    argnums = tuple(range(len(args)))
    g = jax.jit(jax.grad(lambda *a: _sum_sin(fn(*a)), argnums))(*args)
    g_plain = jax.jit(jax.grad(lambda *a: _sum_sin(plain(*a)), argnums))(*args)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_plain)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
        assert np.all(np.isfinite(a))


def _check_same_jvp(fn, plain, args):
    tangents = jax.tree.map(lambda a: jnp.cos(3.0 * a), args)
    jvp, jvp_plain = (jax.jit(lambda a, t, f=f: jax.jvp(f, a, t)) for f in (fn, plain))
    for a, b in zip(jax.tree.leaves(jvp(args, tangents)), jax.tree.leaves(jvp_plain(args, tangents))):
        np.testing.assert_array_equal(a, b)


# The checkpointed bodies are the same code in 2D and 3D. 2D runs by default; one 3D case (G2P, AFLIP)
# is in the slow set: P2G's 3D VJP through its seven arguments took 7 minutes of compiling on one
# core, G2P's other kinds 75 s each, and the engine's 3D gradients are checked in tests/test_gradients.py.
def _p2g_case(dim):
    grid, x, p, _ = _inputs(dim)

    def run(body):
        def fn(x, mass, v, C, vol0, tau, pressure):
            return body(make_stencil(x, grid), mass, v, C, vol0, tau, grid.n_nodes, pressure)
        return fn

    return run(transfer.p2g), run(transfer._p2g), (x, p["mass"], p["v"], p["C"], p["vol0"], p["tau"], p["pressure"])


def test_p2g_matches_its_body():
    _check_same(*_p2g_case(2), jvp=False)


@pytest.mark.slow  # 12 s of compiling; G2P's JVP is checked by default
def test_p2g_jvp_matches_its_body():
    _check_same_jvp(*_p2g_case(2))


@pytest.mark.parametrize(("kind", "dim"), [("aflip", 2), pytest.param("apic", 2, marks=pytest.mark.slow),
                                           pytest.param("pic", 2, marks=pytest.mark.slow),
                                           pytest.param("aflip", 3, marks=pytest.mark.slow)])
def test_g2p_matches_its_body(kind, dim):
    grid, x, _, n = _inputs(dim)
    alpha = 0.0 if kind == "apic" else 0.95

    def run(body):
        def fn(x, v_old, v_new, v_p):
            return body(make_stencil(x, grid), v_old, v_new, v_p, grid.dx, kind, alpha)
        return fn

    _check_same(run(transfer.g2p_planes), run(transfer._g2p_planes), (x, n["v_old"], n["v_new"], n["v_p"]),
                jvp=dim == 2)


def _s4_loss():
    """The tiny S4 (144 particles, 0.03 s, float64): the front and the column's mean height."""
    scene = jm.scenes.cohesive_collapse(beta=0.25, dx=0.089 / 6, pc0=500.0, xi=50.0, dtype="float64",
                                        t_end=0.03, rest=False)
    rollout = jm.make_rollout(scene.config, observer=None)

    def loss(mu1, beta):
        final, _ = rollout(scene.state, scene.params.replace(mu1=mu1, beta=beta))
        return jnp.max(final.x[:, 0]) + 3.0 * jnp.mean(final.x[:, 1])

    return loss, (scene.params.mu1, scene.params.beta)


@pytest.mark.slow  # a minute of compiling four programs; the transfers' own checks run by default
def test_critical_state_gradient_matches_plain_transfers_and_differences(monkeypatch):
    loss, args = _s4_loss()
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))(*args)
    with monkeypatch.context() as patch:
        _use_plain_transfers(patch)
        plain = jax.jit(jax.grad(loss, argnums=(0, 1)))(*args)
    np.testing.assert_allclose(grad, plain, rtol=1e-10, atol=0)
    f = jax.jit(loss)
    h = 1e-6
    fd = [(f(args[0] + h, args[1]) - f(args[0] - h, args[1])) / (2 * h),
          (f(args[0], args[1] + h) - f(args[0], args[1] - h)) / (2 * h)]
    np.testing.assert_allclose(grad, fd, rtol=1e-6)
    assert all(abs(float(g)) > 1e-4 for g in grad)  # the check is not of zeros


def _saved_residuals(step, state, params) -> list[str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        print_saved_residuals(step, state, params)
    return [line for line in out.getvalue().splitlines() if line.strip()]


def test_step_vjp_stores_the_transfers_inputs(monkeypatch):
    """The elastic block's step: 200 saved arrays (474 with the plain transfers, which store the
    stencil's products and every gathered node value)."""
    config, state, params = jm.scenes.falling_block(n_particles=400, dtype="float64")
    step = jm.make_step(config)
    n_remat = len(_saved_residuals(step, state, params))
    _use_plain_transfers(monkeypatch)
    n_plain = len(_saved_residuals(jm.make_step(config), state, params))
    assert n_remat <= 230 and n_plain >= 2 * n_remat, (n_remat, n_plain)
