"""Uncertainty beyond Gauss–Newton: the profile likelihood of a key (``profile_likelihood``), the
likelihood's noise by block (``noise_levels``) and the model's own error in it (``model_error``).

χ² is Σ_b Σ (e_b / σ_b)² on the noise σ_b of each block that the fit used, so every check is on
the scale of the fit's own interval. What the checks say: docs/verdict.md and docs/posteriors.md.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..problem.bounds import MAX_STEP
from ..problem.options import _is_int, _is_number
from ..problem.protocol import ObjectiveLike
from .gridcheck import GRID_DRAWS, GRID_ORDER, GRID_RATIO
from .noise import NOISE_FLOOR, chi2_of, chi2_quantile
from .scatter import SAMPLING_SEEDS, clean_runs, coarse_residuals, redrawn_residuals

__all__ = ["noise_levels", "row_weights", "ModelError", "model_error", "ProfileLikelihood", "profile_likelihood"]


#: Δχ² of a 95 % interval of one parameter (Wilks' theorem).
DELTA_CHI2_95 = chi2_quantile(0.95, 1)


def noise_levels(objective: ObjectiveLike, fit_result, noise) -> dict[str, float]:
    """σ by block of ``objective``: the given ``noise`` (a float: every block; a mapping: by
    block name), else the fit's (``fit_result.uncertainty.noise``). Raises ``ValueError`` when a
    block has no level. The scale of every χ² here and in ``calibration.inference.mcmc``."""
    if noise is not None:
        sigma = ({name: float(noise) for name in objective.blocks} if not isinstance(noise, Mapping)
                 else {k: float(v) for k, v in noise.items()})
    else:
        unc = getattr(fit_result, "uncertainty", None)
        if unc is None or not unc.noise:
            raise ValueError("fit_result: it carries no noise level (fit with uncertainty=True, or pass noise=)")
        sigma = dict(unc.noise)
    missing = sorted(name for name in objective.blocks if sigma.get(name) is None)
    if missing:
        raise ValueError(f"noise: no level for the block(s) {missing} of the objective")
    return sigma


@dataclasses.dataclass(frozen=True)
class ModelError:
    """The model's own error in the residuals, σ by block in the blocks' relative units
    (``model_error``; docs/posteriors.md): ``draw``, a residual's spread over particle draws;
    ``grid``, Richardson's estimate of the residuals' discretisation error. ``noise(data)`` is
    what a likelihood uses: σ_b² = σ_data,b² + draw_b² + grid_b², every residual independent."""

    draw: dict[str, float]
    grid: dict[str, float]
    draws: int  # runs that gave the draw term (the objective's own draw and the redrawn ones)
    coarse_draws: int  # runs averaged on the coarse grid
    ratio: float
    order: float
    dx: float
    wall_s: float

    def total(self) -> dict[str, float]:
        """σ of the model's error by block: sqrt(draw² + grid²)."""
        return {b: math.hypot(self.draw[b], self.grid[b]) for b in self.draw}

    def noise(self, data: Mapping[str, float] | float) -> dict[str, float]:
        """σ by block of a likelihood with this model error beside the data's ``data`` (a float:
        every block; a mapping: by block): sqrt(σ_data² + draw² + grid²)."""
        sigma = ({b: float(data) for b in self.draw} if not isinstance(data, Mapping)
                 else {b: float(v) for b, v in data.items()})
        missing = sorted(set(self.draw) - set(sigma))
        if missing:
            raise ValueError(f"data: no noise level for the block(s) {missing}")
        return {b: math.sqrt(sigma[b] ** 2 + self.draw[b] ** 2 + self.grid[b] ** 2) for b in self.draw}

    def to_dict(self) -> dict[str, Any]:
        return {"draw": self.draw, "grid": self.grid, "total": self.total(), "draws": self.draws,
                "coarse_draws": self.coarse_draws, "ratio": self.ratio, "order_assumed": self.order, "dx": self.dx,
                "wall_s": round(self.wall_s, 2)}


