"""Whether a point is a fit of the data (``assess_fit``), and a fit's end point judged: verdict and
interval together (``judge_point``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from jaxmpm.params import RELATIONS

from ..problem.protocol import ObjectiveLike
from .gauss_newton import gauss_newton_uncertainty
from .gridcheck import GRID_DRAWS, GridCheck, check_grid_options, grid_shift
from .noise import ABOVE_NOISE_P, NOISE_FLOOR, block_noise, chi2_quantile
from .probe import LossProbe, probe_loss
from .scatter import ROUNDOFF_SAMPLES, ModelScatter, model_scatter, roundoff_limit, sampling_scatter

__all__ = ["Verdict", "assess_fit", "judge_point"]


@dataclasses.dataclass(frozen=True)
class Verdict:
    """Whether a point is a fit of the data, and if not, why (docs/verdict.md)."""

    is_fit: bool
    reasons: tuple[str, ...]
    verified: bool  # the optimiser met one of its convergence tests
    at_bound: tuple[str, ...]
    noise: dict[str, float | None]  # σ by block (None: not estimable)
    noise_source: str
    chi2: dict[str, float]  # by block with a noise level
    chi2_limit: dict[str, float]
    statement: str
    convergence: str = ""  # how the minimum was verified (the optimiser's test, or the run's round-off)
    scatter: ModelScatter | None = None
    noise_note: str = ""  # the blocks the noise test left out, in words
    probe: LossProbe | None = None  # the loss about the point (``probe_loss``; None: not run)

    def failing(self, reason: str) -> Verdict:
        """This verdict with one more reason the point is not a fit of the data."""
        reasons = (*self.reasons, reason)
        return dataclasses.replace(self, is_fit=False, reasons=reasons, statement=_statement(reasons, self.noise_note))

    def to_dict(self) -> dict[str, Any]:
        out = {"is_fit": self.is_fit, "verdict": "a fit of the data" if self.is_fit else "not a fit of the data",
               "reasons": list(self.reasons), "verified_minimum": self.verified, "at_bound": list(self.at_bound),
               "noise": self.noise, "noise_source": self.noise_source, "chi2": self.chi2,
               "chi2_limit": self.chi2_limit, "statement": self.statement}
        if self.convergence:
            out["convergence"] = self.convergence
        return out


def _statement(reasons, noise_note: str) -> str:
    if not reasons:
        statement = "A fit of the data: a verified minimum, off the bounds, with a misfit within the noise."
    else:
        statement = ("Not a fit of the data: " + "; ".join(reasons) + ". No Gauss–Newton interval is given: it "
                     "describes the curvature at a minimum of the data's misfit, which this point is not.")
    return statement + noise_note


def broken_relations(keys, theta) -> list[str]:
    """The rules across fitted keys (``jaxmpm.params.RELATIONS``, μ2 >= μ1) that θ breaks, in words.
    The boxes of the bounds cannot hold them, so a fit can end where the model is not the one
    docs/model.md describes (μ2 < μ1 makes μ(I) rate-weakening)."""
    values = dict(zip(keys, np.asarray(theta, float).tolist()))
    return [f"{rel.key} = {values[rel.key]:.4g} below {rel.other} = {values[rel.other]:.4g} ({rel.key} is {rel.why}: "
            f"the point lies outside the model's rheology)"
            for rel in RELATIONS if rel.key in values and rel.other in values and values[rel.key] < values[rel.other]]


def assess_fit(r, row_scale, blocks: Mapping[str, slice], theta, *, converged: bool, message: str = "",
               bounds=None, noise: Mapping[str, float] | float | None = None, J=None,
               scatter: ModelScatter | None = None) -> Verdict:
    """Judge the point θ with residuals ``r`` (the objective's weighted ones): a verified
    minimum (``converged``, ``message`` the optimiser's), off the bounds, with a misfit within
    the noise in every block (the given ``noise``, or the residuals' structural noise).

    With the run's ``scatter`` (``model_scatter``) and the Jacobian ``J``: a point where the
    optimiser stopped without converging still counts as a verified minimum when its remaining
    Gauss–Newton step lies within the scatter (the run cannot resolve a better point), and each
    block's noise for the χ² test is sqrt(σ² + σ_num²)."""
    theta = np.asarray(theta, float)
    e = np.asarray(r, float) / np.asarray(row_scale, float)
    m, n = e.size, theta.size
    reasons = []
    convergence = message if converged else ""
    if not converged and scatter is not None and J is not None:
        distance = scatter.gauss_newton_distance(J, r)
        limit_d = roundoff_limit(n, scatter.samples)
        if distance <= limit_d:
            converged = True
            convergence = (f"converged within the run's round-off: the remaining Gauss–Newton step is {distance:.2g} "
                           f"standard deviations of the scatter {scatter.samples} perturbed runs show (limit "
                           f"{limit_d:.2g}); the optimiser had {message or 'stopped'}")
        else:
            message = (f"{message or 'the optimiser did not converge'}; the remaining Gauss–Newton step is "
                       f"{distance:.2g} standard deviations of the run's round-off scatter, beyond {limit_d:.2g}")
    if not converged:
        reasons.append(f"not a verified minimum ({message or 'the optimiser did not converge'})")
    at_bound = tuple(bounds.near_bound(theta)) if bounds is not None else ()
    if at_bound:
        reasons.append(f"{', '.join(at_bound)} at a bound (the misfit falls towards or beyond the physical range)")
    reasons.extend(broken_relations(bounds.keys, theta) if bounds is not None else ())
    sigma, counts, source = block_noise(r, row_scale, blocks, noise)
    if scatter is not None:
        sigma = {name: None if v is None else math.hypot(v, scatter.noise.get(name, 0.0)) for name, v in sigma.items()}
        source += ", with the run's round-off scatter added in quadrature"
    chi2, limit, unknown = {}, {}, []
    for name, sl in blocks.items():
        if sigma[name] is None:
            unknown.append(f"{name} ({sl.stop - sl.start} residuals: too few to estimate its noise)")
            continue
        mb = sl.stop - sl.start
        chi2[name] = float(np.sum(e[sl] ** 2)) / max(sigma[name], NOISE_FLOOR) ** 2
        inflate = 1.0 if counts[name] == 0 else 1.0 + 3.0 * 4.0 / math.sqrt(counts[name])
        limit[name] = chi2_quantile(ABOVE_NOISE_P, max(mb - n * mb / m, 1.0)) * inflate
        if chi2[name] > limit[name]:
            rms = math.sqrt(float(np.mean(e[sl] ** 2)))
            reasons.append(f"{name} misfit well above the noise (rms {rms:.3g} against σ {sigma[name]:.3g} "
                           f"{'given' if source == 'given' else 'estimated'}; χ² {chi2[name]:.3g} > {limit[name]:.3g})")
    noise_note = " The noise test left out " + ", ".join(unknown) + "." if unknown else ""
    return Verdict(not reasons, tuple(reasons), bool(converged), at_bound, sigma, source, chi2, limit,
                   _statement(reasons, noise_note), convergence, scatter, noise_note)


def judge_point(objective: ObjectiveLike, r, J, theta, *, converged: bool, message: str,
                noise: Mapping[str, float] | float | None = None, uncertainty: bool = True,
                roundoff_samples: int = ROUNDOFF_SAMPLES, sampling_seeds: int = 0, reference_noise: float = 0.01,
                threshold: float = 0.1, grid_ratio: float | None = None, grid_draws: int = GRID_DRAWS,
                grid_levels: int = 1, probe: bool = True, workers=None, scatter: ModelScatter | None = None,
                grid: GridCheck | None = None):
    """The verdict on a fit's end point and, when ``uncertainty``, its Gauss–Newton uncertainty
    (intervals withheld unless the verdict is a fit): what ``fit`` and ``search`` report for
    their best point. The other options are ``JudgeOptions``': ``roundoff_samples`` for
    ``model_scatter``, ``sampling_seeds`` for ``sampling_scatter``, ``grid_ratio``, ``grid_draws``
    and ``grid_levels`` for ``grid_shift`` (0 or None: not measured; unmeasured, the round-off is
    taken as nil). ``scatter``: the round-off scatter already measured at θ with
    ``roundoff_samples`` runs (the optimiser's, ``calibration.optim.fit.roundoff_stop``), reused;
    ``grid``: the grid term already measured (a ladder of fits, ``calibration.optim.ladder``), used
    instead of ``grid_shift``.
    All runs go to ``workers`` (a ``calibration.batch.workers.Workers``) when given.
    Returns ``(verdict, uncertainty or None)``."""
    check_grid_options(grid_ratio, grid_draws, grid_levels)
    J = np.asarray(J, float)
    finite = np.all(np.isfinite(J))
    if not (roundoff_samples and finite):
        scatter = None
    elif scatter is None:
        scatter = model_scatter(objective, theta, r, J, samples=roundoff_samples, workers=workers)
    verdict = assess_fit(r, objective.row_scale, objective.blocks, theta, converged=converged, message=message,
                         bounds=objective.bounds, noise=noise, J=J if scatter is not None else None,
                         scatter=scatter)
    if not uncertainty:
        return verdict, None
    sampling = None
    if sampling_seeds and finite:
        sampling = sampling_scatter(objective, theta, r, J, seeds=sampling_seeds, workers=workers)
    grid_note = ""
    if grid is None and grid_ratio is not None and finite:
        try:
            grid = grid_shift(objective, theta, J, ratio=grid_ratio, draws=grid_draws, levels=grid_levels,
                              workers=workers)
        except ValueError as error:
            grid_note = str(error)
        except NotImplementedError as error:  # a closed form's (as coarse_objectives says it)
            grid_note = f"{type(objective).__name__} has no coarser grid ({error})"
        else:
            if grid is None:
                grid_note = f"no run at {grid_ratio:g} × dx ran without status bits"
    def interval(verdict):
        return gauss_newton_uncertainty(J, r, objective.keys, theta, objective.blocks, objective.row_scale,
                                        noise=noise, bounds=objective.bounds, verdict=verdict, scatter=scatter,
                                        sampling=sampling, grid=grid, grid_note=grid_note,
                                        reference_noise=reference_noise, threshold=threshold)

    unc = interval(verdict)
    # A verified minimum inside the box and the rheology is probed whatever its misfit: a stop on a
    # ripple of the valley's wall can leave a misfit above the noise too.
    if probe and verdict.verified and not verdict.at_bound and not broken_relations(objective.keys, theta):
        cov = unc.cov if not unc.withheld else interval(None).cov
        found = probe_loss(objective, theta, r, J, cov, verdict.noise, scatter=scatter, workers=workers)
        verdict = dataclasses.replace(verdict, probe=found)
        if not found.passed:
            verdict = verdict.failing(found.reason(objective.keys))
            unc = interval(verdict)
        elif not unc.withheld:
            unc = _widened(unc, found)
    return verdict, unc


def _widened(unc, found: LossProbe):
    """``unc`` with its interval stretched where the probe's χ² had not risen by 1.96² at an edge
    (``LossProbe.widened``), the Gauss–Newton one kept as ``ci95_linearised``; ``unc`` itself
    where nothing moved."""
    ci95 = found.widened(unc.theta, unc.ci95)
    if np.allclose(ci95, unc.ci95, rtol=0.0, atol=0.0):
        return unc
    moved = [f"{k} to [{lo:.4g}, {hi:.4g}]" for k, (lo, hi), old in zip(unc.keys, ci95, unc.ci95)
             if not np.array_equal([lo, hi], old)]
    note = (" The loss is flatter than its curvature at the point says: the probe's χ² had not risen by 1.96² at "
            "an edge, so the interval is widened to where it has: " + ", ".join(moved) + ".")
    return dataclasses.replace(unc, ci95=ci95, ci95_linearised=unc.ci95, statement=unc.statement + note)
