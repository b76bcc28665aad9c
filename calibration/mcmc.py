"""A posterior by gradient-based MCMC: the No-U-Turn sampler (blackjax), for any number of keys.

``nuts_posterior(objective, fit_result)`` samples p(θ | data) ∝ exp(−χ²(θ)/2) under a flat prior
inside the bounds (and μ2 ≥ μ1 where both enter), χ² on the noise σ_b of each block that the fit
used (``calibration.likelihood``'s convention, so the three checks are on one scale). Where the
quadrature of ``grid_posterior`` stops (more than two keys) this is the way to the posterior, and
for one or two keys the two are a check on each other.

How it samples (the choices, and why):

- **Coordinates.** The chains move in w, the unconstrained z = logit((θ − lo)/(hi − lo)) of the
  bounds (``calibration.observe.to_physical``) whitened by the fit's Gauss–Newton covariance
  mapped to z: z = ẑ + L w. The flat prior in θ becomes the log-Jacobian Σ log dθ/dz, the bounds
  are never crossed, and where the Gauss–Newton picture holds the target is close to a standard
  normal, so an identity mass matrix is right and NUTS needs few leapfrog steps (typically 3) per
  draw. Where it does not hold (a curved valley, a bound), NUTS still samples the true target:
  the whitening only preconditions it.
- **Gradients in forward mode.** χ² is a ``jax.custom_vjp`` whose derivative is 2 Jᵀ W r with J
  from ``jacobian_by_columns`` (k forward-mode passes, for k keys about 3.5 runs at two keys; the
  checkpointed reverse mode costs 7 to 9). A failed run (status bits set) or a non-finite χ² has
  log density −∞ and χ²'s gradient 0 (never NaN): NUTS counts the trajectory as divergent and
  never moves there.
- **Warm-up.** Dual averaging of the step size only (blackjax's, target acceptance
  ``target_accept``), per chain, from dispersed starts w ~ N(0, ``spread``² I); the mass matrix
  stays the identity of the whitened coordinates (adapting it from a few hundred draws would
  add noise, not information, where the Gauss–Newton covariance already scales the problem).
- **Diagnostics.** Rank-normalised split R̂, bulk and tail effective sample sizes (Vehtari et al.
  2021, blackjax's, the same estimators as ArviZ's defaults), the number of divergent
  transitions, the mean acceptance and the mean number of leapfrog steps (each one run's
  Jacobian). ``converged`` asks R̂ < 1.01 and a bulk ESS of at least 100 (the thresholds of Vehtari
  et al.) and no divergence.

blackjax is an optional dependency: ``pip install "jaxmpm[bayes]"``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .likelihood import _sigma
from .observe import jacobian_by_columns, to_physical
from .uncertainty import NOISE_FLOOR

__all__ = ["McmcPosterior", "nuts_posterior", "posterior_predictive"]

#: R̂ and bulk-ESS thresholds of Vehtari et al. (2021) for a posterior to be reported as converged.
RHAT_MAX, ESS_MIN = 1.01, 100.0


def _blackjax():
    try:
        import blackjax
    except ImportError as err:  # pragma: no cover - exercised without the extra
        raise ImportError("nuts_posterior needs blackjax: pip install 'jaxmpm[bayes]'") from err
    return blackjax


@dataclasses.dataclass(frozen=True)
class McmcPosterior:
    """NUTS draws of the fitted keys and their diagnostics. ``draws`` (chains, n, k): physical θ
    after warm-up; ``log_density`` (chains, n); by key the posterior ``mean``, ``sd``, equal-tailed
    95 % credible interval ``ci95``, ``rhat``, ``ess_bulk`` and ``ess_tail``, beside the fit's
    point ``theta_hat`` and Gauss–Newton standard error. Per chain: the adapted ``step_size``
    (in the whitened coordinates, where 1 is the scale of the Gauss–Newton posterior), the
    ``divergences``, the mean ``acceptance`` and the mean leapfrog ``steps`` per draw;
    ``gradient_evaluations`` counts the runs' Jacobians, warm-up included."""

    keys: tuple[str, ...]
    draws: np.ndarray
    log_density: np.ndarray
    mean: dict[str, float]
    sd: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    rhat: dict[str, float]
    ess_bulk: dict[str, float]
    ess_tail: dict[str, float]
    theta_hat: dict[str, float]
    gn_stderr: dict[str, float]
    step_size: tuple[float, ...]
    divergences: tuple[int, ...]
    acceptance: tuple[float, ...]
    steps: tuple[float, ...]
    gradient_evaluations: int
    warmup: int
    noise: dict[str, float]
    seed: int
    wall_s: float

    @property
    def chains(self) -> int:
        return self.draws.shape[0]

    @property
    def converged(self) -> bool:
        """R̂ < 1.01 and bulk ESS ≥ 100 for every key, and no divergent transition."""
        return (all(v < RHAT_MAX for v in self.rhat.values()) and all(v >= ESS_MIN for v in self.ess_bulk.values())
                and sum(self.divergences) == 0)

    def flat(self) -> np.ndarray:
        """The draws of every chain, (chains · n, k)."""
        return self.draws.reshape(-1, len(self.keys))

    def to_json(self) -> dict[str, Any]:
        return {"keys": list(self.keys),
                "method": "NUTS (blackjax), whitened logit coordinates, forward-mode gradients",
                "prior": "flat inside the bounds", "chains": self.chains, "warmup": self.warmup,
                "draws_per_chain": int(self.draws.shape[1]), "seed": self.seed,
                "mean": self.mean, "sd": self.sd, "ci95": {k: list(v) for k, v in self.ci95.items()},
                # R-hat needs two chains: null (not NaN) for one
                "rhat": {k: v if math.isfinite(v) else None for k, v in self.rhat.items()},
                "ess_bulk": self.ess_bulk, "ess_tail": self.ess_tail,
                "converged": self.converged, "theta_hat": self.theta_hat, "gauss_newton_stderr": self.gn_stderr,
                "sd_over_gauss_newton": {k: self.sd[k] / self.gn_stderr[k] for k in self.keys},
                "step_size": list(self.step_size), "divergences": list(self.divergences),
                "acceptance": list(self.acceptance), "leapfrog_steps_per_draw": list(self.steps),
                "gradient_evaluations": self.gradient_evaluations, "noise": self.noise, "wall_s": round(self.wall_s, 2),
                "draws": {k: self.draws[..., j].tolist() for j, k in enumerate(self.keys)}}


