"""What was measured, as a fit compares it: a deposit profile (``ProfileTarget``) and a front history
(``FrontTarget``), and the checks that refuse data that cannot come from the scene they are said to
come from (a deposit taller than 1.5 columns, units off by 10^3, points outside the grid).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["ProfileTarget", "FrontTarget"]


@dataclasses.dataclass(frozen=True)
class ProfileTarget:
    """A deposit profile to match: heights ``h`` (m) at points ``x`` (m) at time ``time_s``
    (None: the end of the run). ``source``: where the numbers came from (a file), named in
    error messages."""

    x: np.ndarray
    h: np.ndarray
    time_s: float | None = None
    source: str | None = None

    @classmethod
    def of(cls, data) -> ProfileTarget:
        """From a ``calibration.data.loaders.Profile`` (or anything with ``x``, ``h`` and ``time_s``)."""
        return cls(np.asarray(data.x, float), np.asarray(data.h, float), getattr(data, "time_s", None),
                   getattr(data, "path", None))


@dataclasses.dataclass(frozen=True)
class FrontTarget:
    """Front positions ``x_front`` (m) at times ``t`` (s); ``source`` as for ``ProfileTarget``.

    ``correlation_time`` (s): None (default) treats the front's errors as independent; a time τ
    assumes an exponentially correlated error, corr(e_i, e_j) = exp(−|t_i − t_j|/τ), whose
    residuals the fit whitens (``observe.whiten_front``; docs/verdict.md, "Correlated front
    errors")."""

    t: np.ndarray
    x_front: np.ndarray
    source: str | None = None
    correlation_time: float | None = None

    @classmethod
    def of(cls, data) -> FrontTarget:
        return cls(np.asarray(data.t, float), np.asarray(data.x_front, float), getattr(data, "path", None))


#: Plausibility limits of data against the scene they are said to come from (``check_data``):
#: no deposit is taller than 1.5 column heights or lower than 1 % of one, none holds more than
#: twice the column's area L·H, and the measured material lies on the grid.
MAX_HEIGHT_RATIO, MIN_HEIGHT_RATIO, MAX_AREA_RATIO = 1.5, 0.01, 2.0


#: A point counts as "material" for the grid check when h exceeds this fraction of max h.
MATERIAL_FRACTION = 0.01


def _check_profile_plausible(label: str, x: np.ndarray, h: np.ndarray, scene, x_lo: float, x_hi: float, dtype):
    """Refuse a profile that cannot be a deposit of ``scene`` (units off by 10^3, another scene's
    data, numbers beyond the run's precision), naming ``label`` (the file)."""
    info = scene.info
    _check_representable(label, dtype, x, h)
    h_max = float(h.max())
    height, length = info.height, info.length
    where = f"scene {scene.name}'s column (H = {height:g} m)" if height else ""
    if height:
        if h_max > MAX_HEIGHT_RATIO * height:
            raise ValueError(f"{label}: its highest point, h = {h_max:g} m, is {h_max / height:.3g} x the height of "
                             f"{where}: no deposit of this scene is that tall (wrong units? millimetres read as "
                             "metres are 1000 x too large)")
        if h_max < MIN_HEIGHT_RATIO * height:
            raise ValueError(f"{label}: its highest point, h = {h_max:g} m, is only {h_max / height:.3g} x the height "
                             f"of {where}: no deposit of this scene is that flat (wrong units? metres read as "
                             "millimetres are 1000 x too small)")
    if height and length and x.size > 1:
        area = float(np.sum(0.5 * (np.maximum(h[1:], 0) + np.maximum(h[:-1], 0)) * np.diff(x)))
        if area > MAX_AREA_RATIO * length * height:
            raise ValueError(f"{label}: the profile holds {area:g} m^2, {area / (length * height):.3g} x the area "
                             f"L H = {length * height:g} m^2 of scene {scene.name}'s column: more material than the "
                             "scene has")
    material = h > MATERIAL_FRACTION * h_max
    outside = material & ((x < x_lo) | (x > x_hi))
    if np.all((x < x_lo) | (x > x_hi)):
        raise ValueError(f"{label}: all its points (x = {x.min():g} .. {x.max():g} m) lie outside the scene's grid, "
                         f"x = {x_lo:g} .. {x_hi:g} m")
    if np.any(outside):
        shown = ", ".join(f"{v:g}" for v in x[outside][:3])
        raise ValueError(f"{label}: {int(outside.sum())} point(s) with material (h > {MATERIAL_FRACTION:g} max h) lie "
                         f"outside the scene's grid, x = {x_lo:g} .. {x_hi:g} m, where the model's deposit is always "
                         f"zero (x = {shown} m): enlarge the scene or trim the data")


def _check_representable(label: str, dtype, *arrays) -> None:
    with np.errstate(over="ignore"):
        if not all(np.all(np.isfinite(np.asarray(a, dtype))) for a in arrays):
            raise ValueError(f"{label}: values beyond the range of {np.dtype(dtype).name}, in which the run computes")


def _check_front_plausible(label: str, t: np.ndarray, xf: np.ndarray, scene, x_lo: float, x_hi: float, dtype):
    _check_representable(label, dtype, xf, t)
    outside = (xf < x_lo) | (xf > x_hi)
    if np.any(outside):
        k = int(np.argmax(outside))
        raise ValueError(f"{label}: the front at t = {t[k]:g} s, x = {xf[k]:g} m, lies outside the scene's grid, "
                         f"x = {x_lo:g} .. {x_hi:g} m, which the model's front never leaves (wrong units?)")
    front0 = scene.info.front0
    if front0 and float(xf.max()) < 0.5 * front0:
        raise ValueError(f"{label}: every front position (at most {float(xf.max()):g} m) lies behind half the "
                         f"initial front x = {front0:g} m of scene {scene.name}, which the front only leaves "
                         "forwards (wrong units? metres read as millimetres are 1000 x too small)")


def _check_array(name: str, values, n: int | None = None) -> np.ndarray:
    arr = np.asarray(values, float)
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array, got shape {arr.shape}")
    if n is not None and arr.size != n:
        raise ValueError(f"{name} must have {n} values, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr[~np.isfinite(arr)][:3]}")
    return arr


def _targets(profile, front) -> tuple[tuple[ProfileTarget, ...], FrontTarget | None]:
    """The profiles (none, one or a list) and the front as ``ProfileTarget``s and a ``FrontTarget``."""
    if not profile and front is None:
        raise ValueError("give profile and/or front: there is nothing to fit")
    if profile is None:
        profiles = ()
    elif isinstance(profile, (list, tuple)):
        profiles = tuple(profile)
    else:
        profiles = (profile,)
    profiles = tuple(p if isinstance(p, ProfileTarget) else ProfileTarget.of(p) for p in profiles)
    return profiles, front if front is None or isinstance(front, FrontTarget) else FrontTarget.of(front)
