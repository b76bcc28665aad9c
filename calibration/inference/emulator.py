"""A posterior for many keys at a few dozen runs: NUTS on a quadratic emulator of the residuals,
corrected to the model's own posterior by Pareto-smoothed importance sampling.

The model's Jacobians at a design around a centre (3k + 1 points in whitened logit coordinates
w) fit the emulator (``surrogates``), each point weighed by exp(−|w|²/(2 ``reach``²)); NUTS
samples it; the design is re-centred on the draws until it settles; the model's χ² at
``checks`` draws gives the importance weights. The steps, why each is there and when to believe
the answer (Pareto k̂ < 0.7): docs/posteriors.md.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
import types
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..batch.workers import jacobians_z, residuals_at
from ..problem.bounds import dphysical_dz, physical, unconstrained
from ..problem.options import check_int
from ..problem.protocol import ObjectiveLike
from .gridpost import weighted_summary
from .gridterm import GridTerm, coarse_objectives, with_grid_term
from .likelihood import checked_point, noise_levels, row_weights
from .surrogates import EMULATORS, EmulatedObjective, psis

__all__ = ["EmulatedPosterior", "log_uniform", "scale_keys", "prior_sensitivity", "emulated_posterior"]


#: The least effective sample size of a reported posterior (``calibration.inference.mcmc``'s, Vehtari et al. 2021).
ESS_MIN = 100.0


#: Pareto k̂ above which importance weights are unreliable (Vehtari et al. 2024, for S ≥ 2,000 draws).
PARETO_K_MAX = 0.7


@dataclasses.dataclass(frozen=True)
class EmulatedPosterior(GridTerm):
    """The model's posterior from NUTS on an emulator and the importance correction.
    ``mean``, ``sd``, ``ci95`` by key: the corrected ones; ``emulated``: the emulator's NUTS
    posterior; ``pareto_k`` and ``ess_importance``: the correction's reliability; ``checks``:
    (θ (n, k), raw log importance weight (n,)) at the checked draws (−∞: the model's run failed
    there, ``failed_checks`` of them); ``rounds``: per emulator its design points, the kernel's
    weight (``kernel_points``), the fit's ``emulator_rms``, how far its posterior's mean lay from
    its design's centre (``posterior_mean_from_centre_sd``, in the posterior's sd) and, from the
    second on, the previous emulator's χ² error at the new star (``new_points_dchi2``);
    ``jacobians`` and ``runs``: the model's Jacobians and forward runs spent; ``check_chi2``: the
    model's χ² at the checked draws (∞: failed) on ``noise``, the likelihood's σ by block;
    ``prior``: the normal priors it was sampled with (None: flat in the bounds)."""

    keys: tuple[str, ...]
    mean: dict[str, float]
    sd: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    emulated: Any
    pareto_k: float
    ess_importance: float
    checks: tuple[np.ndarray, np.ndarray]
    failed_checks: int
    rounds: tuple[dict[str, Any], ...]
    jacobians: int
    runs: int
    wall_s: float
    emulator: str = "corrected"
    check_chi2: np.ndarray | None = None
    noise: dict[str, float] | None = None
    prior: dict[str, tuple[float, float]] | None = None

    @property
    def settled(self) -> bool:
        """The last emulator's posterior lay where its design was centred (the rounds stopped
        there, not at their limit)."""
        return bool(self.rounds[-1].get("settled", False))

    @property
    def converged(self) -> bool:
        """The emulator's chains converged (R̂ < 1.01, bulk ESS ≥ 100, no divergence) and the
        correction is reliable: Pareto k̂ < 0.7 and an importance ESS of at least 100 (the
        chains' own threshold)."""
        return bool(self.emulated.converged and self.pareto_k < PARETO_K_MAX and self.ess_importance >= ESS_MIN)

    def _weights(self, log_prior=None) -> tuple[np.ndarray, float]:
        """The checks' Pareto-smoothed weights (and k̂), under the flat prior or ``log_prior``."""
        log_w = self.checks[1]
        if log_prior is not None:
            extra = np.asarray(log_prior(self.checks[0]), float)
            if extra.shape != log_w.shape or np.any(np.isnan(extra)):
                raise ValueError(f"log_prior must give one log density per check ({log_w.shape}), got {extra.shape}")
            log_w = log_w + extra
        smoothed, k_hat = psis(log_w)
        return np.exp(smoothed), k_hat

    def credible_level(self, chi2: float, log_prior=None) -> float:
        """The posterior's mass where the model's χ² is below ``chi2`` (the importance-weighted
        checks): the smallest joint credible region, ordered by the likelihood, that holds a point
        of χ² ``chi2``; a point is inside the joint 95 % region when the level is at most 0.95.
        Unlike a marginal interval, it is not moved by the room a ridge has in the box.
        ``log_prior``: the same region's mass under another prior (``reweighted``)."""
        if self.check_chi2 is None:
            raise ValueError("this posterior carries no χ² at its checks (made before they were kept)")
        if not (isinstance(chi2, (int, float, np.floating)) and not math.isnan(chi2)):
            raise ValueError(f"chi2 must be a number, got {chi2!r}")
        w, _ = self._weights(log_prior)
        return float(np.sum(w[self.check_chi2 < chi2]))

    def reweighted(self, log_prior) -> dict[str, Any]:
        """The posterior under another prior, from the same checks: ``log_prior`` maps θ (n, k),
        keys in order, to the new prior's log density (n,) up to a constant (``log_uniform``).
        The mean, sd and 95 % interval by key, with ``pareto_k`` and ``ess_importance`` (a prior
        whose mass lies where the checks are few leaves few effective draws: then sample it)."""
        w, k_hat = self._weights(log_prior)
        mean, sd, ci = weighted_summary(self.keys, self.checks[0], w)
        return {"mean": mean, "sd": sd, "ci95": {k: list(v) for k, v in ci.items()},
                "pareto_k": k_hat if math.isfinite(k_hat) else None, "ess_importance": float(1.0 / np.sum(w**2))}

    def chi2_at(self, objective: ObjectiveLike, theta) -> float:
        """The model's χ² at ``theta`` (a mapping by key, or values in key order) with this
        posterior's noise: one forward run. ∞ where the run fails."""
        if self.noise is None:
            raise ValueError("this posterior carries no noise level (made before it was kept)")
        if tuple(objective.keys) != self.keys:
            raise ValueError(f"objective: its keys {tuple(objective.keys)} are not this posterior's {self.keys}")
        r, pred = objective.residuals(checked_point(objective, theta))
        if int(np.max(np.asarray(pred["status"]))) != 0:
            return math.inf
        return float(np.sum(row_weights(objective, self.noise) * np.asarray(r, float) ** 2))

    def to_json(self) -> dict[str, Any]:
        emulated = {k: v for k, v in self.emulated.to_json().items() if k not in ("draws", "log_density")}
        kind = {"quadratic": "a quadratic emulator of the residuals",
                "corrected": "a quadratic emulator of the residuals corrected by a Gaussian process through the "
                             "design points"}[self.emulator]
        return {"keys": list(self.keys), "method": f"NUTS on {kind}, corrected by Pareto-smoothed importance sampling "
                "with the model's runs", "emulator": self.emulator, "mean": self.mean, "sd": self.sd,
                "ci95": {k: list(v) for k, v in self.ci95.items()}, "converged": self.converged,
                "settled": self.settled, "pareto_k": self.pareto_k if math.isfinite(self.pareto_k) else None,
                "pareto_k_max": PARETO_K_MAX, "ess_importance": self.ess_importance,
                "ess_min": ESS_MIN,
                "checks": int(self.checks[1].size), "failed_checks": self.failed_checks,
                "rounds": list(self.rounds), "model_jacobians": self.jacobians, "model_runs": self.runs,
                "wall_s": round(self.wall_s, 1), "emulated": emulated,
                "check_draws": {k: self.checks[0][:, j].tolist() for j, k in enumerate(self.keys)},
                "check_log_weights": [v if math.isfinite(v) else None for v in self.checks[1].tolist()],
                "check_chi2": None if self.check_chi2 is None else [v if math.isfinite(v) else None
                                                                    for v in self.check_chi2.tolist()],
                "noise": self.noise,
                "prior": None if self.prior is None else {k: list(v) for k, v in self.prior.items()},
                **self.grid_json()}


def log_uniform(keys, *names: str):
    """The log density, up to a constant, of a prior uniform in log θ for the keys ``names``
    (flat in the others) relative to the flat one: −Σ log θ_j, for ``EmulatedPosterior.reweighted``.
    The scale-free prior of a positive key whose box spans decades (I0)."""
    keys = tuple(keys)
    unknown = [n for n in names if n not in keys]
    if unknown or not names:
        raise ValueError(f"names must be keys of {keys}, got {list(names)}")
    columns = [keys.index(n) for n in names]

    def log_prior(thetas):
        thetas = np.asarray(thetas, float)[:, columns]
        if np.any(thetas <= 0):
            raise ValueError(f"a log-uniform prior needs {list(names)} > 0")
        return -np.sum(np.log(thetas), axis=1)

    return log_prior


def scale_keys(bounds, decades: float = 2.0) -> tuple[str, ...]:
    """The keys of ``bounds`` whose box is positive and spans at least ``decades`` decades (I0's
    0.001-3): for them a prior flat in θ and one flat in log θ are both defensible and differ."""
    return tuple(k for k, lo, hi in zip(bounds.keys, np.asarray(bounds.lower, float), np.asarray(bounds.upper, float))
                 if lo > 0 and math.log10(hi / lo) >= decades)


def prior_sensitivity(posterior: EmulatedPosterior, keys: tuple[str, ...]) -> dict[str, Any]:
    """``posterior`` again under a prior uniform in log θ for ``keys`` (``reweighted``), with
    each key's mean shift in the flat prior's sd: a key the data fix does not move; one whose
    interval is the prior's (a ridge the data leave open) does."""
    other = posterior.reweighted(log_uniform(posterior.keys, *keys))
    shift = {k: (other["mean"][k] - posterior.mean[k]) / posterior.sd[k] if posterior.sd[k] > 0 else 0.0
             for k in posterior.keys}
    return {"log_uniform_keys": list(keys), **other, "mean_shift_sd": shift}


def _laplace_cov_z(objective, weights, z, Jz, prior=None) -> np.ndarray:
    """The Laplace covariance in z at ``z``: the inverse of Gauss–Newton's JᵀWJ plus the
    curvature of the flat prior's log-Jacobian, 2 s(1 − s) per key (s = sigmoid z), and of a
    ``prior`` (``gaussian_prior``'s terms), (dθ/dz / sd)². The flat prior's term keeps a key the
    data do not fix at the scale of its box (a logistic's), not at infinity."""
    z = np.asarray(z, float)
    s = 1.0 / (1.0 + np.exp(-z))
    curvature = 2.0 * s * (1.0 - s)
    if prior is not None:
        idx, _, sd = prior
        span = np.asarray(objective.bounds.upper, float) - np.asarray(objective.bounds.lower, float)
        dtheta_dz = span * s * (1.0 - s)
        curvature[idx] += (dtheta_dz[idx] / sd) ** 2
    precision = Jz.T @ (weights[:, None] * Jz) + np.diag(curvature)
    return np.linalg.inv(precision)


def emulated_posterior(objective: ObjectiveLike, centre, *, noise: Mapping[str, float] | float | None = None,
                       rounds: int = 6, settle: float = 1.0, axial: float = 2.0, reach: float = 3.0,
                       checks: int = 200, chains: int = 4,
                       warmup: int = 200, draws: int = 1000, seed: int = 0, emulator: str = "corrected",
                       target_accept: float = 0.8, prior: Mapping[str, tuple[float, float]] | None = None,
                       grid_ratio: float | None = None, grid_levels: int = 1,
                       workers=None, progress: bool = False) -> EmulatedPosterior:
    """The posterior of ``objective``'s keys from NUTS on a quadratic emulator whose design follows
    the posterior (at most ``rounds`` re-centrings, until the emulated posterior's mean lies within
    ``settle`` of its standard deviations of the design's centre), corrected with the model's runs
    at ``checks`` draws (docs/posteriors.md).

    ``centre``: a fit (its point, Gauss–Newton covariance and noise whiten the first round), or
    parameter values by key, which need ``noise``: then the first whitening is the Laplace
    covariance there, with the flat prior's curvature in the logit coordinates so that keys the
    data leave free span their box (a point the verdict refuses still has a posterior).
    ``noise``: σ by block (default: the fit's). ``axial``: the star's reach and ``reach`` the
    kernel's, in whitened units; ``chains``, ``warmup``, ``draws``, ``target_accept``: the
    emulator's NUTS; ``workers``: processes for the model's runs (``calibration.batch.workers``),
    3k + 1 + (2k + 1) per re-centring with the Jacobian and ``checks`` without. ``emulator``:
    "corrected" (``CorrectedQuadratic``) or "quadratic" (``QuadraticEmulator``). ``prior``:
    {key: (mean, sd)}, a normal in θ for keys measured elsewhere (``nuts.gaussian_prior``), which
    the emulator's chains and the model's posterior both carry. ``grid_ratio``, ``grid_levels``:
    the grid term (``calibration.inference.gridterm``; None: not measured), the same posterior on
    the objective rebuilt at ``grid_ratio`` × dx (and its square with ``grid_levels=2``)."""
    from .nuts import gaussian_prior

    keys = tuple(objective.keys)
    _check_settings(rounds=rounds, checks=checks, chains=chains, warmup=warmup, draws=draws, axial=axial,
                    reach=reach, settle=settle, emulator=emulator, target_accept=target_accept)
    prior_terms = gaussian_prior(keys, prior)
    coarse, grid_note = coarse_objectives(objective, grid_ratio, grid_levels)
    theta_hat, m, sigma, gn_cov = _centre_point(objective, centre, noise)
    clock = time.perf_counter()
    weights = row_weights(objective, sigma)
    rng = np.random.default_rng(seed)
    say = lambda text: _say(progress, clock, text)  # noqa: E731
    design, L, record = _first_design(objective, theta_hat, m, gn_cov, weights, prior_terms, rng, axial=axial,
                                      workers=workers, say=say)
    jacobians = 3 * len(keys) + 1
    nuts = dict(chains=chains, warmup=warmup, draws=draws, target_accept=target_accept, prior=prior)
    for c in range(rounds + 1):
        target, posterior, m_new, cov_z, fitted = _round(objective, design, m, L, sigma, seed=seed + c, settle=settle,
                                                         reach=reach, emulator=emulator, nuts=nuts, say=say)
        record[-1].update(fitted)
        if c == rounds or fitted["settled"]:
            break
        m, L = m_new, np.linalg.cholesky(cov_z)  # re-centre and re-whiten on the draws (in z), and a new star there
        design, added = _new_star(objective, design, target, m, L, weights, axial=axial, workers=workers, say=say)
        jacobians += 2 * len(keys) + 1
        record.append(added)
    thetas, log_w, chi2_model, (mean, sd, ci, k_hat, ess_importance) = _correction(
        objective, target, posterior.flat(), weights, rng, checks=checks, workers=workers, say=say)
    found = EmulatedPosterior(keys, mean, sd, ci, posterior, k_hat, ess_importance, (thetas, log_w),
                              int(np.sum(~np.isfinite(chi2_model))), tuple(record), jacobians, checks,
                              time.perf_counter() - clock, emulator, chi2_model,
                              {k: float(v) for k, v in sigma.items()},
                              None if prior_terms is None else {k: tuple(map(float, v)) for k, v in prior.items()},
                              grid_note=grid_note)
    if not coarse:
        return found
    settings = dict(rounds=rounds, settle=settle, axial=axial, reach=reach, checks=checks, chains=chains,
                    warmup=warmup, draws=draws, seed=seed, emulator=emulator, target_accept=target_accept,
                    prior=prior, workers=workers, progress=progress)
    return _with_grid_term(found, objective, coarse, grid_ratio, settings, say)


def _check_settings(*, rounds, checks, chains, warmup, draws, axial, reach, settle, emulator, target_accept):
    """``emulated_posterior``'s counts, whitened lengths, emulator and acceptance target."""
    for name, value, least in (("rounds", rounds, 0), ("checks", checks, 30), ("chains", chains, 2),
                               ("warmup", warmup, 1), ("draws", draws, 4)):
        check_int(name, value, least)
    for name, value in (("axial", axial), ("reach", reach), ("settle", settle)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number (whitened units), got {value!r}")
    if emulator not in EMULATORS:
        raise ValueError(f"emulator must be one of {sorted(EMULATORS)}, got {emulator!r}")
    if not (isinstance(target_accept, float) and 0.0 < target_accept < 1.0):
        raise ValueError(f"target_accept must be a float strictly between 0 and 1, got {target_accept!r}")
    if checks > chains * draws:
        raise ValueError(f"checks: {checks} draws to check, the chains keep only {chains * draws}")


def _box(objective) -> tuple[np.ndarray, np.ndarray]:
    """The objective's bounds (lower, upper) as float arrays."""
    return np.asarray(objective.bounds.lower, float), np.asarray(objective.bounds.upper, float)


def _centre_point(objective: ObjectiveLike, centre, noise):
    """The centre's θ̂ (strictly inside the bounds) and its z, the noise σ by block and the
    Gauss–Newton covariance (None for values by key, which need ``noise``)."""
    from .nuts import gauss_newton_point

    keys = tuple(objective.keys)
    lower, upper = _box(objective)
    if isinstance(centre, Mapping):
        if set(centre) != set(keys):
            raise ValueError(f"centre must give every key of the objective {keys}, got {sorted(centre)}")
        theta_hat = np.array([float(centre[key]) for key in keys])
        if noise is None:
            raise ValueError("noise: a centre without a fit needs the data's noise (a float or σ by block)")
        sigma = noise_levels(objective, None, noise)
        gn_cov = None
    else:
        theta_hat, sigma, gn_cov = gauss_newton_point(objective, centre, noise, name="centre", hint=(
            "; pass its point as a mapping of values and the noise, for the Laplace whitening there"))
    if not np.all((theta_hat > lower) & (theta_hat < upper)):
        raise ValueError(f"centre: {dict(zip(keys, theta_hat.tolist()))} is not strictly inside the bounds")
    return theta_hat, np.asarray(unconstrained(theta_hat, lower, upper), float), sigma, gn_cov


def _say(progress: bool, clock: float, text: str) -> None:
    """A progress line on stderr, with the seconds since ``clock`` (nothing without ``progress``)."""
    if progress:
        print(f"emulated posterior: {text} ({time.perf_counter() - clock:.0f} s)", file=sys.stderr, flush=True)


@dataclasses.dataclass(frozen=True)
class _Design:
    """The design: points in z (n, k), residuals (n, m) and dr/dz (n, m, k) where the model ran."""

    Z: np.ndarray
    R: np.ndarray | None = None
    Jz: np.ndarray | None = None


def _run_design(objective, design: _Design, points, workers) -> tuple[_Design, np.ndarray, np.ndarray]:
    """The model's runs at the rows of ``points`` (z): the design with the good ones, their r, which."""
    r, jz, _, pred = jacobians_z(objective, points, workers)
    ok = (np.asarray(pred["status"]).reshape(len(points), -1) == 0).all(axis=1) & np.all(np.isfinite(jz), (1, 2))
    r, jz = np.asarray(r, float)[ok], np.asarray(jz, float)[ok]
    return _Design(np.concatenate([design.Z, points[ok]]), r if design.R is None else np.concatenate([design.R, r]),
                   jz if design.Jz is None else np.concatenate([design.Jz, jz])), r, ok


def _first_design(objective, theta_hat, m, gn_cov, weights, prior_terms, rng, *, axial, workers, say):
    """The first design around m and its whitening L (z = m + L w): the Gauss–Newton covariance's, or
    the Laplace covariance's from the model's Jacobian at the centre; with the first round's record."""
    k = len(m)
    design, star = _Design(np.zeros((0, k))), np.concatenate([axial * np.eye(k), -axial * np.eye(k)])
    if gn_cov is None:  # the Laplace whitening from the model's Jacobian at the centre (the first design point)
        say("the model's Jacobian at the centre")
        design, _, ok = _run_design(objective, design, m[None, :], workers)
        if not ok.all():
            raise RuntimeError(f"centre: the model's run fails at {dict(zip(objective.keys, theta_hat.tolist()))}")
        L = np.linalg.cholesky(_laplace_cov_z(objective, weights, m, design.Jz[0], prior_terms))
        W = np.concatenate([star, rng.normal(0.0, axial / 2, size=(k, k))])
    else:
        dtheta_dz = np.asarray(dphysical_dz(jnp.asarray(m), *map(jnp.asarray, _box(objective))), float)
        L = np.linalg.cholesky(gn_cov / np.outer(dtheta_dz, dtheta_dz))
        W = np.concatenate([np.zeros((1, k)), star, rng.normal(0.0, axial / 2, size=(k, k))])
    say(f"the model's Jacobians at {len(W)} design points")
    design, _, ok = _run_design(objective, design, m + W @ L.T, workers)
    return design, L, [{"design_points": int(len(design.Z)), "failed_runs": int(np.sum(~ok))}]


def _round(objective, design: _Design, m, L, sigma, *, seed, settle, reach, emulator, nuts, say):
    """One round: the emulator fitted on the design in w = L⁻¹(z − m), NUTS on it (``nuts``: its settings):
    the emulated objective, its posterior, the draws' mean and covariance in z, and the round's record."""
    from .mcmc import nuts_posterior

    keys, k = tuple(objective.keys), len(m)
    lower, upper = _box(objective)
    jl, ju = jnp.asarray(lower), jnp.asarray(upper)
    Wd = (design.Z - m) @ np.linalg.inv(L).T
    kernel = np.exp(-0.5 * np.sum(Wd**2, axis=1) / reach**2)
    model = EMULATORS[emulator].fit(Wd, design.R, design.Jz @ L, weights=kernel)
    target = EmulatedObjective(objective, model, m, L)
    theta_m = np.asarray(physical(jnp.asarray(m), jl, ju), float)
    dtheta_dz = np.asarray(dphysical_dz(jnp.asarray(m), jl, ju), float)
    cov = L @ L.T * np.outer(dtheta_dz, dtheta_dz)  # the whitening, as a fit would give it to nuts_posterior
    uncertainty = types.SimpleNamespace(cov=cov, stderr=np.sqrt(np.diag(cov)), withheld=False, noise=sigma)
    whitening = types.SimpleNamespace(keys=keys, theta=dict(zip(keys, theta_m.tolist())), uncertainty=uncertainty)
    say(f"NUTS on the emulator of {len(design.Z)} points")
    posterior = nuts_posterior(target, whitening, seed=seed, noise=sigma, **nuts)
    z_draws = np.asarray(unconstrained(posterior.flat(), lower, upper), float)
    z_draws = z_draws[np.all(np.isfinite(z_draws), axis=1)]  # a float32 draw rounded onto a bound
    m_new, cov_z = z_draws.mean(axis=0), np.cov(z_draws.T).reshape(k, k)
    moved = float(np.sqrt(np.sum((np.linalg.solve(np.linalg.cholesky(cov_z), m_new - m)) ** 2)))
    say(f"the emulated posterior's mean lies {moved:.1f} of its sds from the design's centre"
        + (" (settled)" if moved < settle else ""))
    return target, posterior, m_new, cov_z, {"emulator_rms": model.rms, "kernel_points": float(kernel.sum()),
                                             "posterior_mean_from_centre_sd": moved, "settled": moved < settle}


def _new_star(objective, design: _Design, target, m, L, weights, *, axial, workers, say) -> tuple[_Design, dict]:
    """The model's Jacobians at the new (m, L)'s centre and star, and the next round's record."""
    k = len(m)
    points = m + np.concatenate([np.zeros((1, k)), axial * np.eye(k), -axial * np.eye(k)]) @ L.T
    say(f"the model's Jacobians at the {len(points)} points of a star on the emulator's posterior")
    thetas = np.asarray(physical(jnp.asarray(points), *map(jnp.asarray, _box(objective))))
    before = np.asarray(jax.vmap(target.residual_fn)(jnp.asarray(thetas, jnp.result_type(float)))[0], float)
    design, r_new, ok = _run_design(objective, design, points, workers)
    dchi2 = np.sum(weights * r_new**2, axis=-1) - np.sum(weights * before[ok] ** 2, axis=-1)
    say(f"the model's chi2 minus the emulator's at the star: {np.array2string(dchi2, precision=1)}")
    return design, {"design_points": int(len(design.Z)), "failed_runs": int(np.sum(~ok)),
                    "new_points_dchi2": dchi2.tolist()}


def _correction(objective, target, flat, weights, rng, *, checks, workers, say):
    """The model's runs at ``checks`` of the draws ``flat``: those draws, their log importance weights and
    χ² (−∞, ∞: failed), and the Pareto-smoothed mean, sd, 95 % interval by key, k̂ and effective size."""
    keys = tuple(objective.keys)
    thetas = flat[rng.choice(flat.shape[0], size=checks, replace=False)]
    say(f"the model's runs at {checks} draws")
    results = residuals_at(objective, thetas, workers)
    chi2_model = np.array([np.sum(weights * np.asarray(r, float) ** 2) if int(np.max(pred["status"])) == 0
                           else np.inf for r, pred in results])
    emulated_r = np.asarray(jax.vmap(target.residual_fn)(jnp.asarray(thetas, jnp.result_type(float)))[0], float)
    log_w = -0.5 * (chi2_model - np.sum(weights * emulated_r**2, axis=-1))
    log_w[~np.isfinite(chi2_model)] = -np.inf
    smoothed, k_hat = psis(log_w)
    w = np.exp(smoothed)
    mean, sd, ci = weighted_summary(keys, thetas, w)
    return thetas, log_w, chi2_model, (mean, sd, ci, k_hat, float(1.0 / np.sum(w**2)))


def _with_grid_term(found: EmulatedPosterior, objective, coarse, grid_ratio, settings, say) -> EmulatedPosterior:
    """``found`` with the grid term: the same posterior (``settings``) on the coarser objectives."""
    return with_grid_term(found, objective, coarse, grid_ratio,
                          lambda obj: emulated_posterior(obj, dict(found.mean), noise=found.noise, **settings),
                          lambda other: {"settled": other.settled,
                                         "pareto_k": other.pareto_k if math.isfinite(other.pareto_k) else None,
                                         "ess_importance": other.ess_importance, "model_jacobians": other.jacobians,
                                         "model_runs": other.runs}, say)
