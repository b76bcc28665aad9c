"""The sampler behind ``calibration.inference.mcmc``: the log density in whitened logit coordinates,
a normal prior for keys measured elsewhere, and NUTS chains (blackjax) run draw by draw.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.bounds import log_jacobian, physical, unconstrained
from ..problem.protocol import ObjectiveLike
from ..problem.residuals import jacobian_by_columns
from .likelihood import noise_levels, row_weights

__all__ = [
    "gauss_newton_point", "gaussian_prior", "log_density_fn", "row_weights", "Sampler", "ChainDraws", "nuts_sampler",
    "start_chain", "warm_up", "sample_chain", "whitened",
]


def _blackjax():
    """blackjax (the sampler), with arviz-stats (the diagnostics) checked too: the ``bayes`` extra."""
    try:
        import arviz_stats  # noqa: F401
        import blackjax
    except ImportError as err:  # pragma: no cover - exercised without the extra
        raise ImportError(f"the posteriors need {err.name}: pip install 'jaxmpm[bayes]'") from err
    return blackjax


def _support(objective: ObjectiveLike, theta):
    """False where θ (with each part's scene's other values) breaks μ2 ≥ μ1 (the bounds hold by
    construction)."""
    ok = jnp.bool_(True)
    if not {"mu1", "mu2"} & {key.split("@")[0] for key in objective.keys}:
        return ok
    for part, index, _ in objective.parts:
        if "mu1" in part.keys or "mu2" in part.keys:
            params = part.params_of(theta[index])
            ok = ok & (params.mu2 >= params.mu1)
    return ok


def gauss_newton_point(objective: ObjectiveLike, fit_result, noise, *, name: str = "fit_result",
                       hint: str = "") -> tuple[np.ndarray, dict[str, float], np.ndarray]:
    """(θ̂, σ by block, Gauss–Newton covariance) of ``fit_result``, a fit of ``objective``'s keys
    that carries an interval: what whitens the chains here and the emulator's first design
    (``calibration.inference.emulator``). Raises ``ValueError`` naming ``name`` (with ``hint`` after the
    reason) for another objective's fit or a fit without a covariance."""
    keys = tuple(objective.keys)
    if tuple(fit_result.keys) != keys:
        raise ValueError(f"{name} fits {tuple(fit_result.keys)}, the objective {keys}")
    unc = getattr(fit_result, "uncertainty", None)
    if unc is None or unc.withheld:
        raise ValueError(f"{name}: the fit carries no Gauss-Newton covariance (not a fit of the data, or fitted "
                         f"without uncertainty){hint}")
    theta_hat = np.array([fit_result.theta[k] for k in keys], float)
    return theta_hat, noise_levels(objective, fit_result, noise), np.asarray(unc.cov, float)


