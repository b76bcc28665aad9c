"""A material-point driver: what a lab triaxial cell or shear box does to one point.

``drive(material, params, L, dt, n_steps, ...)`` applies a velocity gradient history to one
material point with the same update the MPM step uses (F_e,trial = (I + dt L) F_e, then the
material's return map) and records the history of p, q, p_c, ε_v^p, γ̇, I and μ_eff = q/p̄.
The point starts stress-free or, with ``pressure``, isotropically compressed to p = pressure.
In the ``triaxial`` test the lateral Cauchy stress is held at -pressure by solving for the
lateral strain rate each step (mixed control).

The start must lie inside the yield surface: for the critical-state material an isotropic
state p = pressure is admissible only up to the compressive strength p_c0. A start beyond it
(the old default, 1000 Pa against p_c0 = 100 Pa) is not a state of the material, and in the
triaxial test the lateral control is then asked to hold a confining stress that no admissible
state carries: with ξ = 0 the cap never grows, the control's Newton step on the lateral rate
divides by a slope near zero, the first step compacts by ε_v^p ≈ -354 and the next overflows to
NaN. ``element_test`` refuses such a start; its default pressure is p_c0 / 2.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..linalg import det, mm, safe_div
from ..materials.base import Material, invariants
from ..materials.critical_state import CriticalState, bulk_modulus
from ..params import Params, validate_params

__all__ = ["TESTS", "ElementHistory", "drive", "element_test"]

TESTS = ("isotropic", "simple-shear", "triaxial")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ElementHistory:
    """Per-step histories (length n_steps) of the element test."""

    t: Any
    p: Any
    q: Any
    pc: Any
    eps_v_p: Any
    gamma_dot: Any
    I: Any  # noqa: E741 - the inertial number I: a public field, named like the "I" internal variable
    mu_eff: Any
    F: Any  # elastic deformation gradient
    lateral_error: Any  # triaxial: |lateral Cauchy stress + pressure| after the step (Pa); else 0

    def failure(self) -> str | None:
        """Why this history cannot be trusted, or None: a non-finite value anywhere in it (not
        only at the last step), or, in the triaxial test, a lateral stress the control did not
        hold to 1e-6 of the stresses reached."""
        broken = sorted(f.name for f in dataclasses.fields(self)
                        if not np.all(np.isfinite(np.asarray(getattr(self, f.name)))))
        if broken:
            steps = len(np.asarray(self.t))
            rows = [np.isfinite(np.asarray(getattr(self, name))).reshape(steps, -1).all(axis=1) for name in broken]
            first = int(np.argmax(~np.logical_and.reduce(rows)))
            return f"non-finite {', '.join(broken)} (first at step {first})"
        error = np.asarray(self.lateral_error)
        tol = 1e-6 * max(1.0, float(np.max(np.abs(np.asarray(self.p)))))
        if np.max(error) > tol:
            return (f"the triaxial control did not hold the lateral stress: off by up to "
                    f"{float(np.max(error)):.3g} Pa (step {int(np.argmax(error))})")
        return None

    def final(self) -> dict[str, float]:
        return {
            "p": float(self.p[-1]), "q": float(self.q[-1]), "p_c": float(self.pc[-1]),
            "eps_v_p": float(self.eps_v_p[-1]), "gamma_dot": float(self.gamma_dot[-1]),
            "I": float(self.I[-1]), "mu_eff": float(self.mu_eff[-1]),
        }


def _initial_F(params, dim, pressure, dtype):
    """Isotropic elastic state with p = pressure (Hencky: p = -K tr e, e = -pressure/(K dim) I)."""
    _, K = bulk_modulus(params, dim)
    stretch = jnp.exp(-jnp.asarray(pressure, dtype) / (K * dim))
    return stretch * jnp.eye(dim, dtype=dtype)


def drive(
    material: Material,
    params: Params,
    velocity_gradient,
    dt: float,
    n_steps: int,
    dim: int = 2,
    pressure: float = 0.0,
    lateral_control: bool = False,
    control_iterations: int = 40,
    rate_bound: float = 100.0,
) -> ElementHistory:
    """Drive one material point. Pure and differentiable in ``params``.

    ``velocity_gradient`` is a (dim, dim) array (constant) or (n_steps, dim, dim). With
    ``lateral_control`` the diagonal entries other than axis 1 are unknowns chosen each step so
    that the lateral Cauchy stresses equal -pressure (a triaxial cell; axis 1 is axial).

    The lateral rate is the root of r(rate) = σ_lateral + pressure, which increases with the
    rate (more lateral extension, less lateral compression). It is found by safeguarded Newton
    steps inside the bracket ±``rate_bound`` × the applied rate (bisection when a step leaves
    the bracket), ``control_iterations`` of them on stop-gradient values, then one Newton step on
    live values for the implicit-function derivative. Plain Newton from the last step's rate
    (what this did before) diverges when a step crosses from the elastic range onto a
    perfectly plastic cap, where r is nearly flat: with 200 steps the default triaxial test
    reached NaN at the third step. ``lateral_error`` records |r| after each step.
    """
    dtype = jnp.asarray(params.E).dtype
    L = jnp.asarray(velocity_gradient, dtype)
    if L.ndim == 2:
        L = jnp.broadcast_to(L, (n_steps, dim, dim))
    eye = jnp.eye(dim, dtype=dtype)
    lateral = jnp.diag(jnp.asarray([0.0 if a == 1 else 1.0 for a in range(dim)], dtype))
    pressure = jnp.asarray(pressure, dtype)

    def update(F, internal, L_step, prm):
        return material.update(mm(eye + dt * L_step, F), internal, prm, dt)

    def lateral_residual(rate, F, internal, L_step, prm):
        F_new, tau, _ = update(F, internal, L_step + rate * lateral, prm)
        return tau[0, 0] / det(F_new) + pressure  # lateral Cauchy stress + confining pressure

    def step(carry, L_step):
        F, internal, t, rate = carry
        if lateral_control:
            rate = _lateral_rate(lateral_residual, rate, (F, internal, L_step, params), control_iterations,
                                 rate_bound)
            L_step = L_step + rate * lateral
        F, tau, internal = update(F, internal, L_step, params)
        p, q = invariants(tau)
        pc = internal.get("pc", jnp.zeros_like(p))
        p_bar = p + params.beta * pc
        error = jnp.abs(tau[0, 0] / det(F) + pressure) if lateral_control else jnp.zeros_like(p)
        out = {
            "t": t + dt, "p": p, "q": q, "pc": pc,
            "eps_v_p": internal.get("eps_v_p", jnp.zeros_like(p)),
            "gamma_dot": internal.get("gamma_dot", jnp.zeros_like(p)),
            "I": internal.get("I", jnp.zeros_like(p)),
            "mu_eff": safe_div(q, p_bar), "F": F, "lateral_error": error,
        }
        return (F, internal, t + dt, rate), out

    F0 = _initial_F(params, dim, pressure, dtype)
    internal0 = jax.tree.map(lambda a: a[0], material.init_internal(1, dtype))
    carry = (F0, internal0, jnp.zeros((), dtype), jnp.zeros((), dtype))
    _, history = jax.lax.scan(step, carry, L)
    return ElementHistory(**history)


def _lateral_rate(residual, rate0, args, iterations: int, rate_bound: float):
    """The root of ``residual(rate, F, internal, L_step, params)`` (increasing in the rate; ``args``
    the last four) from ``rate0``: ``iterations`` safeguarded Newton steps on stop-gradient F,
    internal and params inside the bracket ±``rate_bound`` × the applied rate (bisection when a
    step leaves the bracket), then one Newton step on live values for the implicit-function
    derivative (see ``drive``)."""
    sg = jax.lax.stop_gradient
    F, internal, L_step, params = args
    F_s, internal_s, params_s = sg((F, internal, params))
    fn = lambda x: residual(x, F_s, internal_s, L_step, params_s)  # noqa: E731
    bound = rate_bound * jnp.max(jnp.abs(L_step))

    def body(_, carry):
        x, neg, pos = carry  # iterate; bracket ends where r < 0 and r > 0 (neg < pos)
        r, slope = jax.jvp(fn, (x,), (jnp.ones_like(x),))
        neg = jnp.where(r < 0, x, neg)
        pos = jnp.where(r > 0, x, pos)
        newton = x - safe_div(r, slope, fill=0.0)
        inside = (newton > neg) & (newton < pos) & (slope > 0)
        return jnp.where(r == 0, x, jnp.where(inside, newton, 0.5 * (neg + pos))), neg, pos

    x, neg, pos = jax.lax.fori_loop(0, iterations, body, (jnp.clip(rate0, -bound, bound), -bound, bound))
    r, slope = jax.jvp(lambda y: residual(y, *args), (x,), (jnp.ones_like(x),))
    correction = -safe_div(r, sg(slope), fill=0.0)
    small = jnp.isfinite(correction) & (jnp.abs(correction) <= sg(pos - neg) + 1e-12)
    return x + jnp.where(small, correction, 0.0)


def element_test(
    test: str,
    params: Params | None = None,
    rate: float = 1.0,
    pressure: float | None = None,
    steps: int = 2000,
    strain: float | None = None,
    dim: int = 2,
    material: Material | None = None,
) -> ElementHistory:
    """A standard test: ``isotropic`` compression (volumetric strain rate ``rate``),
    ``simple-shear`` at engineering shear rate ``rate`` and constant volume, or ``triaxial``
    compression at axial strain rate ``rate`` under lateral stress ``pressure`` (Pa). The point
    starts at p = ``pressure`` (default: half of p_c0, an admissible, lightly overconsolidated
    start), which for the critical-state material must not exceed p_c0; ``strain`` is the total
    applied strain (default 0.1 for isotropic and triaxial, 0.5 for shear), reached in ``steps``
    steps."""
    if test not in TESTS:
        raise ValueError(f"test must be one of {TESTS}, got {test!r}")
    for name, value in (("rate", rate), ("steps", steps)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be > 0, got {value!r}")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    params = Params.create() if params is None else params
    validate_params(params)
    material = material or CriticalState()
    critical_state = isinstance(material, CriticalState)
    if pressure is None:
        pressure = 0.5 * float(params.pc0) if critical_state else 0.0
    if not (np.isfinite(pressure) and pressure >= 0):
        raise ValueError(f"pressure must be >= 0, got {pressure!r}")
    if critical_state and pressure > float(params.pc0):
        raise ValueError(f"pressure = {pressure:g} Pa exceeds the compressive strength pc0 = {float(params.pc0):g} Pa: "
                         "an isotropic start at p = pressure lies outside the yield surface (and a triaxial cell "
                         "could not hold it); lower the pressure or raise pc0")
    strain = strain if strain is not None else (0.5 if test == "simple-shear" else 0.1)
    if not (np.isfinite(strain) and strain > 0):
        raise ValueError(f"strain must be > 0, got {strain!r}")
    dt = strain / (rate * steps)
    L = np.zeros((dim, dim))
    if test == "isotropic":
        L -= np.eye(dim) * rate / dim
    elif test == "simple-shear":
        L[0, 1] = rate
    else:
        L[1, 1] = -rate
    fn = jax.jit(drive, static_argnames=("material", "n_steps", "dim", "lateral_control"))
    return fn(material, params, L, dt, n_steps=int(steps), dim=dim, pressure=pressure,
              lateral_control=(test == "triaxial"))
