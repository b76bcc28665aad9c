"""Reverse mode's layout: planes split by ``unstack`` (whose transpose is one
stack, where indexing transposes into padded arrays summed element by element) give the values
and gradients of the indexing-based reference to round-off (float64), and finite gradients at
F = I."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.kernels import make_stencil
from jaxmpm.linalg import planes
from jaxmpm.transfer import g2p_planes

jax.config.update("jax_enable_x64", True)


def _reference_planes(a):
    return [[a[..., i, j] for j in range(a.shape[-1])] for i in range(a.shape[-2])]


def _sum_sq(tree):
    return sum(jnp.sum(jnp.sin(x) * x) for x in jax.tree.leaves(tree))


@pytest.mark.parametrize("dim", [2, 3])
def test_planes_match_indexing(dim):
    a = jnp.asarray(np.random.default_rng(0).normal(size=(7, dim, dim)))
    assert all(np.array_equal(p, r) for p, r in zip(jax.tree.leaves(planes(a)), jax.tree.leaves(_reference_planes(a))))
    g, g_ref = (jax.grad(lambda a, f=f: _sum_sq(f(a)))(a) for f in (planes, _reference_planes))
    np.testing.assert_allclose(g, g_ref, rtol=1e-15, atol=1e-15)
    t = jnp.ones_like(a)
    np.testing.assert_array_equal(jax.jvp(planes, (a,), (t,))[1], jax.jvp(_reference_planes, (a,), (t,))[1])


@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])  # 3D: 22 s of compiling
def test_g2p_gradient_matches_indexed_gather(dim):
    """g2p_planes (rows by unstack) against the same sums over rows indexed from the gather."""
    config, state, _ = jm.scenes.falling_block(n_particles=8**dim // 2 ** (dim - 1), dim=dim, dtype="float64")
    grid = config.grid
    rng = np.random.default_rng(1)
    v_old, v_new = (jnp.asarray(rng.normal(size=(dim, grid.n_nodes))) for _ in range(2))
    v_p = list(jnp.unstack(state.v + 0.1, axis=-1))

    def new(x, a, b, v):
        return g2p_planes(make_stencil(x, grid), a, b, v, grid.dx, "aflip", 0.95)

    def reference(x, a, b, v):
        st = make_stencil(x, grid)
        out = {"v_pic": [], "dv": []}
        for c in range(dim):
            gn, go = b[c][st.index], a[c][st.index]
            out["v_pic"].append(sum(st.weight_plane(s) * gn[s] for s in range(3**dim)))
            out["dv"].append(sum(st.weight_plane(s) * (gn[s] - go[s]) for s in range(3**dim)))
            out[f"grad{c}"] = [sum(gn[s] * st.grad_plane(s, e) for s in range(3**dim)) for e in range(dim)]
            out[f"C{c}"] = [4.0 / grid.dx**2 * sum(st.weight_plane(s) * gn[s] * st.offset_plane(s, e)
                                                    for s in range(3**dim)) for e in range(dim)]
        out["v"] = [0.95 * (v[c] + out["dv"][c]) + 0.05 * out["v_pic"][c] for c in range(dim)]
        del out["dv"]
        return out

    def as_dict(t):
        return {"v_pic": t.v_pic, "v": t.v, **{f"grad{c}": t.grad_v[c] for c in range(dim)},
                **{f"C{c}": t.C[c] for c in range(dim)}}

    args = (state.x, v_old, v_new, v_p)
    for a, b in zip(jax.tree.leaves(as_dict(new(*args))), jax.tree.leaves(reference(*args))):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)
    g = jax.grad(lambda *a: _sum_sq(as_dict(new(*a))), argnums=(0, 1, 2, 3))(*args)
    g_ref = jax.grad(lambda *a: _sum_sq(reference(*a)), argnums=(0, 1, 2, 3))(*args)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_ref)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11)
