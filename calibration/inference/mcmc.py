"""A posterior by gradient-based MCMC: the No-U-Turn sampler (blackjax), for any number of keys.

``nuts_posterior(objective, fit_result)`` samples p(θ | data) ∝ exp(−χ²(θ)/2) under a flat prior
inside the bounds (and μ2 ≥ μ1 where both enter), χ² on the fit's noise σ_b by block, in the
bounds' logit coordinates whitened by the fit's Gauss–Newton covariance, with forward-mode
gradients and a step size adapted per chain. ``resume=`` makes stored chains longer;
``take`` and ``join`` split them across processes and back. Each choice and its reason:
docs/posteriors.md. blackjax is an optional dependency: ``pip install "jaxmpm[bayes]"``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.bounds import dphysical_dz, unconstrained
from ..problem.options import check_int
from ..problem.protocol import ObjectiveLike
from .gridterm import GridTerm, coarse_objectives, with_grid_term
from .nuts import (
    ChainDraws,
    _blackjax,
    _chain_keys,
    _chain_reporter,
    _run_chain,
    gauss_newton_point,
    gaussian_prior,
    log_density_fn,
    nuts_sampler,
    row_weights,
    whitened,
)

__all__ = ["McmcPosterior", "diagnose", "nuts_posterior", "posterior_predictive"]


#: The fields ``_summary`` computes, in its order.
_SUMMARY = ("mean", "sd", "ci95", "rhat", "ess_bulk", "ess_tail")


#: R̂ and bulk-ESS thresholds of Vehtari et al. (2021) for a posterior to be reported as converged.
RHAT_MAX, ESS_MIN = 1.01, 100.0


@dataclasses.dataclass(frozen=True)
class McmcPosterior(GridTerm):
    """NUTS draws of the fitted keys and their diagnostics. ``draws`` (chains, n, k): physical θ
    after warm-up; ``log_density`` (chains, n); by key the posterior ``mean``, ``sd``, equal-tailed
    95 % credible interval ``ci95``, ``rhat``, ``ess_bulk`` and ``ess_tail``, beside the fit's
    point ``theta_hat`` and Gauss–Newton standard error. Per chain: the adapted ``step_size``
    (in the whitened coordinates, where 1 is the scale of the Gauss–Newton posterior), the
    ``divergences``, the mean ``acceptance`` and the mean leapfrog ``steps`` per draw;
    ``gradient_evaluations`` counts the runs' Jacobians, warm-up included. ``gn_cov``: the
    Gauss–Newton covariance that whitened the chains (None where an old record lacks it);
    ``segments``: (seed, draws per chain) of the first run and of every ``resume`` after it;
    ``chain_ids``: each chain's number in its run (``take`` and ``join`` keep them); ``prior``:
    {key: (mean, sd)}, the normal priors the chains were drawn with (None: flat in the bounds);
    ``grid``, ``ci95_with_grid``, ``grid_posteriors``, ``grid_note``: the grid term
    (``calibration.inference.gridterm``; not kept by ``take``, ``join`` and ``from_json``)."""

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
    gn_cov: np.ndarray | None = None
    segments: tuple[tuple[int, int], ...] = ()
    chain_ids: tuple[int, ...] = ()
    prior: dict[str, tuple[float, float]] | None = None

    @property
    def ids(self) -> tuple[int, ...]:
        """Each chain's number in the run it belongs to (0, 1, ... unless ``take`` chose some)."""
        return self.chain_ids or tuple(range(self.draws.shape[0]))

    def take(self, chains) -> McmcPosterior:
        """The posterior of the chains at positions ``chains`` only (to resume them apart, in
        another process, and ``join`` them again); diagnostics of those chains."""
        idx = [int(c) for c in chains]
        if not idx or any(not 0 <= c < self.chains for c in idx) or len(set(idx)) != len(idx):
            raise ValueError(f"chains must be distinct positions in range({self.chains}), got {list(chains)!r}")
        pick = lambda values: tuple(values[c] for c in idx)  # noqa: E731
        draws = self.draws[idx]
        return dataclasses.replace(
            self, draws=draws, log_density=self.log_density[idx], **dict(zip(_SUMMARY, _summary(self.keys, draws))),
            step_size=pick(self.step_size), divergences=pick(self.divergences), acceptance=pick(self.acceptance),
            steps=pick(self.steps), chain_ids=pick(self.ids),
            gradient_evaluations=round(self.gradient_evaluations * len(idx) / self.chains), **_NO_GRID)

    @classmethod
    def join(cls, parts) -> McmcPosterior:
        """One posterior of the chains of ``parts`` (posteriors of one fit and target, with the
        same segments, from ``take`` and a resume each), ordered by chain number; diagnostics of
        the whole. Wall time is the longest part's (they ran side by side)."""
        parts = sorted(parts, key=lambda part: part.ids[0])
        first = parts[0]
        for part in parts[1:]:
            same = (part.keys == first.keys and part.segments == first.segments and part.warmup == first.warmup
                    and part.noise == first.noise and part.theta_hat == first.theta_hat and part.prior == first.prior
                    and part.draws.shape[1:] == first.draws.shape[1:])
            if not same:
                raise ValueError("parts: every part must sample the same keys, fit and noise with the same segments")
        ids = sum((part.ids for part in parts), ())
        if len(set(ids)) != len(ids):
            raise ValueError(f"parts: a chain is in more than one part ({list(ids)})")
        draws = np.concatenate([part.draws for part in parts])
        cat = lambda name: sum((tuple(getattr(part, name)) for part in parts), ())  # noqa: E731
        return dataclasses.replace(
            first, draws=draws, log_density=np.concatenate([part.log_density for part in parts]),
            **dict(zip(_SUMMARY, _summary(first.keys, draws))), step_size=cat("step_size"),
            divergences=cat("divergences"), acceptance=cat("acceptance"), steps=cat("steps"), chain_ids=ids,
            gradient_evaluations=sum(part.gradient_evaluations for part in parts),
            wall_s=max(part.wall_s for part in parts), **_NO_GRID)

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
                "prior": "flat inside the bounds" + ("" if not self.prior else ", times a normal in θ for "
                                                     + ", ".join(self.prior)),
                "normal_prior": None if not self.prior else {k: list(v) for k, v in self.prior.items()},
                "chains": self.chains, "warmup": self.warmup,
                "draws_per_chain": int(self.draws.shape[1]), "seed": self.seed,
                "mean": self.mean, "sd": self.sd, "ci95": {k: list(v) for k, v in self.ci95.items()},
                # R-hat needs two chains, the ESS four draws a chain: null (not NaN) without
                "rhat": _nulls(self.rhat), "ess_bulk": _nulls(self.ess_bulk), "ess_tail": _nulls(self.ess_tail),
                "converged": self.converged, "theta_hat": self.theta_hat, "gauss_newton_stderr": self.gn_stderr,
                "sd_over_gauss_newton": {k: self.sd[k] / self.gn_stderr[k] for k in self.keys},
                "step_size": list(self.step_size), "divergences": list(self.divergences),
                "acceptance": list(self.acceptance), "leapfrog_steps_per_draw": list(self.steps),
                "gradient_evaluations": self.gradient_evaluations, "noise": self.noise, "wall_s": round(self.wall_s, 2),
                "gauss_newton_cov": None if self.gn_cov is None else np.asarray(self.gn_cov).tolist(),
                "segments": [list(seg) for seg in self.segments], "chain_ids": list(self.ids),
                "draws": {k: self.draws[..., j].tolist() for j, k in enumerate(self.keys)},
                "log_density": None if not np.all(np.isfinite(self.log_density)) else self.log_density.tolist(),
                **self.grid_json()}

    @classmethod
    def from_json(cls, record: Mapping[str, Any]) -> McmcPosterior:
        """The posterior back from ``to_json`` (so that ``nuts_posterior(..., resume=)`` can extend
        a stored run). A record written before the fields existed has no log densities (NaN here),
        no covariance (None: a resume then checks the standard errors only), one segment and the
        flat prior it states."""
        keys = tuple(record["keys"])
        draws = np.stack([np.asarray(record["draws"][k], float) for k in keys], axis=-1)
        if draws.ndim != 3:
            raise ValueError(f"record: draws must be (chains, n) per key, got shape {draws.shape[:-1]}")
        logp = record.get("log_density")
        logp = np.full(draws.shape[:2], np.nan) if logp is None else np.asarray(logp, float)
        nans = lambda d: {k: float("nan") if v is None else float(v) for k, v in d.items()}  # noqa: E731
        rhat = nans(record["rhat"])
        cov = record.get("gauss_newton_cov")
        segments = tuple(tuple(int(v) for v in seg) for seg in record.get("segments") or
                         [(record["seed"], draws.shape[1])])
        return cls(keys, draws, logp, dict(record["mean"]), dict(record["sd"]),
                   {k: tuple(v) for k, v in record["ci95"].items()}, rhat, nans(record["ess_bulk"]),
                   nans(record["ess_tail"]), dict(record["theta_hat"]), dict(record["gauss_newton_stderr"]),
                   tuple(record["step_size"]), tuple(int(v) for v in record["divergences"]),
                   tuple(record["acceptance"]), tuple(record["leapfrog_steps_per_draw"]),
                   int(record["gradient_evaluations"]), int(record["warmup"]), dict(record["noise"]),
                   int(record["seed"]), float(record["wall_s"]), None if cov is None else np.asarray(cov, float),
                   segments, tuple(int(c) for c in record.get("chain_ids") or range(draws.shape[0])),
                   _prior_of(record.get("normal_prior")))


