"""The critical-state μ(I) rheology (docs/model.md §1-3): Hencky elasticity, a cohesive Modified
Cam-Clay yield surface with associative flow and implicit exponential hardening, and μ(I)
rate dependence through a cohesive inertial number.

Glossary
--------
e            Hencky strain ½ log(F_e F_eᵀ) (symmetric dim×dim); e_v = tr e, dev e its deviator
p, q         pressure -K e_v (compression positive) and q = sqrt(½ s:s), s = 2G dev e
p_c          compressive strength, p_c = p_c0 exp(-ξ ε_v^p)
p̄            effective pressure p + β p_c;  S = sqrt((p_c - p) p̄), so q_static = μ1 S on the surface
y            yield function q² + μ1² (p - p_c)(p + β p_c)
ε            plastic volumetric increment of this step, Δε_v^p = (p - p_tr)/K
γ̇            plastic shear rate of the overstress (μ(I)) law;  I = γ̇ d / sqrt(p̄/ρ_s)

The static return is a one-unknown problem in ε. With p = p_tr + K ε and p_c = p_c,n e^{-ξε},
the flow rule p = p_tr - K Δγ μ1² h, h = 2p + (β-1) p_c, gives Δγ = -ε/(μ1² h), and the radial
return q = q_tr/(1 + 2GΔγ) = q_tr μ1² h / (μ1² h - 2Gε). The root of g(ε) = y(p, q, p_c) lies
between the trial state (ε = 0, g > 0) and the apex of the updated ellipse (h = 0, g < 0); it is
found by a fixed number of safeguarded Newton steps (bisection when a step leaves the bracket).
There is no tip rule (docs/model.md §2, as corrected): a trial state in tension beyond the tip
(p_tr < -β p_c,n) takes the same return, which is continuous in the trial state and reaches the
tension tip p = -β p_c, q = 0 only as q_tr -> 0 (as the reference code's one Newton solve does).
The iterations run on stop-gradient values; one final Newton step on live
values gives the exact implicit-function derivative, so no derivative flows through the loop
and the forward cost of a gradient is that of the forward pass plus one step.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from ..linalg import mm_planes, planes, safe_div, safe_sqrt, sym_exp_planes, unplanes
from .base import Material, lame
from .hencky import hencky_strain_planes

__all__ = ["CriticalState", "return_map", "return_map_planes", "return_invariants", "surface_residual",
           "yield_function", "mu_of_I",
           "INTERNAL_KEYS"]

#: A solve stops once no lane moves by more than STEP_TOL machine epsilons of its scale in one
#: step: at that point a Newton step only moves the root by round-off.
STEP_TOL = 4

#: Internal variables carried per particle: the plastic volumetric strain and the diagnostics of
#: the last update (shear rate γ̇, inertial number I, friction μ(I), plastic flag 0/1, p_c).
INTERNAL_KEYS = ("eps_v_p", "pc", "gamma_dot", "I", "mu_I", "plastic")


def yield_function(p, q, pc, params):
    """y(p, q; p_c) = q² + μ1² (p - p_c)(p + β p_c); <= 0 is admissible."""
    return q * q + params.mu1**2 * (p - pc) * (p + params.beta * pc)


def mu_of_I(I, params):  # noqa: E741 - I is the inertial number, as in μ(I); renaming would change the API
    """μ(I) = μ1 + (μ2 - μ1) I / (I0 + I)."""
    return params.mu1 + (params.mu2 - params.mu1) * safe_div(I, params.I0 + I)


def bulk_modulus(params, dim):
    G, lam = lame(params)
    return G, lam + 2.0 * G / dim


# ---------------------------------------------------------------------------------------------
# Scalar solves (elementwise over particles)


def _iterate(update, carry, iterations, value, scale):
    """Apply ``update`` to ``carry`` until no lane's ``value(carry)`` moves by more than
    ``STEP_TOL`` · ``scale`` in one application, or ``iterations`` times (a ``while_loop``: the
    quadratically converging solves below take 2-4 steps where a fixed count ran 12, and the
    iteration count never affects a derivative, which the final implicit step provides).
    ``scale`` is the lane's natural size; a lane of scale 0 (one whose value is not used, an
    elastic one) never holds the loop."""
    tol = STEP_TOL * jnp.finfo(jnp.result_type(value(carry))).eps * scale

    def cond(state):
        k, moved, _ = state
        return (k < iterations) & moved

    def body(state):
        k, _, c = state
        new = update(c)
        return k + 1, jnp.any((jnp.abs(value(new) - value(c)) > tol) & (scale > 0)), new

    return jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), jnp.asarray(True), carry))[2]


def _apex_increment(p_tr, pc_n, params, K, iterations, scale):
    """ε at the apex of the updated ellipse: h(ε) = 2(p_tr + Kε) - (1-β) p_c,n e^{-ξε} = 0.

    h is increasing and concave in ε, so Newton from the linearised root approaches from the
    left and converges monotonically."""
    one_minus_beta = 1.0 - params.beta

    def h_and_slope(eps):
        pc = pc_n * jnp.exp(-params.xi * eps)
        return 2.0 * (p_tr + K * eps) - one_minus_beta * pc, 2.0 * K + one_minus_beta * params.xi * pc

    h0, s0 = h_and_slope(jnp.zeros_like(p_tr))
    eps = -h0 / s0

    def update(eps):
        h, s = h_and_slope(eps)
        return eps - h / s

    return _iterate(update, eps, iterations, lambda e: e, scale)


def _tip_increments(p_tr, pc_n, params, K, iterations, scale):
    """ε at the compression tip p = p_c and at the tension tip p = -β p_c of the updated ellipse,
    t(ε) = p_tr + Kε ∓ s p_c,n e^{-ξε} = 0 (s = 1, β), by Newton from the root with p_c frozen.

    The return of a trial state far beyond a tip ends near that tip, and Newton on g(ε) from the
    trial state or the bracket's middle only halves the distance per step out there (g is
    quadratic in p): started from the tip it converges at once. t is monotone (K > ξ β p_c
    wherever a step is stable) and convex or concave, so Newton converges from one side."""

    def solve(factor, sign):  # the tip p = sign · factor · p_c
        tip = factor * pc_n

        def update(eps):
            pc = tip * jnp.exp(-params.xi * eps)
            t, slope = p_tr + K * eps - sign * pc, K + sign * params.xi * pc
            return eps - safe_div(t, slope, fill=0.0)

        return _iterate(update, (sign * tip - p_tr) / K, iterations, lambda e: e, scale)

    return solve(1.0, 1.0), solve(params.beta, -1.0)


def _near_apex(eps_apex, q_tr, pc_n, params, K, G):
    """A start for a large overstress, whose return ends just short of the apex (the top of the
    updated ellipse, h = 0): there q(ε) = q_tr μ1²h/(μ1²h − 2Gε) is nearly linear in ε − ε_apex
    while the surface's q_s = μ1 (1+β) p_c/2 barely moves, so the root lies about
    (1+β) p_c (−G ε_apex)/(q_tr μ1 h') from the apex (h' = dh/dε). Newton on g (quadratic in q)
    from the trial state would only halve its distance to this root per step."""
    pc = pc_n * jnp.exp(-params.xi * eps_apex)
    slope = 2.0 * K + (1.0 - params.beta) * params.xi * pc
    return eps_apex + safe_div((1.0 + params.beta) * pc * (-G * eps_apex), q_tr * params.mu1 * slope)


def surface_residual(eps, p_tr, q_tr, pc_n, params, K, G):
    """g(ε) = y(p(ε), q(ε), p_c(ε)) along the return path: the residual of the scalar solve the
    return map's Newton iterations zero (``docs/scripts/profile_step.py`` measures it)."""
    p = p_tr + K * eps
    pc = pc_n * jnp.exp(-params.xi * eps)
    h = 2.0 * p + (params.beta - 1.0) * pc
    mu2h = params.mu1**2 * h
    q = q_tr * safe_div(mu2h, mu2h - 2.0 * G * eps)
    return yield_function(p, q, pc, params)


