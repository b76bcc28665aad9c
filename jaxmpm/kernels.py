"""Quadratic B-spline shape functions on a dense grid (docs/model.md §5).

A particle at x (grid units xi = (x - origin) / dx) touches the 3 nodes per axis starting at
``base = floor(xi - 0.5)``. With ``fx = xi - base`` in [0.5, 1.5) the weights are

    w0 = (1.5 - fx)^2 / 2,   w1 = 0.75 - (fx - 1)^2,   w2 = (fx - 0.5)^2 / 2,

which sum to one and reproduce linear fields exactly (sum_i w_i (x_i - x_p) = 0). The tensor
product over ``dim`` axes gives S = 3^dim weights per particle, in row-major node order.

Layout: a stencil keeps each axis's three weights, their derivatives and the node offsets as
separate (N,) arrays, and the S weights of a particle are formed where they are used, as
products of contiguous arrays (``Stencil.weight_plane``): XLA's CPU backend vectorises such
products, while building (S, N) tensors from stacked per-axis arrays made it emit slow,
unvectorised kernels. The (S, N) arrays (``weight``, ``grad``, ``offset``) remain available.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["Stencil", "bspline_weights", "make_stencil", "node_strides", "stencil_nodes", "APIC_INERTIA"]

#: Inverse of the APIC inertia tensor D = dx^2/4 I for quadratic B-splines, in units of 1/dx^2.
APIC_INERTIA = 4.0


def stencil_nodes(dim: int) -> tuple[tuple[int, ...], ...]:
    """The per-axis node numbers (0, 1 or 2 along each axis) of the S = 3^dim stencil entries,
    in row-major order (the last axis fastest), the order of ``Stencil.index``."""
    return tuple(itertools.product(range(3), repeat=dim))


class Stencil(NamedTuple):
    """Per-particle interpolation data for S = 3^dim nodes each.

    ``w[a][k]``, ``dw[a][k]`` and ``off[a][k]`` are the weight, its derivative and the offset
    x_i - x_p of node k (0, 1, 2) along axis a, each an (N,) array."""

    index: jnp.ndarray  # (S, N) int32 flat node index
    w: tuple  # per axis, the 3 weights
    dw: tuple  # per axis, d w / d x (1/m)
    off: tuple  # per axis, x_i - x_p (m)

    @property
    def dim(self) -> int:
        return len(self.w)

    def weight_plane(self, s: int):
        """w_ip of stencil entry ``s`` (an (N,) array)."""
        node = stencil_nodes(self.dim)[s]
        out = self.w[0][node[0]]
        for a in range(1, self.dim):
            out = out * self.w[a][node[a]]
        return out

    def grad_plane(self, s: int, b: int):
        """Component ``b`` of ∇w_ip of stencil entry ``s`` (1/m)."""
        node = stencil_nodes(self.dim)[s]
        out = None
        for a in range(self.dim):
            factor = self.dw[a][node[a]] if a == b else self.w[a][node[a]]
            out = factor if out is None else out * factor
        return out

    def offset_plane(self, s: int, b: int):
        """Component ``b`` of x_i - x_p of stencil entry ``s`` (m)."""
        return self.off[b][stencil_nodes(self.dim)[s][b]]

    @property
    def weight(self):
        """(S, N) weights."""
        return jnp.stack([self.weight_plane(s) for s in range(3**self.dim)])

    @property
    def grad(self):
        """(dim, S, N) weight gradients (1/m)."""
        return jnp.stack([jnp.stack([self.grad_plane(s, b) for s in range(3**self.dim)]) for b in range(self.dim)])

    @property
    def offset(self):
        """(dim, S, N) node offsets x_i - x_p (m)."""
        return jnp.stack([jnp.stack([self.offset_plane(s, b) for s in range(3**self.dim)]) for b in range(self.dim)])


def bspline_weights(fx):
    """Weights and derivatives d/dfx for the 3 nodes, each a list of 3 arrays shaped like fx."""
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    dw = [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]
    return w, dw


def node_strides(node_shape) -> np.ndarray:
    """Strides of the flat, row-major node numbering."""
    return np.cumprod((1,) + tuple(node_shape[::-1]))[:-1][::-1].astype(np.int32)


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
    for f in jnp.unstack(fx, axis=-1):  # unstack: its transpose is a stack (linalg.planes)
        w, dw = bspline_weights(f)
        w_axis.append(tuple(w))
        dw_axis.append(tuple(d / dx for d in dw))
        off_axis.append(tuple((k - f) * dx for k in range(3)))

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
    return Stencil(index=index, w=tuple(w_axis), dw=tuple(dw_axis), off=tuple(off_axis))
