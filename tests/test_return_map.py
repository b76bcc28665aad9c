"""The critical-state return map on single material points (docs/model.md §1-3), float64.

What is checked, with the tolerances used (all relative to the compressive strength p_c or to
the natural scale named in each docstring):

1. Static returns (μ2 = μ1) land on the yield surface and satisfy the discrete consistency
   equations (flow rule in p, radial return in q, implicit hardening law).
2. Cohesion: tension is carried down to -β p_c; beyond it the one associative return applies
   (no tip rule, docs/model.md §2): continuous in the trial state, the tip only as q_tr -> 0.
3. Elastic unloading from a plastic state is exactly Hencky elastic.
4. Rate dependence: q = μ(I) S and q = q_tr - G dt γ̇ at the returned state.
5. Hypothesis properties: finite outputs and gradients, admissibility, idempotence.
6. Gradients: finite differences agree at smooth states; no NaN exactly at the kinks.

Known defects of the library are recorded as strict ``xfail`` tests at the end of the file
(they pass here when the defect is fixed, and then the xfail marker must be removed).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxmpm as jm
from jaxmpm.materials import CriticalState, invariants
from jaxmpm.materials.critical_state import bulk_modulus, return_invariants, return_map, yield_function

# Compiled once per shape/dim; params are traced leaves, so changing them never recompiles.
_ri = jax.jit(return_invariants, static_argnames=("dim", "iterations"))
_rm = jax.jit(return_map, static_argnames=("iterations",))

DT = 1e-4  # a typical MPM time step [s]


def _params(**kw):
    return jm.Params.create(**kw)


def _static(**kw):
    """Rate-independent parameters: μ2 = μ1 (the μ(I) overstress vanishes)."""
    mu1 = kw.pop("mu1", jm.DEFAULTS["mu1"])
    return _params(mu1=mu1, mu2=mu1, **kw)


def _moduli(params, dim):
    """(G, K) as Python floats, computed here independently of the library."""
    E, nu = float(params.E), float(params.nu)
    G = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return G, lam + 2.0 * G / dim


def _pc(params, eps_v_p):
    return float(params.pc0) * np.exp(-float(params.xi) * np.asarray(eps_v_p))


def _q_surface(p, pc, params):
    """q on the static surface at pressure p: μ1 sqrt((p_c - p)(p + β p_c))."""
    beta, mu1 = float(params.beta), float(params.mu1)
    return mu1 * np.sqrt(np.maximum((pc - p) * (p + beta * pc), 0.0))


def _unit_deviators(rng, n, dim):
    """Random symmetric traceless matrices D with ½ D:D = 1 (so the q of 2G·(q/2G)·D is q)."""
    d = rng.normal(size=(n, dim, dim))
    d = d + np.swapaxes(d, 1, 2)
    d -= (np.trace(d, axis1=1, axis2=2) / dim)[:, None, None] * np.eye(dim)
    return d / np.sqrt(0.5 * np.sum(d * d, axis=(1, 2)))[:, None, None]


def _strain_from_invariants(p, q, params, dim, direction):
    """Hencky strain with pressure p and deviatoric invariant q (direction: unit deviator)."""
    G, K = _moduli(params, dim)
    p, q = np.asarray(p, float), np.asarray(q, float)
    return (-p / (K * dim))[..., None, None] * np.eye(dim) + (q / (2.0 * G))[..., None, None] * direction


def _trial_invariants(strain, params):
    dim = strain.shape[-1]
    G, K = _moduli(params, dim)
    e_v = np.trace(strain, axis1=-2, axis2=-1)
    dev = strain - (e_v / dim)[..., None, None] * np.eye(dim)
    return -K * e_v, 2.0 * G * np.sqrt(0.5 * np.sum(dev * dev, axis=(-2, -1))), dev


def _np(out):
    return {k: np.asarray(v) for k, v in out.items()}


def hencky_stress_from_strain(e, params):
    """τ = λ tr(e) I + 2G e for a Hencky strain e (…, d, d)."""
    G, lam = jm.materials.lame(params)
    dim = e.shape[-1]
    return lam * jnp.trace(e, axis1=-2, axis2=-1)[..., None, None] * jnp.eye(dim) + 2.0 * G * e


# ---------------------------------------------------------------------------------------------
# 1. Static returns land on the surface and satisfy the consistency equations


def _surface_trial_states(params, dim, n, seed, log_scale=(-9.0, -2.0)):
    """Points on the current surface (random ε_v^p, p over the whole ellipse, random deviatoric
    direction) plus random symmetric strain increments of norm 10^U(log_scale)."""
    rng = np.random.default_rng(seed)
    eps_v_p = rng.uniform(-0.02, 0.02, n)
    pc = _pc(params, eps_v_p)
    beta = float(params.beta)
    p = rng.uniform(-beta * pc, pc)
    q = _q_surface(p, pc, params)
    strain = _strain_from_invariants(p, q, params, dim, _unit_deviators(rng, n, dim))
    inc = rng.normal(size=(n, dim, dim))
    inc = 0.5 * (inc + np.swapaxes(inc, 1, 2))
    inc *= (10.0 ** rng.uniform(*log_scale, n) / np.linalg.norm(inc, axis=(1, 2)))[:, None, None]
    return strain + inc, eps_v_p


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("beta", [0.0, 0.3])
@pytest.mark.parametrize("xi", [0.0, 50.0])
def test_static_return_on_surface_and_consistent(dim, beta, xi):
    """μ2 = μ1, 600 trial states: surface points + strain increments of norm 1e-9 … 1e-2 (so
    |p_tr| reaches ~100 p_c, far beyond both tips). For every plastic return:

    - on the surface: |y(p, q; p_c)| / p_c² < 1e-10 (measured ≤ 4e-15);
    - radial return + flow rule: Δγ = (q_tr/q − 1)/(2G) ≥ 0 recovered from the q equation makes
      the p equation p = p_tr − K Δγ μ1² (2p + (β−1) p_c) hold to 1e-10 (|p − p_tr| + p_c)
      (measured ≤ 1e-12), for every plastic return, those from tension beyond −β p_c included;
    - Δε_v^p = (p − p_tr)/K to 1e-10 (|p − p_tr|/K + p_c/K), ε_v^p accumulated exactly, and the
      hardening law p_c = p_c0 exp(−ξ ε_v^p) at the *updated* ε_v^p to 1e-13 (implicit, not lagged);
    - compaction on the cap (p above the apex of the updated ellipse) has Δε_v^p ≤ 0, dilation
      left of the apex has Δε_v^p ≥ 0;
    - τ = −p I + 2G (q/q_tr) dev e_tr and τ is the Hencky stress of the returned strain
      (1e-12 p_c + 1e-12 |τ|).
    Elastic states (y_tr ≤ 0) are returned unchanged. Trial states barely outside the surface
    (overstress 1e-8) are also checked on their own in test_barely_plastic_return_is_consistent.
    """
    params = _static(beta=beta, xi=xi)
    G, K = _moduli(params, dim)
    mu1 = float(params.mu1)
    strain_tr, evp = _surface_trial_states(params, dim, 600, seed=10 * dim + int(xi) + int(10 * beta))
    strain, tau, out = _rm(jnp.asarray(strain_tr), jnp.asarray(evp), params, DT)
    strain, tau, out = np.asarray(strain), np.asarray(tau), _np(out)
    p_tr, q_tr, dev_tr = _trial_invariants(strain_tr, params)
    pc_n = _pc(params, evp)
    p, q, pc = out["p"], out["q"], out["pc"]

    for v in (strain, tau, *out.values()):
        assert np.all(np.isfinite(v))
    y_tr = q_tr**2 + mu1**2 * (p_tr - pc_n) * (p_tr + beta * pc_n)
    plastic = out["plastic"] > 0
    np.testing.assert_array_equal(plastic, y_tr > 0)
    tension = plastic & (p_tr < -beta * pc_n)
    regular = plastic  # no tip rule: the trial states beyond the tension tip take the same return
    assert regular.sum() > 200 and (~plastic).sum() > 50 and tension.sum() > 20

    # On the surface.
    y = np.asarray(yield_function(out["p"], out["q"], out["pc"], params))
    assert np.max(np.abs(y[plastic]) / pc[plastic] ** 2) < 1e-10

    # Flow rule and radial return, with Δγ recovered from the q equation.
    pr, qr, pcr = p[regular], q[regular], pc[regular]
    assert np.all(qr > 0)
    dgamma = (q_tr[regular] / qr - 1.0) / (2.0 * G)
    assert np.all(dgamma >= 0)
    res = pr - (p_tr[regular] - K * dgamma * mu1**2 * (2.0 * pr + (beta - 1.0) * pcr))
    assert np.max(np.abs(res) / (np.abs(pr - p_tr[regular]) + pcr)) < 1e-10

    # Plastic volumetric strain and implicit hardening.
    deps = out["deps_v_p"]
    np.testing.assert_allclose(deps, (p - p_tr) / K, rtol=0, atol=1e-10 * np.max(np.abs(p - p_tr) / K + pc / K))
    np.testing.assert_array_equal(deps[~plastic], 0.0)
    np.testing.assert_allclose(out["eps_v_p"], evp + deps, rtol=1e-15, atol=1e-18)
    np.testing.assert_allclose(pc, float(params.pc0) * np.exp(-xi * out["eps_v_p"]), rtol=1e-13)
    apex = 0.5 * (1.0 - beta) * pcr
    assert np.all(deps[regular][pr > apex] <= 0) and np.all(deps[regular][pr < apex] >= 0)

    # Elastic states are untouched.
    np.testing.assert_allclose(p[~plastic], p_tr[~plastic], rtol=1e-14, atol=1e-12 * float(params.pc0))
    np.testing.assert_allclose(q[~plastic], q_tr[~plastic], rtol=1e-14, atol=1e-12 * float(params.pc0))

    # The stress tensor.
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(q_tr > 0, q / q_tr, 0.0)
    tau_expected = -p[:, None, None] * np.eye(dim) + 2.0 * G * ratio[:, None, None] * dev_tr
    atol = 1e-12 * float(params.pc0)
    np.testing.assert_allclose(tau, tau_expected, rtol=1e-12, atol=atol * np.max(pc / float(params.pc0)))
    tau_hencky = np.asarray(hencky_stress_from_strain(jnp.asarray(strain), params))
    np.testing.assert_allclose(tau, tau_hencky, rtol=1e-12, atol=atol * np.max(np.abs(tau)) / float(params.pc0))
    p_inv, q_inv = (np.asarray(a) for a in invariants(jnp.asarray(tau)))
    np.testing.assert_allclose(p_inv, p, rtol=1e-12, atol=atol * np.max(np.abs(p)) / float(params.pc0))
    np.testing.assert_allclose(q_inv, q, rtol=1e-12, atol=atol * np.max(np.abs(p)) / float(params.pc0))


@pytest.mark.parametrize("dim", [2, 3])
def test_compression_tip_return(dim):
    """Isotropic compression beyond the compression tip (q_tr = 0, p_tr > p_c) returns to the tip
    of the updated ellipse: p = p_c(ε) (1e-12 relative), Δε_v^p < 0 (hardening for ξ > 0), and
    q = 0 exactly (before q_static was capped at q_tr, round-off in p_c − p under the square root
    gave q = 2.1e-8 p_c at p_tr = 50 p_c0, ξ = 50, in 2D)."""
    for xi in (0.0, 50.0):
        params = _static(beta=0.2, xi=xi)
        G, K = _moduli(params, dim)
        p_tr = jnp.asarray([120.0, 300.0, 5e3])
        out = _np(_ri(p_tr, jnp.zeros(3), jnp.zeros(3), params, DT, dim))
        np.testing.assert_allclose(out["p"], out["pc"], rtol=1e-12)
        np.testing.assert_array_equal(out["q"], 0.0)
        assert np.all(out["deps_v_p"] < 0)
        np.testing.assert_allclose(out["pc"], 100.0 * np.exp(-xi * out["deps_v_p"]), rtol=1e-13)
        np.testing.assert_allclose(out["deps_v_p"], (out["p"] - np.asarray(p_tr)) / K, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# 2. Cohesion and the tension tip


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("xi", [0.0, 50.0])
def test_tension_and_tip(dim, xi):
    """β = 0.3: a state with −β p_c < p_tr < 0 and small q is elastic (returned unchanged,
    1e-14 relative). Beyond the tip (p_tr < −β p_c) there is no tip rule (docs/model.md §2): with
    q_tr = 0 the return ends on the tip of the updated ellipse, p = −β p_c(ε) and q = 0 (1e-12 p_c),
    τ = β p_c I; with q_tr > 0 it ends on the surface (|y| ≤ 1e-10 p_c²) with q > 0 and
    −β p_c < p (dilation moves p to the right: Δε_v^p = (p − p_tr)/K > 0), p_c = p_c,n exp(−ξ Δε_v^p)
    (softening). β = 0: any p_tr < 0 with q_tr = 0 returns to p = 0 (|p| ≤ 1e-12 p_c)."""
    G, K = _moduli(_params(), dim)
    evp = 0.004
    # β = 0.3, inside in tension.
    params = _static(beta=0.3, xi=xi)
    pc_n = float(_pc(params, evp))
    p_in = np.array([-0.01, -0.5, -0.95]) * 0.3 * pc_n
    q_in = 0.5 * _q_surface(p_in, pc_n, params)
    out = _np(_ri(jnp.asarray(p_in), jnp.asarray(q_in), jnp.full(3, evp), params, DT, dim))
    np.testing.assert_array_equal(out["plastic"], 0.0)
    np.testing.assert_allclose(out["p"], p_in, rtol=1e-14)
    np.testing.assert_allclose(out["q"], q_in, rtol=1e-14)
    np.testing.assert_allclose(out["pc"], pc_n, rtol=1e-14)

    # β = 0.3 and β = 0, beyond the tip, through return_map.
    rng = np.random.default_rng(3)
    for beta, p_over in ((0.3, [-1.0001, -1.5, -3.0, -40.0]), (0.0, [-1e-6, -0.3, -1.0, -10.0])):
        params = _static(beta=beta, xi=xi)
        pc_n = float(_pc(params, evp))
        tip = -beta * pc_n
        p_tr = np.repeat(np.array(p_over) * (0.3 * pc_n if beta else pc_n), 3)
        q_tr = np.tile([0.0, 0.5 * pc_n, 5.0 * pc_n], len(p_over))
        assert np.all(p_tr < tip)
        e = _strain_from_invariants(p_tr, q_tr, params, dim, _unit_deviators(rng, len(p_tr), dim))
        strain, tau, out = _rm(jnp.asarray(e), jnp.full(len(p_tr), evp), params, DT)
        out, tau = _np(out), np.asarray(tau)
        np.testing.assert_array_equal(out["plastic"], 1.0)
        np.testing.assert_allclose(out["deps_v_p"], (out["p"] - p_tr) / K, rtol=1e-12, atol=1e-12 * pc_n / K)
        assert np.all(out["deps_v_p"] > 0)
        np.testing.assert_allclose(out["pc"], pc_n * np.exp(-xi * out["deps_v_p"]), rtol=1e-13)
        y = np.asarray(yield_function(out["p"], out["q"], out["pc"], params))
        assert np.max(np.abs(y)) < 1e-10 * pc_n**2
        at_tip = q_tr == 0
        assert np.max(np.abs(out["p"][at_tip] + beta * out["pc"][at_tip])) < 1e-12 * pc_n
        np.testing.assert_allclose(out["q"][at_tip], 0.0, rtol=0, atol=1e-12 * pc_n)  # round-off of dev(e)
        expected = (beta * out["pc"][at_tip])[:, None, None] * np.eye(dim)
        np.testing.assert_allclose(tau[at_tip], expected, rtol=0, atol=1e-12 * pc_n)
        assert np.all(out["q"][~at_tip] > 0)
        assert np.all(out["p"][~at_tip] + beta * out["pc"][~at_tip] > 0)
        if beta == 0.0:
            assert np.max(np.abs(out["p"][at_tip])) <= 1e-12 * pc_n


# ---------------------------------------------------------------------------------------------
# 3. Elastic unloading


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("xi", [0.0, 50.0])
def test_elastic_unloading_after_plastic_return(dim, xi):
    """Take the output strain of plastic returns (cap, dilatant side, near the apex, and from
    tension beyond the tip), unload it — scale the deviator by (1 − a), a ∈ {0.1, 0.5, 1}, and
    move p a fraction b ∈ {0, 0.3} of the way to the apex (the admissible q grows towards the
    apex) —
    and return again with the updated ε_v^p: the flag is 0, ε_v^p and p_c are unchanged, the
    strain is returned as is (1e-15 relative to its scale) and τ equals the Hencky stress
    λ tr(e) I + 2G e of the unloaded strain (1e-12 relative to max|τ|). Both static (μ2 = μ1)
    and rate-dependent parameters."""
    rng = np.random.default_rng(7 + dim)
    for beta in (0.0, 0.3):
        p_static = _static(beta=beta, xi=xi)
        G, K = _moduli(p_static, dim)
        pc0 = float(p_static.pc0)
        # Loading states: (p_tr, q_tr) all beyond the surface.
        p_tr = np.array([95.0, 70.0, 30.0, 10.0, 0.5 * (1 - beta) * pc0 + 0.2, 150.0, -50.0 if beta else -20.0])
        q_tr = np.array([40.0, 60.0, 90.0, 40.0, 80.0, 30.0, 10.0])
        e0 = _strain_from_invariants(p_tr, q_tr, p_static, dim, _unit_deviators(rng, len(p_tr), dim))
        strain1, _, out1 = _rm(jnp.asarray(e0), jnp.full(len(p_tr), 0.002), p_static, DT)
        out1 = _np(out1)
        assert np.all(out1["plastic"] == 1.0)
        strain1 = np.asarray(strain1)
        p1 = out1["p"]
        apex = 0.5 * (1 - beta) * out1["pc"]
        e_v = np.trace(strain1, axis1=1, axis2=2)
        dev = strain1 - (e_v / dim)[:, None, None] * np.eye(dim)
        for a in (0.1, 0.5, 1.0):
            for b in (0.0, 0.3):
                p_u = p1 + b * (apex - p1)
                e_u = (-p_u / (K * dim))[:, None, None] * np.eye(dim) + (1 - a) * dev
                for params in (p_static, _params(beta=beta, xi=xi)):
                    strain2, tau2, out2 = _rm(jnp.asarray(e_u), jnp.asarray(out1["eps_v_p"]), params, DT)
                    out2 = _np(out2)
                    np.testing.assert_array_equal(out2["plastic"], 0.0)
                    np.testing.assert_array_equal(out2["deps_v_p"], 0.0)
                    np.testing.assert_array_equal(out2["eps_v_p"], out1["eps_v_p"])
                    np.testing.assert_allclose(out2["pc"], out1["pc"], rtol=1e-14)
                    np.testing.assert_allclose(strain2, e_u, rtol=0, atol=1e-15 * np.max(np.abs(e_u)))
                    tau_h = np.asarray(hencky_stress_from_strain(jnp.asarray(e_u), params))
                    np.testing.assert_allclose(tau2, tau_h, rtol=0, atol=1e-12 * np.max(np.abs(tau_h)))


# ---------------------------------------------------------------------------------------------
# 4. Rate dependence at a single return


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("beta", [0.0, 0.3])
def test_mu_of_I_at_a_single_return(dim, beta):
    """μ2 > μ1 (docs/model.md §4 defaults), ξ = 20, dt ∈ {1e-3, 1e-5, 1e-6} s, trial states on the cap,
    the dilatant side and near the apex with overstress from 1 % to 20 p_c. At the returned state,
    with S = sqrt((p_c − p) p̄), p̄ = p + β p_c, I = γ̇ d / sqrt(p̄/ρ_s),
    μ(I) = μ1 + (μ2 − μ1)/(1 + I0/I):

    - q = μ(I) S and q = q_tr − G dt γ̇ to 1e-10 relative (measured ≤ 3e-14 and ≤ 5e-15; the
      states span μ(I) = 0.382 … 0.640), γ̇ > 0,
      μ1 S < q < μ2 S (the max(q_static, ·) is not active);
    - the diagnostics I and mu_I equal the formulas (1e-12 relative);
    - p, p_c, ε_v^p are those of the static return (the volumetric part is rate-independent;
      1e-14 relative);
    - a smaller dt leaves more overstress (q decreases with dt)."""
    base = _params(beta=beta, xi=20.0)
    stat = base.replace(mu2=base.mu1)
    G, K = _moduli(base, dim)
    mu1, mu2, I0 = float(base.mu1), float(base.mu2), float(base.I0)
    d, rho_s = float(base.d), float(base.rho_s)
    pc_n = float(_pc(base, 0.001))
    ps = np.array([90.0, 70.0, 20.0, 5.0, 0.5 * (1 - beta) * pc_n + 0.3]) * pc_n / 100.0
    over = np.array([1.01, 1.5, 3.0, 20.0])
    p_tr = np.repeat(ps, len(over))
    q_tr = np.maximum(np.tile(over, len(ps)) * _q_surface(p_tr, pc_n, base), np.tile(over - 1.0, len(ps)) * pc_n)
    evp = jnp.full(p_tr.shape, 0.001)
    prev_q = None
    for dt in (1e-3, 1e-5, 1e-6):
        out = _np(_ri(jnp.asarray(p_tr), jnp.asarray(q_tr), evp, base, dt, dim))
        ref = _np(_ri(jnp.asarray(p_tr), jnp.asarray(q_tr), evp, stat, dt, dim))
        assert np.all(out["plastic"] == 1.0)
        for key in ("p", "pc", "eps_v_p"):
            np.testing.assert_allclose(out[key], ref[key], rtol=1e-14, atol=1e-14 * pc_n)
        p, q, pc, gd = out["p"], out["q"], out["pc"], out["gamma_dot"]
        p_bar = p + beta * pc
        S = np.sqrt((pc - p) * p_bar)
        inertial = gd * d / np.sqrt(p_bar / rho_s)
        mu_I = mu1 + (mu2 - mu1) / (1.0 + I0 / inertial)
        assert np.all(gd > 0)
        np.testing.assert_allclose(q, mu_I * S, rtol=1e-10)
        np.testing.assert_allclose(q, q_tr - G * dt * gd, rtol=1e-10)
        np.testing.assert_allclose(out["I"], inertial, rtol=1e-12)
        np.testing.assert_allclose(out["mu_I"], mu_I, rtol=1e-12)
        assert np.all(q > mu1 * S) and np.all(q < mu2 * S)
        np.testing.assert_allclose(ref["q"], mu1 * S, rtol=1e-12)
        if prev_q is not None:
            assert np.all(q > prev_q)
        prev_q = q
    # The stress tensor carries the rate-dependent q.
    rng = np.random.default_rng(5)
    e = _strain_from_invariants(p_tr, q_tr, base, dim, _unit_deviators(rng, len(p_tr), dim))
    _, tau, out = _rm(jnp.asarray(e), evp, base, 1e-5)
    p_inv, q_inv = (np.asarray(a) for a in invariants(tau))
    np.testing.assert_allclose(p_inv, np.asarray(out["p"]), rtol=1e-12, atol=1e-12 * pc_n)
    np.testing.assert_allclose(q_inv, np.asarray(out["q"]), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# 5. Property tests


def _params_from(beta, xi, pc0, mu1=jm.DEFAULTS["mu1"], mu2=None):
    base = _params()
    return base.replace(
        beta=jnp.asarray(beta), xi=jnp.asarray(xi), pc0=jnp.asarray(pc0),
        mu1=jnp.asarray(mu1), mu2=jnp.asarray(mu1 if mu2 is None else mu2),
    )


def _all_outputs_scalar(out):
    return sum(out[k] for k in ("p", "q", "pc", "eps_v_p", "gamma_dot", "I", "mu_I"))


@jax.jit
def _point_checks(p_tr, q_tr, evp, beta, xi, pc0, mu2, dt):
    """Rate-dependent (μ2) outputs and their gradients w.r.t. everything, for dim 2 and 3."""
    results = []
    for dim in (2, 3):
        def f(p_tr, q_tr, evp, beta, xi, pc0, mu1, mu2, I0, dim=dim):  # dim bound: f is used in this iteration
            params = _params().replace(beta=beta, xi=xi, pc0=pc0, mu1=mu1, mu2=mu2, I0=I0)
            out = return_invariants(p_tr, q_tr, evp, params, dt, dim)
            return _all_outputs_scalar(out), out

        args = (p_tr, q_tr, evp, beta, xi, pc0, jnp.asarray(jm.DEFAULTS["mu1"]), mu2, jnp.asarray(jm.DEFAULTS["I0"]))
        grads, out = jax.grad(f, argnums=tuple(range(9)), has_aux=True)(*args)
        results.append((out, grads))
    return results


_finite_floats = dict(allow_nan=False, allow_infinity=False)


def _floor(x):
    """Trial stresses below 1e-12 p_c0 in magnitude are sent to exactly 0: at p̄ ≲ 1e-205 Pa
    (reached from |p_tr| or q_tr ≲ 1e-100 Pa) the gradient of the inertial number overflows,
    see test_inertial_number_gradient_at_vanishing_pressure."""
    return 0.0 if abs(x) < 1e-12 else x


# |p_tr|, q_tr ≤ 300 p_c0 and |ξ ε_v^p| ≤ 0.5 keep p_tr/p_c below ~500: see
# test_far_beyond_compression_tip_converges for trial states further out.
_p_tr = st.one_of(st.just(0.0), st.floats(-20.0, 20.0, **_finite_floats),
                  st.floats(-300.0, 300.0, **_finite_floats)).map(_floor)
_q_tr = st.one_of(st.just(0.0), st.floats(0.0, 20.0, **_finite_floats),
                  st.floats(0.0, 300.0, **_finite_floats)).map(_floor)
_beta = st.one_of(st.just(0.0), st.floats(0.0, 0.6, **_finite_floats))
_xi = st.one_of(st.just(0.0), st.floats(0.0, 50.0, **_finite_floats))
_evp = st.floats(-0.01, 0.01, **_finite_floats)
_pc0 = st.sampled_from([1.0, 100.0, 1e4])
# Trial stresses are capped at 4e4 Pa (a 5 % trial volume strain at K = 8.3e5 Pa): beyond
# ξ |p_tr|/K ~ 30 the 12 iterations do not converge (test_far_beyond_compression_tip_converges).
_P_CAP = 4e4


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p=_p_tr, q=_q_tr, evp=_evp, beta=_beta, xi=_xi, pc0=_pc0,
       dmu=st.one_of(st.just(0.0), st.floats(0.0, 0.5, **_finite_floats)),
       dt=st.sampled_from([1e-6, 1e-4, 1e-2]))
def test_property_finite_values_and_gradients(p, q, evp, beta, xi, pc0, dmu, dt):
    """Random trial states (p_tr, q_tr in units of p_c0, from −300 to 300 p_c0, capped at
    ±4e4 Pa, tension included, exact zeros included, magnitudes below 1e-12 p_c0 sent to 0, see
    _floor), ε_v^p, β ∈ [0, 0.6], ξ ∈ [0, 50], μ2 − μ1 ∈ [0, 0.5] (exact zeros included, and any
    tiny or subnormal value hypothesis picks), dt, dim 2 and 3: every output and every gradient
    (w.r.t. p_tr, q_tr, ε_v^p, β, ξ, p_c0, μ1, μ2, I0) is finite; q ≥ 0, γ̇ ≥ 0,
    μ1 ≤ μ(I) ≤ μ2, and −β p_c ≤ p ≤ p_c up to 1e-12 (p_c + |p_tr|) (p = p_tr + K Δε_v^p carries
    the round-off of p_tr; measured 1.1e-12 p_c at p_tr = 594 p_c, just outside this range, where
    12 iterations leave the compression-tip root 20× the round-off away)."""
    mu1 = jm.DEFAULTS["mu1"]
    p_tr, q_tr = float(np.clip(p * pc0, -_P_CAP, _P_CAP)), min(q * pc0, _P_CAP)
    results = _point_checks(jnp.asarray(p_tr), jnp.asarray(q_tr), jnp.asarray(evp), jnp.asarray(beta),
                            jnp.asarray(xi), jnp.asarray(pc0), jnp.asarray(mu1 + dmu), jnp.asarray(dt))
    for out, grads in results:
        out = _np(out)
        for key, v in out.items():
            assert np.isfinite(v), key
        for g in grads:
            assert np.isfinite(np.asarray(g)), grads
        pc = out["pc"]
        tol = 1e-12 * (pc + abs(p_tr))
        assert out["q"] >= 0 and out["gamma_dot"] >= 0
        assert out["p"] + beta * pc >= -tol
        assert out["p"] <= pc + tol
        assert mu1 * (1 - 1e-15) <= out["mu_I"] <= (mu1 + dmu) * (1 + 1e-15)


@jax.jit
def _idempotence(strain, evp, beta, xi, pc0):
    params = _params_from(beta, xi, pc0)
    s1, t1, o1 = return_map(strain, evp, params, DT)
    s2, t2, o2 = return_map(s1, o1["eps_v_p"], params, DT)
    y = yield_function(o1["p"], o1["q"], o1["pc"], params)
    return (s1, t1, o1), (s2, t2, o2), y


_strain_entry = st.floats(-1.0, 1.0, **_finite_floats)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(dim=st.sampled_from([2, 3]), entries=st.lists(_strain_entry, min_size=6, max_size=6),
       log_scale=st.floats(-3.0, 1.8, **_finite_floats), evp=_evp, beta=_beta, xi=_xi, pc0=_pc0)
def test_property_static_admissible_and_idempotent(dim, entries, log_scale, evp, beta, xi, pc0):
    """μ2 = μ1, random symmetric trial strains with entries of size 10^[-3, 1.8] p_c0/K, capped at
    2 % (|p_tr| up to ~200 p_c0 and ξ |tr e| ≤ 3, tension and shear of either sign; see
    test_far_beyond_compression_tip_converges for larger ones, where 12 iterations do not
    converge).

    Admissible: y ≤ y_tol = 1e-10 p_c² + (p_c + δ) δ with δ = 1e-14 |p_tr| (100 ε_mach |p_tr|: p
    carries the absolute round-off of p = p_tr + K Δε_v^p), and |y| ≤ y_tol when plastic (measured,
    with wider strains than now: 9e-14 = 1e-10 p_c² at a tension return from p_tr = −29 p_c0 with
    p_c softened to 3e-6 p_c0, and 1.5e-21 Pa² from p_tr = −1.3e6 Pa, p_c softened to 2e-18 Pa).

    Idempotent: a second return_map on the output strain with the updated ε_v^p changes p and p_c
    by ≤ δp = 1e-9 (p_c + |p|) + δ (measured 1.7e-11 Pa after a tension return from
    p_tr = −3e5 Pa), ε_v^p by ≤ δp/K, q by ≤ q_tol = 1e-9 (p_c + q) + 1e-14 q_tr (q = q_tr − G dt γ̇
    carries the round-off of q_tr), the strain by ≤ δp/K + q_tol/G and τ by ≤ δp + 2 q_tol.
    (Before q_static was capped at q_tr, a round-off p̄ ~ 1e-17 at a tip became q ~ 1e-9 p_c > q_tr
    under the square root, and the second pass grew it further: see
    test_return_never_increases_q.)"""
    a = np.zeros((dim, dim))
    idx = np.triu_indices(dim)
    a[idx] = entries[: len(idx[0])]
    G, K = _moduli(_params(), dim)
    a = (a + a.T) * 0.5 * min(10.0**log_scale * pc0 / K, 0.02)
    p_tr, q_tr, _ = _trial_invariants(a, _params())
    (s1, t1, o1), (s2, t2, o2), y = _idempotence(jnp.asarray(a), jnp.asarray(evp), jnp.asarray(beta),
                                                   jnp.asarray(xi), jnp.asarray(pc0))
    s1, t1, s2, t2, y = map(np.asarray, (s1, t1, s2, t2, y))
    o1, o2 = _np(o1), _np(o2)
    for v in (s1, t1, s2, t2, *o1.values(), *o2.values()):
        assert np.all(np.isfinite(v))
    pc = float(o1["pc"])
    dp_round = 1e-14 * abs(p_tr)  # 100 ε_mach |p_tr|: absolute round-off of p = p_tr + K Δε_v^p
    y_tol = 1e-10 * pc**2 + (pc + dp_round) * dp_round
    assert y <= y_tol
    if o1["plastic"]:
        assert abs(y) <= y_tol

    p1 = abs(float(o1["p"]))
    dp = 1e-9 * (pc + p1) + dp_round
    q_tol = 1e-9 * (pc + float(o1["q"])) + 1e-14 * q_tr
    for key in ("p", "pc"):
        np.testing.assert_allclose(o2[key], o1[key], rtol=0, atol=dp)
    np.testing.assert_allclose(o2["eps_v_p"], o1["eps_v_p"], rtol=0, atol=dp / K)
    np.testing.assert_allclose(o2["q"], o1["q"], rtol=0, atol=q_tol)

    # Tensors: the deviatoric error (q_tol) is carried by ratio = q/q_tr times the trial deviator
    # and may show up in any component.
    np.testing.assert_allclose(s2, s1, rtol=0, atol=dp / K + q_tol / G)
    np.testing.assert_allclose(t2, t1, rtol=0, atol=dp + 2.0 * q_tol)


# ---------------------------------------------------------------------------------------------
# 6. Gradients

# (name, dim, p_tr, q_tr, eps_v_p, {params}, dt, scale [Pa], fd step)
# p_c0 = 100 Pa; the defaults have μ2 > μ1, so the μ(I) part is live in every plastic state.
_mu1 = jm.DEFAULTS["mu1"]
GRAD_STATES = [
    ("elastic", 3, 40.0, 10.0, 0.003, dict(beta=0.1, xi=20.0), 1e-5, 100.0, 1e-6),
    ("cap", 3, 90.0, 35.0, 0.003, dict(beta=0.1, xi=20.0), 1e-5, 100.0, 1e-6),
    ("cap_2d", 2, 90.0, 35.0, -0.003, dict(beta=0.0, xi=50.0), 1e-4, 100.0, 1e-6),
    ("dilatant", 3, 12.0, 40.0, 0.003, dict(beta=0.1, xi=20.0), 1e-5, 100.0, 1e-6),
    ("dilatant_2d", 2, 8.0, 30.0, 0.0, dict(beta=0.3, xi=10.0), 1e-6, 100.0, 1e-6),
    ("near_apex", 3, 45.0 * math.exp(-0.06) + 0.5, 60.0, 0.003, dict(beta=0.1, xi=20.0), 1e-5, 100.0, 1e-6),
    ("beyond_compression_tip", 3, 160.0, 10.0, 0.003, dict(beta=0.1, xi=20.0), 1e-5, 100.0, 1e-6),
    ("beyond_tension_tip", 3, -50.0, 20.0, 0.003, dict(beta=0.3, xi=20.0), 1e-5, 100.0, 1e-6),
    ("beyond_tension_tip_2d", 2, -60.0, 5.0, -0.01, dict(beta=0.3, xi=50.0), 1e-4, 100.0, 1e-6),
    # Free surface: p̄ of order 1e-2 Pa (β = 0 at p ≈ 0, β = 0.3 at p ≈ −β p_c), elastic and
    # plastic; inputs, outputs and steps scaled to 1e-2 Pa.
    ("tiny_pressure_elastic", 3, 1e-2, 0.05, 0.0, dict(beta=0.0, xi=20.0), 1e-4, 1e-2, 1e-6),
    ("tiny_pressure_plastic", 3, 1e-2, 0.5, 0.0, dict(beta=0.0, xi=20.0), 1e-4, 1e-2, 1e-6),
    ("tiny_pbar_cohesive", 2, -30.0 + 2e-2, 0.05, 0.0, dict(beta=0.3, xi=20.0), 1e-4, 1e-2, 1e-6),
    ("tiny_pbar_cohesive_plastic", 2, -30.0 + 2e-2, 1.0, 0.0, dict(beta=0.3, xi=20.0), 1e-4, 1e-2, 1e-6),
]


def _theta0(kw):
    base = _params(**kw)
    return jnp.asarray([float(base.beta), float(base.mu1), float(base.mu2), float(base.I0),
                        float(base.xi) / 10.0, float(base.pc0) / 100.0])


@jax.jit
def _theta_params(theta):
    return _params().replace(beta=theta[0], mu1=theta[1], mu2=theta[2], I0=theta[3],
                             xi=10.0 * theta[4], pc0=100.0 * theta[5])


def _inv_core(x, theta, dt, scale, dim):
    """(p_tr, q_tr)/scale, 100 ε_v^p and θ → (p, q, p_c/100)/scale·…: normalised so that every
    input and output is O(1) at the state's own pressure scale."""
    out = return_invariants(scale * x[0], scale * x[1], 0.01 * x[2], _theta_params(theta), dt, dim)
    return jnp.stack([out["p"], out["q"], out["pc"] * (scale / 100.0)]) / scale