def gaussian_prior(keys, prior) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``prior``, {key: (mean, sd)}: a measurement of some keys from another experiment (an
    incline's I0), an independent normal in θ for each, beside the flat prior inside the bounds.
    Returns (key indices, means, sds), None for no prior; raises ``ValueError`` naming a key that
    is not fitted or a (mean, sd) that is not two finite numbers with sd > 0."""
    if prior is None or (isinstance(prior, Mapping) and not prior):
        return None
    if not isinstance(prior, Mapping):
        raise ValueError(f"prior must be a mapping {{key: (mean, sd)}}, got {type(prior).__name__}")
    keys = tuple(keys)
    unknown = sorted(k for k in prior if k not in keys)
    if unknown:
        raise ValueError(f"prior: {unknown} not among the fitted keys {keys}")
    idx, mean, sd = [], [], []
    for k, value in prior.items():
        try:
            m, s = (float(v) for v in value)
        except (TypeError, ValueError):
            raise ValueError(f"prior: {k} must be (mean, sd), got {value!r}") from None
        if not (math.isfinite(m) and math.isfinite(s) and s > 0):
            raise ValueError(f"prior: {k} must be a finite mean and sd > 0, got {value!r}")
        idx.append(keys.index(k))
        mean.append(m)
        sd.append(s)
    return np.asarray(idx), np.asarray(mean), np.asarray(sd)


def log_density_fn(objective: ObjectiveLike, weights, z_hat, L, lower, upper, prior=None):
    """``(log_density, theta_of)`` of the chains' coordinates w, θ = physical(ẑ + L w, lower,
    upper): log p(w) = −χ²(θ)/2 + log |dθ/dz| up to a constant, χ² = Σ ``weights`` r², with a
    forward-mode gradient (a ``jax.custom_vjp``); −∞ where the run fails or θ leaves the
    support; ``prior``, ``gaussian_prior``'s (indices, means, sds), adds −½ Σ ((θ_j − m_j)/s_j)²
    (docs/posteriors.md)."""
    dtype = z_hat.dtype

    def theta_of(w):
        return physical(z_hat + L @ w, lower, upper)

    def chi2_parts(w):
        r, pred = objective.residual_fn(theta_of(w))
        return r.astype(dtype), pred["status"]  # the sampler's precision, whatever the run's

    def masked(value, status, w):
        ok = (status == 0) & jnp.isfinite(value) & _support(objective, theta_of(w))
        return ok, jnp.where(ok, value, jnp.inf)

    @jax.custom_vjp
    def chi2(w):
        r, status = chi2_parts(w)
        return masked(jnp.sum(weights * r * r), status, w)[1]

    def chi2_fwd(w):
        J, (r, status) = jacobian_by_columns(chi2_parts, w)
        ok, value = masked(jnp.sum(weights * r * r), status, w)
        grad = 2.0 * (J.T @ (weights * r))
        return value, jnp.where(ok & jnp.all(jnp.isfinite(grad)), grad, jnp.zeros_like(grad))

    chi2.defvjp(chi2_fwd, lambda grad, g: (g * grad,))

    def log_prior(w):
        if prior is None:
            return jnp.zeros((), dtype)
        idx, mean, sd = prior
        return -0.5 * jnp.sum(((theta_of(w)[idx] - jnp.asarray(mean, dtype)) / jnp.asarray(sd, dtype)) ** 2)

    def log_density(w):
        log_jac = log_jacobian(z_hat + L @ w, lower, upper)  # flat prior in θ, sampled in z
        return (-0.5 * chi2(w) + log_jac + log_prior(w)).astype(dtype)

    return log_density, theta_of


class Sampler(NamedTuple):
    """The jitted NUTS pieces of one target (blackjax's kernel at an identity mass matrix in the
    whitened coordinates): ``init(w)`` a chain's state at w; ``step(state, key, step_size)`` one
    draw, with (acceptance, divergent, leapfrog steps); ``warmup_step(state, da, key)`` one draw
    at the adapting step size and the dual averaging's update; ``da_init(step_size)`` the dual
    averaging's start; ``dtype`` the chains' precision."""

    init: Callable
    step: Callable
    warmup_step: Callable
    da_init: Callable
    dtype: Any


@dataclasses.dataclass(frozen=True)
class ChainDraws:
    """One chain's kept draws: ``w`` (n, k) in the whitened coordinates, their ``log_density``,
    ``acceptance``, ``divergent`` flags and leapfrog ``steps`` per draw, and the ``step_size``
    they were drawn with."""

    w: np.ndarray
    log_density: np.ndarray
    acceptance: np.ndarray
    divergent: np.ndarray
    steps: np.ndarray
    step_size: float


def nuts_sampler(log_density: Callable, k: int, dtype, *, target_accept: float = 0.8,
                 max_doublings: int = 6) -> Sampler:
    """The ``Sampler`` of ``log_density`` (w of ``k`` entries -> log p) in precision ``dtype``:
    NUTS with at most 2^``max_doublings`` leapfrog steps per draw, its step size adapted by dual
    averaging towards acceptance ``target_accept``."""
    blackjax = _blackjax()
    inverse_mass = jnp.ones(k, dtype)
    da_init, da_update, _ = blackjax.adaptation.step_size.dual_averaging_adaptation(target_accept)

    # blackjax mixes the run's dtype with its own (momenta, energies): promote as numpy does, even
    # where a caller traces under jax_numpy_dtype_promotion="strict".
    promote = lambda: jax.numpy_dtype_promotion("standard")  # noqa: E731

    @jax.jit
    def step(state, rng, step_size):
        with promote():
            kernel = blackjax.nuts(log_density, step_size, inverse_mass, max_num_doublings=max_doublings)
            state, info = kernel.step(rng, state)
        return state, (info.acceptance_rate, info.is_divergent, info.num_integration_steps)

    @jax.jit
    def warmup_step(state, da, rng):  # one step at the adapting step size, then its update
        state, info = step(state, rng, jnp.exp(da.log_step_size).astype(dtype))
        with promote():
            return state, da_update(da, info[0]), info

    def init_fn(w):
        with promote():
            return blackjax.nuts(log_density, 1.0, inverse_mass).init(w)

    return Sampler(jax.jit(init_fn), step, warmup_step, da_init, dtype)


def start_chain(sampler: Sampler, rng: np.random.Generator, k: int, spread: float, chain: int = 0,
                tries: int = 20) -> tuple[Any, int]:
    """A chain's state at a dispersed start w ~ N(0, ``spread``² I) drawn from ``rng``, drawn
    again (up to ``tries`` times) while its run fails or breaks the support; and the runs spent."""
    for attempt in range(1, tries + 1):
        state = sampler.init(jnp.asarray(spread * rng.standard_normal(k), sampler.dtype))
        if np.isfinite(float(state.logdensity)):
            return state, attempt
    raise RuntimeError(f"nuts_posterior: chain {chain}: {tries} starts around the fit all failed or lay "
                       "outside the prior's support")


def warm_up(sampler: Sampler, state, keys, progress: Callable | None = None) -> tuple[Any, Any, int]:
    """One chain's warm-up: a NUTS draw per random key of ``keys``, its step size adapted by dual
    averaging (from 1, the scale of the Gauss–Newton posterior in the whitened coordinates).
    Returns the chain's state after it, the adapted step size (the dual averaging's average) and
    the leapfrog steps taken. ``progress(i, step_size)``, if given, is called after draw i."""
    da = sampler.da_init(1.0)
    evaluations = 0
    for i, key in enumerate(keys):
        state, da, (_, _, n) = sampler.warmup_step(state, da, key)
        evaluations += int(n)
        if progress is not None:
            progress(i, jnp.exp(da.log_step_size))
    return state, jnp.asarray(jnp.exp(da.log_step_size_avg), sampler.dtype), evaluations


def sample_chain(sampler: Sampler, state, step_size, keys, progress: Callable | None = None) -> tuple[Any, ChainDraws]:
    """One chain's kept draws: a NUTS draw per random key of ``keys`` at the fixed ``step_size``.
    Returns the chain's last state and its ``ChainDraws``. ``progress(i, step_size)``, if given,
    is called after draw i."""
    kept, logp, acc, div, nsteps = [], [], [], [], []
    for i, key in enumerate(keys):
        state, (a, d, n) = sampler.step(state, key, step_size)
        kept.append(np.asarray(state.position, float))
        logp.append(float(state.logdensity))
        acc.append(float(a))
        div.append(bool(d))
        nsteps.append(int(n))
        if progress is not None:
            progress(i, step_size)
    return state, ChainDraws(np.stack(kept), np.array(logp), np.array(acc), np.array(div, bool),
                             np.array(nsteps, int), float(step_size))


def whitened(theta, z_hat, L, lower, upper):
    """θ (n, k) -> w with θ = physical(ẑ + L w): the inverse of the chains' map."""
    return np.linalg.solve(L, (unconstrained(theta, lower, upper) - z_hat).T).T


