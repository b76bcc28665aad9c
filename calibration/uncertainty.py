"""Uncertainty and identifiability from the residual Jacobian at the optimum (Gauss–Newton).

For residual blocks e_b (relative misfits of the profile, of the front, ...) with independent
noise of standard deviation σ_b, the linearised covariance of the fitted parameters is

    Cov = (Σ_b J_bᵀ J_b / σ_b²)⁻¹,

with J_b = de_b/dθ. σ_b is either given (a known measurement precision) or estimated from the
residuals at the optimum, s_b² = Σ e_b² / (m_b − n m_b / m) (each block takes its share of the
n degrees of freedom). Standard errors are sqrt(diag Cov), 95 % intervals θ ± 1.96 se (a normal
quantile: the data have many more points than parameters), and correlations Cov_ij / (se_i se_j).

**Identifiability** must not depend on how small the residual happens to be (a noise-free
twin has s_b ≈ 0 and would call everything constrained). So a parameter is called
*constrained* when, at a reference noise of ``reference_noise`` (1 % of the block's scale, or
the estimated noise if larger), its 95 % half-width is at most ``threshold`` (10 %) of its
scale (|θ|, or 1 % of its bound range when θ ≈ 0). The eigenvectors of the Fisher matrix in
these relative units name the combinations the data fix well and the one they fix worst.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["Uncertainty", "gauss_newton_uncertainty"]

Z95 = 1.959963984540054


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    keys: tuple[str, ...]
    theta: np.ndarray
    stderr: np.ndarray
    cov: np.ndarray
    corr: np.ndarray
    ci95: np.ndarray  # (n, 2)
    noise: dict[str, float]  # the σ_b used, by block
    noise_estimated: dict[str, float]
    reference_stderr: np.ndarray  # se at the reference noise (for identifiability)
    relative_halfwidth: np.ndarray  # 1.96 se_ref / scale
    constrained: tuple[str, ...]
    eigenvalues: np.ndarray  # of the relative Fisher matrix, descending
    eigenvectors: np.ndarray  # columns
    statement: str

    def to_dict(self) -> dict[str, Any]:
        by_key = lambda a: {k: float(v) for k, v in zip(self.keys, a)}  # noqa: E731
        return {
            "stderr": by_key(self.stderr),
            "ci95": {k: [float(lo), float(hi)] for k, (lo, hi) in zip(self.keys, self.ci95)},
            "corr": {a: by_key(row) for a, row in zip(self.keys, self.corr)},
            "noise": self.noise, "noise_estimated": self.noise_estimated,
            "relative_halfwidth_at_reference_noise": by_key(self.relative_halfwidth),
            "constrained": list(self.constrained),
            "statement": self.statement,
        }


def _combination(vec, keys, tol=0.2) -> str:
    vec = vec / np.max(np.abs(vec))
    vec = vec if vec[np.argmax(np.abs(vec))] > 0 else -vec
    terms = [f"{'+' if c > 0 else '−'} {abs(c):.2f}·{k}" for c, k in zip(vec, keys) if abs(c) >= tol]
    text = " ".join(terms)
    return text[2:] if text.startswith("+ ") else text


def _inverse(fisher, rcond: float = 1e-14):
    """The inverse of a symmetric positive semi-definite matrix, with eigenvalues below
    ``rcond`` × the largest raised to that floor: a direction the data do not see gets a huge,
    finite variance (a pseudo-inverse would give it zero, i.e. claim it is perfectly known)."""
    evals, evecs = np.linalg.eigh(fisher)
    floor = rcond * max(float(np.max(evals)), 1e-300)
    return (evecs / np.maximum(evals, floor)) @ evecs.T


def gauss_newton_uncertainty(
    J, r, keys: Sequence[str], theta, blocks: Mapping[str, slice], row_scale,
    *, noise: Mapping[str, float] | float | None = None, reference_noise: float = 0.01,
    threshold: float = 0.1, bounds=None,
) -> Uncertainty:
    """Covariance, standard errors and identifiability at the optimum.

    ``J`` (m × n) and ``r`` (m) are the objective's weighted residuals and Jacobian in physical
    units; ``blocks`` and ``row_scale`` (the objective's) undo the weights. ``noise``: the known
    σ of each block in the block's relative units (a float applies to every block); None:
    estimate it from the residuals.
    """
    keys = tuple(keys)
    J = np.asarray(J, float)
    r = np.asarray(r, float)
    theta = np.asarray(theta, float)
    row_scale = np.asarray(row_scale, float)
    m, n = J.shape
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        raise ValueError("J and r must be finite (the run at the optimum failed?)")
    e = r / row_scale  # raw relative misfits
    Je = J / row_scale[:, None]
    if noise is not None and not isinstance(noise, Mapping):
        noise = {name: float(noise) for name in blocks}
    estimated, used, reference = {}, {}, {}
    fisher = np.zeros((n, n))
    fisher_ref = np.zeros((n, n))
    for name, sl in blocks.items():
        mb = sl.stop - sl.start
        dof = max(mb - n * mb / m, 1.0)
        s = math.sqrt(float(np.sum(e[sl] ** 2)) / dof)
        estimated[name] = s
        sigma = float(noise[name]) if noise is not None else s
        used[name] = sigma
        reference[name] = max(s, reference_noise)
        Jb = Je[sl]
        fisher_ref += Jb.T @ Jb / reference[name] ** 2
        fisher += Jb.T @ Jb / max(sigma, 1e-12) ** 2  # σ = 0 only for an exact fit: ~zero-width intervals
    cov = _inverse(fisher)
    stderr = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(stderr, stderr)
    corr = np.where(np.isfinite(corr), corr, 0.0)
    ci95 = np.stack([theta - Z95 * stderr, theta + Z95 * stderr], axis=1)

    if bounds is not None:
        span = np.asarray(bounds.upper) - np.asarray(bounds.lower)
    else:
        span = np.ones(n)
    scale = np.maximum(np.abs(theta), 0.01 * span)
    cov_ref = _inverse(fisher_ref)
    se_ref = np.sqrt(np.maximum(np.diag(cov_ref), 0.0))
    rel = Z95 * se_ref / scale
    constrained = tuple(k for k, v in zip(keys, rel) if v <= threshold)

    fisher_rel = fisher_ref * np.outer(scale, scale)
    evals, evecs = np.linalg.eigh(fisher_rel)
    order = np.argsort(evals)[::-1]
    evals, evecs = evals[order], evecs[:, order]

    lines = []
    if constrained:
        lines.append("The data constrain " + ", ".join(
            f"{k} (±{100 * v:.2g} % at {100 * reference_noise:.2g} % noise)" for k, v in zip(keys, rel)
            if k in constrained) + ".")
    weak = [k for k in keys if k not in constrained]
    if weak:
        lines.append("They do not constrain " + ", ".join(
            f"{k} (±{100 * v:.3g} %)" if math.isfinite(v) else f"{k} (no sensitivity)"
            for k, v in zip(keys, rel) if k in weak)
            + f" to within {100 * threshold:.0f} %.")
    if n > 1:
        lines.append(f"Best-fixed combination: {_combination(evecs[:, 0], keys)}; worst: "
                     f"{_combination(evecs[:, -1], keys)} (Fisher eigenvalue ratio "
                     f"{evals[0] / max(evals[-1], 1e-300):.3g}).")
    strong = [(keys[i], keys[j], corr[i, j]) for i in range(n) for j in range(i + 1, n) if abs(corr[i, j]) > 0.9]
    for a, b, c in strong:
        lines.append(f"{a} and {b} are strongly correlated ({c:+.2f}): the data fix a combination, not each.")
    return Uncertainty(keys, theta, stderr, cov, corr, ci95, used, estimated, se_ref, rel, constrained,
                       evals, evecs, " ".join(lines))