#: A posterior of some of a run's chains (``take``, ``join``) has not the run's grid term.
_NO_GRID = {"grid": None, "ci95_with_grid": None, "grid_posteriors": (), "grid_note": ""}


def _prior_of(prior) -> dict[str, tuple[float, float]] | None:
    """{key: (mean, sd)} as floats (None or empty: the flat prior)."""
    return {k: (float(v[0]), float(v[1])) for k, v in prior.items()} if prior else None


def _nulls(values: Mapping[str, float]) -> dict[str, float | None]:
    return {k: v if math.isfinite(v) else None for k, v in values.items()}


def diagnose(keys: tuple[str, ...], chains: list[ChainDraws], theta_of: Callable, *, fit_result,
             sigma: Mapping[str, float], warmup: int, seed: int, evaluations: int, wall_s: float,
             chain_ids: tuple[int, ...], resume: McmcPosterior | None = None, prior=None) -> McmcPosterior:
    """The ``McmcPosterior`` of the kept draws of ``chains`` (mapped to θ by ``theta_of``): the
    draws in θ and their summary and diagnostics (``_summary``), per chain the step size,
    divergences, mean acceptance and mean leapfrog steps. With ``resume``, the new draws extend
    its chains and every figure is that of the whole chains (per-draw means weighted by the
    segments' lengths, counts summed)."""
    unc = fit_result.uncertainty
    dtype = jnp.result_type(float)
    samples = np.stack([np.asarray(jax.vmap(theta_of)(jnp.asarray(c.w, dtype)), float) for c in chains])
    log_dens = np.stack([c.log_density for c in chains])  # (chains, n, k), (chains, n)
    draws = samples.shape[1]
    sizes = [c.step_size for c in chains]
    divs = [int(np.sum(c.divergent)) for c in chains]
    accs = [float(np.mean(c.acceptance)) for c in chains]
    steps_mean = [float(np.mean(c.steps)) for c in chains]
    segments = ((int(seed), int(draws)),)
    if resume is not None:  # the whole chains: per-draw means weighted by the segments' lengths
        n0 = resume.draws.shape[1]
        weigh = lambda old, new: tuple((n0 * a + draws * b) / (n0 + draws) for a, b in zip(old, new))  # noqa: E731
        accs, steps_mean = weigh(resume.acceptance, accs), weigh(resume.steps, steps_mean)
        divs = [a + b for a, b in zip(resume.divergences, divs)]
        samples = np.concatenate([resume.draws, samples], axis=1)
        log_dens = np.concatenate([resume.log_density, log_dens], axis=1)
        evaluations += resume.gradient_evaluations
        wall_s += resume.wall_s
        segments = tuple(resume.segments) + segments
    theta_hat = [fit_result.theta[k] for k in keys]
    return McmcPosterior(keys, samples, log_dens, *_summary(keys, samples),
                         dict(zip(keys, np.asarray(theta_hat, float).tolist())),
                         dict(zip(keys, np.asarray(unc.stderr, float).tolist())),
                         tuple(sizes), tuple(divs), tuple(accs), tuple(steps_mean), evaluations, warmup,
                         {key: float(v) for key, v in sigma.items()}, int(segments[0][0]), wall_s,
                         np.asarray(unc.cov, float), segments, chain_ids, _prior_of(prior))


