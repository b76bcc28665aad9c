"""What a fit reports: its JSON, built from the result and the objective it fitted, and the
checks beyond Gauss–Newton run on its point.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..inference.gridcheck import check_grid_options
from ..problem.options import OptionError, _is_int, _require
from ..problem.protocol import ObjectiveLike

__all__ = ["fit_report", "next_steps", "PosteriorChecks", "PosteriorOptions", "posterior_checks"]


def fit_report(objective: ObjectiveLike, result, search=None) -> dict[str, Any]:
    """The JSON of a fit (``FitResult``) or of a search (``SearchResult``, whose best point is
    ``result``): the result's own fields, the residuals in metres, the front residuals'
    correlation, the notes on the bounds and a warning for any key that ended at a bound. What
    ``python -m calibration fit`` prints, less the command's own fields (scene, files, outputs)."""
    out = search.to_json() if search is not None else result.to_json()
    metres = objective.in_metres(result.residuals)
    profile = [v for name, v in metres.items() if "profile" in name]
    out["residual_rms_m"] = float(np.sqrt(np.mean(np.concatenate(profile) ** 2))) if profile else None
    out["residual_rms_m_by_block"] = {name: float(np.sqrt(np.mean(v ** 2))) for name, v in metres.items()}
    if "front" in metres and metres["front"].size >= 3:
        from ..inference.noise import front_correlation

        out["front_residual_correlation"] = {
            **front_correlation(objective.observations.front_times, metres["front"]),
            "assumed_correlation_time_s": objective.front.correlation_time}
    if objective.bound_notes:
        out["bound_notes"] = list(objective.bound_notes)
    near = objective.bounds.near_bound([result.theta[k] for k in result.keys])
    if near:
        out["warning"] = f"{near} ended at a bound: the data push them outside the physical range"
    advice = next_steps(result)
    if advice:
        out["next"] = advice
    return out


def next_steps(result) -> list[str]:
    """What to run next where a fit (``FitResult``) did not end in a usable answer: one line per
    reason the verdict or the interval gives (none for a fit of the data converged in the grid),
    read from their fields and the optimiser's message, not from the verdict's sentences."""
    from ..inference.verdict import broken_relations

    verdict, unc = result.verdict, result.uncertainty
    if verdict is None:
        return []
    steps, unverified = [], not verdict.verified
    if unverified and result.message.startswith("stopped after"):
        steps.append(f"LM ran out of iterations ({result.iterations}): continue it with --out FIT.h5 --resume "
                     f"--steps {2 * result.iterations} (a fit without --out starts again: give --steps instead)")
    if unverified and "rejected steps in a row" in result.message:
        steps.append("LM found no lower loss near the point, yet the point is no verified minimum: the loss is "
                     "rough at the scale of its last steps (the particles' draw and the grid, not the data). "
                     "Look at the loss about it (python -m calibration posterior FIT.h5 --profiles 9), measure the "
                     "draw's share (--sampling-seeds 4), or fit on a ladder of grids (--grid-ladder 3)")
    if verdict.at_bound:
        steps.append(f"{', '.join(verdict.at_bound)} ended at a bound: the data ask for what the model or the box "
                     "does not allow. Check the scene against the experiment (a channel's side walls: "
                     "--side-walls W,MU_W; the floor; the data's units), or fit fewer keys")
    if broken_relations(result.keys, [result.theta[k] for k in result.keys]):
        steps.append("the point breaks a rule of the rheology (mu2 below mu1): start from a point that keeps it "
                     "(--init), or hold one of the two (--set)")
    if verdict.probe is not None and not verdict.probe.passed:
        start = " ".join(f"--init {k}={v:.4g}" for k, v in zip(result.keys, verdict.probe.lowest))
        steps.append(f"the loss is lower near the point than at it: fit again from the lowest point the probe ran "
                     f"({start}). Where the loss is rough (the probe's rises jump from one point to the next), one "
                     "fit ends on whichever ripple it meets: scan the loss (python -m calibration sweep --over "
                     "KEY=LO:HI:N, and --seed for other particle draws) and fit on a finer grid")
    if any(value > verdict.chi2_limit[name] for name, value in verdict.chi2.items()):
        steps.append("the model does not reach the data: before reading any number, check what the scene leaves "
                     "out (a channel's side walls, the floor's friction, the release), and give the data's "
                     "known noise (--noise) where the residuals' own estimate is too small")
    if unc is not None and unc.grid_converged is False:
        steps.append("the grid's share of the interval exceeds the data's: refit at a finer --dx (the statement "
                     "says how much finer), or read the grid term from a ladder of fits (--grid-ladder 3)")
    return steps