def _map_core(e, evp, theta, dt, scale):
    """Trial strain in units of scale/K, 100 ε_v^p, θ → τ/scale."""
    params = _theta_params(theta)
    _, K = bulk_modulus(params, e.shape[-1])
    _, tau, _ = return_map((scale / K) * e, 0.01 * evp, params, dt)
    return tau / scale


# One compiled function per dim (and per derivative mode), shared by every state.
_inv_core_jit = jax.jit(_inv_core, static_argnames=("dim",))
_map_core_jit = jax.jit(_map_core)


@pytest.mark.parametrize("state", GRAD_STATES, ids=[s[0] for s in GRAD_STATES])
def test_gradients_match_finite_differences(state):
    """check_grads (order 1, fwd and rev, central differences in one random direction) of
    (p, q, p_c) from return_invariants and of τ from return_map, w.r.t. the trial state, ε_v^p and
    θ = (β, μ1, μ2, I0, ξ, p_c0), at states many steps away from every kink (every plastic one has
    γ̇ > 0, so the μ(I) branch is live). Inputs and outputs are normalised by the state's pressure
    scale so that the default float64 tolerance (atol = rtol = 1e-5) and the step 1e-6 are
    meaningful; the plastic/elastic flag is checked not to change under 100 steps. Measured
    |JVP − FD| / (|FD| + 1e-8) ≤ 1e-7 in random directions."""
    name, dim, p_tr, q_tr, evp, kw, dt, scale, step = state
    theta = _theta0(kw)
    dt, sc = jnp.asarray(dt), jnp.asarray(scale)
    x = jnp.asarray([p_tr / scale, q_tr / scale, 100.0 * evp])
    check_grads(lambda x, th: _inv_core_jit(x, th, dt, sc, dim), (x, theta), order=1, modes=("fwd", "rev"), eps=step)

    rng = np.random.default_rng(11)
    G, K = _moduli(_params(**kw), dim)
    e = _strain_from_invariants(p_tr, q_tr, _params(**kw), dim, _unit_deviators(rng, 1, dim)[0])
    check_grads(lambda e, evp, th: _map_core_jit(e, evp, th, dt, sc),
                (jnp.asarray(e * K / scale), jnp.asarray(100.0 * evp), theta), order=1, modes=("fwd", "rev"), eps=step)

    # Not on a kink: the flag does not change within 100 steps.
    params = _params(**kw)
    p_shift = jnp.asarray([p_tr - 100 * step * scale, p_tr, p_tr + 100 * step * scale])
    flags = _ri(p_shift, jnp.full(3, q_tr), jnp.full(3, evp), params, dt, dim)["plastic"]
    assert len(set(np.asarray(flags).tolist())) == 1, flags