def nuts_posterior(objective: ObjectiveLike, fit_result, *, chains: int | None = None, warmup: int | None = None,
                   draws: int = 200, seed: int = 0, noise: Mapping[str, float] | float | None = None,
                   target_accept: float = 0.8, max_doublings: int = 6, spread: float = 1.0,
                   resume: McmcPosterior | None = None, prior: Mapping[str, tuple[float, float]] | None = None,
                   grid_ratio: float | None = None, grid_levels: int = 1, progress: bool = False) -> McmcPosterior:
    """NUTS draws of ``objective``'s keys around ``fit_result``, whose Gauss–Newton covariance
    preconditions the sampler. ``chains`` (default 4) run one after the other (on the CPU a
    vmapped batch of runs costs more than the runs in turn), each with ``warmup`` (default 100)
    step-size adaptation steps, then ``draws`` kept; ``noise``: σ by block (default: the fit's);
    ``max_doublings``: at most 2^``max_doublings`` leapfrog steps per draw; ``prior``: {key:
    (mean, sd)}, a normal in θ for keys measured elsewhere (``gaussian_prior``). ``grid_ratio``,
    ``grid_levels``: the grid term (``calibration.inference.gridterm``; None: not measured), the
    same chains on the objective rebuilt at ``grid_ratio`` × dx; not with ``resume``.

    ``resume``: a posterior of the same objective, fit and noise (``McmcPosterior.from_json`` of
    a record will do) whose chains go on for ``draws`` more each, with their step sizes and no
    new warm-up; the result holds every draw, and its diagnostics are those of the whole chains.

    The parts: ``log_density_fn`` (the target), ``nuts_sampler`` (the kernels), per chain
    ``start_chain``, ``warm_up`` and ``sample_chain``, and ``diagnose`` (the summary)."""
    _blackjax()
    prior_terms = gaussian_prior(objective.keys, prior)
    coarse, grid_note = coarse_objectives(objective, grid_ratio, grid_levels)
    chains, warmup = _check_settings(chains, warmup, draws, max_doublings, target_accept, spread, resume=resume,
                                     prior=prior, grid_ratio=grid_ratio)
    keys = tuple(objective.keys)
    theta_hat, sigma, gn_cov = gauss_newton_point(objective, fit_result, noise,
                                                  hint="; the sampler needs one to precondition the chains")
    if resume is not None:
        _check_resume(resume, keys, fit_result, sigma)
    clock = time.perf_counter()
    # The chains' precision: JAX's default float (float64 where x64 is on, even for a float32 run,
    # whose residuals are cast: blackjax's own arrays follow the default and must not mix).
    dtype = jnp.result_type(float)
    log_density, theta_of, lasts = _whitened_target(objective, theta_hat, sigma, gn_cov, prior_terms, dtype, resume)
    sampler = nuts_sampler(log_density, len(keys), dtype, target_accept=target_accept, max_doublings=max_doublings)
    rng = np.random.default_rng(seed)
    chain_ids, keys_all = _chain_keys(seed, chains, resume)
    n_warm = 0 if resume is not None else warmup
    out, evaluations = [], 0
    for c in range(chains):
        report = _chain_reporter(progress, c, chains, n_warm + draws, clock)
        resume_at = None if resume is None else (lasts[c], resume.step_size[c])  # its last draw and step size
        drawn, spent = _run_chain(sampler, c, keys_all[c], draws, report, resume_at=resume_at, rng=rng, k=len(keys),
                                  spread=spread, n_warm=n_warm)
        evaluations += spent
        out.append(drawn)
    found = diagnose(keys, out, theta_of, fit_result=fit_result, sigma=sigma, warmup=warmup, seed=seed,
                     evaluations=evaluations, wall_s=time.perf_counter() - clock, chain_ids=chain_ids, resume=resume,
                     prior=prior)
    if not coarse:
        return dataclasses.replace(found, grid_note=grid_note)
    settings = dict(chains=chains, warmup=warmup, draws=draws, seed=seed, noise=sigma, target_accept=target_accept,
                    max_doublings=max_doublings, spread=spread, prior=prior, progress=progress)
    return _with_grid_term(found, objective, coarse, grid_ratio, fit_result, settings)