def _row_weights(objective, sigma: Mapping[str, float]) -> np.ndarray:
    """W with χ² = Σ W r²: 1 / (row_scale σ_b)² on the rows of blocks with a noise level, else 0."""
    w = np.zeros(objective.n_residuals)
    for name, sl in objective.blocks.items():
        if sigma.get(name) is not None:
            w[sl] = 1.0 / max(float(sigma[name]), NOISE_FLOOR) ** 2
    return w / np.asarray(objective.row_scale, float) ** 2


def _support(objective, theta):
    """False where θ (with the scene's other values) breaks μ2 ≥ μ1 (the bounds hold by construction)."""
    if "mu1" not in objective.keys and "mu2" not in objective.keys:
        return jnp.bool_(True)
    params = getattr(objective, "members", [objective])[0].params_of(theta)
    return params.mu2 >= params.mu1


def _log_density_fn(objective, weights, z_hat, L, lower, upper):
    """w -> log p(w) (up to a constant) with a forward-mode gradient; see the module docstring."""
    dtype = z_hat.dtype

    def theta_of(w):
        return to_physical(z_hat + L @ w, lower, upper)

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

    def log_density(w):
        s = jax.nn.sigmoid(z_hat + L @ w)
        log_jac = jnp.sum(jnp.log((upper - lower) * s * (1 - s)))  # flat prior in θ, sampled in z
        return (-0.5 * chi2(w) + log_jac).astype(dtype)

    return log_density, theta_of