def model_error(objective: ObjectiveLike, theta, *, draws: int = SAMPLING_SEEDS,
                ratio: float = GRID_RATIO, coarse_draws: int = GRID_DRAWS,
                order: float = GRID_ORDER, workers=None) -> ModelError:
    """The model's error in ``objective``'s residuals at ``theta`` (a mapping of the keys' values
    or an array in key order), by block (``ModelError``): the objective's own particle draw and
    ``draws`` others at θ give the draw term; ``coarse_draws`` draws on the grid ``ratio`` times
    coarser (``Objective.coarsened``) the grid term, for a convergence of order ``order``. Runs
    ``1 + draws + coarse_draws`` forward runs (on ``workers``). Raises ``ValueError`` when the
    particles cannot be drawn again (a lattice sampling) or fewer than two draws, or no coarse
    run, ran without status bits: an unmeasured term is not taken as zero."""
    for name, value in (("draws", draws), ("coarse_draws", coarse_draws)):
        if not _is_int(value):
            raise ValueError(f"{name} must be an integer, got {value!r}")
    if draws < 2:
        raise ValueError(f"draws must be >= 2 (a spread beside the objective's own draw), got {draws!r}")
    if not (_is_number(ratio) and ratio > 1.0):
        raise ValueError(f"ratio must be a finite factor > 1 of the grid spacing, got {ratio!r}")
    if coarse_draws < 1:
        raise ValueError(f"coarse_draws must be >= 1, got {coarse_draws!r}")
    if not (_is_number(order) and order > 0):
        raise ValueError(f"order must be > 0, got {order!r}")
    if not objective.seeded:
        raise ValueError("objective: its particles cannot be drawn again (a lattice sampling), so the draw term "
                         "cannot be measured; sample the body at random (a seed)")
    theta = checked_point(objective, theta)
    clock = time.perf_counter()
    fine = clean_runs([objective.residuals(theta)]) + redrawn_residuals(objective, theta, draws, workers)
    if len(fine) < 2:
        raise ValueError(f"theta: {len(fine)} of {draws + 1} particle draws ran without status bits; the draw "
                         "term needs two")
    _, coarse = coarse_residuals(objective, theta, ratio, coarse_draws, workers)
    if not coarse:
        raise ValueError(f"theta: no run on the grid {ratio:g} times coarser ran without status bits")
    scale = np.asarray(objective.row_scale, float)
    F, C = np.stack(fine) / scale, np.stack(coarse) / scale
    var = np.var(F, axis=0, ddof=1)
    diff2 = (F.mean(axis=0) - C.mean(axis=0)) ** 2
    factor = ratio ** order - 1.0
    draw, grid = {}, {}
    for name, sl in objective.blocks.items():
        v = float(np.mean(var[sl]))
        draw[name] = math.sqrt(v)
        # E (F̄ − C̄)² = δ² + v (1/n_F + 1/n_C), v the fine draws' variance (the coarse's is larger: kept, conservatively)
        grid[name] = math.sqrt(max(float(np.mean(diff2[sl])) - v * (1 / len(fine) + 1 / len(coarse)), 0.0)) / factor
    return ModelError(draw, grid, len(fine), len(coarse), float(ratio), float(order), objective.dx,
                      time.perf_counter() - clock)


def checked_point(objective: ObjectiveLike, theta) -> np.ndarray:
    """``theta`` (a mapping of the keys' values, or values in key order) as an array in key order,
    checked finite and inside ``objective``'s bounds; ``ValueError`` naming "theta" otherwise."""
    if isinstance(theta, Mapping):
        missing = [k for k in objective.keys if k not in theta]
        if missing:
            raise ValueError(f"theta: no value for the key(s) {missing}")
        theta = [theta[k] for k in objective.keys]
    theta = np.asarray(theta, float)
    if theta.shape != (len(objective.keys),) or not np.all(np.isfinite(theta)):
        raise ValueError(f"theta must be {len(objective.keys)} finite values for the keys {objective.keys}, got "
                         f"{theta.tolist()}")
    objective.check_thetas(theta[None, :], "theta")
    return theta


def _stderr(fit_result) -> np.ndarray | None:
    unc = getattr(fit_result, "uncertainty", None)
    return None if unc is None or unc.withheld else np.asarray(unc.stderr, float)


def _check_span(span, n):
    if not (math.isfinite(span) and span > 0):
        raise ValueError(f"span must be > 0 (standard errors), got {span!r}")
    if not (isinstance(n, int) and n >= 3):
        raise ValueError(f"n must be an integer >= 3, got {n!r}")