def _check_settings(chains, warmup, draws, max_doublings, target_accept, spread, *, resume, prior, grid_ratio):
    """``nuts_posterior``'s settings checked, and its ``chains`` and ``warmup`` with their defaults
    (a resumed run's own)."""
    if resume is not None and grid_ratio is not None:
        raise ValueError("grid_ratio: the grid term samples fresh chains on coarser grids, which a resumed run "
                         "would not match; measure it on a fresh run")
    if resume is not None:
        if not isinstance(resume, McmcPosterior):
            raise ValueError(f"resume must be a McmcPosterior (McmcPosterior.from_json of a record), got "
                             f"{type(resume).__name__}")
        if resume.prior != _prior_of(prior):
            raise ValueError(f"prior: the resumed chains were drawn with {resume.prior or 'the flat prior'}, got "
                             f"{_prior_of(prior) or 'the flat prior'}: a chain goes on only on its own target")
        if warmup is not None:
            raise ValueError("warmup: a resumed chain keeps its adapted step size and runs no warm-up; pass none")
        if chains is not None and chains != resume.chains:
            raise ValueError(f"chains: resume holds {resume.chains} chains, got chains={chains!r}")
        chains, warmup = resume.chains, resume.warmup
    chains = 4 if chains is None else chains
    warmup = 100 if warmup is None else warmup
    for name, value, least in (("chains", chains, 1), ("warmup", warmup, 1), ("draws", draws, 4),
                               ("max_doublings", max_doublings, 1)):
        check_int(name, value, least)
    if not 0 < target_accept < 1:
        raise ValueError(f"target_accept must lie in (0, 1), got {target_accept!r}")
    if not (math.isfinite(spread) and spread > 0):
        raise ValueError(f"spread must be a positive number, got {spread!r}")
    return chains, warmup


