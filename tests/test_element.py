"""The material-point driver against the closed forms of docs/model.md §2-3: isotropic hardening,
steady simple shear on μ(I), rate independence at μ1 = μ2, and the element command line."""

import json
import math
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.materials import mu_of_I
from jaxmpm.studies.element import element_test


def test_isotropic_compression_follows_the_hardening_law():
    """Past p_c0, p_c = p_c0 exp(-ξ ε_v^p) with the ε_v^p the driver reports (to round-off),
    the state stays on the tip of the cap (q = 0, p = p_c), and compaction gives ε_v^p < 0."""
    params = jm.Params.create(pc0=500.0, xi=20.0)
    h = element_test("isotropic", params, rate=1.0, pressure=100.0, steps=1000, strain=0.1)
    eps, pc, p, q = (np.asarray(a) for a in (h.eps_v_p, h.pc, h.p, h.q))
    np.testing.assert_allclose(pc, 500.0 * np.exp(-20.0 * eps), rtol=1e-12)
    yielded = eps < 0
    assert yielded.sum() > 500 and eps[-1] < -0.05
    np.testing.assert_allclose(p[yielded], pc[yielded], rtol=1e-10)
    np.testing.assert_allclose(q, 0.0, atol=1e-9)
    # Before yield the response is elastic and below p_c0.
    first = int(np.argmax(yielded))
    assert first > 0 and p[first - 1] < 500.0


@pytest.mark.parametrize("rate", [1.0, 30.0, 900.0])
def test_steady_simple_shear_lies_on_mu_of_I(rate):
    """Shearing at constant volume from the apex (p_c0 = 2P, β = 0, ξ = 0) keeps p̄ = P and
    converges to μ_eff = q/p̄ = μ(I), I = γ̇ d / sqrt(p̄/ρ_s), to 1e-4 (measured < 1e-6).
    Rates 1, 30, 900 1/s span I ≈ 1e-3, 3e-2, 1 with d = 0.7 mm, P = 1 kPa."""
    P = 1000.0
    params = jm.Params.create(pc0=2 * P, xi=0.0)
    h = element_test("simple-shear", params, rate=rate, pressure=P, steps=4000, strain=0.5)
    final = h.final()
    inertial = rate * float(params.d) / math.sqrt(final["p"] / float(params.rho_s))
    expected = float(mu_of_I(jnp.asarray(inertial), params))
    assert abs(final["p"] / P - 1) < 1e-9
    assert abs(final["mu_eff"] / expected - 1) < 1e-4, (final, expected)
    assert abs(final["I"] / inertial - 1) < 1e-4


def test_rate_independent_when_mu1_equals_mu2():
    """With μ2 = μ1 the steady friction is μ1 at every rate (to 1e-6)."""
    P = 1000.0
    params = jm.Params.create(pc0=2 * P, xi=0.0, mu2=jm.DEFAULTS["mu1"])
    for rate in (1.0, 900.0):
        final = element_test("simple-shear", params, rate=rate, pressure=P, steps=2000).final()
        assert abs(final["mu_eff"] / float(params.mu1) - 1) < 1e-6


@pytest.mark.parametrize("pressure", [0.0, 1.0, 50.0, 100.0])
def test_triaxial_control_holds_the_lateral_stress_at_any_step_size(pressure):
    """The lateral stress is held at -P to 1e-9 Pa in every step, whether the strain comes in 20
    or 200 steps (plain Newton from the last rate diverged to NaN with 200). The final states
    agree to 1e-3 (measured 6e-4 at P = 0 against 2000 steps: the μ(I) overstress depends on G dt), and lie
    on the 2D triaxial path: Cauchy q = p - P, i.e. q = p - J P for the Kirchhoff invariants."""
    finals = []
    for steps in (20, 200):
        h = element_test("triaxial", jm.Params.create(), pressure=pressure, steps=steps)
        assert np.all(np.isfinite(np.asarray(h.p))) and np.all(np.isfinite(np.asarray(h.F)))
        assert float(np.max(h.lateral_error)) < 1e-9
        J = float(np.linalg.det(np.asarray(h.F[-1])))
        assert abs(float(h.q[-1]) - (float(h.p[-1]) - J * pressure)) < 1e-8
        finals.append(h.final())
    for final in finals[:1]:
        assert abs(final["p"] / finals[-1]["p"] - 1) < 1e-3 and abs(final["q"] / finals[-1]["q"] - 1) < 1e-3


def test_triaxial_default_pressure_is_half_of_pc0():
    h = element_test("triaxial", jm.Params.create(pc0=300.0), steps=20)
    J = float(np.linalg.det(np.asarray(h.F[-1])))
    assert float(np.max(h.lateral_error)) < 1e-9
    assert abs(float(h.p[-1]) - float(h.q[-1]) - 150.0 * J) < 1e-8  # the lateral stress is -150 Pa


def test_triaxial_gradient_through_the_control_matches_central_differences():
    """The control's last Newton step on live values gives the implicit-function derivative."""
    from jaxmpm.materials import CriticalState
    from jaxmpm.studies.element import drive

    base = jm.Params.create(xi=20.0)
    L = np.zeros((2, 2))
    L[1, 1] = -1.0

    def final_q(mu1, steps=20):
        h = drive(CriticalState(), base.replace(mu1=mu1), L, 0.1 / steps, n_steps=steps, pressure=50.0,
                  lateral_control=True)
        return h.q[-1]

    # Forward mode (a fraction of reverse mode's compile time); one compiled function gives both
    # the derivative and the values for the central difference.
    value_and_tangent = jax.jit(lambda m: jax.jvp(final_q, (m,), (jnp.ones_like(m),)))
    grad = float(value_and_tangent(jnp.asarray(0.38))[1])
    fd = float((value_and_tangent(jnp.asarray(0.38 + 1e-6))[0] - value_and_tangent(jnp.asarray(0.38 - 1e-6))[0]) / 2e-6)
    assert abs(grad / fd - 1) < 1e-6, (grad, fd)


def test_element_rejects_bad_input():
    with pytest.raises(ValueError, match="test must be one of"):
        element_test("torsion")
    with pytest.raises(ValueError, match="rate must be > 0"):
        element_test("simple-shear", rate=-1.0)
    with pytest.raises(ValueError, match="pressure must be >= 0"):
        element_test("isotropic", pressure=-5.0)
    with pytest.raises(ValueError, match="exceeds the compressive strength pc0 = 100 Pa"):
        element_test("triaxial", pressure=1000.0)  # the old default: beyond the yield surface


def test_element_command_line(tmp_path):
    png = tmp_path / "path.png"
    out = subprocess.run(
        [sys.executable, "-m", "jaxmpm", "element", "simple-shear", "--rate", "30", "--pressure", "1000",
         "--set", "pc0=2000", "--set", "xi=0", "--steps", "1000", "--json", "--plot", str(png)],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    final = json.loads(out.stdout)
    assert set(final) == {"p", "q", "p_c", "eps_v_p", "gamma_dot", "I", "mu_eff"}
    assert abs(final["p"] - 1000.0) < 1e-6 and png.stat().st_size > 10_000
