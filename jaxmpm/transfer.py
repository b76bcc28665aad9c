"""Particle-to-grid and grid-to-particle transfers (docs/model.md §5).

P2G is APIC: node momentum sum_p w_ip m_p (v_p + C_p (x_i - x_p)), with internal force
-sum_p V0_p τ_p ∇w_ip accumulated in the same scatter. G2P blends FLIP into PIC (AFLIP, Fei et
al. 2021): v_p <- α (v_p + sum_i w_ip (v_i^new - v_i^old)) + (1 - α) v_PIC, keeps the affine
matrix C_p = (4/dx²) sum_i w_ip v_i^new (x_i - x_p)ᵀ (zero for plain PIC), and reports the PIC
velocity (which moves the particles) and the velocity gradient sum_i v_i^new ⊗ ∇w_ip.

Layout, chosen by measurement on the CPU: grid fields are channel-major (channels, n_nodes);
stencil data is (S, N) planes (see ``kernels``); small-matrix algebra is unrolled over the
dimension. The gathered node values pass an ``optimization_barrier``: fusing the gather into
the reductions that consume it made XLA's CPU backend 3-4 times slower.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .kernels import APIC_INERTIA, Stencil
from .linalg import safe_div

__all__ = ["GridFields", "Transferred", "p2g", "grid_velocities", "g2p", "xpic_velocity"]


class GridFields(NamedTuple):
    mass: jnp.ndarray  # (n_nodes,)
    momentum: jnp.ndarray  # (dim, n_nodes)
    force: jnp.ndarray  # (dim, n_nodes) internal force


class Transferred(NamedTuple):
    v: jnp.ndarray  # (N, dim) new particle velocity (AFLIP blend)
    v_pic: jnp.ndarray  # (N, dim) PIC velocity: moves the particles
    C: jnp.ndarray  # (N, dim, dim) affine matrix
    grad_v: jnp.ndarray  # (N, dim, dim) velocity gradient


def p2g(stencil: Stencil, mass, v, C, vol0, tau, n_nodes: int) -> GridFields:
    """Scatter mass, APIC momentum and internal force to the grid in one pass."""
    dim = v.shape[-1]
    mw = mass * stencil.weight  # (S, N)
    channels = [mw]
    for a in range(dim):
        affine = sum(C[:, a, b] * stencil.offset[b] for b in range(dim))
        channels.append(mw * (v[:, a] + affine))
    for a in range(dim):
        channels.append(-vol0 * sum(tau[:, a, b] * stencil.grad[b] for b in range(dim)))
    # One scalar scatter per channel: a multi-channel scatter makes XLA interleave the channels
    # into rows first, which costs more than the scatters themselves.
    index = stencil.index.reshape(-1)
    empty = jnp.zeros((n_nodes,), v.dtype)
    grid = [empty.at[index].add(c.reshape(-1)) for c in jax.lax.optimization_barrier(channels)]
    return GridFields(grid[0], jnp.stack(grid[1 : 1 + dim]), jnp.stack(grid[1 + dim :]))


def grid_velocities(fields: GridFields, dt, gravity):
    """Old (p/m) and updated ((p + dt f)/m + dt g) node velocities, (dim, n_nodes); zero on
    empty nodes."""
    inv_mass = safe_div(1.0, fields.mass)
    v_old = fields.momentum * inv_mass
    v_new = (fields.momentum + dt * fields.force) * inv_mass
    v_new = jnp.where(fields.mass > 0, v_new + dt * gravity[:, None], 0.0)
    return v_old, v_new


def g2p(stencil: Stencil, v_old, v_new, v_p, dx, transfer: str, alpha: float) -> Transferred:
    """Gather node velocities back to particles with the chosen transfer. ``v_p`` is the
    particle velocity the FLIP part starts from (the particles' own, or its XPIC filter)."""
    dim = v_p.shape[-1]
    flip = transfer != "pic" and alpha != 0.0
    grid = jnp.concatenate([v_new, v_old]) if flip else v_new
    nodes = jax.lax.optimization_barrier(grid[:, stencil.index])  # (channels, S, N)
    vn = nodes[:dim]
    w = stencil.weight
    v_pic = jnp.sum(w * vn, axis=1).T
    grad_v = _outer_sum(vn, stencil.grad)
    if transfer == "pic":
        return Transferred(v_pic, v_pic, jnp.zeros_like(grad_v), grad_v)
    C = (APIC_INERTIA / dx**2) * _outer_sum(w * vn, stencil.offset)
    if not flip:
        return Transferred(v_pic, v_pic, C, grad_v)
    dv = jnp.sum(w * (vn - nodes[dim:]), axis=1).T
    return Transferred(alpha * (v_p + dv) + (1.0 - alpha) * v_pic, v_pic, C, grad_v)


def _outer_sum(a, b):
    """(N, d, d) matrices sum_s a[i, s] b[j, s] from component-first (d, S, N) arrays."""
    dim = a.shape[0]
    rows = [jnp.stack([jnp.sum(a[i] * b[j], axis=0) for j in range(dim)], -1) for i in range(dim)]
    return jnp.stack(rows, axis=-2)


def xpic_velocity(stencil: Stencil, mass, grid_mass, v_p, order: int):
    """The particle velocity XPIC(m) keeps of the last step (Hammerquist & Nairn 2017), for the
    FLIP part of the update: with S the grid-to-particle interpolation and T the mass-weighted
    particle-to-grid projection (plain PIC, no affine part), A = S T, the FLIP part v_p + S Δv
    becomes [I − (I − A)^m] v_p + S Δv. The null-space noise of v_p (what A maps to zero) is
    removed; m = 1 is PIC, m -> ∞ FLIP. With v_g^(1) = T v_p and v_g^(k+1) = T S v_g^(k) it is
    S Σ_{k=1..m} (−1)^{k+1} C(m, k) v_g^(k): m extra scatters and gathers. Returns (N, dim)."""
    from math import comb

    dim = v_p.shape[-1]
    index = stencil.index.reshape(-1)
    inv_mass = safe_div(1.0, grid_mass)
    mw = mass * stencil.weight  # (S, N)
    empty = jnp.zeros_like(grid_mass)

    def project(vp):  # (dim, N) particle values -> (dim, nodes): T
        return jnp.stack([empty.at[index].add((mw * vp[a]).reshape(-1)) for a in range(dim)]) * inv_mass

    def interpolate(vg):  # (dim, nodes) -> (dim, N): S
        return jnp.sum(stencil.weight * vg[:, stencil.index], axis=1)

    v_k = project(v_p.T)
    total = order * v_k
    for k in range(2, order + 1):
        v_k = project(interpolate(v_k))
        total = total + (-1) ** (k + 1) * comb(order, k) * v_k
    return interpolate(total).T