def _kink_states():
    """(name, dim, p_tr, q_tr, eps_v_p, params kw) exactly at the non-smooth points."""
    pc = 100.0
    states = []
    for beta in (0.0, 0.3):
        for xi in (0.0, 20.0):
            kw = dict(beta=beta, xi=xi)
            pars = _params(**kw)
            apex = 0.5 * (1.0 - beta) * pc
            q_ap = float(_q_surface(np.asarray(apex), pc, pars))
            p_s = 0.5 * apex
            q_s = float(_q_surface(np.asarray(p_s), pc, pars))
            states += [
                ("zero_trial", 0.0, 0.0, 0.0, kw),
                ("q_tr_zero_inside", 0.4 * pc, 0.0, 0.0, kw),
                ("q_tr_zero_beyond_compression_tip", 1.5 * pc, 0.0, 0.0, kw),
                ("apex_exact", apex, 2.0 * q_ap + 1.0, 0.0, kw),
                ("apex_exact_on_surface", apex, q_ap, 0.0, kw),
                ("compression_tip_exact", pc, 0.0, 0.0, kw),
                ("compression_tip_with_shear", pc, 10.0, 0.0, kw),
                ("tension_tip_exact", -beta * pc, 0.0, 0.0, kw),
                ("tension_tip_with_shear", -beta * pc, 10.0, 0.0, kw),
                ("beyond_tension_tip", -beta * pc - 20.0, 10.0, 0.0, kw),
                ("on_surface_gamma_dot_zero", p_s, q_s, 0.0, kw),
                ("mu2_equals_mu1", 0.5 * apex, 3.0 * q_s + 1.0, 0.0, dict(kw, mu2=_mu1)),
                ("p_bar_zero_shear", -beta * pc, 1e-3, 0.0, kw),
            ]
    return states