def _whitened_target(objective, theta_hat, sigma, gn_cov, prior_terms, dtype, resume):
    """The log density in w (z = ẑ + L w, L from the Gauss–Newton covariance mapped to z) and its
    map to θ, in ``dtype``; with ``resume``, its chains' last draws in w (else None)."""
    keys = tuple(objective.keys)
    lower_np, upper_np = np.asarray(objective.bounds.lower, float), np.asarray(objective.bounds.upper, float)
    if np.any((theta_hat <= lower_np) | (theta_hat >= upper_np)):
        raise ValueError(f"fit_result: the point {dict(zip(keys, theta_hat))} is not strictly inside the bounds")
    z_hat = unconstrained(theta_hat, lower_np, upper_np)
    dtheta_dz = np.asarray(dphysical_dz(jnp.asarray(z_hat), jnp.asarray(lower_np), jnp.asarray(upper_np)), float)
    L = np.linalg.cholesky(gn_cov / np.outer(dtheta_dz, dtheta_dz))
    as_dtype = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    log_density, theta_of = log_density_fn(objective, as_dtype(row_weights(objective, sigma)), as_dtype(z_hat),
                                           as_dtype(L), as_dtype(lower_np), as_dtype(upper_np), prior_terms)
    lasts = None if resume is None else whitened(resume.draws[:, -1, :], z_hat, L, lower_np, upper_np)
    return log_density, theta_of, lasts


def _with_grid_term(found: McmcPosterior, objective, coarse, grid_ratio, fit_result, settings) -> McmcPosterior:
    """``found`` with the grid term: the same chains (``settings``, the fit's whitening) on the
    coarser objectives."""
    return with_grid_term(
        found, objective, coarse, grid_ratio, lambda obj: nuts_posterior(obj, fit_result, **settings),
        lambda other: {"rhat_max": max((v for v in other.rhat.values() if math.isfinite(v)), default=None),
                       "divergences": int(sum(other.divergences)), "gradient_evaluations": other.gradient_evaluations})


