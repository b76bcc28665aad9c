"""The grid only where the material is (``Config(active_nodes=K)``, ``jaxmpm.sparse``): the same
run as the dense grid's to round-off, its gradient and batch too, and a full grid flagged."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm import sparse
from jaxmpm.kernels import make_stencil
from jaxmpm.rollout import make_rollout
from jaxmpm.scenes import S4_SIDE, cohesive_collapse


@pytest.fixture(scope="module")
def collapse():
    """S4 at dx = L/8 (576 particles, 738 dense nodes; about 110 touched at rest), to 0.15 s."""
    return cohesive_collapse(dx=S4_SIDE / 8, t_end=0.15, beta=0.25)


def test_activate_numbers_the_touched_nodes_in_order():
    index = jnp.asarray([[7, 3, 7], [9, 3, 2]], jnp.int32)
    slots, keys, count = sparse.activate(index, 6, 100, consecutive_rows=False)
    assert int(count) == 4
    np.testing.assert_array_equal(keys, [2, 3, 7, 9, 100, 100])
    np.testing.assert_array_equal(keys[slots], index)


@pytest.mark.slow  # by default the equality runs on S2 (test_sparse_grid_equals_dense_grid_on_s2)
def test_sparse_grid_equals_dense_grid(collapse):
    """With enough slots the sparse grid renumbers the dense grid's nodes and nothing else: the
    final state is the same to the last bit in float64 (measured: identical), and a smaller
    capacity that still holds the touched nodes changes nothing."""
    cfg, state, params = collapse.config, collapse.state, collapse.params
    dense = jax.jit(make_rollout(cfg, observer=None))(state, params)[0]
    for capacity in (cfg.grid.n_nodes, 160):
        got = jax.jit(make_rollout(dataclasses.replace(cfg, active_nodes=capacity), observer=None))(state, params)[0]
        assert int(got.status) == 0 and int(got.steps) == int(dense.steps)
        for name in ("x", "v", "C", "F", "tau"):
            np.testing.assert_allclose(getattr(got, name), getattr(dense, name), rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.slow  # 11 s; the sparse grid's slots and flags are tested by default
def test_sparse_grid_equals_dense_grid_on_s2():
    """S2 (two gates lifted at 2.5 m/s: moving walls, whose contact uses the slots' node
    positions), coarse, over 0.03 s: the same to float64 round-off."""
    from jaxmpm.scenes import gates_collapse

    cfg, state, params = gates_collapse(dx=0.005, t_end=0.03)
    dense = jax.jit(make_rollout(cfg, observer=None))(state, params)[0]
    got = jax.jit(make_rollout(dataclasses.replace(cfg, active_nodes=9 * state.n_particles), observer=None))(
        state, params)[0]
    assert int(got.status) == 0 and int(got.steps) == int(dense.steps) > 10
    for name in ("x", "v", "tau"):
        np.testing.assert_allclose(getattr(got, name), getattr(dense, name), rtol=1e-12, atol=1e-12, err_msg=name)


def test_full_sparse_grid_is_flagged(collapse):
    cfg = dataclasses.replace(collapse.config, active_nodes=60)
    result = jm.simulate(cfg, collapse.state, collapse.params, observer=None, throw=False)
    assert int(result.state.status) & jm.GRID_FULL
    assert any("active_nodes" in text for text in jm.describe_status(int(result.state.status)))


@pytest.mark.slow  # 35 s; the forward equality runs by default
def test_sparse_grid_gradient_and_batch_equal_the_dense_grid(collapse):
    """d(mean final height)/dβ through 100 steps, and a vmapped pair of β, on both grids."""
    cfg = dataclasses.replace(collapse.config, t_end=10.0, max_steps=100)
    state, params = collapse.state, collapse.params

    def height(c):
        rollout = make_rollout(c, observer=None)
        return lambda b: jnp.mean(rollout(state, params.replace(beta=b))[0].x[:, 1])

    configs = (cfg, dataclasses.replace(cfg, active_nodes=200))
    dense_g, sparse_g = (jax.jit(jax.grad(height(c)))(params.beta) for c in configs)
    assert np.isfinite(dense_g) and dense_g != 0.0
    np.testing.assert_allclose(sparse_g, dense_g, rtol=1e-10)
    betas = jnp.asarray([0.0, 0.3])
    dense_b, sparse_b = (jax.jit(jax.vmap(height(c)))(betas) for c in configs)
    np.testing.assert_allclose(sparse_b, dense_b, rtol=1e-12)


def test_active_nodes_is_checked():
    grid = jm.Grid((8, 8), 0.1)
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="active_nodes must be a positive integer"):
            jm.Config(grid=grid, t_end=0.1, max_steps=10, active_nodes=bad)
    with pytest.raises(ValueError, match="must fit in int32"):
        jm.Config(grid=jm.Grid((50_000, 50_000), 0.1), t_end=0.1, max_steps=10, active_nodes=100)


def test_slot_positions_are_the_dense_node_positions():
    grid = jm.Grid((5, 7), 0.13, origin=(-0.4, 1.1))
    keys = jnp.arange(grid.n_nodes, dtype=jnp.int32)
    np.testing.assert_array_equal(sparse.slot_positions(keys, grid, jnp.float64), grid.node_positions().T)
    x = jnp.asarray([[0.05, 1.6], [0.21, 1.9]])
    st = make_stencil(x, grid)
    slots, held, _ = sparse.activate(st.index, 40, grid.n_nodes)
    np.testing.assert_array_equal(held[slots], st.index)