def _chain_keys(seed: int, chains: int, resume=None) -> tuple[tuple[int, ...], Any]:
    """Each chain's number and random key: split from ``seed``, or for a resumed run's new segment
    one per chain by its number, folded in with the draws so far (the same whether a part's chains
    go on in one process or in several: ``McmcPosterior.take`` and ``join``)."""
    key = jax.random.key(seed)
    if resume is None:
        return tuple(range(chains)), jax.random.split(key, chains)
    key = jax.random.fold_in(key, resume.draws.shape[1])
    return resume.ids, [jax.random.fold_in(key, i) for i in resume.ids]


def _chain_reporter(progress: bool, c: int, chains: int, total: int, clock: float) -> Callable:
    """``report(i, step_size, offset=0, stage="sampling")``: chain c's draw i + offset of ``total``
    on stderr, about ten lines a chain (nothing without ``progress``)."""

    def report(i, size, offset=0, stage="sampling"):
        i += offset
        if progress and (i + 1) % max(1, total // 10) == 0:
            print(f"nuts: chain {c + 1}/{chains}, {stage} {i + 1}/{total}, step {float(size):.3g}, "
                  f"{time.perf_counter() - clock:.0f} s", file=sys.stderr, flush=True)

    return report


def _run_chain(sampler: Sampler, c: int, chain_key, draws: int, report: Callable, *, resume_at=None,
               rng: np.random.Generator | None = None, k: int = 0, spread: float = 1.0,
               n_warm: int = 0) -> tuple[ChainDraws, int]:
    """Chain c, on the random keys split from ``chain_key``: resumed at ``resume_at`` (its last
    draw in w and its step size), or started at a dispersed point (``start_chain``) and warmed up
    for ``n_warm`` draws (``warm_up``); then ``draws`` kept (``sample_chain``). Returns its draws
    and the log density's gradient evaluations spent."""
    chain_keys = jax.random.split(chain_key, n_warm + draws)
    if resume_at is not None:
        state = sampler.init(jnp.asarray(resume_at[0], sampler.dtype))
        evaluations = 1
        if not np.isfinite(float(state.logdensity)):
            raise RuntimeError(f"resume: chain {c}'s last draw has no finite log density here: "
                               "not the objective it was drawn from")
        step_size = jnp.asarray(resume_at[1], sampler.dtype)
    else:
        state, spent = start_chain(sampler, rng, k, spread, c)
        state, step_size, warm_evaluations = warm_up(sampler, state, chain_keys[:n_warm],
                                                     lambda i, size: report(i, size, 0, "warm-up"))
        evaluations = spent + warm_evaluations
    _, drawn = sample_chain(sampler, state, step_size, chain_keys[n_warm:], lambda i, size: report(i, size, n_warm))
    return drawn, evaluations + int(np.sum(drawn.steps))