KINK_STATES = _kink_states()


@jax.jit
def _kink_grads(p_tr, q_tr, evp, theta, dt):
    """Gradients of a scalar combination of every output of return_invariants (dim 2 and 3) and
    of τ, strain from return_map (trial strain built from p_tr, q_tr) w.r.t. everything."""
    def f(p_tr, q_tr, evp, theta):
        params = _theta_params(theta)
        total = jnp.zeros(())
        for dim in (2, 3):
            out = return_invariants(p_tr, q_tr, evp, params, dt, dim)
            total = total + _all_outputs_scalar(out)
            G, K = bulk_modulus(params, dim)
            D = jnp.zeros((dim, dim)).at[0, 1].set(1.0).at[1, 0].set(1.0)  # ½ D:D = 1
            e = (-p_tr / (K * dim)) * jnp.eye(dim) + (q_tr / (2.0 * G)) * D
            strain, tau, out2 = return_map(e, evp, params, dt)
            total = total + jnp.sum(tau * jnp.arange(1.0, dim * dim + 1.0).reshape(dim, dim)) + 1e4 * jnp.sum(strain)
            total = total + _all_outputs_scalar(out2)
        return total

    return jax.grad(f, argnums=(0, 1, 2, 3))(p_tr, q_tr, evp, theta)


