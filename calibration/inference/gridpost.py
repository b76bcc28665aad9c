"""The posterior of one or two keys by quadrature on a grid (``grid_posterior``), and the held-out
prediction of data the fit never saw (``predict_heldout``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..batch.sweep import sweep
from ..problem.protocol import ObjectiveLike, is_valid
from .likelihood import _check_span, _stderr, noise_levels
from .noise import Z95, chi2_of

__all__ = ["GridPosterior", "weighted_quantile", "weighted_summary", "grid_posterior", "HeldOut", "predict_heldout"]


@dataclasses.dataclass(frozen=True)
class GridPosterior:
    """The posterior on a grid (flat prior inside the bounds). The grid is regular in the
    whitened coordinates u of the fit's Gauss–Newton covariance, θ = θ̂ + L u (L its Cholesky
    factor; per key ± ``span`` in u), so that a narrow, correlated valley is resolved along and
    across; without a covariance it is regular in θ over ``ranges``. ``points`` (N, k) are the
    grid's θ, ``chi2`` and ``weight`` (summing to 1: the quadrature's masses, the map's Jacobian is
    constant) are per point, ``shape`` the grid's. By key: the marginal ``mean``, ``sd`` and
    equal-tailed 95 % credible interval (weighted quantiles), beside the fit's point and
    Gauss–Newton standard error. ``mass_at_edge``: the largest weight on the grid's boundary
    relative to the largest weight (a grid that cuts the posterior off shows it); ``failed``:
    grid points whose run failed (weight 0)."""

    keys: tuple[str, ...]
    points: np.ndarray
    chi2: np.ndarray
    weight: np.ndarray
    shape: tuple[int, ...]
    whitened: bool
    mean: dict[str, float]
    sd: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    theta_hat: dict[str, float]
    gn_stderr: dict[str, float] | None
    mass_at_edge: float
    failed: int
    noise: dict[str, float]
    wall_s: float

    def marginal(self, key: str, bins: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(x, density) of ``key``'s marginal: for one key the grid itself; else a weighted
        histogram with ``bins`` (default: the grid's points per key) bins."""
        j = self.keys.index(key)
        x = self.points[:, j]
        if len(self.keys) == 1:
            order = np.argsort(x)
            x, w = x[order], self.weight[order]
            spacing = np.gradient(x)
            return x, w / spacing
        hist, edges = np.histogram(x, bins=bins or self.shape[j], weights=self.weight, density=True)
        return 0.5 * (edges[1:] + edges[:-1]), hist

    def to_json(self) -> dict[str, Any]:
        return {"keys": list(self.keys), "points": {k: self.points[:, j].tolist() for j, k in enumerate(self.keys)},
                # null: a point outside the prior's support (the bounds, mu1 <= mu2) or a failed run
                "chi2": [float(v) if np.isfinite(v) else None for v in self.chi2], "shape": list(self.shape),
                "whitened": self.whitened,
                "mean": self.mean, "sd": self.sd,
                "ci95": {k: list(v) for k, v in self.ci95.items()}, "theta_hat": self.theta_hat,
                "gauss_newton_stderr": self.gn_stderr, "sd_over_gauss_newton": None if self.gn_stderr is None else
                {k: self.sd[k] / self.gn_stderr[k] for k in self.keys}, "mass_at_edge": self.mass_at_edge,
                "failed": self.failed, "noise": self.noise, "prior": "flat inside the bounds",
                "method": "quadrature on a grid" + (" in the Gauss-Newton covariance's whitened coordinates"
                                                    if self.whitened else ""), "wall_s": round(self.wall_s, 2)}


def weighted_quantile(values, weights, q):
    """The ``q`` quantiles of ``values`` (n,) under ``weights`` (n,, not all zero): the inverse of
    the weighted empirical distribution, with each point's mass centred on it (points without mass
    are not in it)."""
    values, weights = np.asarray(values, float), np.asarray(weights, float)
    values, weights = values[weights > 0], weights[weights > 0]
    order = np.argsort(values)
    v, w = values[order], weights[order]
    cum = np.cumsum(w) - 0.5 * w
    return np.interp(np.asarray(q, float), cum / np.sum(w), v)


