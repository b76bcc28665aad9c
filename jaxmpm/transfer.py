"""Particle-to-grid and grid-to-particle transfers (docs/model.md §5).

P2G is APIC: node momentum sum_p w_ip m_p (v_p + C_p (x_i - x_p)), with internal force
-sum_p V0_p τ_p ∇w_ip accumulated in the same scatter. G2P blends FLIP into PIC (AFLIP, Fei et
al. 2021): v_p <- α (v_p + sum_i w_ip (v_i^new - v_i^old)) + (1 - α) v_PIC, keeps the affine
matrix C_p = (4/dx²) sum_i w_ip v_i^new (x_i - x_p)ᵀ (zero for plain PIC), and reports the PIC
velocity (which moves the particles) and the velocity gradient sum_i v_i^new ⊗ ∇w_ip.

Layout, chosen by measurement on the CPU (docs/performance.md): grid fields are channel-major
(channels, n_nodes); per-particle values are planes (lists of (N,) arrays, ``jaxmpm.linalg``);
P2G scatters each channel on its own (a multi-channel scatter makes XLA interleave the channels
into rows first, which costs more than the scatters), one (N,) plane per stencil entry added in
place, and G2P gathers each grid channel on its own. In 3D, P2G first stores the
particle planes it reads (v, C, τ) contiguously, and G2P sums the 27 gathered nodes of a channel
axis by axis (the weights are products w_x w_y w_z): together 0.8 of a 3D step's time; neither
changes a 2D step, which keeps the plain sums.

Reverse mode: each transfer runs under ``jax.checkpoint``, so that its VJP keeps only its inputs
(the stencil's planes, the particles' planes, the grid's arrays). A scatter or a gather is linear
and its transpose needs only the node indices; the per-particle products it scatters or gathers
are recomputed in the backward pass beside their derivatives, where XLA fuses them, instead of
being stored: the elastic block's step stores 200 arrays instead of 474, and its gradient costs
about 4.8 forward runs instead of 6.3 (docs/performance.md, "Reverse mode"). Values and
forward-mode derivatives are those of the plain functions (``_p2g``, ``_g2p_planes``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .kernels import APIC_INERTIA, Stencil
from .linalg import planes, safe_div, unplanes

__all__ = ["GridFields", "Transferred", "p2g", "grid_velocities", "g2p", "g2p_planes", "xpic_velocity"]


class GridFields(NamedTuple):
    mass: jnp.ndarray  # (n_nodes,)
    momentum: jnp.ndarray  # (dim, n_nodes)
    force: jnp.ndarray  # (dim, n_nodes) internal force
    pressure: jnp.ndarray | None = None  # (n_nodes,) Σ w V p, where asked for (side walls)


class Transferred(NamedTuple):
    """G2P's results: arrays from ``g2p``, planes (lists of (N,) arrays) from ``g2p_planes``."""

    v: jnp.ndarray  # (N, dim) new particle velocity (AFLIP blend)
    v_pic: jnp.ndarray  # (N, dim) PIC velocity: moves the particles
    C: jnp.ndarray  # (N, dim, dim) affine matrix
    grad_v: jnp.ndarray  # (N, dim, dim) velocity gradient


def _vector_planes(a):
    return list(jnp.unstack(a, axis=-1))  # unstack transposes into a stack (``jaxmpm.linalg.planes``)


def _matrix_planes(a):
    return planes(a)


def _contiguous(tree):
    """The planes of ``tree`` stored side by side in one array, read back as planes. The 3D P2G
    builds 189 (N,) planes, each of which reads entries of v, C and τ; read in place from the
    (N, d, d) state arrays, each is a strided load, which costs a 3D step 10 % more."""
    leaves, treedef = jax.tree.flatten(tree)
    return jax.tree.unflatten(treedef, list(jnp.unstack(jax.lax.optimization_barrier(jnp.stack(leaves)))))


def p2g(stencil: Stencil, mass, v, C, vol0, tau, n_nodes: int, pressure=None) -> GridFields:
    """Scatter mass, APIC momentum and internal force to the grid. ``v`` (N, dim) and ``C``,
    ``tau`` (N, dim, dim) are arrays or planes. ``pressure`` (N,), if given, is scattered too
    (``GridFields.pressure``: Σ_p w_ip pressure_p)."""
    return _p2g_remat(stencil, mass, v, C, vol0, tau, n_nodes, pressure)


