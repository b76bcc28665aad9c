"""What a fit reports: its JSON, built from the result and the objective it fitted, and the
checks beyond Gauss–Newton run on its point."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .protocol import ObjectiveLike

__all__ = ["PosteriorChecks", "fit_report", "posterior_checks"]


def fit_report(objective: ObjectiveLike, result, search=None) -> dict[str, Any]:
    """The JSON of a fit (``FitResult``) or of a search (``SearchResult``, whose best point is
    ``result``): the result's own fields, the residuals in metres (RMS of the profiles and of
    every block), the front residuals' correlation where a front history was fitted, the notes on
    the bounds and a warning for any key that ended at a bound. What ``python -m calibration fit``
    prints, less the command's own fields (scene, files, outputs)."""
    out = search.to_json() if search is not None else result.to_json()
    metres = objective.in_metres(result.residuals)
    profile = [v for name, v in metres.items() if "profile" in name]
    out["residual_rms_m"] = float(np.sqrt(np.mean(np.concatenate(profile) ** 2))) if profile else None
    out["residual_rms_m_by_block"] = {name: float(np.sqrt(np.mean(v ** 2))) for name, v in metres.items()}
    if "front" in metres and metres["front"].size >= 3:
        from .uncertainty import front_correlation

        out["front_residual_correlation"] = {
            **front_correlation(objective.observations.front_times, metres["front"]),
            "assumed_correlation_time_s": objective.front.correlation_time}
    if objective.bound_notes:
        out["bound_notes"] = list(objective.bound_notes)
    near = objective.bounds.near_bound([result.theta[k] for k in result.keys])
    if near:
        out["warning"] = f"{near} ended at a bound: the data push them outside the physical range"
    return out


@dataclasses.dataclass(frozen=True)
class PosteriorChecks:
    """The checks beyond Gauss–Newton on a fit's point: ``report``, the JSON blocks they add
    to the fit's ("profile_likelihood", "posterior", "nuts", or why one was skipped);
    ``profiles``, the ``ProfileLikelihood`` of every key scanned; ``posterior``, the
    ``GridPosterior`` (None where not computed)."""

    report: dict[str, Any] = dataclasses.field(default_factory=dict)
    profiles: list = dataclasses.field(default_factory=list)
    posterior: Any = None