def _newton_value_and_slope(fn, eps):
    return jax.jvp(fn, (eps,), (jnp.ones_like(eps),))


def _cleared_residual(eps, p_tr, q_tr, pc_n, params, K, G):
    """F(ε) = (μ1²h − 2Gε) q_s − q_tr μ1²h: zero where q(ε) = q_s(ε), the surface's q at p(ε),
    like g, but with the hyperbola q(ε) cleared, so that it is nearly linear in ε wherever q_s
    is smooth (away from the tips). Newton on g from the trial state takes many short steps
    there: q falls as 1/(μ1²h − 2Gε) with 2G far above the pressures. Returns (F, inside):
    ``inside`` where p(ε) lies strictly between the tips, the only place F is a residual."""
    p = p_tr + K * eps
    pc = pc_n * jnp.exp(-params.xi * eps)
    mu2h = params.mu1**2 * (2.0 * p + (params.beta - 1.0) * pc)
    spread = (pc - p) * (p + params.beta * pc)
    inside = spread > 0
    q_surface = params.mu1 * jnp.sqrt(jnp.where(inside, spread, 1.0))
    return (mu2h - 2.0 * G * eps) * q_surface - q_tr * mu2h, inside


def _safeguarded_newton(fn, lo, hi, eps0, iterations, scale, cleared=None):
    """Root of ``fn`` in [lo, hi] with fn(lo) < 0 < fn(hi) (either order of lo, hi in value):
    Newton steps, replaced by bisection when they leave the current bracket, until no lane's
    step exceeds round-off of its ``scale`` plus the bracket's width (at most ``iterations``).
    ``cleared``: a function with the same root, ε -> (F, valid), whose Newton step is taken
    instead where it is valid and stays in the bracket (which follows the sign of ``fn``)."""

    def update(carry):
        eps, neg, pos = carry  # current iterate; bracket ends where fn < 0 and fn > 0
        g, slope = _newton_value_and_slope(fn, eps)
        neg = jnp.where(g < 0, eps, neg)
        pos = jnp.where(g > 0, eps, pos)
        lower, upper = jnp.minimum(neg, pos), jnp.maximum(neg, pos)
        step = eps - safe_div(g, slope, fill=0.0)
        inside = (step >= lower) & (step <= upper) & (slope != 0)
        if cleared is not None:
            (f, valid), (f_slope, _) = jax.jvp(cleared, (eps,), (jnp.ones_like(eps),))
            f_step = eps - safe_div(f, f_slope, fill=0.0)
            f_inside = valid & (f_slope != 0) & (f_step >= lower) & (f_step <= upper)
            step, inside = jnp.where(f_inside, f_step, step), inside | f_inside
        eps = jnp.where(g == 0, eps, jnp.where(inside, step, 0.5 * (neg + pos)))
        return eps, neg, pos

    scale = jnp.where(scale > 0, scale + jnp.abs(hi - lo), 0.0)
    eps, _, _ = _iterate(update, (eps0, lo, hi), iterations, lambda c: c[0], scale)
    return eps