def _p2g(stencil: Stencil, mass, v, C, vol0, tau, n_nodes: int, pressure=None) -> GridFields:
    v = _vector_planes(v) if hasattr(v, "shape") else v
    C = _matrix_planes(C) if hasattr(C, "shape") else C
    tau = _matrix_planes(tau) if hasattr(tau, "shape") else tau
    dim = len(v)
    if dim == 3:
        v, C, tau = _contiguous((v, C, tau))
    # One scalar scatter per channel and stencil entry, each adding one (N,) plane in place into
    # the channel's grid array: stacking a channel's S planes for a single scatter costs a
    # concatenation and a layout copy of the (S, N) updates, 0.3 of a 3D P2G.
    rows = jnp.unstack(stencil.index)
    empty = jnp.zeros((n_nodes,), mass.dtype)
    grid_mass, momentum, force = empty, [empty] * dim, [empty] * dim
    grid_pressure = None if pressure is None else empty
    for s, row in enumerate(rows):
        mw = mass * stencil.weight_plane(s)
        grid_mass = grid_mass.at[row].add(mw)
        for a in range(dim):
            affine = sum(C[a][b] * stencil.offset_plane(s, b) for b in range(dim))
            momentum[a] = momentum[a].at[row].add(mw * (v[a] + affine))
            force[a] = force[a].at[row].add(-vol0 * sum(tau[a][b] * stencil.grad_plane(s, b) for b in range(dim)))
        if pressure is not None:
            grid_pressure = grid_pressure.at[row].add(pressure * stencil.weight_plane(s))
    return GridFields(grid_mass, jnp.stack(momentum), jnp.stack(force), grid_pressure)


def grid_velocities(fields: GridFields, dt, gravity):
    """Old (p/m) and updated ((p + dt f)/m + dt g) node velocities, (dim, n_nodes); zero on
    empty nodes."""
    inv_mass = safe_div(1.0, fields.mass)
    v_old = fields.momentum * inv_mass
    v_new = (fields.momentum + dt * fields.force) * inv_mass
    v_new = jnp.where(fields.mass > 0, v_new + dt * gravity[:, None], 0.0)
    return v_old, v_new


def g2p_planes(stencil: Stencil, v_old, v_new, v_p, dx, transfer: str, alpha: float) -> Transferred:
    """G2P with the chosen transfer, every result as planes. ``v_p`` (planes) is the particle
    velocity the FLIP part starts from (the particles' own, or its XPIC filter)."""
    return _g2p_remat(stencil, v_old, v_new, v_p, dx, transfer, alpha)


def _g2p_planes(stencil: Stencil, v_old, v_new, v_p, dx, transfer: str, alpha: float) -> Transferred:
    dim = v_new.shape[0]
    if dim == 3:
        return _g2p3(stencil, v_old, v_new, v_p, dx, transfer, alpha)
    n_stencil = stencil.index.shape[0]
    flip = transfer != "pic" and alpha != 0.0
    # (S, N) gathers split into rows by ``unstack``, whose transpose is one ``stack``: indexing
    # the rows (``g[s]``) would transpose into S padded (S, N) arrays summed element by element,
    # which made the reverse pass of G2P cost 9 forward G2Ps (docs/performance.md).
    new = [jnp.unstack(v_new[a][stencil.index]) for a in range(dim)]  # S (N,) rows each
    old = [jnp.unstack(v_old[a][stencil.index]) for a in range(dim)] if flip else None
    weights = [stencil.weight_plane(s) for s in range(n_stencil)]

    def over_stencil(term):
        return sum(term(s) for s in range(n_stencil))

    v_pic = [over_stencil(lambda s, a=a: weights[s] * new[a][s]) for a in range(dim)]
    grad_v = [[over_stencil(lambda s, a=a, b=b: new[a][s] * stencil.grad_plane(s, b)) for b in range(dim)]
              for a in range(dim)]
    if transfer == "pic":
        zero = jnp.zeros_like(v_pic[0])
        return Transferred(v_pic, v_pic, [[zero] * dim for _ in range(dim)], grad_v)
    scale = APIC_INERTIA / dx**2
    C = [[scale * over_stencil(lambda s, a=a, b=b: weights[s] * new[a][s] * stencil.offset_plane(s, b))
          for b in range(dim)] for a in range(dim)]
    if not flip:
        return Transferred(v_pic, v_pic, C, grad_v)
    dv = [over_stencil(lambda s, a=a: weights[s] * (new[a][s] - old[a][s])) for a in range(dim)]
    v = [alpha * (v_p[a] + dv[a]) + (1.0 - alpha) * v_pic[a] for a in range(dim)]
    return Transferred(v, v_pic, C, grad_v)


# The transfers' bodies under ``jax.checkpoint`` (the module docstring, "Reverse mode").
_p2g_remat = jax.checkpoint(_p2g, static_argnums=(6,))
_g2p_remat = jax.checkpoint(_g2p_planes, static_argnums=(4, 5, 6))


