"""Differentiable observables of a collapse: deposit height profile and front position.

Both are smooth functions of particle positions and volumes, so they can sit inside a loss:
- ``deposit_profile``: h(x) = Σ_p A_p K_σ(x - x_p) with A_p the particle's current area in the
  (x, y) plane (2D: V_p; 3D: V_p / channel width) and K_σ a normalised Gaussian of width σ
  (default: the particle spacing dx/ppc, which makes h of a uniform layer flat). The current
  volume is V_p = V0 det(F_e) exp(ε_v^p) (elastic and plastic volume change).
- ``front_position``: a smooth maximum of the particles' x, σ_f log Σ_p w_p exp(x_p/σ_f), with
  weights w_p = A_p / Σ A_p; it tends to max x_p as σ_f -> 0 and is finite everywhere.
- ``front_from_profile``: the front as the point where h(x) falls below a threshold,
  x_ref + ∫_{x > x_ref} s(h(x)) dx with s a C1 step from 0 to 1 around h_thr. For a connected
  deposit that starts at x_ref (a back wall) this is where the deposit ends; unlike the maximum
  particle x it ignores single particles that detach ahead of the front, and it is how a
  front is read from a measured profile (where the height drops below what can be seen).
Gradients are finite everywhere, including where the profile is empty (h = 0 far from the flow).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .linalg import det

__all__ = ["back_wall_x", "deposit_profile", "front_from_profile", "front_position", "particle_volumes"]


def particle_volumes(state):
    """Current particle volumes V0 det(F_e) exp(ε_v^p) (ε_v^p = 0 for elastic materials)."""
    eps_v_p = state.internal.get("eps_v_p", 0.0) if isinstance(state.internal, dict) else 0.0
    return state.vol0 * det(state.F) * jnp.exp(eps_v_p)


def deposit_profile(x, volumes, xs, sigma, width=None, mirror=None):
    """Height h(xs) of the deposit from particle positions ``x`` (N, dim) and ``volumes`` (N,),
    sampled at ``xs`` (M,), with a Gaussian of width ``sigma`` (m). In 3D pass the channel
    ``width`` (m); the profile is then the width average.

    ``mirror``: the x (m) of a wall the deposit rests against on its left (a collapse's back
    wall, ``back_wall_x``). Without it the kernel reads half the height at the wall, where half
    of it lies behind the wall on no material; with it each particle's image behind the wall
    fills that half (the reflection method), and h is 0 behind the wall."""
    area = volumes if width is None else volumes / width
    xs = jnp.asarray(xs, jnp.asarray(x).dtype)  # the particles' precision (float64 points on float32 runs)

    def smoothed(px):
        z = (xs[:, None] - px[None, :]) / sigma
        return (jnp.exp(-0.5 * z * z) / (sigma * jnp.sqrt(2.0 * jnp.pi))) @ area

    if mirror is None:
        return smoothed(x[:, 0])
    return jnp.where(xs >= mirror, smoothed(x[:, 0]) + smoothed(2.0 * mirror - x[:, 0]), 0.0)


def back_wall_x(walls) -> float | None:
    """The x (m) of the fixed wall facing +x (a collapse's back wall) that deposit profiles are
    mirrored at, the rightmost if several; None without one (gates that lift are not walls the
    deposit rests against)."""
    xs = [float(w.point[0]) for w in walls
          if not w.moving and w.normal[0] == 1.0 and not any(c != 0.0 for c in w.normal[1:])]
    return max(xs) if xs else None


def front_position(x, volumes, sigma):
    """Smooth maximum of particle x (m) with temperature ``sigma`` (m), volume weighted."""
    weights = volumes / jnp.sum(volumes)
    return sigma * jax.nn.logsumexp(x[:, 0] / sigma, b=weights)


def front_from_profile(xs, h, threshold, x_ref=0.0, softness=None):
    """Front position (m) from a profile ``h`` sampled on a uniform grid ``xs``: ``x_ref`` plus
    the length beyond ``x_ref`` where h exceeds ``threshold`` (m). The step is the C1 smoothstep
    3u² − 2u³ over h ∈ [threshold − softness, threshold + softness] (default softness:
    threshold / 2): exactly 0 below, so empty ground adds nothing (and a zero gradient), and
    exactly 1 above. Assumes the deposit is connected beyond ``x_ref``."""
    xs = jnp.asarray(xs)
    step = xs[1] - xs[0]
    softness = threshold / 2.0 if softness is None else softness
    u = jnp.clip((h - threshold + softness) / (2.0 * softness), 0.0, 1.0)
    inside = u * u * (3.0 - 2.0 * u)
    return x_ref + step * jnp.sum(jnp.where(xs >= x_ref, inside, 0.0))