def weighted_summary(keys, thetas, weight) -> tuple[dict, dict, dict]:
    """By key: the mean, sd and equal-tailed 95 % interval of the points ``thetas`` (n, k) under
    ``weight`` (n,, summing to 1)."""
    mean = {k: float(np.sum(weight * thetas[:, j])) for j, k in enumerate(keys)}
    sd = {k: float(np.sqrt(np.sum(weight * (thetas[:, j] - mean[k]) ** 2))) for j, k in enumerate(keys)}
    ci = {k: tuple(float(v) for v in weighted_quantile(thetas[:, j], weight, [0.025, 0.975]))
          for j, k in enumerate(keys)}
    return mean, sd, ci


def grid_posterior(objective: ObjectiveLike, fit_result, *, span: float = 4.0, n: int = 21,
                   ranges: Mapping[str, tuple[float, float]] | None = None,
                   noise: Mapping[str, float] | float | None = None, chunk: int | None = None) -> GridPosterior:
    """The posterior of one or two fitted keys by quadrature on an ``n``-point grid per key:
    over ± ``span`` in the whitened coordinates of the fit's Gauss–Newton covariance (the
    default), or over ``ranges`` by key (regular in θ; needed when the fit has no interval).
    Points outside the bounds get zero weight (the flat prior's support). Every grid point is
    one run (``calibration.batch.sweep``, batched)."""
    clock = time.perf_counter()
    keys = tuple(objective.keys)
    if len(keys) > 2:
        raise ValueError(f"grid_posterior: {len(keys)} keys; quadrature is for one or two (sample more with MCMC)")
    _check_span(span, n)
    sigma = noise_levels(objective, fit_result, noise)
    theta_hat = np.array([fit_result.theta[k] for k in keys], float)
    se = _stderr(fit_result)
    lower, upper = np.asarray(objective.bounds.lower), np.asarray(objective.bounds.upper)
    margin = 1e-6 * (upper - lower)
    u_axes = [np.linspace(-span, span, n)] * len(keys)
    mesh = np.stack([m.ravel() for m in np.meshgrid(*u_axes, indexing="ij")], axis=1)
    whitened = not ranges and se is not None
    if whitened:
        thetas = theta_hat[None, :] + mesh @ np.linalg.cholesky(np.asarray(fit_result.uncertainty.cov, float)).T
    else:
        ranges = dict(ranges or {})
        missing = [k for k in keys if k not in ranges]
        if missing:
            raise ValueError(f"ranges: give {missing}'s range (the fit has no Gauss–Newton interval)")
        lo = np.array([float(ranges[k][0]) for k in keys])
        hi = np.array([float(ranges[k][1]) for k in keys])
        lo, hi = np.maximum(lo, lower + margin), np.minimum(hi, upper - margin)
        for k, a, b in zip(keys, lo, hi):
            if not a < b:
                raise ValueError(f"ranges[{k!r}]: ({a:g}, {b:g}) is empty inside the bounds")
        thetas = lo + (mesh + span) / (2 * span) * (hi - lo)
    inside = np.all((thetas > lower + margin) & (thetas < upper - margin), axis=1)
    inside &= np.array([is_valid(objective, t) for t in thetas])  # the engine's rules (mu1 <= mu2): no support
    chi2 = np.full(thetas.shape[0], np.nan)
    if np.any(inside):
        result = sweep(objective, thetas[inside], chunk=chunk)
        chi2[inside] = [chi2_of(r, objective.row_scale, objective.blocks, sigma) if np.isfinite(loss) else np.nan
                        for r, loss in zip(result.residuals, result.loss)]
    finite = np.isfinite(chi2)
    if not np.any(finite):
        raise ValueError("grid_posterior: every grid point is outside the bounds or its run failed")
    weight = np.where(finite, np.exp(-0.5 * (np.where(finite, chi2, 0.0) - np.nanmin(chi2))), 0.0)
    weight /= weight.sum()
    mean, sd, ci = weighted_summary(keys, thetas, weight)
    on_edge = np.any(np.abs(mesh) >= span * (1 - 1e-12), axis=1)
    return GridPosterior(keys, thetas, chi2, weight, (n,) * len(keys), whitened, mean, sd, ci,
                         dict(zip(keys, theta_hat.tolist())), None if se is None else dict(zip(keys, se.tolist())),
                         float(weight[on_edge].max() / weight.max()), int((inside & ~finite).sum()),
                         {k: float(v) for k, v in sigma.items()}, time.perf_counter() - clock)