def nuts_posterior(objective, fit_result, *, chains: int = 4, warmup: int = 100, draws: int = 200, seed: int = 0,
                   noise: Mapping[str, float] | float | None = None, target_accept: float = 0.8,
                   max_doublings: int = 6, spread: float = 1.0, progress: bool = False) -> McmcPosterior:
    """NUTS draws of ``objective``'s keys around ``fit_result`` (which must carry a Gauss–Newton
    covariance: the sampler's preconditioner, see the module docstring). ``chains`` run one after
    the other (on the CPU a vmapped batch of runs costs more than the runs in turn), each with
    ``warmup`` step-size adaptation steps, then ``draws`` kept; ``noise``: σ by block (default: the
    fit's); ``max_doublings``: the tree depth limit (2^depth leapfrog steps at most per draw)."""
    blackjax = _blackjax()
    for name, value, least in (("chains", chains, 1), ("warmup", warmup, 1), ("draws", draws, 4),
                               ("max_doublings", max_doublings, 1)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if not 0 < target_accept < 1:
        raise ValueError(f"target_accept must lie in (0, 1), got {target_accept!r}")
    if not (math.isfinite(spread) and spread > 0):
        raise ValueError(f"spread must be a positive number, got {spread!r}")
    keys = tuple(objective.keys)
    if tuple(fit_result.keys) != keys:
        raise ValueError(f"fit_result fits {tuple(fit_result.keys)}, the objective {keys}")
    unc = getattr(fit_result, "uncertainty", None)
    if unc is None or unc.withheld:
        raise ValueError("fit_result: no Gauss-Newton covariance (not a fit of the data, or fitted without "
                         "uncertainty); the sampler needs one to precondition the chains")
    sigma = _sigma(objective, fit_result, noise)
    clock = time.perf_counter()
    # The chains' precision: JAX's default float (float64 where x64 is on, even for a float32 run,
    # whose residuals are cast: blackjax's own arrays follow the default and must not mix).
    dtype = jnp.result_type(float)
    lower_np, upper_np = np.asarray(objective.bounds.lower, float), np.asarray(objective.bounds.upper, float)
    theta_hat = np.array([fit_result.theta[k] for k in keys], float)
    s = (theta_hat - lower_np) / (upper_np - lower_np)
    if np.any((s <= 0) | (s >= 1)):
        raise ValueError(f"fit_result: the point {dict(zip(keys, theta_hat))} is not strictly inside the bounds")
    dtheta_dz = (upper_np - lower_np) * s * (1 - s)
    cov_z = np.asarray(unc.cov, float) / np.outer(dtheta_dz, dtheta_dz)
    L = np.linalg.cholesky(cov_z)
    z_hat = np.log(s) - np.log1p(-s)
    as_dtype = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    log_density, theta_of = _log_density_fn(objective, as_dtype(_row_weights(objective, sigma)), as_dtype(z_hat),
                                            as_dtype(L), as_dtype(lower_np), as_dtype(upper_np))
    k = len(keys)
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

    init = jax.jit(init_fn)
    rng = np.random.default_rng(seed)
    keys_all = jax.random.split(jax.random.key(seed), chains)
    out_draws, out_logp, sizes, divs, accs, steps_mean = [], [], [], [], [], []
    evaluations = 0
    for c in range(chains):
        for _ in range(20):  # a start whose run fails or breaks the support is drawn again
            state = init(as_dtype(spread * rng.standard_normal(k)))
            evaluations += 1
            if np.isfinite(float(state.logdensity)):
                break
        else:
            raise RuntimeError(f"nuts_posterior: chain {c}: 20 starts around the fit all failed or lay "
                               "outside the prior's support")
        da = da_init(1.0)
        chain_keys = jax.random.split(keys_all[c], warmup + draws)
        kept, logp, acc, div, nsteps = [], [], [], [], []
        for i in range(warmup + draws):
            if i < warmup:
                state, da, (a, d, n) = warmup_step(state, da, chain_keys[i])
                if i == warmup - 1:
                    size_final = as_dtype(jnp.exp(da.log_step_size_avg))
            else:
                state, (a, d, n) = step(state, chain_keys[i], size_final)
            evaluations += int(n)
            if i >= warmup:
                kept.append(np.asarray(state.position, float))
                logp.append(float(state.logdensity))
                acc.append(float(a))
                div.append(bool(d))
                nsteps.append(int(n))
            if progress and (i + 1) % max(1, (warmup + draws) // 10) == 0:
                size = jnp.exp(da.log_step_size) if i < warmup else size_final
                print(f"nuts: chain {c + 1}/{chains}, {'warm-up' if i < warmup else 'sampling'} "
                      f"{i + 1}/{warmup + draws}, step {float(size):.3g}, {time.perf_counter() - clock:.0f} s",
                      file=sys.stderr, flush=True)
        w = np.stack(kept)
        out_draws.append(np.asarray(jax.vmap(theta_of)(as_dtype(w)), float))
        out_logp.append(np.array(logp))
        sizes.append(float(size_final))
        divs.append(int(np.sum(div)))
        accs.append(float(np.mean(acc)))
        steps_mean.append(float(np.mean(nsteps)))
    samples = np.stack(out_draws)  # (chains, n, k)
    flat = samples.reshape(-1, k)
    mean = {key: float(flat[:, j].mean()) for j, key in enumerate(keys)}
    sd = {key: float(flat[:, j].std(ddof=1)) for j, key in enumerate(keys)}
    ci = {key: (float(np.quantile(flat[:, j], 0.025)), float(np.quantile(flat[:, j], 0.975)))
          for j, key in enumerate(keys)}
    diag = blackjax.diagnostics
    rhat, ess_b, ess_t = {}, {}, {}
    for j, key in enumerate(keys):
        x = jnp.asarray(samples[..., j])
        with jax.numpy_dtype_promotion("standard"):  # blackjax's estimators mix int and float
            rhat[key] = float(diag.rhat(x)) if chains > 1 else float("nan")
            ess_b[key] = float(diag.ess_bulk(x))
            ess_t[key] = float(diag.ess_tail(x))
    return McmcPosterior(keys, samples, np.stack(out_logp), mean, sd, ci, rhat, ess_b, ess_t,
                         dict(zip(keys, theta_hat.tolist())), dict(zip(keys, np.asarray(unc.stderr, float).tolist())),
                         tuple(sizes), tuple(divs), tuple(accs), tuple(steps_mean), evaluations, warmup,
                         {key: float(v) for key, v in sigma.items()}, seed, time.perf_counter() - clock)


def posterior_predictive(objective, posterior: McmcPosterior, *, n: int = 40, seed: int = 0,
                         chunk: int | None = None) -> dict[str, Any]:
    """The model's prediction of ``objective``'s data (an ``Objective``: the fitted one, or one
    with held-out data) at ``n`` draws of ``posterior`` chosen at random from every chain, in one
    batched sweep: ``thetas`` (n, k) and, by block, ``at``, ``data`` and ``predicted`` (n, m), in
    metres (``calibration.plots.plot_posterior_predictive`` draws them). Its spread is the
    parameters' uncertainty; the measurement noise ``noise`` (by block, relative) comes beside it."""
    from .likelihood import observed_blocks
    from .sweep import sweep

    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if set(objective.keys) != set(posterior.keys):
        raise ValueError(f"objective fits {tuple(objective.keys)}, the posterior {posterior.keys}")
    flat = posterior.flat()[:, [posterior.keys.index(k) for k in objective.keys]]
    pick = np.random.default_rng(seed).choice(flat.shape[0], size=min(n, flat.shape[0]), replace=False)
    thetas = flat[pick]
    result = sweep(objective, thetas, chunk=chunk)
    ok = np.isfinite(np.asarray(result.loss, float))
    errors = [objective.in_metres(r) for r in np.asarray(result.residuals, float)[ok]]
    blocks = {name: {"at": at, "data": measured, "predicted": np.stack([e[name] for e in errors]) + measured}
              for name, (at, measured) in observed_blocks(objective).items()}
    return {"thetas": thetas[ok], "failed": int((~ok).sum()), "blocks": blocks, "noise": posterior.noise}