@pytest.mark.parametrize("state", KINK_STATES, ids=[f"{s[0]}-b{s[4]['beta']}-xi{s[4]['xi']}" for s in KINK_STATES])
def test_gradients_finite_at_kinks(state):
    """Exactly at the kinks (zero trial strain = F_e = I, q_tr = 0, the apex, both tips, on the
    surface where γ̇ = 0, μ2 = μ1, p̄ = 0): jax.grad of a scalar combination of all outputs of
    return_invariants and return_map (dim 2 and 3, dt ∈ {1e-4, 1e-6}) w.r.t. p_tr, q_tr, ε_v^p
    and each of β, μ1, μ2, I0, ξ, p_c0 is finite (no NaN, no inf)."""
    name, p_tr, q_tr, evp, kw = state
    theta = _theta0(kw)
    for dt in (1e-4, 1e-6):
        grads = _kink_grads(jnp.asarray(p_tr), jnp.asarray(q_tr), jnp.asarray(evp), theta, dt)
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g))), (name, grads)


_PARAM_NAMES = ("beta", "mu1", "mu2", "I0", "xi", "pc0")


def _update_outputs(F, evp, vals):
    """CriticalState.update on a batch of trial F: (F_e, τ, internal) with parameters vals."""
    params = _params().replace(**dict(zip(_PARAM_NAMES, vals)))
    internal = dict(CriticalState().init_internal(F.shape[0], F.dtype), eps_v_p=evp)
    return CriticalState().update(F, internal, params, DT)