def _summary(keys, samples):
    """By key: mean, sd, 95 % interval, R̂ (NaN for one chain), bulk and tail ESS (NaN below four
    draws a chain) of draws (chains, n, k). The diagnostics are arviz-stats' (a port of the
    reference implementation, the R package posterior: Vehtari et al. 2021's rank-normalised
    split R̂, and the bulk and 5 %/95 % tail ESS), computed in float64 on the draws as numpy."""
    from arviz_stats.base import array_stats

    samples = np.asarray(samples, float)
    flat = samples.reshape(-1, len(keys))
    mean = {key: float(flat[:, j].mean()) for j, key in enumerate(keys)}
    sd = {key: float(flat[:, j].std(ddof=1)) for j, key in enumerate(keys)}
    ci = {key: (float(np.quantile(flat[:, j], 0.025)), float(np.quantile(flat[:, j], 0.975)))
          for j, key in enumerate(keys)}
    nan = np.full(len(keys), np.nan)
    enough = samples.shape[1] >= 4  # the split-chain estimators need two draws per half
    axes = dict(chain_axis=0, draw_axis=1)
    rhat = array_stats.rhat(samples, method="rank", **axes) if enough and samples.shape[0] > 1 else nan
    ess_b = array_stats.ess(samples, method="bulk", **axes) if enough else nan
    ess_t = array_stats.ess(samples, method="tail", prob=(0.05, 0.95), **axes) if enough else nan
    by_key = lambda values: {key: float(v) for key, v in zip(keys, np.asarray(values, float))}  # noqa: E731
    return mean, sd, ci, by_key(rhat), by_key(ess_b), by_key(ess_t)


def _check_resume(resume, keys, fit_result, sigma):
    """A resumed chain must go on on the target it was drawn from: the same keys and noise (to
    1e-5 relative), and the whitening of the same fit (its point to 1e-3 standard errors, its
    covariance to 1e-3 relative). The whitening only preconditions, so a fit that differs by
    round-off leaves the chain valid; a different fit is refused as a sign of a mix-up."""
    if tuple(resume.keys) != keys:
        raise ValueError(f"resume samples {tuple(resume.keys)}, the objective fits {keys}")
    unc = fit_result.uncertainty
    if set(resume.noise) != set(sigma):
        raise ValueError(f"resume was drawn with noise on blocks {sorted(resume.noise)}, this one on {sorted(sigma)}")
    se = np.asarray(unc.stderr, float)
    checks = [("the fit's point", np.array([resume.theta_hat[k] for k in keys]),
               np.array([fit_result.theta[k] for k in keys], float), 0.0, 1e-3 * se),
              ("the Gauss-Newton standard errors", np.array([resume.gn_stderr[k] for k in keys]), se, 1e-3, 0.0),
              ("the noise", np.array([resume.noise[b] for b in sorted(sigma)]),
               np.array([float(sigma[b]) for b in sorted(sigma)]), 1e-5, 0.0)]
    if resume.gn_cov is not None:
        cov = np.asarray(unc.cov, float)
        checks.append(("the Gauss-Newton covariance", np.asarray(resume.gn_cov, float), cov, 0.0,
                       1e-3 * np.sqrt(np.outer(se, se))))
    for what, a, b, rtol, atol in checks:
        if np.any(np.abs(a - b) > rtol * np.abs(b) + atol):
            raise ValueError(f"resume: {what} differs from this fit's ({a.tolist()} against {b.tolist()}): "
                             "the chains were drawn for another fit")


def posterior_predictive(objective, posterior: McmcPosterior, *, n: int = 40, seed: int = 0,
                         chunk: int | None = None) -> dict[str, Any]:
    """The model's prediction of ``objective``'s data (an ``Objective``: the fitted one, or one
    with held-out data) at ``n`` draws of ``posterior`` chosen at random from every chain, in one
    batched sweep: ``thetas`` (n, k) and, by block, ``at``, ``data`` and ``predicted`` (n, m), in
    metres (``calibration.plots.posteriors.plot_posterior_predictive`` draws them). Its spread is the
    parameters' uncertainty; the measurement noise ``noise`` (by block, relative) comes beside it."""
    from ..batch.sweep import sweep
    from .gridpost import observed_blocks

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