def _crossings(values, dchi2, centre: float, level: float) -> tuple[float | None, float | None]:
    """Where Δχ² first reaches ``level`` either side of ``centre`` (linear interpolation between
    grid points); None where it does not within ``values``."""
    i0 = int(np.argmin(np.abs(values - centre)))

    def cross(i, k):  # between grid points i (below the level) and k
        a, b = dchi2[i], dchi2[k]
        return float(values[i] + (level - a) / (b - a) * (values[k] - values[i]))

    lo = next((cross(i, i - 1) for i in range(i0, 0, -1) if dchi2[i] < level <= dchi2[i - 1]), None)
    hi = next((cross(i, i + 1) for i in range(i0, len(values) - 1) if dchi2[i] < level <= dchi2[i + 1]), None)
    return lo, hi


@dataclasses.dataclass(frozen=True)
class ProfileLikelihood:
    """χ² of the fit's noise along ``key`` with the other keys refitted (``others``, physical
    values, one row per value), its minimum, the Wilks 95 % interval (None where the scan does
    not reach Δχ² = 3.84) beside the Gauss–Newton one."""

    key: str
    keys: tuple[str, ...]
    values: np.ndarray
    chi2: np.ndarray
    others: np.ndarray
    status: np.ndarray
    theta_hat: float
    chi2_hat: float
    ci95: tuple[float | None, float | None]
    gn_ci95: tuple[float, float] | None
    noise: dict[str, float]
    wall_s: float

    @property
    def delta_chi2(self) -> np.ndarray:
        return self.chi2 - min(self.chi2_hat, float(np.nanmin(self.chi2)))

    def to_json(self) -> dict[str, Any]:
        return {"key": self.key, "keys": list(self.keys), "values": self.values.tolist(), "chi2": self.chi2.tolist(),
                "others": {k: self.others[:, j].tolist() for j, k in enumerate(k for k in self.keys if k != self.key)},
                "status": self.status.tolist(), "theta_hat": self.theta_hat, "chi2_hat": self.chi2_hat,
                "ci95_profile": list(self.ci95),
                "ci95_gauss_newton": None if self.gn_ci95 is None else list(self.gn_ci95),
                "delta_chi2_95": DELTA_CHI2_95, "noise": self.noise, "wall_s": round(self.wall_s, 2)}


def row_weights(objective: ObjectiveLike, sigma: Mapping[str, float]) -> np.ndarray:
    """W with χ² = Σ W r²: 1 / (row_scale σ_b)² on the rows of blocks with a noise level, else 0."""
    w = np.zeros(np.size(objective.row_scale))
    for name, sl in objective.blocks.items():
        if sigma.get(name) is not None:
            w[sl] = 1.0 / max(float(sigma[name]), NOISE_FLOOR) ** 2
    return w / np.asarray(objective.row_scale, float) ** 2


def _refit_others(objective: ObjectiveLike, z, fixed: int, sigma, steps: int, lam0: float = 1e-3):
    """Damped Gauss–Newton on every z but ``fixed``, minimising χ² (the residuals weighted by
    each block's noise); returns (z, r, status). Steps capped at 2 in z (``calibration.problem.bounds.MAX_STEP``)."""
    w = np.sqrt(row_weights(objective, sigma))  # Σ (w r)² is χ²
    free = [j for j in range(z.size) if j != fixed]

    def evaluate(z_):
        r_, J_, _, p_ = objective.residuals_and_jacobian_z(z_)
        return np.asarray(r_, float), np.asarray(J_, float) * w[:, None], p_

    r, Jz, pred = evaluate(z)
    chi2 = float(np.sum((w * r) ** 2))
    lam = lam0
    for _ in range(steps):
        Jf = Jz[:, free]
        A = Jf.T @ Jf
        g = Jf.T @ (w * r)
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
            break
        accepted = False
        for _ in range(6):
            dz = -np.linalg.solve(A + lam * np.diag(np.maximum(np.diag(A), 1e-30)), g)
            dz *= min(1.0, MAX_STEP / max(float(np.max(np.abs(dz))), 1e-300))
            trial = z.copy()
            trial[free] += dz
            r_t, J_t, p_t = evaluate(trial)
            chi2_t = float(np.sum((w * r_t) ** 2))
            if int(np.asarray(p_t["status"])) == 0 and np.isfinite(chi2_t) and chi2_t < chi2:
                z, r, Jz, pred, chi2, lam = trial, r_t, J_t, p_t, chi2_t, lam / 3
                accepted = True
                break
            lam *= 10
        if not accepted or np.max(np.abs(dz)) < 1e-7:
            break
    return z, r, int(np.asarray(pred["status"]))