@jax.jit
def _update_grads(F, evp, vals):
    """Reverse-mode gradient of a scalar of all outputs w.r.t. F, ε_v^p and the parameters."""
    def scalar(F, evp, vals):
        F_new, tau, internal = _update_outputs(F, evp, vals)
        w = jnp.arange(1.0, F.shape[-1] ** 2 + 1.0).reshape(F.shape[-2:])
        return (jnp.sum(F_new * w) + jnp.sum(tau * w) / 100.0
                + sum(jnp.sum(v) for v in internal.values()))

    return jax.grad(scalar, argnums=(0, 1, 2))(F, evp, vals)


def test_update_gradient_finite_at_identity():
    """2D (the 3D compile alone takes ~10 s; 3D return_map at zero strain is covered by
    test_gradients_finite_at_kinks and 3D sym_log/sym_exp at F = I by test_gradients.py).
    CriticalState.update (Hencky strain of F, return map, F_e = exp(e − e_tr) F_tr) at
    F_e,trial = I exactly (every particle at t = 0), at repeated stretches 0.99 I, 0.9 I (isotropic
    compression beyond the compression tip), 1.001 I (tension: beyond the tip for β = 0, elastic
    for β = 0.3), each with ε_v^p ∈ {0, 0.01}, β ∈ {0, 0.3}, ξ = 20: the reverse-mode gradient
    w.r.t. F, ε_v^p and each of β, μ1, μ2, I0, ξ, p_c0 is finite."""
    eye = np.eye(2)
    F = jnp.asarray(np.stack([s * eye for s in (1.0, 0.99, 0.9, 1.001) for _ in (0, 1)]))
    evp = jnp.asarray([0.0, 0.01] * 4)
    for beta in (0.0, 0.3):
        base = _params(beta=beta, xi=20.0)
        vals = tuple(getattr(base, n) for n in _PARAM_NAMES)
        grads = _update_grads(F, evp, vals)
        for leaf in jax.tree_util.tree_leaves(grads):
            assert np.all(np.isfinite(np.asarray(leaf)))


# ---------------------------------------------------------------------------------------------
# Defects found while writing these tests: fixed ones are plain tests now; the remaining
# strict xfails start passing when the library is fixed


@pytest.mark.parametrize("dim", [2, 3])
def test_barely_plastic_return_is_consistent(dim):
    """Trial states just outside the static surface, q_tr = (1 + δ) q_surface(p_tr) with δ = 1e-8
    (overstress of 1e-8, as in slow steady flow): the returned state must satisfy the flow rule,
    Δγ from the p equation, −Δε_v^p/(μ1² h), equal to Δγ from the q equation, (q_tr/q − 1)/2G,
    to 1e-6 relative. Measured before the fix: Δε_v^p = 0 exactly (Δγ_p = 0, relative error 1)."""
    params = _static()
    G, K = _moduli(params, dim)
    mu1 = float(params.mu1)
    p_tr = np.array([20.0, 80.0, 95.0])
    q_tr = (1 + 1e-8) * _q_surface(p_tr, 100.0, params)
    out = _np(_ri(jnp.asarray(p_tr), jnp.asarray(q_tr), jnp.zeros(3), params, DT, dim))
    assert np.all(out["plastic"] == 1.0)
    h = 2.0 * out["p"] - out["pc"]
    dgamma_p = -out["deps_v_p"] / (mu1**2 * h)
    dgamma_q = (q_tr / out["q"] - 1.0) / (2.0 * G)
    np.testing.assert_allclose(dgamma_p, dgamma_q, rtol=1e-6)