def observed_blocks(objective) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """By block of ``objective`` (an ``Objective``): (where, measured), in metres and seconds:
    a profile's x and heights, a front's times and positions (the order of ``in_metres``)."""
    data = {"h": np.asarray(objective.data["h"], float), "front": np.asarray(objective.data["front"], float)}
    offsets = {"h": 0, "front": 0}
    where = iter(objective.observations.profile_x)
    out = {}
    for name, sl in objective.blocks.items():
        kind = "front" if name == "front" else "h"
        size = sl.stop - sl.start
        measured = data[kind][offsets[kind]:offsets[kind] + size]
        offsets[kind] += size
        at = objective.observations.front_times if kind == "front" else next(where)
        out[name] = (np.asarray(at, float), measured)
    return out


@dataclasses.dataclass(frozen=True)
class HeldOut:
    """The fitted model's prediction of observations the fit did not use: by block of the
    held-out objective, where (``at``: x of a profile's points, m; times of a front, s), the
    measured values (``data``), the prediction at the fit's point
    (``predicted``) and its 95 % half-width (``band``) from the fit's covariance (delta method,
    the statistical and numerical parts the fit reported), all in metres; ``rms`` of predicted −
    data by block and ``inside`` the fraction of points whose data lie within the band."""

    blocks: dict[str, dict[str, np.ndarray]]
    rms: dict[str, float]
    inside: dict[str, float]
    theta: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {"theta": self.theta, "rms_m": self.rms, "inside_band": self.inside,
                "blocks": {name: {k: v.tolist() for k, v in b.items()} for name, b in self.blocks.items()}}


def predict_heldout(fit_result, objective) -> HeldOut:
    """Predict ``objective``'s data (observations the fit never saw: another time, another
    quantity, another scene with the same fitted keys) at ``fit_result``'s point, with a 95 %
    band from its covariance. ``objective`` must fit the same keys."""
    keys = tuple(objective.keys)
    if set(keys) != set(fit_result.keys):
        raise ValueError(f"objective fits {keys}, the fit {tuple(fit_result.keys)}")
    unc = getattr(fit_result, "uncertainty", None)
    if unc is None or unc.withheld:
        raise ValueError("fit_result: no covariance (not a fit of the data, or fitted without uncertainty)")
    order = [list(fit_result.keys).index(k) for k in keys]
    cov = np.asarray(unc.cov, float)[np.ix_(order, order)]
    theta = np.array([fit_result.theta[k] for k in keys], float)
    r, J, _ = objective.residuals_and_jacobian(theta)
    r, J = np.asarray(r, float), np.asarray(J, float)
    err = objective.in_metres(r)  # predicted − data, m
    cols = [objective.in_metres(J[:, i]) for i in range(len(keys))]  # d(predicted)/dθ_i, m
    blocks, rms, inside = {}, {}, {}
    observed = observed_blocks(objective)
    for name, e in err.items():
        G = np.stack([c[name] for c in cols], axis=1)
        band = Z95 * np.sqrt(np.maximum(np.einsum("mi,ij,mj->m", G, cov, G), 0.0))
        at, measured = observed[name]
        blocks[name] = {"at": at, "data": measured, "predicted": measured + e, "band": band}
        rms[name] = float(np.sqrt(np.mean(e ** 2)))
        inside[name] = float(np.mean(np.abs(e) <= band))
    return HeldOut(blocks, rms, inside, dict(zip(keys, theta.tolist())))
