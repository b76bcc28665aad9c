"""The noise of the residuals and the χ² it gives: given by block, or estimated from the residuals'
structure (``structural_noise``), and the serial correlation of a front's residuals.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

__all__ = ["NOISE_FLOOR", "chi2_quantile", "structural_noise", "block_noise", "chi2_of"]


Z95 = 1.959963984540054


#: Noise (relative units) below which no misfit is told apart from the run's own round-off.
NOISE_FLOOR = 1e-6


#: A block's misfit is "well above the noise" beyond this quantile of χ².
ABOVE_NOISE_P = 0.999


#: Blocks with fewer residuals than this get no structural noise estimate.
MIN_NOISE_POINTS = 5


def chi2_quantile(p: float, dof: float) -> float:
    """The ``p`` quantile of χ² with ``dof`` degrees of freedom (scipy ships with jax)."""
    from scipy.stats import chi2

    return float(chi2.ppf(p, dof))


def structural_noise(e) -> tuple[float | None, int]:
    """The noise σ of residuals ``e`` (in data order, e.g. along x) from their high-frequency
    part: 1.4826 · median |e[i−1] − 2 e[i] + e[i+1]| / sqrt(6), a robust spread of second
    differences (which remove any linear trend and nearly all of a smooth misfit). Triples that
    are exactly zero (no material in model and data, beyond the front) carry no information and
    are left out. Returns ``(σ, c)`` with c the number of second differences used; σ is None
    when fewer than ``MIN_NOISE_POINTS`` remain."""
    e = np.asarray(e, float)
    if e.size < 3:
        return None, 0
    d2 = e[:-2] - 2.0 * e[1:-1] + e[2:]
    informative = (e[:-2] != 0) | (e[1:-1] != 0) | (e[2:] != 0)
    d2 = d2[informative]
    if d2.size < MIN_NOISE_POINTS:
        return None, int(d2.size)
    return float(1.482602218505602 * np.median(np.abs(d2)) / math.sqrt(6.0)), int(d2.size)


def front_correlation(t, e) -> dict[str, float | None]:
    """The serial correlation of front residuals ``e`` (m, model − data, at times ``t``): the
    lag-1 autocorrelation ρ = Σ e_i e_{i−1} / Σ e_i² (about zero, not the mean: an offset that
    persists over frames is correlated error too), the correlation time τ = −mean(Δt) / ln ρ of
    the exponential model ``FrontTarget.correlation_time`` assumes (None where ρ ≤ 0.05: no
    measurable correlation), and the effective number of independent points
    n (1 − ρ) / (1 + ρ) (AR(1)). Feed τ back as the target's ``correlation_time`` and refit."""
    t, e = np.asarray(t, float), np.asarray(e, float)
    if t.shape != e.shape or e.ndim != 1 or e.size < 3:
        raise ValueError(f"t and e must be 1-D of one length >= 3, got {t.shape} and {e.shape}")
    denom = float(np.sum(e * e))
    rho = float(np.sum(e[1:] * e[:-1]) / denom) if denom > 0 else 0.0
    rho = min(rho, 0.999)
    tau = float(-np.mean(np.diff(t)) / math.log(rho)) if rho > 0.05 else None
    return {"lag1": rho, "correlation_time_s": tau, "n": int(e.size),
            "n_effective": float(e.size * (1 - max(rho, 0.0)) / (1 + max(rho, 0.0)))}


def block_noise(r, row_scale, blocks: Mapping[str, slice], noise: Mapping[str, float] | float | None = None
                ) -> tuple[dict[str, float | None], dict[str, int], str]:
    """σ of each block (relative units): the given ``noise`` (a float applies to every block; a
    mapping gives the blocks it names), else ``structural_noise`` of the block's residuals.
    Returns ``(sigma, counts, source)``, counts the number of second differences behind each
    estimate (0 for given noise)."""
    e = np.asarray(r, float) / np.asarray(row_scale, float)
    if noise is not None and not isinstance(noise, Mapping):
        noise = {name: float(noise) for name in blocks}
    given = {name: float(noise[name]) for name in blocks if name in noise} if noise is not None else {}
    sigma, counts = dict(given), {name: 0 for name in given}
    for name, sl in blocks.items():
        if name not in given:
            sigma[name], counts[name] = structural_noise(e[sl])
    estimated = "estimated from the residuals' second differences"
    if len(given) == len(blocks):
        return sigma, counts, "given"
    if not given:
        return sigma, counts, estimated
    return sigma, counts, f"given for {', '.join(given)}; {estimated} for the others"


def chi2_of(r, row_scale, blocks: Mapping[str, slice], sigma: Mapping[str, float | None]) -> float:
    """Σ_b Σ e_b² / σ_b² over the blocks with a noise level (σ floored at ``NOISE_FLOOR``)."""
    e = np.asarray(r, float) / np.asarray(row_scale, float)
    return sum(float(np.sum(e[sl] ** 2)) / max(sigma[name], NOISE_FLOOR) ** 2
               for name, sl in blocks.items() if sigma.get(name) is not None)
