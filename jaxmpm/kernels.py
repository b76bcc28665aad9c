"""Quadratic B-spline shape functions on a dense grid (docs/model.md §5).

A particle at x (grid units xi = (x - origin) / dx) touches the 3 nodes per axis starting at
``base = floor(xi - 0.5)``. With ``fx = xi - base`` in [0.5, 1.5) the weights are

    w0 = (1.5 - fx)^2 / 2,   w1 = 0.75 - (fx - 1)^2,   w2 = (fx - 0.5)^2 / 2,

which sum to one and reproduce linear fields exactly (sum_i w_i (x_i - x_p) = 0). The tensor
product over ``dim`` axes gives S = 3^dim weights per particle, in row-major node order.

Layout: stencil data is stencil-major, (S, N), and vector-valued data component-first,
(dim, S, N), so that every kernel runs over contiguous planes and sums over the stencil are
sums of S planes. On the CPU this is several times faster than particle-major (N, S, dim).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["Stencil", "bspline_weights", "make_stencil", "node_strides", "APIC_INERTIA"]

#: Inverse of the APIC inertia tensor D = dx^2/4 I for quadratic B-splines, in units of 1/dx^2.
APIC_INERTIA = 4.0


class Stencil(NamedTuple):
    """Per-particle interpolation data for S = 3^dim nodes each."""

    index: jnp.ndarray  # (S, N) int32 flat node index
    weight: jnp.ndarray  # (S, N) w_ip
    grad: jnp.ndarray  # (dim, S, N) ∇w_ip (1/m)
    offset: jnp.ndarray  # (dim, S, N) x_i - x_p (m)


def bspline_weights(fx):
    """Weights and derivatives d/dfx for the 3 nodes, each a list of 3 arrays shaped like fx."""
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    dw = [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]
    return w, dw


def node_strides(node_shape) -> np.ndarray:
    """Strides of the flat, row-major node numbering."""
    return np.cumprod((1,) + tuple(node_shape[::-1]))[:-1][::-1].astype(np.int32)


def _outer(per_axis):
    """Tensor product over axes of per-axis (3, N) arrays, flattened to (3^dim, N)."""
    dim = len(per_axis)
    out = 1.0
    for a, arr in enumerate(per_axis):
        shape = tuple(3 if b == a else 1 for b in range(dim)) + (arr.shape[-1],)
        out = out * arr.reshape(shape)
    return out.reshape(-1, per_axis[0].shape[-1])


def make_stencil(x, grid) -> Stencil:
    """Weights, gradients, node offsets and flat node indices for particles at ``x`` (N, dim)
    on ``grid`` (a ``config.Grid``).

    Base indices are clamped into the grid on non-periodic axes, so that a stray particle can
    never write into another row of the flat grid; the step records such particles in the
    status bits (``state.LEFT_GRID``). On periodic axes node indices wrap around.
    """
    dim = x.shape[-1]
    dx, node_shape = grid.dx, grid.nodes
    xi = (x - jnp.asarray(grid.origin, x.dtype)) / dx
    base = jnp.floor(xi - 0.5).astype(jnp.int32)
    clamp_hi = np.where(grid.periodic, np.iinfo(np.int32).max, np.asarray(node_shape) - 3).astype(np.int32)
    clamp_lo = np.where(grid.periodic, np.iinfo(np.int32).min, 0).astype(np.int32)
    base = jnp.clip(base, clamp_lo, clamp_hi)
    fx = xi - base.astype(x.dtype)  # (N, dim)

    w_axis, dw_axis, off_axis = [], [], []
    for a in range(dim):
        w, dw = bspline_weights(fx[:, a])
        w_axis.append(jnp.stack(w))
        dw_axis.append(jnp.stack(dw) / dx)
        off_axis.append((jnp.arange(3, dtype=x.dtype)[:, None] - fx[None, :, a]) * dx)
    weight = _outer(w_axis)
    grad = jnp.stack([_outer(w_axis[:a] + [dw_axis[a]] + w_axis[a + 1 :]) for a in range(dim)])
    ones = jnp.ones_like(w_axis[0])
    offset = jnp.stack([_outer([ones] * a + [off_axis[a]] + [ones] * (dim - a - 1)) for a in range(dim)])

    strides = node_strides(node_shape)
    if any(grid.periodic):
        per_axis = []
        for a in range(dim):
            nodes = base[None, :, a] + jnp.arange(3, dtype=jnp.int32)[:, None]  # (3, N)
            if grid.periodic[a]:
                nodes = jnp.mod(nodes, node_shape[a])
            per_axis.append(nodes * strides[a])
        index = sum(
            p.reshape(tuple(3 if b == a else 1 for b in range(dim)) + (p.shape[-1],)) for a, p in enumerate(per_axis)
        ).reshape(-1, x.shape[0])
    else:
        flat_offsets = np.array([0], np.int32)
        for a in range(dim):
            flat_offsets = (flat_offsets[:, None] + np.arange(3, dtype=np.int32)[None, :] * strides[a]).reshape(-1)
        index = jnp.asarray(flat_offsets)[:, None] + jnp.sum(base * strides, axis=-1, dtype=jnp.int32)[None, :]
    return Stencil(index=index, weight=weight, grad=grad, offset=offset)
