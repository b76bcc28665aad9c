"""Shape functions and P2G/G2P: partition of unity, exact transfer of rigid motions, and
conservation of mass, momentum and (APIC) angular momentum. Tolerances are round-off."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxmpm as jm
from jaxmpm.kernels import make_stencil
from jaxmpm.transfer import g2p, grid_velocities, p2g

RTOL = 1e-12


def _cloud(dim, n=200, seed=0):
    rng = np.random.default_rng(seed)
    grid = jm.Grid((12,) * dim, 0.1, origin=(-0.3,) * dim)
    x = rng.uniform(-0.1, 0.75, (n, dim))
    return grid, jnp.asarray(x)


@pytest.mark.parametrize("dim", [2, 3])
def test_partition_of_unity_and_linear_reproduction(dim):
    grid, x = _cloud(dim)
    st = make_stencil(x, grid)
    np.testing.assert_allclose(st.weight.sum(0), 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose((st.weight * st.offset).sum(1), 0.0, atol=1e-14)
    np.testing.assert_allclose(st.grad.sum(1), 0.0, atol=1e-12)
    # sum_i w (x_i - x_p)(x_i - x_p)^T = dx^2/4 I: the APIC inertia for quadratic B-splines.
    inertia = jnp.einsum("asn,bsn->nab", st.weight * st.offset, st.offset)
    np.testing.assert_allclose(inertia, np.broadcast_to(np.eye(dim) * grid.dx**2 / 4, inertia.shape), atol=1e-14)
    # Node positions agree with the flat index.
    nodes = jnp.asarray(grid.node_positions())
    np.testing.assert_allclose(nodes[st.index] - x[None], jnp.moveaxis(st.offset, 0, -1), atol=1e-13)


# 3D: 21 s, slow-marked to keep the default suite under CI's 15 minutes (2D runs by default).
@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_shape_function_gradients(dim):
    grid, x = _cloud(dim, n=5)
    # Keep points away from cell boundaries, where the base node (and so the stencil) switches.
    x = (jnp.floor(x / grid.dx) + 0.37) * grid.dx
    weight = jax.jit(lambda x: make_stencil(x, grid).weight)  # jitted: a third of the eager checks' time
    check_grads(weight, (x,), order=2, modes=("fwd", "rev"), eps=1e-6)
    # The stencil's analytic gradient is ∇N_i evaluated at x_p: d w_ip / d x_p, nodes fixed.
    st = make_stencil(x, grid)
    jac = jax.jacfwd(weight)(x)  # (S, N, N, dim)
    diag = jnp.einsum("snnd->dsn", jac)
    np.testing.assert_allclose(st.grad, diag, rtol=1e-12, atol=1e-12)


def _rigid(dim, x):
    v0 = jnp.asarray([0.3, -0.2, 0.1][:dim])
    omega = 1.7
    center = jnp.full(dim, 0.3)
    if dim == 2:
        W = jnp.asarray([[0.0, -omega], [omega, 0.0]])
    else:
        W = jnp.asarray([[0.0, -omega, 0.4], [omega, 0.0, -0.2], [-0.4, 0.2, 0.0]])
    v = v0 + (x - center) @ W.T
    return v, jnp.broadcast_to(W, (x.shape[0], dim, dim))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("transfer,alpha", [("apic", 0.0), ("aflip", 0.95)])
def test_rigid_motion_survives_transfer(dim, transfer, alpha):
    """A velocity field v0 + W (x - c) with its APIC affine matrix C = W comes back exactly."""
    grid, x = _cloud(dim, n=400)
    v, C = _rigid(dim, x)
    m = jnp.full(x.shape[0], 0.01)
    st = make_stencil(x, grid)
    zeros = jnp.zeros_like(C)
    fields = p2g(st, m, v, C, m, zeros, grid.n_nodes)
    v_old, v_new = grid_velocities(fields, 0.0, jnp.zeros(dim))
    # Every node that received mass carries the rigid field exactly.
    nodes = jnp.asarray(grid.node_positions())
    expected, _ = _rigid(dim, nodes)
    has = fields.mass > 0
    np.testing.assert_allclose(v_new.T[has], expected[has], rtol=RTOL, atol=1e-13)
    out = g2p(st, v_old, v_new, v, grid.dx, transfer, alpha)
    np.testing.assert_allclose(out.v, v, atol=1e-13)
    np.testing.assert_allclose(out.C, C, atol=1e-12)
    np.testing.assert_allclose(out.grad_v, C, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_p2g_conserves_mass_momentum_angular_momentum(dim):
    grid, x = _cloud(dim, n=300, seed=3)
    rng = np.random.default_rng(4)
    v = jnp.asarray(rng.normal(size=x.shape))
    C = jnp.asarray(rng.normal(size=(x.shape[0], dim, dim)))
    m = jnp.asarray(rng.uniform(0.5, 2.0, x.shape[0]))
    st = make_stencil(x, grid)
    fields = p2g(st, m, v, C, m, jnp.zeros_like(C), grid.n_nodes)
    np.testing.assert_allclose(fields.mass.sum(), m.sum(), rtol=RTOL)
    np.testing.assert_allclose(fields.momentum.sum(1), (m[:, None] * v).sum(0), rtol=RTOL, atol=1e-12)

    # APIC angular momentum of a particle: m (x × v) + m D ε:C^T with D = dx²/4.
    def particle_L(x, v, C):
        D = grid.dx**2 / 4
        if dim == 2:
            return jnp.sum(m * (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0] + D * (C[:, 1, 0] - C[:, 0, 1])))
        lin = jnp.cross(x, v)
        aff = D * jnp.stack([C[:, 2, 1] - C[:, 1, 2], C[:, 0, 2] - C[:, 2, 0], C[:, 1, 0] - C[:, 0, 1]], -1)
        return jnp.sum(m[:, None] * (lin + aff), 0)

    nodes = jnp.asarray(grid.node_positions())
    p = fields.momentum.T
    L_grid = jnp.sum(nodes[:, 0] * p[:, 1] - nodes[:, 1] * p[:, 0]) if dim == 2 else jnp.sum(jnp.cross(nodes, p), 0)
    L_before = particle_L(x, v, C)
    np.testing.assert_allclose(L_grid, L_before, rtol=1e-11)
    # G2P with APIC and no forces returns the same angular momentum (positions unchanged).
    v_old, v_new = grid_velocities(fields, 0.0, jnp.zeros(dim))
    out = g2p(st, v_old, v_new, v, grid.dx, "apic", 0.0)
    np.testing.assert_allclose(particle_L(x, out.v, out.C), L_before, rtol=1e-11)


def test_periodic_axis_wraps_stencil_and_positions():
    """On a periodic x axis, a cloud straddling the seam transfers like one in the interior:
    mass and momentum are conserved, a uniform velocity comes back exactly, and positions wrap
    into [origin, origin + L) during a step."""
    grid = jm.Grid((8, 10), 0.1, origin=(0.0, -0.2), periodic=(True, False))
    assert grid.nodes == (8, 11)
    rng = np.random.default_rng(7)
    x = jnp.asarray(np.stack([rng.uniform(0.0, 0.8, 300), rng.uniform(0.0, 0.6, 300)], -1))
    st = make_stencil(x, grid)
    assert int(st.index.max()) < grid.n_nodes and int(st.index.min()) >= 0
    m = jnp.full(300, 0.5)
    v = jnp.broadcast_to(jnp.asarray([0.7, -0.2]), x.shape)
    fields = p2g(st, m, v, jnp.zeros((300, 2, 2)), m, jnp.zeros((300, 2, 2)), grid.n_nodes)
    np.testing.assert_allclose(fields.mass.sum(), 150.0, rtol=1e-13)
    np.testing.assert_allclose(fields.momentum.sum(1), [105.0, -30.0], rtol=1e-13)
    v_old, v_new = grid_velocities(fields, 0.0, jnp.zeros(2))
    out = g2p(st, v_old, v_new, v, grid.dx, "apic", 0.0)
    np.testing.assert_allclose(out.v, v, atol=1e-13)

    cfg = jm.Config(grid=grid, t_end=0.2, max_steps=100, walls=(jm.Wall((0.0, 0.0), (0.0, 1.0), "separable"),),
                    gravity=(2.0, -9.81))
    xs, vol = jm.seed_box((0.6, 0.0), (0.8, 0.2), 0.1, 2)
    result = jm.simulate(cfg, jm.init_state(cfg, xs, vol, v=(1.0, 0.0)), jm.Params.create(E=1e5))
    xf = np.asarray(result.state.x)
    assert result.status == 0 and np.all((xf[:, 0] >= 0.0) & (xf[:, 0] < 0.8))
    # Frictionless floor, uniform drive: the block's centre translates by 1.0·t + ½·2·t² = 0.24 m
    # (wrapped), plus the symplectic-Euler term ½·2·t·dt ≈ 1.2e-3 m; particles also spread a
    # little under the block's own weight (Poisson effect).
    shift = np.mod(xf[:, 0] - xs[:, 0], 0.8)
    assert abs(shift.mean() - 0.24) < 2e-3 and np.ptp(shift) < 5e-3


@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])  # 3D: 15 s
def test_xpic_filter_orders(dim):
    """XPIC(m) (transfer.xpic_velocity) on a random particle velocity field v_p: m = 1 is the PIC
    velocity S T v_p; the filter is 1 − (1 − A)^m with A = S T, checked against the dense
    matrices (1e-12); the part of v_p the grid cannot see (the null space of T) is removed at
    every order (2D, where 120 particles outnumber the nodes they touch); for a field the grid
    represents exactly (a uniform velocity), every order returns it (round-off)."""
    from jaxmpm.transfer import xpic_velocity

    grid, x = _cloud(dim, n=120)
    st = make_stencil(x, grid)
    rng = np.random.default_rng(4)
    mass = jnp.asarray(rng.uniform(0.5, 2.0, x.shape[0]))
    v = jnp.asarray(rng.normal(size=x.shape))
    fields = p2g(st, mass, jnp.zeros_like(v), jnp.zeros(x.shape + (dim,)), mass, jnp.zeros(x.shape + (dim,)),
                 grid.n_nodes)
    # Dense S (N × nodes) and T (nodes × N).
    S = np.zeros((x.shape[0], grid.n_nodes))
    np.add.at(S, (np.broadcast_to(np.arange(x.shape[0]), st.index.shape), np.asarray(st.index)), np.asarray(st.weight))
    gm = np.asarray(fields.mass)
    T = np.where(gm[:, None] > 0, (S * np.asarray(mass)[:, None]).T / np.where(gm > 0, gm, 1.0)[:, None], 0.0)
    A = S @ T
    eye = np.eye(x.shape[0])
    for m in (1, 2, 3, 5):
        expected = (eye - np.linalg.matrix_power(eye - A, m)) @ np.asarray(v)
        got = np.asarray(xpic_velocity(st, mass, fields.mass, v, m))
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
        # Null-space part removed: v minus its least-squares preimage under T (pinv carries
        # round-off of ~1e-11 here, so the bound is 1e-9 of |v|, against |null| ~ 1).
        null = np.asarray(v) - np.linalg.pinv(T) @ (T @ np.asarray(v))
        if dim == 2:  # in 3D the 120 particles touch ~700 nodes: T has no null space
            assert np.abs(null).max() > 0.1
            assert np.abs(np.asarray(xpic_velocity(st, mass, fields.mass, jnp.asarray(null), m))).max() < 1e-9
        uniform = jnp.broadcast_to(jnp.arange(1.0, dim + 1.0), x.shape)
        np.testing.assert_allclose(xpic_velocity(st, mass, fields.mass, uniform, m), uniform, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(xpic_velocity(st, mass, fields.mass, v, 1)), S @ (T @ np.asarray(v)),
                               rtol=1e-12, atol=1e-12)