@dataclasses.dataclass(frozen=True)
class PosteriorOptions:
    """Which checks beyond Gauss–Newton to run on a fit's point (each 0: off), validated once:
    ``profiles`` points per key of the profile likelihood, ``posterior`` points per key of the
    grid posterior of one or two keys, ``nuts`` draws per chain of the NUTS posterior on
    ``chains`` chains, ``emulated`` model runs checking the emulated posterior with its
    ``emulator``; ``model_error``: particle draws measuring the model's own error at the point
    (``calibration.inference.likelihood.model_error``, at ``grid_ratio``, 1.5 where that is off);
    ``prior``: {key: (mean, sd)}, a normal prior of the NUTS and emulated posteriors;
    ``grid_ratio`` (None: off) and ``grid_levels``: those posteriors' grid term. The least values
    are checked in ``__post_init__``."""

    profiles: int = 0
    posterior: int = 0
    nuts: int = 0
    chains: int = 4
    emulated: int = 0
    emulator: str = "corrected"
    model_error: int = 0
    prior: Mapping[str, tuple[float, float]] | None = None
    grid_ratio: float | None = None
    grid_levels: int = 1

    def __post_init__(self):
        from ..inference.surrogates import EMULATORS

        for name, least, what in (("profiles", 3, ""), ("posterior", 3, ""), ("nuts", 4, " draws per chain"),
                                  ("emulated", 30, " checked draws"), ("model_error", 2, " particle draws")):
            value = getattr(self, name)
            _require(_is_int(value) and (value == 0 or value >= least), name, f"0 (off) or >= {least}{what}", value)
        _require(_is_int(self.chains) and self.chains >= 1, "chains", ">= 1", self.chains)
        if self.emulated:
            _require(self.chains >= 2, "chains", ">= 2 with emulated (R-hat compares chains)", self.chains)
        _require(self.emulator in EMULATORS, "emulator", f"one of {tuple(EMULATORS)}", self.emulator)
        if self.prior and not (self.nuts or self.emulated):
            raise OptionError("prior", "enters the posteriors of nuts and emulated (not the fit): ask for one of them")
        check_grid_options(self.grid_ratio, 1, self.grid_levels)

    @property
    def any(self) -> bool:
        """Whether any check is asked for."""
        return bool(self.profiles or self.posterior or self.nuts or self.emulated)


@dataclasses.dataclass(frozen=True)
class PosteriorChecks:
    """The checks beyond Gauss–Newton on a fit's point: ``report``, the JSON blocks they add
    to the fit's ("profile_likelihood", "posterior", "nuts", or why one was skipped);
    ``profiles``, the ``ProfileLikelihood`` of every key scanned; ``posterior``, the
    ``GridPosterior``; ``nuts``, the ``McmcPosterior``; ``emulated``, the ``EmulatedPosterior``
    (each None where not computed)."""

    report: dict[str, Any] = dataclasses.field(default_factory=dict)
    profiles: list = dataclasses.field(default_factory=list)
    posterior: Any = None
    nuts: Any = None
    emulated: Any = None


def posterior_checks(objective, result, options: PosteriorOptions, *, noise=None, workers=None,
                     progress: bool = False) -> PosteriorChecks:
    """The checks of ``options`` around ``result``, a fit of ``objective`` (``noise``: the data's
    known noise, None: the fit's). The profile likelihoods, the grid posterior and NUTS need the
    point's interval and are skipped without one, with the reason in the report; the emulated
    posterior needs none and runs centred on the point. The model's own error at the point
    (``options.model_error``) is added in quadrature to the noise of every check's likelihood, and
    the fit's grid term to the profile and grid-posterior intervals where it carries one. What
    ``python -m calibration posterior`` runs."""
    if not options.any:
        return PosteriorChecks()
    report: dict[str, Any] = {}
    if options.prior:
        report["prior"] = {k: list(map(float, v)) for k, v in options.prior.items()}
    unc = result.uncertainty
    fitted = getattr(unc, "noise", None)  # the fit's noise by block (estimated or given)
    sigma = noise if noise is not None else (dict(fitted) if fitted else None)
    error = _model_error(objective, result, options, workers) if options.model_error else None
    if isinstance(error, str):
        report["model_error_skipped"] = error
    elif error is not None:
        if sigma is None:
            report["model_error_skipped"] = "no noise level of the data to add it to: give --noise"
        else:
            sigma = noise = error.noise(sigma)
            report.update(model_error=error.to_dict(), posterior_noise=noise)
    emulated = None
    if options.emulated:
        block, emulated = _emulated(objective, result, options, sigma, workers, progress)
        report.update(block)
    if not (options.profiles or options.posterior or options.nuts):
        return PosteriorChecks(report, emulated=emulated)
    if unc is None or unc.withheld:
        return PosteriorChecks({**report, "profile_likelihood_skipped": "the point is not a fit of the data: no "
                                                                        "interval to scan around"}, emulated=emulated)
    return dataclasses.replace(_around_the_interval(objective, result, options, noise, report, progress),
                               emulated=emulated)


