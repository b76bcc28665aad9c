"""What a fit reports: its JSON, built from the result and the objective it fitted."""

from __future__ import annotations

from typing import Any

import numpy as np

from .protocol import ObjectiveLike

__all__ = ["fit_report"]


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