def profile_likelihood(objective: ObjectiveLike, fit_result, key: str, *, span: float = 4.0, n: int = 13,
                       steps: int = 8,
                       values: Sequence[float] | None = None,
                       noise: Mapping[str, float] | float | None = None) -> ProfileLikelihood:
    """The profile likelihood of ``key`` around ``fit_result``'s point: ``n`` values over
    ± ``span`` Gauss–Newton standard errors (clipped inside the bounds; or the given
    ``values``; the fit's own value is one of the grid's), the other keys refitted at each
    (``steps`` damped Gauss–Newton steps, warm started from the neighbour nearer the fit).
    ``noise``: σ by block (default: the fit's)."""
    clock = time.perf_counter()
    keys = tuple(objective.keys)
    if key not in keys:
        raise ValueError(f"key: {key!r} is not a fitted key {keys}")
    _check_span(span, n)
    sigma = noise_levels(objective, fit_result, noise)
    j = keys.index(key)
    theta_hat = np.array([fit_result.theta[k] for k in keys], float)
    lo_b, hi_b = objective.bounds.lower[j], objective.bounds.upper[j]
    se = _stderr(fit_result)
    if values is None:
        if se is None:
            raise ValueError("fit_result: no Gauss–Newton interval (not a fit of the data); pass values=")
        half = span * se[j]
        margin = 1e-6 * (hi_b - lo_b)
        lo, hi = max(theta_hat[j] - half, lo_b + margin), min(theta_hat[j] + half, hi_b - margin)
        below = n // 2  # the fit's value is a grid point, with about as many values either side
        grid = np.concatenate([np.linspace(lo, theta_hat[j], below + 1)[:-1], np.linspace(theta_hat[j], hi, n - below)])
    else:
        grid = np.asarray(values, float)
        if grid.ndim != 1 or grid.size < 3 or np.any(np.diff(grid) <= 0):
            raise ValueError("values must be at least 3 increasing numbers")
        for v in grid:
            if not lo_b < v < hi_b:
                raise ValueError(f"values: {key} = {v:g} must lie strictly inside its bounds ({lo_b:g}, {hi_b:g})")
    chi2 = np.full(grid.size, np.nan)
    others = np.full((grid.size, len(keys) - 1), np.nan)
    status = np.zeros(grid.size, int)
    z_hat = objective.bounds.to_unconstrained(theta_hat)
    centre = int(np.argmin(np.abs(grid - theta_hat[j])))
    for order in (range(centre, grid.size), range(centre - 1, -1, -1)):
        z = z_hat.copy()
        for i in order:
            theta = np.array(objective.bounds.to_physical(jnp.asarray(z)), float)
            theta[j] = grid[i]
            z = objective.bounds.to_unconstrained(theta)
            if len(keys) == 1:
                r, pred = objective.residuals(theta)
                r, st = np.asarray(r, float), int(np.asarray(pred["status"]))
            else:
                z, r, st = _refit_others(objective, z, j, sigma, steps)
            theta = np.array(objective.bounds.to_physical(jnp.asarray(z)), float)
            chi2[i] = chi2_of(r, objective.row_scale, objective.blocks, sigma)
            others[i] = np.delete(theta, j)
            status[i] = st
    r_hat = np.asarray(fit_result.residuals, float)
    chi2_hat = chi2_of(r_hat, objective.row_scale, objective.blocks, sigma)
    floor = min(chi2_hat, float(np.nanmin(chi2)))
    ci = _crossings(grid, chi2 - floor, theta_hat[j], DELTA_CHI2_95)
    gn = None if se is None else tuple(float(v) for v in fit_result.uncertainty.ci95[j])
    return ProfileLikelihood(key, keys, grid, chi2, others, status, float(theta_hat[j]), float(chi2_hat), ci, gn,
                             {k: max(float(v), NOISE_FLOOR) for k, v in sigma.items()}, time.perf_counter() - clock)