def _axis_sums(rows, w, dw, wo):
    """Of one gathered channel g (27 rows, node (i, j, k) at 9i + 3j + k), the sums Σ w g, Σ ∇w g
    (3) and Σ w (x_i - x_p) g (3), summed over z, then y, then x: with the weights products
    w_x w_y w_z the partial sums are shared between the seven. ``w``, ``dw``, ``wo`` per axis:
    the weights, their derivatives and the weights times the offsets."""
    def z_sum(f, i, j):
        return sum(f[2][k] * rows[9 * i + 3 * j + k] for k in range(3))

    def y_sum(f, part, i):
        return sum(f[1][j] * part[i][j] for j in range(3))

    def x_sum(f, part):
        return sum(f[0][i] * part[i] for i in range(3))

    z_w, z_dw, z_wo = ([[z_sum(f, i, j) for j in range(3)] for i in range(3)] for f in (w, dw, wo))
    ww = [y_sum(w, z_w, i) for i in range(3)]
    value = x_sum(w, ww)
    grad = [x_sum(dw, ww), x_sum(w, [y_sum(dw, z_w, i) for i in range(3)]),
            x_sum(w, [y_sum(w, z_dw, i) for i in range(3)])]
    moment = [x_sum(wo, ww), x_sum(w, [y_sum(wo, z_w, i) for i in range(3)]),
              x_sum(w, [y_sum(w, z_wo, i) for i in range(3)])]
    return value, grad, moment


def _weighted_sum(rows, w):
    """Σ w g of one gathered channel (27 rows), summed axis by axis."""
    return sum(w[0][i] * sum(w[1][j] * sum(w[2][k] * rows[9 * i + 3 * j + k] for k in range(3)) for j in range(3))
               for i in range(3))


def _g2p3(stencil: Stencil, v_old, v_new, v_p, dx, transfer: str, alpha: float) -> Transferred:
    """``g2p_planes`` in 3D, each channel's sums over the stencil taken axis by axis (``_axis_sums``)."""
    flip = transfer != "pic" and alpha != 0.0
    w, dw = stencil.w, stencil.dw
    wo = [[w[b][k] * stencil.off[b][k] for k in range(3)] for b in range(3)]
    sums = [_axis_sums(jnp.unstack(v_new[a][stencil.index]), w, dw, wo) for a in range(3)]
    v_pic = [s[0] for s in sums]
    grad_v = [s[1] for s in sums]
    if transfer == "pic":
        zero = jnp.zeros_like(v_pic[0])
        return Transferred(v_pic, v_pic, [[zero] * 3 for _ in range(3)], grad_v)
    scale = APIC_INERTIA / dx**2
    C = [[scale * m for m in s[2]] for s in sums]
    if not flip:
        return Transferred(v_pic, v_pic, C, grad_v)
    dv = [v_pic[a] - _weighted_sum(jnp.unstack(v_old[a][stencil.index]), w) for a in range(3)]
    v = [alpha * (v_p[a] + dv[a]) + (1.0 - alpha) * v_pic[a] for a in range(3)]
    return Transferred(v, v_pic, C, grad_v)


def g2p(stencil: Stencil, v_old, v_new, v_p, dx, transfer: str, alpha: float) -> Transferred:
    """Gather node velocities back to particles with the chosen transfer (``g2p_planes`` with
    array results: v, v_pic (N, dim), C, grad_v (N, dim, dim)). ``v_p`` (N, dim) is the particle
    velocity the FLIP part starts from (the particles' own, or its XPIC filter)."""
    out = g2p_planes(stencil, v_old, v_new, _vector_planes(v_p), dx, transfer, alpha)
    return Transferred(jnp.stack(out.v, -1), jnp.stack(out.v_pic, -1), unplanes(out.C), unplanes(out.grad_v))


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
    weight = stencil.weight
    inv_mass = safe_div(1.0, grid_mass)
    mw = mass * weight  # (S, N)
    empty = jnp.zeros_like(grid_mass)

    def project(vp):  # (dim, N) particle values -> (dim, nodes): T
        return jnp.stack([empty.at[index].add((mw * vp[a]).reshape(-1)) for a in range(dim)]) * inv_mass

    def interpolate(vg):  # (dim, nodes) -> (dim, N): S
        return jnp.sum(weight * vg[:, stencil.index], axis=1)

    v_k = project(v_p.T)
    total = order * v_k
    for k in range(2, order + 1):
        v_k = project(interpolate(v_k))
        total = total + (-1) ** (k + 1) * comb(order, k) * v_k
    return interpolate(total).T