def _implicit_step(fn, eps_star, width):
    """One Newton step from a converged root, on live inputs: its value refines the root and its
    derivative is the implicit-function derivative -(∂fn/∂θ)/(∂fn/∂ε). It is not clipped (a clip
    would zero the derivative of a root on the bracket's edge: a barely plastic state, the
    apex); a correction that is non-finite or larger than the bracket ``width`` (an unconverged
    or discarded lane) is dropped instead."""
    eps_star = jax.lax.stop_gradient(eps_star)
    g, slope = _newton_value_and_slope(fn, eps_star)
    correction = -safe_div(g, jax.lax.stop_gradient(slope), fill=0.0)
    small = jnp.isfinite(correction) & (jnp.abs(correction) <= jax.lax.stop_gradient(width) + 1e-8)
    return eps_star + jnp.where(small, correction, 0.0)


# ---------------------------------------------------------------------------------------------
# The return map


def return_invariants(p_tr, q_tr, eps_v_p, params, dt, dim, iterations=12):
    """Return map in invariants. Returns a dict with p, q, pc, eps_v_p (accumulated), deps_v_p
    (this step), gamma_dot, I, mu_I and plastic (1.0 where the trial state was inadmissible).
    Every inadmissible trial state, in tension beyond -β p_c included, takes the one associative
    return (docs/model.md §2)."""
    G, K = bulk_modulus(params, dim)
    sg = jax.lax.stop_gradient
    pc_n = params.pc0 * jnp.exp(-params.xi * eps_v_p)
    y_tr = yield_function(p_tr, q_tr, pc_n, params)
    plastic = y_tr > 0

    # The loops run on stop-gradient copies of the inputs (their derivatives are never needed);
    # the final implicit step uses the live ones.
    p_s, q_s, pc_s, params_s, K_s, G_s = sg((p_tr, q_tr, pc_n, params, K, G))
    zero = jnp.zeros_like(p_tr)

    # --- regular (cap or shear side) return: root of g(ε) between the trial state (g > 0) and
    # the apex of the updated ellipse (g < 0). Newton starts at the trial state, the middle of
    # the bracket or the nearer tip (compression or tension), whichever has the smallest residual
    # (a barely plastic state starts at the trial state and converges quadratically, one far
    # beyond a tip at the tip); bisection takes over when a step leaves the bracket.
    # The apex solve is a monotone Newton iteration (quadratic convergence from the first step):
    # half the iterations suffice.
    # Each solve stops at round-off of its scale: ε's own size and that of p_tr/K and p_c/K,
    # whose cancellation in p = p_tr + Kε limits how well any ε can be resolved.
    scale = jnp.where(plastic, (jnp.abs(p_s) + pc_s) / K_s, 0.0)
    eps_apex = _apex_increment(p_s, pc_s, params_s, K_s, max(3, iterations // 2), scale)
    residual_s = lambda e: surface_residual(e, p_s, q_s, pc_s, params_s, K_s, G_s)  # noqa: E731
    lo, hi = jnp.minimum(eps_apex, zero), jnp.maximum(eps_apex, zero)
    start, best = zero, jnp.abs(residual_s(zero))
    candidates = (0.5 * eps_apex, _near_apex(eps_apex, q_s, pc_s, params_s, K_s, G_s),
                  *_tip_increments(p_s, pc_s, params_s, K_s, 3, scale))
    for candidate in candidates:
        candidate = jnp.clip(candidate, lo, hi)  # a start inside the bracket (NaN-free: t's slope is > 0)
        g = jnp.abs(residual_s(candidate))
        better = g < best  # False for NaN: a candidate that failed is never taken
        start, best = jnp.where(better, candidate, start), jnp.where(better, g, best)
    cleared_s = lambda e: _cleared_residual(e, p_s, q_s, pc_s, params_s, K_s, G_s)  # noqa: E731
    eps_root = _safeguarded_newton(residual_s, eps_apex, zero, start, iterations, scale, cleared_s)
    eps_reg = _implicit_step(
        lambda e: surface_residual(e, p_tr, q_tr, pc_n, params, K, G), eps_root, jnp.abs(eps_apex)
    )

    eps = jnp.where(plastic, eps_reg, 0.0)
    p = p_tr + K * eps
    pc = pc_n * jnp.exp(-params.xi * eps)
    p_bar = p + params.beta * pc
    S = safe_sqrt(jnp.maximum(pc - p, 0.0) * jnp.maximum(p_bar, 0.0))
    q_static = jnp.minimum(params.mu1 * S, q_tr)  # a return never raises q (round-off near a tip)

    # --- μ(I) overstress on the static state (docs/model.md §3).
    # sqrt(p̄/ρ_s), zero below 1e-20 m²/s² (p̄ ~ 1e-17 Pa): the derivative of I ∝ p̄^(-3/2) stays finite.
    sqrt_p = safe_sqrt(jnp.maximum(p_bar, 0.0) / params.rho_s, eps=1e-20)
    Q = params.I0 * sqrt_p / params.d
    excess = jnp.maximum(q_tr - q_static, 0.0)
    a = G * dt
    b = (params.mu2 - params.mu1) * S + a * Q - excess
    c = -excess * Q
    root = safe_sqrt(b * b - 4.0 * a * c)
    gamma_dot = jnp.where(b >= 0, safe_div(-2.0 * c, b + root), safe_div(-b + root, 2.0 * a))
    gamma_dot = jnp.where(plastic, gamma_dot, 0.0)
    q = jnp.where(plastic, jnp.maximum(q_static, q_tr - a * gamma_dot), q_tr)
    inertial = safe_div(gamma_dot * params.d, sqrt_p)
    mu_I = jnp.where(plastic, params.mu1 + (params.mu2 - params.mu1) * safe_div(gamma_dot, gamma_dot + Q), params.mu1)
    return {
        "p": p,
        "q": q,
        "pc": pc,
        "eps_v_p": eps_v_p + eps,
        "deps_v_p": eps,
        "gamma_dot": gamma_dot,
        "I": inertial,
        "mu_I": mu_I,
        "plastic": plastic.astype(p.dtype),
    }


def return_map_planes(strain_trial, eps_v_p, params, dt, iterations=12):
    """``return_map`` on a symmetric trial strain held as planes (``jaxmpm.linalg``)."""
    dim = len(strain_trial)
    G, K = bulk_modulus(params, dim)
    e_v = sum(strain_trial[i][i] for i in range(dim))
    mean = e_v / dim
    dev = [[e - mean if i == j else e for j, e in enumerate(row)] for i, row in enumerate(strain_trial)]
    q_tr = 2.0 * G * safe_sqrt(0.5 * sum(d * d for row in dev for d in row))
    p_tr = -K * e_v
    out = return_invariants(p_tr, q_tr, eps_v_p, params, dt, dim, iterations)
    # Elastic lanes keep their deviator exactly (ratio 1, so dτ/de = 2G even at e = 0).
    ratio = jnp.where(out["plastic"] > 0, safe_div(out["q"], q_tr), 1.0)
    p = out["p"]
    iso_strain, shear = -p / (K * dim), 2.0 * G * ratio
    strain = [[(iso_strain if i == j else 0.0) + ratio * d for j, d in enumerate(row)] for i, row in enumerate(dev)]
    tau = [[(-p if i == j else 0.0) + shear * d for j, d in enumerate(row)] for i, row in enumerate(dev)]
    return strain, tau, out


def return_map(strain_trial, eps_v_p, params, dt, iterations=12):
    """The constitutive update for trial Hencky strains (..., d, d).

    Returns ``(strain, tau, out)``: the new Hencky strain, the Kirchhoff stress
    τ = -p I + 2G (q/q_tr) dev e_tr, and the invariant results of ``return_invariants``.
    """
    strain, tau, out = return_map_planes(planes(strain_trial), eps_v_p, params, dt, iterations)
    return unplanes(strain), unplanes(tau), out


@dataclasses.dataclass(frozen=True)
class CriticalState(Material):
    """The critical-state μ(I) material. ``iterations``: the most Newton steps of each scalar
    solve (each stops earlier once its step is at round-off)."""

    keys: ClassVar[tuple[str, ...]] = ("E", "nu", "rho", "rho_s", "d", "mu1", "mu2", "I0", "beta", "pc0", "xi")
    iterations: int = 12

    def __post_init__(self):
        if int(self.iterations) != self.iterations or self.iterations < 1:
            raise ValueError(f"iterations must be a positive integer, got {self.iterations!r}")

    def init_internal(self, n, dtype):
        zeros = jnp.zeros((n,), dtype)
        return {key: zeros for key in INTERNAL_KEYS}

    def update_planes(self, F_trial, internal, params, dt):
        strain_trial = hencky_strain_planes(F_trial)
        strain, tau, out = return_map_planes(strain_trial, internal["eps_v_p"], params, dt, self.iterations)
        # e_new and e_trial are coaxial, so F_e = exp(e_new - e_trial) F_trial keeps the rotation.
        change = [[a - b for a, b in zip(r1, r2)] for r1, r2 in zip(strain, strain_trial)]
        F = mm_planes(sym_exp_planes(change), F_trial)
        return F, tau, {key: out[key] for key in INTERNAL_KEYS}