def _model_error(objective, result, options: PosteriorOptions, workers):
    """The model's own error at the point (``ModelError``), or why it cannot be measured."""
    from ..inference.gridcheck import GRID_RATIO
    from ..inference.likelihood import model_error

    try:
        return model_error(objective, result.theta, draws=options.model_error,
                           ratio=options.grid_ratio or GRID_RATIO, workers=workers)
    except ValueError as err:
        return str(err)


def _emulated(objective, result, options: PosteriorOptions, sigma, workers, progress: bool):
    """The emulated posterior's block of the report (or why it was skipped) and the posterior
    (None where skipped)."""
    from ..inference.emulator import emulated_posterior, prior_sensitivity, scale_keys

    lower, upper = objective.bounds.lower, objective.bounds.upper
    at_bound = [k for k, lo, hi in zip(objective.keys, lower, upper) if not lo < result.theta[k] < hi]
    if at_bound:
        return {"emulated_posterior_skipped": f"{at_bound} at a bound: the chains' coordinates end there"}, None
    if sigma is None:
        return {"emulated_posterior_skipped": "no noise level: give --noise"}, None
    unc = result.uncertainty  # a fit whitens by its interval; a point without one, by the Laplace covariance there
    interval = unc is not None and not unc.withheld
    found = emulated_posterior(objective, result if interval else dict(result.theta), noise=sigma,
                               checks=options.emulated, chains=options.chains, emulator=options.emulator,
                               prior=options.prior, grid_ratio=options.grid_ratio, grid_levels=options.grid_levels,
                               workers=workers, progress=progress)
    block = found.to_json()
    scale = scale_keys(objective.bounds)
    if scale:  # a key whose box spans decades: how much of its interval is the prior's
        block["prior_sensitivity"] = prior_sensitivity(found, scale)
    return {"emulated_posterior": block}, found


def _around_the_interval(objective, result, options: PosteriorOptions, noise, report, progress) -> PosteriorChecks:
    """NUTS, the profile likelihoods and the grid posterior around a point with an interval."""
    from ..inference.gridpost import grid_posterior
    from ..inference.likelihood import profile_likelihood

    nuts = None
    if options.nuts:
        from ..inference.mcmc import nuts_posterior

        found = nuts_posterior(objective, result, chains=options.chains, warmup=max(20, options.nuts // 2),
                               draws=options.nuts, noise=noise, prior=options.prior, grid_ratio=options.grid_ratio,
                               grid_levels=options.grid_levels, progress=progress)
        report["nuts"] = {k: v for k, v in found.to_json().items() if k != "draws"}
        nuts = found
    scans = ([profile_likelihood(objective, result, k, n=options.profiles, noise=noise) for k in result.keys]
             if options.profiles else [])
    if scans:
        report["profile_likelihood"] = {p.key: p.to_json() for p in scans}
    grid = None
    if options.posterior:
        if len(result.keys) > 2:
            report["posterior_skipped"] = f"{len(result.keys)} keys: the grid posterior is for one or two"
        else:
            grid = grid_posterior(objective, result, n=options.posterior, noise=noise)
            report["posterior"] = grid.to_json()
    _add_fit_grid_term(report, objective, result, scans, grid)
    return PosteriorChecks(report, scans, grid, nuts)


def _add_fit_grid_term(report: dict[str, Any], objective, result, scans, grid) -> None:
    """The fit's grid term (``Uncertainty.grid``: one Gauss–Newton step at ρ dx) on the profile
    intervals and the grid posterior's, as ``ci95_profile_with_grid`` and ``ci95_with_grid``:
    its 95 % half-width in quadrature on each side (``calibration.inference.gridterm.widened``)."""
    from ..inference.gridterm import widened

    term = getattr(result.uncertainty, "grid", None)
    if term is None or not (scans or grid is not None):
        return
    keys = tuple(result.keys)
    bounds = dict(zip(objective.keys, zip(objective.bounds.lower, objective.bounds.upper)))
    half = dict(zip(keys, map(float, term.halfwidth)))
    note = ("the fit's grid term (grid.halfwidth95, one Gauss-Newton step at "
            f"{term.ratio:.3g} x dx) added in quadrature to each side")
    for scan in scans:
        block = report["profile_likelihood"][scan.key]
        block["ci95_profile_with_grid"] = list(widened(*scan.ci95, scan.theta_hat, half[scan.key], *bounds[scan.key]))
        block["grid_term"] = note
    if grid is not None:
        report["posterior"]["ci95_with_grid"] = {k: list(widened(*grid.ci95[k], grid.mean[k], half[k], *bounds[k]))
                                                 for k in grid.keys}
        report["posterior"]["grid_term"] = note
