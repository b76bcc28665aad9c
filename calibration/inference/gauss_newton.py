"""Uncertainty and identifiability from the residual Jacobian at the optimum (Gauss–Newton).

The covariance is the sandwich A⁻¹ B A⁻¹ of the fit as it is weighted (A = Σ_b w_b J_bᵀ J_b,
B = Σ_b w_b² σ_b² J_bᵀ J_b), with σ_b given or estimated from the residuals; the run's round-off,
the particle draw and the grid add their covariances. A key is *constrained* when its 95 %
half-width at a reference noise is within ``threshold`` of its scale, so that a noise-free twin
does not call everything constrained. What each term means: docs/verdict.md and docs/grid_term.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .noise import Z95

if TYPE_CHECKING:  # annotations only: these modules build on this one
    from .gridcheck import GridCheck
    from .scatter import ModelScatter
    from .verdict import Verdict
__all__ = ["Uncertainty", "gauss_newton_uncertainty"]


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    keys: tuple[str, ...]
    theta: np.ndarray
    stderr: np.ndarray | None  # None (with cov, ci95, ...): withheld, the point is not a fit of the data
    cov: np.ndarray | None
    corr: np.ndarray
    ci95: np.ndarray | None  # (n, 2)
    noise: dict[str, float]  # the σ_b used, by block
    noise_estimated: dict[str, float]
    relative_halfwidth: np.ndarray | None  # 1.96 se_ref / scale
    constrained: tuple[str, ...]
    statement: str
    verdict: Verdict | None = None
    stderr_statistical: np.ndarray | None = None  # from the data's noise alone
    stderr_numerical: np.ndarray | None = None  # from the run's round-off scatter alone (None: not measured)
    sampling: ModelScatter | None = None  # the particle sampling's scatter (None: not measured)
    grid: GridCheck | None = None  # the grid's share (None: not measured)
    grid_note: str = ""  # why the grid term is missing, when it was asked for
    ci95_linearised: np.ndarray | None = None  # the Gauss–Newton interval, where the probe widened ``ci95``

    @property
    def grid_converged(self) -> bool | None:
        """Whether the grid term stays within the data's interval for every key (None: not
        measured, or no interval)."""
        if self.grid is None or self.stderr_statistical is None:
            return None
        return bool(np.all(self.grid.stderr <= self.stderr_statistical))

    @property
    def withheld(self) -> bool:
        """True when no interval is given (the verdict: not a fit of the data)."""
        return self.stderr is None

    def to_dict(self) -> dict[str, Any]:
        by_key = lambda a: {k: float(v) for k, v in zip(self.keys, a)}  # noqa: E731
        out = {"corr": {a: by_key(row) for a, row in zip(self.keys, self.corr)},
               "noise": self.noise, "noise_estimated": self.noise_estimated,
               "constrained": list(self.constrained), "statement": self.statement}
        if not self.withheld:
            out["stderr"] = by_key(self.stderr)
            if self.stderr_numerical is not None or self.sampling is not None or self.grid is not None:
                out["stderr_statistical"] = by_key(self.stderr_statistical)
            if self.stderr_numerical is not None:
                out["stderr_numerical"] = by_key(self.stderr_numerical)
            if self.sampling is not None:
                out["stderr_sampling"] = by_key(self.sampling.stderr)
            out["ci95"] = {k: [float(lo), float(hi)] for k, (lo, hi) in zip(self.keys, self.ci95)}
            if self.ci95_linearised is not None:
                out["ci95_linearised"] = {k: [float(lo), float(hi)] for k, (lo, hi) in
                                          zip(self.keys, self.ci95_linearised)}
            out["relative_halfwidth_at_reference_noise"] = by_key(self.relative_halfwidth)
            if self.grid is not None:
                out["stderr_grid"] = by_key(self.grid.stderr)
                out["grid_converged"] = self.grid_converged
        if self.sampling is not None:
            out["sampling"] = self.sampling.to_dict(self.keys)
        if self.grid is not None:
            out["grid"] = self.grid.to_dict(self.keys)
        elif self.grid_note:
            out["grid"] = {"measured": False, "why": self.grid_note}
        return out


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


def _sandwich_fisher(A, B):
    """The inverse of the sandwich covariance A⁻¹ B A⁻¹ of a weighted least-squares estimate
    (A = Jᵀ W J, B = Jᵀ W Σ W J), A B⁻¹ A: with weights W = Σ⁻¹ it is Jᵀ Σ⁻¹ J."""
    F = A @ _inverse(B) @ A
    return 0.5 * (F + F.T)


def gauss_newton_uncertainty(
    J, r, keys: Sequence[str], theta, blocks: Mapping[str, slice], row_scale,
    *, noise: Mapping[str, float] | float | None = None, reference_noise: float = 0.01,
    threshold: float = 0.1, bounds=None, verdict: Verdict | None = None, scatter: ModelScatter | None = None,
    sampling: ModelScatter | None = None, grid: GridCheck | None = None, grid_note: str = "",
) -> Uncertainty:
    """Covariance, standard errors and identifiability at the optimum.

    ``J`` (m × n) and ``r`` (m) are the objective's weighted residuals and Jacobian in physical
    units; ``blocks`` and ``row_scale`` (the objective's) undo the weights. ``noise``: the known
    σ of each block in the block's relative units (a float applies to every block); None:
    estimate it from the residuals. ``verdict`` (``assess_fit``): where the point is not a fit of
    the data, every interval is withheld and the statement says why; only the local geometry
    (correlations, Fisher eigen-directions) is kept. The covariances of ``scatter`` (default: the
    verdict's), ``sampling`` and ``grid`` are added to the statistical one; ``grid_note`` says
    why the grid term is missing, if it is."""
    keys = tuple(keys)
    J = np.asarray(J, float)
    r = np.asarray(r, float)
    theta = np.asarray(theta, float)
    row_scale = np.asarray(row_scale, float)
    m, n = J.shape  # J must be a matrix
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        raise ValueError("J and r must be finite (the run at the optimum failed?)")
    e = r / row_scale  # raw relative misfits
    Je = J / row_scale[:, None]
    if noise is not None and not isinstance(noise, Mapping):
        noise = {name: float(noise) for name in blocks}
    A, B, B_ref, used, estimated = _sandwich_terms(e, Je, row_scale, blocks, noise, reference_noise)
    fisher, fisher_ref = _sandwich_fisher(A, B), _sandwich_fisher(A, B_ref)
    cov_stat = _inverse(fisher)
    if scatter is None and verdict is not None:
        scatter = verdict.scatter
    cov = cov_stat + sum(sc.cov for sc in (scatter, sampling, grid) if sc is not None)
    stderr, corr = _stderr_and_corr(cov)
    ci95 = np.stack([theta - Z95 * stderr, theta + Z95 * stderr], axis=1)
    rel, evals, evecs = _identifiability(fisher_ref, theta, bounds)
    constrained = tuple(k for k, v in zip(keys, rel) if v <= threshold)
    lines = _identifiability_lines(keys, rel, constrained, corr, evals, evecs, reference_noise=reference_noise,
                                   threshold=threshold)
    if verdict is not None and not verdict.is_fit:
        return Uncertainty(keys, theta, None, None, corr, None, used, estimated, None, (),
                           _withheld_statement(keys, lines, verdict, grid), verdict, sampling=sampling, grid=grid,
                           grid_note=grid_note)
    se_stat = np.sqrt(np.maximum(np.diag(cov_stat), 0.0))
    lines += _share_lines(keys, se_stat, scatter, sampling, grid, grid_note)
    return Uncertainty(keys, theta, stderr, cov, corr, ci95, used, estimated, rel, constrained,
                       " ".join(lines), verdict, se_stat,
                       scatter.stderr if scatter is not None else None, sampling, grid, grid_note)


def _sandwich_terms(e, Je, row_scale, blocks, noise, reference_noise):
    """The sandwich's A and B (and B at the reference noise) from the relative misfits ``e`` and
    their Jacobian ``Je``, with the noise used and the noise estimated, by block."""
    m, n = Je.shape
    estimated, used, reference = {}, {}, {}
    # The fit's weights are row_scale², not 1/σ² (a short block's rows weigh more): hence the sandwich.
    weight = row_scale ** 2
    A = np.zeros((n, n))
    B = np.zeros((n, n))
    B_ref = np.zeros((n, n))
    for name, sl in blocks.items():
        mb = sl.stop - sl.start
        dof = max(mb - n * mb / m, 1.0)
        s = math.sqrt(float(np.sum(e[sl] ** 2)) / dof)
        estimated[name] = s
        sigma = float(noise[name]) if noise is not None and name in noise else s  # a block not named: estimated
        used[name] = sigma
        reference[name] = max(s, reference_noise)
        Jb, wb = Je[sl], weight[sl]
        A += Jb.T @ (wb[:, None] * Jb)
        B += Jb.T @ ((wb * wb)[:, None] * Jb) * max(sigma, 1e-12) ** 2  # σ = 0 only for an exact fit
        B_ref += Jb.T @ ((wb * wb)[:, None] * Jb) * reference[name] ** 2
    return A, B, B_ref, used, estimated


def _stderr_and_corr(cov):
    """Standard errors and correlations of ``cov`` (0 where a standard error is 0)."""
    stderr = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(stderr, stderr)
    return stderr, np.where(np.isfinite(corr), corr, 0.0)


def _identifiability(fisher_ref, theta, bounds):
    """At the reference noise: the 95 % half-widths relative to each key's scale (|θ|, at least
    1 % of its bound range), and the relative Fisher matrix's eigenvalues (descending) and
    eigenvectors."""
    if bounds is not None:
        span = np.asarray(bounds.upper) - np.asarray(bounds.lower)
    else:
        span = np.ones(fisher_ref.shape[0])
    scale = np.maximum(np.abs(theta), 0.01 * span)
    cov_ref = _inverse(fisher_ref)
    se_ref = np.sqrt(np.maximum(np.diag(cov_ref), 0.0))
    rel = Z95 * se_ref / scale

    fisher_rel = fisher_ref * np.outer(scale, scale)
    evals, evecs = np.linalg.eigh(fisher_rel)
    order = np.argsort(evals)[::-1]
    return rel, evals[order], evecs[:, order]


def _identifiability_lines(keys, rel, constrained, corr, evals, evecs, *, reference_noise, threshold) -> list[str]:
    """The statement's sentences on what the data constrain, the best- and worst-fixed
    combinations and the strongly correlated pairs."""
    n = len(evals)
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
    return lines


def _withheld_statement(keys, lines, verdict: Verdict, grid: GridCheck | None) -> str:
    """The statement where the verdict withholds the interval: why, then the local geometry only
    (and where the grid would move θ)."""
    geometry = [line for line in lines if not line.startswith(("The data constrain", "They do not"))]
    statement = " ".join([verdict.statement] + (["Local geometry only:"] + geometry if geometry else []))
    if grid is not None:
        statement += (f" At {grid.ratio:.3g} × the grid spacing the same θ would move " + ", ".join(
            f"{k} by {d:+.2g}" for k, d in zip(keys, grid.shift)) + ".")
    return statement


def _share_lines(keys, se_stat, scatter: ModelScatter | None, sampling: ModelScatter | None,
                 grid: GridCheck | None, grid_note: str) -> list[str]:
    """The statement's sentences on the shares of the run's round-off, the particle draw and the
    grid beside the data's interval (``se_stat``)."""
    lines = []
    if scatter is not None:
        dominated = [k for k, a, b in zip(keys, se_stat, scatter.stderr) if b > a]
        if dominated:
            lines.append(f"The run's own round-off ({scatter.samples} perturbed runs) dominates the interval of "
                         f"{', '.join(dominated)}: the data resolve more than the simulator can reproduce.")
    if sampling is not None:
        moved = [f"{k} (±{Z95 * b:.2g} against ±{Z95 * a:.2g})" for k, a, b in zip(keys, se_stat, sampling.stderr)
                 if b > a]
        if moved:
            lines.append(f"Another draw of the particles ({sampling.samples} seeds) moves " + ", ".join(moved)
                         + " by more than the data's interval: at this resolution that part of the answer is a "
                         "property of the discretisation, not of the material.")
    if grid is not None:
        moved = [f"{k} (±{h:.2g} against ±{Z95 * a:.2g})" for k, a, h in zip(keys, se_stat, grid.halfwidth)
                 if h > Z95 * a]
        if moved:
            lines.append(f"Not converged in the grid: a fit at {grid.ratio:.3g} × dx would move " + ", ".join(
                f"{k} by {d:+.2g}" for k, d in zip(keys, grid.shift)) + "; the grid's share of the interval of "
                + ", ".join(moved) + " exceeds the data's. At this dx that part of the answer is a property of "
                "the grid, not of the material: refit at a finer dx."
                + ("" if grid.shift2 is None else f" Grid term from {grid.method}."))
        else:
            seen = (f"one coarser grid ({grid.ratio:.3g} × dx) can show" if grid.shift2 is None
                    else f"two coarser grids ({grid.ratio:.3g} and {grid.ratio ** 2:.3g} × dx) show")
            lines.append(f"Converged in the grid as far as {seen}: its share stays within the data's interval "
                         "for every key.")
    elif grid_note:
        lines.append(f"The grid's share was not measured: {grid_note}.")
    return lines