def test_barely_plastic_return_jacobian():
    """The consistent tangent is continuous along the plastic side: the Jacobian of (p, q) w.r.t.
    (p_tr, q_tr) at overstress δ = 1e-8 equals that at δ = 1e-5 to 1e-3 (before the fix: dp/dp_tr
    = 1 instead of 0.849, dq/dq_tr = 0 instead of 0.151)."""
    params = _static()

    def f(x):
        out = return_invariants(x[0], x[1], jnp.asarray(0.0), params, DT, 3)
        return jnp.stack([out["p"], out["q"]])

    jac = jax.jit(jax.jacfwd(f))
    for p in (20.0, 80.0):
        qs = float(_q_surface(np.asarray(p), 100.0, params))
        j_far = np.asarray(jac(jnp.asarray([p, (1 + 1e-5) * qs])))
        j_near = np.asarray(jac(jnp.asarray([p, (1 + 1e-8) * qs])))
        np.testing.assert_allclose(j_near, j_far, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("dim", [2, 3])
def test_elastic_tangent_at_zero_strain(dim):
    """At e_tr = 0 (F_e = I) with β = 0.3 the state is strictly elastic (y = −β μ1² p_c² < 0), so
    τ(e) = λ tr(e) I + 2G e in a neighbourhood and dτ/de[D] = 2G D for a shear direction D
    (1e-12 relative); the returned strain's derivative is D. Measured before the fix: 0 and 0."""
    params = _params(beta=0.3)
    G, _ = _moduli(params, dim)
    D = jnp.zeros((dim, dim)).at[0, 1].set(1.0).at[1, 0].set(1.0)
    zero = jnp.zeros((dim, dim))
    jvp = jax.jit(lambda e, d: jax.jvp(lambda e: return_map(e, jnp.asarray(0.0), params, DT)[:2], (e,), (d,))[1])
    dstrain, dtau = jvp(zero, D)
    np.testing.assert_allclose(np.asarray(dtau), 2.0 * G * np.asarray(D), rtol=1e-12, atol=1e-12 * G)
    np.testing.assert_allclose(np.asarray(dstrain), np.asarray(D), rtol=1e-12, atol=1e-12)


@pytest.mark.xfail(strict=True, reason="exactly at the apex (p_tr = (1−β) p_c/2, ε_apex = 0) the bracket "
                   "has zero width and the radial-return ratio μ1²h/(μ1²h − 2Gε) is 0/0, so the implicit step "
                   "cannot supply the limit of the plastic tangent (critical_state.py surface_residual)")
def test_apex_derivative_is_continuous():
    """The static return is smooth through the apex: dp/dp_tr exactly at p_tr = apex equals the
    central difference across it (1e-6 relative). Measured now: 1.0 vs 0.847."""
    params = _static()

    p_of = jax.jit(lambda p_tr: return_invariants(p_tr, jnp.asarray(30.0), jnp.asarray(0.0), params, DT, 3)["p"])
    g = float(jax.jit(jax.grad(p_of))(jnp.asarray(50.0)))
    h = 1e-4
    fd = (float(p_of(jnp.asarray(50.0 + h))) - float(p_of(jnp.asarray(50.0 - h)))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


@pytest.mark.parametrize("ratio, xi, pc0", [
    (1e3, 0.0, 100.0), (3e3, 0.0, 100.0), (1e4, 0.0, 100.0),
    pytest.param(120.0, 18.0, 1e4, marks=pytest.mark.xfail(strict=True, reason=(
        "with strong hardening over a 145 % trial volume strain the tip start (p_c frozen, 3 Newton steps) is "
        "far from the tip, and 12 iterations leave p 0.064 p_c off (9.22e5 against 9.92e5 Pa), p_c 4.6x too "
        "large (critical_state.py _tip_increments)"))),
])
def test_far_beyond_compression_tip_converges(ratio, xi, pc0):
    """Trial states (p_tr − p_c)/p_c ∈ {1e3, 3e3, 1e4} beyond the compression tip, q_tr = 0.4 p_tr
    (e.g. p_c softened to ~1 Pa by dilation, then recompressed to ~1 kPa), and one with hardening
    (ξ = 18, p_c0 = 1e4 Pa, p_tr = 1.2e6 Pa, q_tr = 0.27 p_tr: a 145 % trial volume strain, far
    outside what a time step produces): the static return must be converged,
    |p − p_200| ≤ 1e-10 (p_c + 1e-3 |p_tr|) against 200 iterations, and q ≤ q_tr.
    Before the tip start (Newton from the trial state or the bracket's middle only) the first
    three were 1.4e-6, 1.1e-2 and 0.33 p_c off (p = 1.31 p_c at 1e4, outside the ellipse); now
    they agree with 200 iterations to the last bit."""
    params = _static(xi=xi, pc0=pc0)
    p_tr = jnp.asarray(pc0 * (1.0 + ratio))
    q_tr = (0.4 if xi == 0 else 0.2665) * p_tr
    out = _ri(p_tr, q_tr, jnp.asarray(0.0), params, DT, 3)
    ref = _ri(p_tr, q_tr, jnp.asarray(0.0), params, DT, 3, iterations=200)
    pc = float(ref["pc"])
    assert abs(float(out["p"]) - float(ref["p"])) <= 1e-10 * (pc + 1e-3 * float(p_tr))
    assert float(out["q"]) <= float(q_tr)


def test_far_beyond_tension_tip_converges():
    """The trial state hypothesis found (p_tr = −298 p_c0, q_tr = 0, β = 0, ξ = 27, p_c0 = 100 Pa,
    dim 3: p_tr/p_c ≈ −780 once p_c has softened): the return must land on the tension tip
    p = −β p_c = 0 to round-off of p_tr. Before the tip start 12 iterations left p = −3.2e-8 Pa
    (Newton on g, quadratic in p, only halves the distance per step that far out); 16 reached it."""
    params = _params(beta=0.0, xi=27.0, pc0=100.0)
    for p_tr, q_tr, beta in ((-29800.0, 0.0, 0.0), (-29800.0, 0.0, 0.3), (-3e4, 1e-3, 0.1)):
        params = params.replace(beta=jnp.asarray(beta))
        for dim in (2, 3):
            out = _ri(jnp.asarray(p_tr), jnp.asarray(q_tr), jnp.asarray(0.0), params, DT, dim)
            ref = _ri(jnp.asarray(p_tr), jnp.asarray(q_tr), jnp.asarray(0.0), params, DT, dim, iterations=200)
            assert abs(float(out["p"]) - float(ref["p"])) <= 1e-14 * abs(p_tr) + 1e-12 * float(ref["pc"])
            assert float(out["p"]) + beta * float(out["pc"]) >= -1e-14 * abs(p_tr)


def test_no_nan_gradient_for_underflowing_trial_shear():
    """At p_tr = 0, β = 0 (p̄ = 0) with q_tr = 1e-200 Pa (q_tr² underflows, so the state counts as
    elastic), d q/d q_tr must be finite (it is 1). Measured before the fix: NaN for q, γ̇, I and μ(I)."""
    params = _params()
    grad = jax.jit(jax.jacrev(lambda q: return_invariants(jnp.asarray(0.0), q, jnp.asarray(0.0), params, DT, 3)))
    g = grad(jnp.asarray(1e-200))
    for key in ("q", "gamma_dot", "I", "mu_I"):
        assert np.isfinite(float(g[key])), key


def test_return_never_increases_q():
    """A plastic return scales the deviator down, q = q_tr/(1 + 2GΔγ) ≤ q_tr (to 1e-14 relative).
    Cases: isotropic compression beyond the compression tip (q_tr = 0, p_tr = 50 p_c0, β = 0.2,
    ξ = 50, 2D) and a
    point returned exactly to the tension tip returned again (β = 0.3125, ξ = 1, p_c0 = 1 Pa).
    Measured before the fix (q_static = μ1 S was not capped at q_tr): q = 2.7e-6 Pa with q_tr = 0,
    and q = 1.2e-9 Pa from q_tr = 8e-17 Pa."""
    params = _static(beta=0.2, xi=50.0)
    out = _ri(jnp.asarray(5e3), jnp.asarray(0.0), jnp.asarray(0.0), params, DT, 2)
    bad = [float(out["q"])]
    params = _static(beta=0.3125, xi=1.0, pc0=1.0)
    a = np.zeros((3, 3))
    a[0, 0], a[1, 1] = 0.5, -0.25
    a = a * 10.0**0.75 / _moduli(params, 3)[1]
    s1, _, o1 = _rm(jnp.asarray(a), jnp.asarray(0.00390625), params, DT)
    _, _, o2 = _rm(s1, o1["eps_v_p"], params, DT)
    # Returning the returned state again may move q only by the round-off of rebuilding q_tr
    # from the strain (absolute 1e-12 p_c0): before the fix it grew to 1.2e-9 Pa.
    bad.append(float(o2["q"]) - float(o1["q"]) * (1 + 1e-14) - 1e-12)
    assert max(bad) <= 0.0, bad


def test_no_nan_gradient_when_tip_residual_has_no_root():
    """A hardened state (β = 0.3, ξ = 50, ε_v^p = −0.0921, so p_c,n ≈ 1e4 Pa) loaded to
    p_tr = 1.646 p_c,n beyond the compression tip, q_tr = 0, 3D: the value is right (p = p_c) but
    dp/dp_tr must be finite. Measured before the fix: NaN (about 0.2 % of p_tr in [0.5, 3] p_c,n)."""
    params = _params(beta=0.3, xi=50.0)
    f = jax.jit(jax.grad(lambda p: return_invariants(p, jnp.asarray(0.0), jnp.asarray(-0.0921), params, DT, 3)["p"]))
    for p_tr in (16457.19897699022, 16839.633886388685):
        assert np.isfinite(float(f(jnp.asarray(p_tr))))


def test_tension_tip_return_with_strong_softening():
    """β = 0.6, ξ = 50, p_c0 = 3e4 Pa (ξβp_c = 9e5 Pa > K = 8.3e5 Pa), p_tr = −1.01 β p_c, q_tr = 0:
    the return must end on the tip, |p + β p_c| ≤ 1e-10 p_c. Measured before the fix: p = p_tr,
    Δε_v^p = 0, p̄ = −180 Pa (outside the ellipse)."""
    params = _static(beta=0.6, xi=50.0, pc0=3e4)
    out = _ri(jnp.asarray(-1.01 * 0.6 * 3e4), jnp.asarray(0.0), jnp.asarray(0.0), params, DT, 3)
    assert abs(float(out["p"]) + 0.6 * float(out["pc"])) <= 1e-10 * float(out["pc"])


@pytest.mark.parametrize("dim", [2, 3])
def test_inertial_number_gradient_at_vanishing_pressure(dim):
    """β = 0, p_tr = 0, q_tr = 1e-112 Pa (plastic: the return moves p to ~7e-224 Pa, γ̇ = 0):
    dI/dq_tr and dI/dp_tr must be finite (no NaN anywhere, docs/model.md §3). Measured now: NaN for
    q_tr ≤ ~1e-112 Pa (and p_tr = −4e-197 Pa in tension), finite for q_tr ≥ 1e-100 Pa. Physically
    irrelevant magnitudes, but the same p̄^(-3/2) makes I and its gradient round-off noise at any
    tension-tip return (p̄ = round-off there)."""
    params = _params(pc0=1.0)
    grad = jax.jit(jax.grad(lambda x: return_invariants(x[0], x[1], jnp.asarray(0.0), params, DT, dim)["I"]))
    g = np.asarray(grad(jnp.asarray([0.0, 1e-112])))
    assert np.all(np.isfinite(g)), g


@pytest.mark.parametrize("beta", [0.0, 0.25])
def test_return_is_continuous_across_the_tension_tip(beta):
    """No tip rule (docs/model.md §2): the return is continuous in the trial state across
    p_tr = −β p_c (p and q change by ≤ 1e-6 p_c for a trial change of 2e-6 Pa, at q_tr from 0.1 to
    2 p_c), its one-sided derivatives are finite and agree with one-sided differences, and the
    tension tip (p = −β p_c, q = 0) is the limit q_tr -> 0 of the returns beyond it
    (|p + β p_c| and q fall like q_tr). Before the fix the tip rule jumped: p by ~60 Pa at
    q_tr = 80 Pa, β = 0.25, p_c0 = 500 Pa."""
    params = jm.Params.create(beta=beta, pc0=500.0, xi=50.0)
    pc0 = 500.0
    tip = -beta * pc0
    eps0 = jnp.asarray(0.0)
    f = jax.jit(lambda p_tr, q_tr: jnp.stack([
        return_invariants(p_tr, q_tr, eps0, params, 1e-4, 2)[k] for k in ("p", "q")]))
    jac = jax.jit(jax.jacfwd(f, argnums=(0, 1)))
    h = 1e-6
    for q_tr in (0.1 * pc0, 0.5 * pc0, 2.0 * pc0):
        below = np.asarray(f(jnp.asarray(tip - h), jnp.asarray(q_tr)))
        above = np.asarray(f(jnp.asarray(tip + h), jnp.asarray(q_tr)))
        np.testing.assert_allclose(below, above, rtol=0, atol=1e-6 * pc0)
        for side in (-1.0, 1.0):
            p0 = tip + side * 1e-3
            d = np.asarray(jac(jnp.asarray(p0), jnp.asarray(q_tr))[0])
            assert np.all(np.isfinite(d))
            one_sided = (np.asarray(f(jnp.asarray(p0 + side * 1e-4), jnp.asarray(q_tr))) -
                         np.asarray(f(jnp.asarray(p0), jnp.asarray(q_tr)))) / (side * 1e-4)
            np.testing.assert_allclose(d, one_sided, rtol=1e-3, atol=1e-6)
    # The tip as the limit q_tr -> 0 of the returns from beyond it.
    gaps = []
    for q_tr in (1.0, 1e-2, 1e-4):
        p, q = np.asarray(f(jnp.asarray(tip - 50.0), jnp.asarray(q_tr)))
        out = return_invariants(jnp.asarray(tip - 50.0), jnp.asarray(q_tr), eps0, params, 1e-4, 2)
        gaps.append(abs(p + beta * float(out["pc"])) + q)
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 1e-3, gaps
    p, q = np.asarray(f(jnp.asarray(tip - 50.0), jnp.asarray(0.0)))
    out = return_invariants(jnp.asarray(tip - 50.0), jnp.asarray(0.0), eps0, params, 1e-4, 2)
    np.testing.assert_allclose(p, -beta * float(out["pc"]), rtol=0, atol=1e-9 * pc0)
    assert q == 0.0


def test_matches_the_reference_code_at_a_tension_state():
    """The reference code's return (its associative Newton solve, no tip branch) at one
    trial state beyond the tension tip, 2D, β = 0, E = 1e6, ν = 0.3, p_c0 = 100 Pa, ξ = 50,
    dt = 5e-5 s, d = 2 mm: (p_tr, q_tr) = (−5, 50) Pa returns to p = 19.94 Pa (the reference's
    figure, to its 4 digits). The quoted q = 16.55 Pa and γ̇ = 1.775 1/s cannot both hold with
    q = q_tr − G dt γ̇ (G dt = 19.23 Pa s, so q = 16.55 needs γ̇ = 1.739): the rate part is checked
    against that relaxation law and q = μ(I) S instead (test_mu_of_I_at_a_single_return); here q
    must lie within 0.5 % of the reference's 16.55 Pa (16.52 Pa). The tip rule gave (0, 0)."""
    params = jm.Params.create(beta=0.0, E=1e6, nu=0.3, pc0=100.0, xi=50.0, d=2e-3)
    out = _np(_ri(jnp.asarray(-5.0), jnp.asarray(50.0), jnp.asarray(0.0), params, 5e-5, 2))
    assert round(float(out["p"]), 2) == 19.94
    assert abs(float(out["q"]) / 16.55 - 1.0) < 5e-3