def posterior_checks(objective, result, *, profiles: int = 0, posterior: int = 0, nuts: int = 0, chains: int = 4,
                     emulated: int = 0, emulator: str = "corrected", noise=None, model_error=None, prior=None,
                     grid_ratio: float | None = None, grid_levels: int = 1, workers=None,
                     progress: bool = False) -> PosteriorChecks:
    """The profile likelihood of every fitted key at ``profiles`` points, the grid posterior of
    one or two keys at ``posterior`` points per key and a NUTS posterior of ``nuts`` draws per
    chain on ``chains`` chains (each 0: off) around ``result``, a fit of ``objective``
    (``noise``: the data's known noise, None: estimated). Skipped, with the reason in the
    report, where the point has no interval to scan around; the grid posterior also for more
    than two keys. ``emulated``: the posterior of every key from NUTS on an emulator, corrected
    with the model's runs at ``emulated`` draws (``calibration.emulator``, its ``emulator``; on ``workers``): it
    needs no interval, so it runs where the verdict refuses one too, centred on the point with
    the noise given or estimated. ``model_error``: the model's own error at the point
    (``calibration.likelihood.ModelError``), added to the noise of every check's likelihood in
    quadrature (reported as "model_error" and "posterior_noise"). The emulated posterior carries
    its ``prior_sensitivity`` where a key's box spans decades (``calibration.emulator.scale_keys``:
    the same checks under a prior uniform in that key's log). ``prior``: {key: (mean, sd)}, keys
    measured elsewhere, a normal prior in the NUTS and emulated posteriors (reported as "prior").
    ``grid_ratio``, ``grid_levels``: the NUTS and emulated posteriors' grid term (the same
    posterior at ``grid_ratio`` × dx, and its square with two levels; ``calibration.gridterm``;
    None: not measured). The profile likelihood's and the grid posterior's intervals get the fit's
    own grid term where it carries one (``ci95_profile_with_grid``, ``ci95_with_grid``).
    What ``python -m calibration
    fit --profiles N --posterior N --nuts N --emulated N`` adds."""
    if not (profiles or posterior or nuts or emulated):
        return PosteriorChecks()
    report: dict[str, Any] = {}
    if prior:
        report["prior"] = {k: list(map(float, v)) for k, v in prior.items()}
    unc = result.uncertainty
    fitted = getattr(unc, "noise", None)  # the fit's noise by block (estimated or given)
    sigma = noise if noise is not None else (dict(fitted) if fitted else None)
    if model_error is not None:
        if sigma is None:
            report["model_error_skipped"] = "no noise level of the data to add it to: give --noise"
        else:
            sigma = noise = model_error.noise(sigma)
            report.update(model_error=model_error.to_dict(), posterior_noise=noise)
    if emulated:
        from .emulator import emulated_posterior, prior_sensitivity, scale_keys

        lower, upper = objective.bounds.lower, objective.bounds.upper
        at_bound = [k for k, lo, hi in zip(objective.keys, lower, upper) if not lo < result.theta[k] < hi]
        if at_bound:
            report["emulated_posterior_skipped"] = f"{at_bound} at a bound: the chains' coordinates end there"
        elif sigma is None:
            report["emulated_posterior_skipped"] = "no noise level: give --noise"
        else:  # a fit whitens by its interval; a point without one, by the Laplace covariance there
            interval = unc is not None and not unc.withheld
            found = emulated_posterior(objective, result if interval else dict(result.theta), noise=sigma,
                                       checks=emulated, chains=chains, emulator=emulator, prior=prior,
                                       grid_ratio=grid_ratio, grid_levels=grid_levels,
                                       workers=workers, progress=progress)
            report["emulated_posterior"] = found.to_json()
            scale = scale_keys(objective.bounds)
            if scale:  # a key whose box spans decades: how much of its interval is the prior's
                report["emulated_posterior"]["prior_sensitivity"] = prior_sensitivity(found, scale)
    if not (profiles or posterior or nuts):
        return PosteriorChecks(report)
    if result.uncertainty is None or result.uncertainty.withheld:
        return PosteriorChecks({**report, "profile_likelihood_skipped": "the point is not a fit of the data: no "
                                                                        "interval to scan around"})
    if nuts:
        from .mcmc import nuts_posterior

        found = nuts_posterior(objective, result, chains=chains, warmup=max(20, nuts // 2), draws=nuts, noise=noise,
                               prior=prior, grid_ratio=grid_ratio, grid_levels=grid_levels, progress=progress)
        report["nuts"] = {k: v for k, v in found.to_json().items() if k != "draws"}
    from .likelihood import grid_posterior, profile_likelihood

    scans = [profile_likelihood(objective, result, k, n=profiles, noise=noise) for k in result.keys] if profiles else []
    if scans:
        report["profile_likelihood"] = {p.key: p.to_json() for p in scans}
    grid = None
    if posterior:
        if len(result.keys) > 2:
            report["posterior_skipped"] = f"{len(result.keys)} keys: the grid posterior is for one or two"
        else:
            grid = grid_posterior(objective, result, n=posterior, noise=noise)
            report["posterior"] = grid.to_json()
    _add_fit_grid_term(report, objective, result, scans, grid)
    return PosteriorChecks(report, scans, grid)


def _add_fit_grid_term(report: dict[str, Any], objective, result, scans, grid) -> None:
    """The fit's grid term (``Uncertainty.grid``: one Gauss–Newton step at ρ dx) on the profile
    intervals and the grid posterior's, as ``ci95_profile_with_grid`` and ``ci95_with_grid``:
    its 95 % half-width in quadrature on each side (``calibration.gridterm.widened``)."""
    from .gridterm import widened

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
