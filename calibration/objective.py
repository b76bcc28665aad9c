"""The calibration objective: a scene, the parameters to fit, and the data the run must match.

An ``Objective`` turns a vector θ of physical parameter values (ordered as ``keys``) into a
vector of residuals, one rollout per evaluation:

- the deposit profile h(x) at the data's own x points, at the profile's time (one profile or
  several at different times), divided by the data's peak height, so a residual of 0.01 is 1 %
  of the peak (data may be noisy, even slightly negative; ``calibration.data`` validates
  measured files);
- the front position at each of the data's times, divided by the initial column length.

Each block is weighted by sqrt(w / m) (m its number of points), so that the loss
Σ r² = w_h mean(r_h²) + w_f mean(r_f²) is a weighted sum of mean squares that does not depend on
how densely the data were sampled. A squared residual has a zero derivative at zero, so an
exact fit has a finite (zero) gradient.

The rollout records only what the residuals need (h at the data points and the front, at the
data times), with the checkpointed blocks of ``jaxmpm.make_rollout``, so reverse-mode memory
stays bounded. ``residuals_and_jacobian`` uses forward mode, one Jacobian column per tangent
pass (``jacobian_by_columns``): on the CPU a ``jax.jacfwd`` batch of n tangents costs more than
n single passes (docs/calibration.md, "Cost").

What is observed (``objective.observations``: the profile's points and times, the front's
times, the kernel and the mirror; ``calibration.observe``) is kept apart from what was measured
(``objective.data``: heights, fronts and the residuals' scales). The jitted pure functions
(``objective.functions``, ``calibration.observe.model_functions``) take the data as arguments,
so objectives that observe the same run the same way share one compilation; their z-variants
map the unconstrained variables through the bounds inside the traced run.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import PARAM_KEYS, validate_params

from .bounds import Bounds
from .observe import BATCHES, Observations, content_key, jacobian_by_columns, model_functions, unwhiten_front

__all__ = ["jacobian_by_columns", "Objective", "CompositeObjective", "ProfileTarget", "FrontTarget", "run_tasks",
           "jacobians_z", "residuals_at", "ResidualLayout", "ProfileBlock", "FrontBlock", "residual_layout"]


def _column_task(config, observations, keys, z, tangent, lower, upper, state, base, data):
    """One forward-mode pass of an objective (``Objective.column_tasks_z``), in any process."""
    r, dr_z, dr, pred = model_functions(config, observations, keys).column_z(z, tangent, lower, upper, state, base,
                                                                              data)
    return np.asarray(r), np.asarray(dr_z), np.asarray(dr), jax.tree.map(np.asarray, pred)


def _residual_task(config, observations, keys, theta, state, base, data):
    """One run of an objective (``Objective.residual_tasks``), in any process."""
    r, pred = model_functions(config, observations, keys).residuals(theta, state, base, data)
    return np.asarray(r), jax.tree.map(np.asarray, pred)


def run_tasks(workers, tasks) -> list:
    """The results of ``(fn, args)`` tasks, computed by ``workers`` (``calibration.workers``)."""
    from .workers import as_workers

    return as_workers(workers).map(_call, tasks)


def _call(fn, args):
    return fn(*args)


def jacobians_z(objective, Z, workers) -> tuple:
    """(r (k, m), dr/dz (k, m, n), dr/dθ (k, m, n), predictions stacked over k) at the rows of
    ``Z`` (k, n): every forward-mode pass of every row, spread over ``workers``."""
    Z = np.atleast_2d(np.asarray(Z))
    per_row = [objective.column_tasks_z(z) for z in Z]
    results = run_tasks(workers, [t for tasks in per_row for t in tasks])
    rows, start = [], 0
    for tasks in per_row:
        rows.append(objective.combine_columns_z(results[start:start + len(tasks)]))
        start += len(tasks)
    r, Jz, J, preds = zip(*rows)
    return np.stack(r), np.stack(Jz), np.stack(J), jax.tree.map(lambda *a: np.stack(a), *preds)


def residuals_at(objective, thetas, workers, seeds=None) -> list[tuple]:
    """[(r, prediction)] at the rows of ``thetas`` (with the particles drawn with ``seeds``,
    row by row, if given), the runs spread over ``workers``."""
    thetas = np.atleast_2d(np.asarray(thetas, float))
    results = run_tasks(workers, objective.residual_tasks(thetas, seeds))
    return objective.combine_residuals(results, thetas.shape[0])


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
        """From a ``calibration.data.Profile`` (or anything with ``x``, ``h`` and ``time_s``)."""
        return cls(np.asarray(data.x, float), np.asarray(data.h, float), getattr(data, "time_s", None),
                   getattr(data, "path", None))


@dataclasses.dataclass(frozen=True)
class FrontTarget:
    """Front positions ``x_front`` (m) at times ``t`` (s); ``source`` as for ``ProfileTarget``.

    ``correlation_time`` (s): the errors of a front history are not independent (the front one
    frame later is mostly where it was, and a model error in its speed persists over frames).
    None (default) treats them as independent; a time τ assumes an exponentially correlated
    (Ornstein–Uhlenbeck, AR(1) at equal spacing) error, corr(e_i, e_j) = exp(−|t_i − t_j|/τ),
    whose precision matrix factorises exactly into the whitened residuals
    (e_i − φ_i e_{i−1}) / sqrt(1 − φ_i²), φ_i = exp(−(t_i − t_{i−1})/τ) (``observe.whiten_front``).
    The fit, its interval and every χ² then use them; ``uncertainty.front_correlation`` estimates
    τ from a fit's residuals (feasible generalised least squares: fit, estimate, refit)."""

    t: np.ndarray
    x_front: np.ndarray
    source: str | None = None
    correlation_time: float | None = None

    @classmethod
    def of(cls, data) -> FrontTarget:
        return cls(np.asarray(data.t, float), np.asarray(data.x_front, float), getattr(data, "path", None))


#: How a block's weight is shared by its rows (``Objective``'s ``weighting``).
WEIGHTINGS = ("block", "row")

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
    if not (_representable(x, dtype) and _representable(h, dtype)):
        raise ValueError(f"{label}: values beyond the range of {np.dtype(dtype).name}, in which the run computes")
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


def _representable(values, dtype) -> bool:
    with np.errstate(over="ignore"):
        return bool(np.all(np.isfinite(np.asarray(values, dtype))))


def _check_front_plausible(label: str, t: np.ndarray, xf: np.ndarray, scene, x_lo: float, x_hi: float, dtype):
    if not (_representable(xf, dtype) and _representable(t, dtype)):
        raise ValueError(f"{label}: values beyond the range of {np.dtype(dtype).name}, in which the run computes")
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


def _digest(*arrays) -> str:
    """A short content hash of float arrays (as float64, so the dtype of the input does not matter)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a, np.float64))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _engine_bounds(bounds: Bounds, params) -> tuple[Bounds, tuple[str, ...]]:
    """``bounds`` narrowed so that every θ inside them keeps the engine's rule μ1 ≤ μ2 with the
    scene's value of the one not fitted (μ1's upper bound at most μ2; μ2's lower at least μ1),
    and a note for each bound that moved. With both fitted the rule is checked per point
    (``Objective.check_thetas``)."""
    lower, upper, notes = list(bounds.lower), list(bounds.upper), []
    keys = bounds.keys
    # (fitted key, the scene's key it is held against, the bound of the fitted key that moves)
    for key, other, side in (("mu1", "mu2", "upper"), ("mu2", "mu1", "lower")):
        if key not in keys or other in keys:
            continue
        i, value = keys.index(key), float(getattr(params, other))
        limits = upper if side == "upper" else lower
        if (limits[i] > value) if side == "upper" else (limits[i] < value):
            verb = "lowered" if side == "upper" else "raised"
            notes.append(f"{key}'s {side} bound {limits[i]:g} {verb} to the scene's {other} = {value:g} (the engine "
                         "needs mu1 <= mu2)")
            limits[i] = value
    for k, lo, hi in zip(keys, lower, upper):
        if not lo < hi:
            raise ValueError(f"bounds[{k!r}]: ({lo:g}, {hi:g}) is empty once mu1 <= mu2 is imposed with the "
                             "scene's other friction coefficient; widen the bound or change the scene's value")
    return Bounds(keys, tuple(lower), tuple(upper)), tuple(notes)


def _at_run_precision(t, dtype):
    """Observation time(s) rounded to the run's float type: the run lands exactly on its frame
    times in that type, so two times that differ only below its precision are one frame. (The
    caller caps them at t_end again: rounding may carry a time just past it.)"""
    rounded = np.asarray(np.asarray(t, float), jnp.dtype(dtype)).astype(float)
    return float(rounded) if rounded.ndim == 0 else rounded


def _check_array(name: str, values, n: int | None = None) -> np.ndarray:
    arr = np.asarray(values, float)
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array, got shape {arr.shape}")
    if n is not None and arr.size != n:
        raise ValueError(f"{name} must have {n} values, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr[~np.isfinite(arr)][:3]}")
    return arr


def _valid(values) -> bool:
    try:
        validate_params(values)
    except ValueError:
        return False
    return True


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


def _checked_weights(weights, weighting: str, profile: bool, front: bool) -> dict[str, float]:
    """The blocks' weights (1 unless given), checked: finite, >= 0, and not 0 for a block that
    has data; ``weighting`` one of ``WEIGHTINGS``."""
    weights = {"profile": 1.0, "front": 1.0, **dict(weights or {})}
    if set(weights) - {"profile", "front"}:
        raise ValueError(f"weights: keys must be 'profile' and 'front', got {sorted(weights)}")
    for name, w in weights.items():
        if not (math.isfinite(w) and w >= 0):
            raise ValueError(f"weights[{name!r}] must be finite and >= 0, got {w!r}")
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    for name, there in (("profile", profile), ("front", front)):
        if there and weights[name] == 0:
            raise ValueError(f"weights[{name!r}] is 0: the {name} data would have no say in the fit (every "
                             f"residual of theirs zero, their noise undefined); leave the {name} out instead")
    return weights


@dataclasses.dataclass(frozen=True)
class ProfileBlock:
    """One profile's rows: its block ``name``, the points ``x`` (m) and measured heights ``h``
    (m), its ``scale`` (the peak height, m: a residual of 0.01 is 1 % of it) and its ``time``
    (s, at the run's precision)."""

    name: str
    x: np.ndarray
    h: np.ndarray
    scale: float
    time: float


@dataclasses.dataclass(frozen=True)
class FrontBlock:
    """The front's rows: times ``t`` (s, at the run's precision), measured positions ``x_front``
    (m) and the whitening factors ``phi`` of its correlated errors
    (``FrontTarget.correlation_time``; zeros: independent)."""

    t: np.ndarray
    x_front: np.ndarray
    phi: np.ndarray


@dataclasses.dataclass(frozen=True)
class ResidualLayout:
    """Where each residual comes from: the ``profiles`` (in order), then the ``front`` (or None);
    ``blocks`` maps each block's name to its rows, ``row_scale`` is every row's weight factor
    sqrt(w / m) ("block" weighting) or sqrt(w) ("row"); ``front_scale`` (m, the column's
    length) divides the front's rows. Built by ``residual_layout``."""

    profiles: tuple[ProfileBlock, ...]
    front: FrontBlock | None
    blocks: Mapping[str, slice]
    row_scale: np.ndarray
    front_scale: float

    @property
    def n_residuals(self) -> int:
        return int(self.row_scale.size)

    def scales(self) -> np.ndarray:
        """Every row's scale (m): its profile's peak height, or the front's length."""
        return np.concatenate([np.full(p.x.size, p.scale) for p in self.profiles]
                              + ([np.full(self.front.t.size, self.front_scale)] if self.front is not None else [])
                              + [np.zeros(0)])

    def data(self, dtype) -> dict[str, jax.Array]:
        """The measured values and scales as the arrays ``calibration.observe``'s functions take
        (``ModelFunctions``' ``data``), in ``dtype``."""
        front = self.front
        as_array = lambda a: jnp.asarray(a, dtype)  # noqa: E731
        return {
            "h": as_array(np.concatenate([p.h for p in self.profiles] + [np.zeros(0)])),
            "h_scale": as_array(np.concatenate([np.full(p.x.size, p.scale) for p in self.profiles] + [np.zeros(0)])),
            "front": as_array(front.x_front if front is not None else np.zeros(0)),
            "front_scale": as_array(self.front_scale),
            "front_phi": as_array(front.phi if front is not None else np.zeros(0)),
            "row_scale": as_array(self.row_scale),
        }


def residual_layout(scene, profiles: Sequence[ProfileTarget], front: FrontTarget | None, *,
                    weights: Mapping[str, float], weighting: str, dtype, check_data: bool = True) -> ResidualLayout:
    """The ``ResidualLayout`` of ``profiles`` and ``front`` against runs of ``scene``: each
    target's arrays checked (finite, matching lengths, times in (0, t_end], increasing front
    times that stay distinct at the run's precision ``dtype``; with ``check_data`` plausible for
    the scene, naming the target's source), its times rounded to the run's precision, and every
    row's weight factor from ``weights`` and ``weighting``."""
    config = scene.config
    t_end = config.t_end
    x_lo = float(config.grid.origin[0])
    x_hi = x_lo + config.grid.cells[0] * config.grid.dx
    blocks, scales, built = {}, [], []
    m = 0
    for i, prof in enumerate(profiles):
        name = "profile" if len(profiles) == 1 else f"profile[{i}]"
        xp = _check_array(f"{name}.x", prof.x)
        hp = _check_array(f"{name}.h", prof.h, xp.size)
        if hp.max() <= 0:
            raise ValueError(f"{name}.h is zero everywhere: there is no deposit to fit")
        if check_data:
            _check_profile_plausible(prof.source or name, xp, hp, scene, x_lo, x_hi, dtype)
        t_prof = t_end if prof.time_s is None else float(prof.time_s)
        if not (0 < t_prof <= t_end * (1 + 1e-9)):
            raise ValueError(f"{name}.time_s = {t_prof} must lie in (0, t_end = {t_end}]: "
                             "raise the scene's t_end (--t-end)")
        built.append(ProfileBlock(name, xp, hp, float(hp.max()), min(_at_run_precision(t_prof, dtype), t_end)))
        blocks[name] = slice(m, m + xp.size)
        scales.append(np.full(xp.size, math.sqrt(weights["profile"] / (xp.size if weighting == "block" else 1))))
        m += xp.size
    front_block = None
    if front is not None:
        tf = _check_array("front.t", front.t)
        xf = _check_array("front.x_front", front.x_front, tf.size)
        if np.any(tf <= 0) or np.any(tf > t_end * (1 + 1e-9)):
            raise ValueError(f"front.t must lie in (0, t_end = {t_end}], got {tf.min()}..{tf.max()}")
        if np.any(np.diff(tf) <= 0):
            raise ValueError("front.t must be strictly increasing")
        if check_data:
            _check_front_plausible(front.source or "front", tf, xf, scene, x_lo, x_hi, dtype)
        tf = np.minimum(_at_run_precision(tf, dtype), t_end)
        if np.any(np.diff(tf) <= 0):
            raise ValueError(f"front.t: two times coincide at the run's precision ({jnp.dtype(dtype).name}); "
                             "space them further apart or run in float64")
        tau = front.correlation_time
        if tau is not None and not (isinstance(tau, (int, float, np.floating)) and math.isfinite(tau) and tau > 0):
            raise ValueError(f"front.correlation_time must be None or a positive number of seconds, got {tau!r}")
        phi = np.zeros(tf.size) if tau is None else np.concatenate([[0.0], np.exp(-np.diff(tf) / float(tau))])
        front_block = FrontBlock(tf, xf, phi)
        blocks["front"] = slice(m, m + tf.size)
        scales.append(np.full(tf.size, math.sqrt(weights["front"] / (tf.size if weighting == "block" else 1))))
        m += tf.size
    return ResidualLayout(tuple(built), front_block, blocks, np.concatenate(scales), float(scene.info.length))


class Objective:
    """Residuals of one scene against a profile and/or a front history (a
    ``calibration.protocol.ObjectiveLike``).

    Parameters
    ----------
    scene: a ``jaxmpm.scenes.Scene`` (its params are the fixed values of the unfitted keys).
    keys: the parameters to fit, in order (any of ``jaxmpm.PARAM_KEYS`` that has bounds).
    profile: a ``ProfileTarget`` (or the loader's ``Profile``), or a list of them at several times.
    front: a ``FrontTarget`` (or the loader's ``FrontHistory``).
    weights: ``{"profile": w_h, "front": w_f}`` (default 1 each).
    weighting: how the rows of a block share its weight: "block" (the default) gives each block
        (a profile, a front history) its weight in total, whatever its length (row scale
        sqrt(w / n)); "row" gives every row the weight (row scale sqrt(w)): the noise-weighted,
        most efficient fit when every row's relative noise is the same, where "block" lets a
        short block (a few top heights) count as much as a long profile.
    sigma: the width of the profile's smoothing kernel (m; default: the particle spacing).
    front_threshold: the height (m) below which the deposit counts as ended, for the front
        (default: half a particle spacing, below the height of one isolated particle).
    x_ref: where the front is measured from (default: the back wall, x = 0).
    mirror: the x where the profile's kernel is mirrored (``deposit_profile``): "back-wall"
        (the default) takes the scene's ``back_face`` (x = 0 for a collapse with a back wall;
        none for one without); None turns the mirror off (the kernel then reads half the height
        at the wall).
    bounds: overrides of ``calibration.bounds.DEFAULT_BOUNDS`` by key.
    check_data: refuse data that cannot come from ``scene`` (a deposit taller than 1.5 columns or
        lower than 1 % of one, more than twice the column's area, material or a front outside the
        grid, values beyond the run's float range), naming the target's ``source``. Turn it off
        only for placeholder targets (the model's own predictions are wanted, not a fit).
    """

    def __init__(self, scene, keys: Sequence[str], *, profile=None, front=None,
                 weights: Mapping[str, float] | None = None, weighting: str = "block", sigma: float | None = None,
                 front_threshold: float | None = None, x_ref: float = 0.0,
                 bounds: Mapping[str, tuple[float, float]] | None = None, jacobian: str = "ad",
                 fd_step: float = 1e-2, check_data: bool = True, mirror: float | str | None = "back-wall"):
        keys = tuple(keys)
        # What the constructor was given beyond the scene: ``at_dx`` rebuilds from it.
        self._options = dict(profile=profile, front=front, weights=weights, weighting=weighting, sigma=sigma,
                             front_threshold=front_threshold, x_ref=x_ref, bounds=bounds, jacobian=jacobian,
                             fd_step=fd_step, check_data=check_data, mirror=mirror)
        if jacobian not in ("ad", "fd"):
            raise ValueError(f"jacobian must be 'ad' or 'fd', got {jacobian!r}")
        if not (math.isfinite(fd_step) and 0 < fd_step < 0.5):
            raise ValueError(f"fd_step must be in (0, 0.5), got {fd_step!r}")
        self.jacobian, self.fd_step = jacobian, float(fd_step)
        bad = [k for k in keys if k not in PARAM_KEYS]
        if bad:
            raise ValueError(f"keys: unknown parameter(s) {bad}; valid keys are {list(PARAM_KEYS)}")
        self.bounds = Bounds.create(keys, bounds)
        self.keys = keys
        self.profiles, self.front = _targets(profile, front)
        self.weights = _checked_weights(weights, weighting, bool(self.profiles), self.front is not None)
        self.weighting = weighting

        self.scene = scene
        self.bounds, self.bound_notes = _engine_bounds(self.bounds, scene.params)
        config = scene.config
        info = scene.info
        spacing = config.grid.dx / info.ppc
        self.sigma = float(sigma) if sigma is not None else spacing
        self.front_threshold = float(front_threshold) if front_threshold is not None else 0.5 * spacing
        for name, value in (("sigma", self.sigma), ("front_threshold", self.front_threshold)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        self.x_ref = float(x_ref)
        if isinstance(mirror, str):
            if mirror != "back-wall":
                raise ValueError(f"mirror must be 'back-wall', None or a wall's x (m), got {mirror!r}")
            mirror = getattr(scene, "back_face", None)
        elif mirror is not None and not math.isfinite(float(mirror)):
            raise ValueError(f"mirror must be finite, got {mirror!r}")
        self.mirror = None if mirror is None else float(mirror)
        self.length = float(info.length)
        width = info.width if info.dim == 3 else None

        self.dtype = jnp.result_type(scene.params.E)
        self.layout = residual_layout(scene, self.profiles, self.front, weights=self.weights, weighting=weighting,
                                      dtype=self.dtype, check_data=check_data)
        self.blocks, self.row_scale = dict(self.layout.blocks), self.layout.row_scale
        self.n_residuals = self.layout.n_residuals
        front = self.layout.front
        # Uniform points for the front integral: from x_ref to the far edge of the grid.
        upper = config.grid.origin[0] + config.grid.cells[0] * config.grid.dx
        # Where and when the run is observed (no measured value), and what was measured.
        self.observations = Observations(
            profile_x=tuple(p.x for p in self.layout.profiles),
            profile_times=tuple(p.time for p in self.layout.profiles),
            front_times=None if front is None else front.t,
            front_points=np.arange(self.x_ref, upper, 0.5 * spacing), sigma=self.sigma,
            front_threshold=self.front_threshold, x_ref=self.x_ref, mirror=self.mirror, width=width)
        self.data = self.layout.data(self.dtype)
        self.times = self.observations.times  # the run's frame times
        self._model_key = (config, self.observations, self.keys)  # what a worker rebuilds the functions from
        self.functions = model_functions(*self._model_key)
        self.config = self.functions.config
        self._state = scene.state
        self._base = scene.params

    # ---- pure functions of (theta, state, base params) ------------------------------------
    def params_of(self, theta, base=None):
        """The full ``Params`` with the fitted keys set from θ (physical values)."""
        base = self._base if base is None else base
        theta = jnp.asarray(theta, self.dtype)
        return base.replace(**{k: theta[i] for i, k in enumerate(self.keys)})

    def arguments(self, state=None) -> tuple:
        """``(state, base params, data)``: the arguments after θ (or z, lower, upper) of
        ``functions``' members for this objective (``state``: another initial state)."""
        return (self._state if state is None else state), self._base, self.data

    def lower_upper(self):
        """The bounds as arrays of the run's dtype, the ``lower, upper`` of ``functions.jacobian_z``."""
        return jnp.asarray(self.bounds.lower, self.dtype), jnp.asarray(self.bounds.upper, self.dtype)

    @property
    def members(self) -> tuple[Objective]:
        """The single objectives this one is made of: itself (``calibration.protocol``)."""
        return (self,)

    @property
    def sampling_seed(self) -> int | None:
        """The seed of the scene's own particle draw; None where its sampling has no seed (a lattice)."""
        return int(self.scene.info.seed) if self.seeded else None

    def batched_jacobian_z(self) -> Callable:
        """``Z (k, n) -> (r, dr/dz, dr/dθ, prediction)`` stacked over the rows of Z: the model
        functions' ``batched_jacobian_z`` (compiled once per configuration, observations and
        keys, ``calibration.observe.MODEL_FUNCTIONS``) at this objective's bounds and data."""
        lower, upper = self.lower_upper()
        args = self.arguments()
        functions = self.functions

        def batched(Z):
            Jz, J, (r, pred) = functions.batched_jacobian_z(Z, lower, upper, *args)
            return r, Jz, J, pred

        return batched

    # ---- the public calls (jitted once per objective; new θ never recompiles) --------------
    def residual_fn(self, theta):
        """Pure, unjitted θ -> (r, prediction): for ``jax.vmap`` and sweeps."""
        return self.functions.residual(theta, *self.arguments())

    def predict(self, theta):
        """The model's observations at θ, no data involved: {"status", "h" (every profile's
        points, concatenated), "front" (at the front's times)}."""
        return self.functions.predictions(self.as_theta(theta), self._state, self._base)

    def residuals(self, theta):
        """(r, prediction) at θ. ``prediction`` holds ``status`` and the modelled ``h``/``front``."""
        return self.functions.residuals(self.as_theta(theta), *self.arguments())

    def residuals_resampled(self, theta, seed: int):
        """(r, prediction) at θ with the scene's particles sampled with ``seed`` instead
        (``Scene.resampled``): the same objective on another draw of the same body."""
        return self.functions.residuals(self.as_theta(theta), *self.arguments(self.scene.resampled(seed)))

    def at_dx(self, dx: float) -> Objective:
        """The same objective (keys, data, weights, bounds, options) on the scene rebuilt at grid
        spacing ``dx`` (``Scene.at_dx``). A smoothing width or front threshold that was not given
        follows the new particle spacing, as a fit at that ``dx`` would have it."""
        return Objective(self.scene.at_dx(dx), self.keys, **self._options)

    @classmethod
    def from_experiment(cls, experiment, keys: Sequence[str] | None = None, *,
                        front_correlation_time: float | None = None, **options) -> Objective:
        """The objective of a ``jaxmpm.Experiment``: its scene, its measurements
        (``calibration.data.load_measurements``; ``profile=``/``front=`` replace them), the keys of
        its [fit] table (or ``keys``) and its blocks' weights (``weights=`` over them, block by
        block: a block given None keeps the file's); the front's correlation time is the file's
        unless ``front_correlation_time`` is given; ``options`` as for ``Objective``. What
        ``python -m calibration fit EXPERIMENT.toml`` fits."""
        from .data import load_measurements

        spec = experiment.fit
        if keys is None:
            if spec is None:
                raise ValueError(f"{experiment.path or experiment.name}: no [fit] keys; pass keys")
            keys = spec.keys
        if options.get("profile") is None and options.get("front") is None:
            profiles, front = load_measurements(experiment)
            options.update(profile=profiles or None, front=front)
            if not profiles and front is None:
                raise ValueError(f"{experiment.path or experiment.name}: lists no measurement ([[profile]] or "
                                 "[front])")
        given = dict(options.get("weights") or {})
        filed = {"profile": spec.weight_profile, "front": spec.weight_front} if spec is not None else {}
        if filed or given:
            options["weights"] = {k: given[k] if given.get(k) is not None else filed.get(k, 1.0)
                                  for k in ("profile", "front")}
        front = options.get("front")
        if front is not None and front_correlation_time is not None:
            target = front if isinstance(front, FrontTarget) else FrontTarget.of(front)
            options["front"] = dataclasses.replace(target, correlation_time=front_correlation_time)
        elif (front is not None and experiment.front is not None and experiment.front.correlation_time is not None
              and not isinstance(front, FrontTarget)):
            options["front"] = dataclasses.replace(FrontTarget.of(front),
                                                   correlation_time=experiment.front.correlation_time)
        return cls(experiment.scene(), keys, **options)

    @property
    def dx(self) -> float:
        """The scene's grid spacing, m."""
        return float(self.scene.config.grid.dx)

    @property
    def seeded(self) -> bool:
        """Whether the scene's particles can be drawn again with another seed."""
        return getattr(self.scene, "sampler", None) is not None

    def coarsened(self, ratio: float) -> Objective:
        """The same objective on a grid ``ratio`` times coarser (``at_dx``): the grid term's
        coarse run (``calibration.uncertainty.grid_shift``)."""
        return self.at_dx(ratio * self.dx)

    def residuals_and_jacobian_z(self, z, bounds: Bounds | None = None):
        """(r, dr/dz, dr/dθ, prediction) at the unconstrained z of ``bounds`` (default: the
        objective's), θ = ``bounds.to_physical(z)`` inside the traced run (forward mode): both
        Jacobians from one trace (dr/dθ infinite where z saturates a bound, dθ/dz = 0)."""
        bounds = self.bounds if bounds is None else bounds
        lower, upper = (jnp.asarray(b, self.dtype) for b in (bounds.lower, bounds.upper))
        Jz, J, (r, pred) = self.functions.jacobian_z(self.as_theta(z, "z"), lower, upper, *self.arguments())
        return r, Jz, J, pred

    def column_tasks_z(self, z, bounds: Bounds | None = None) -> list[tuple]:
        """The forward-mode passes of dr/dz at z, one per key, as tasks ``(fn, args)`` for
        ``calibration.workers``; ``combine_columns_z`` assembles their results."""
        bounds = self.bounds if bounds is None else bounds
        z = np.asarray(self.as_theta(z, "z"))
        lower, upper = (np.asarray(b, self.dtype) for b in (bounds.lower, bounds.upper))
        args = jax.tree.map(np.asarray, self.arguments())
        eye = np.eye(len(self.keys), dtype=z.dtype)
        return [(_column_task, (*self._model_key, z, eye[j], lower, upper, *args)) for j in range(len(self.keys))]

    @staticmethod
    def combine_columns_z(results) -> tuple:
        """(r, dr/dz, dr/dθ, prediction) from the results of ``column_tasks_z`` (the residuals and
        the prediction of the first pass: every pass computes the same primal)."""
        return (results[0][0], np.stack([col[1] for col in results], axis=-1),
                np.stack([col[2] for col in results], axis=-1), results[0][3])

    def residual_tasks(self, thetas, seeds=None) -> list[tuple]:
        """Runs at the rows of ``thetas`` (each with the scene's particles, or drawn with the
        matching entry of ``seeds``) as tasks for ``calibration.workers``: (r, prediction) each."""
        tasks = []
        for i, theta in enumerate(np.atleast_2d(np.asarray(thetas, float))):
            state = self._state if seeds is None else self.scene.resampled(int(seeds[i]))
            args = jax.tree.map(np.asarray, self.arguments(state))
            tasks.append((_residual_task, (*self._model_key, np.asarray(self.as_theta(theta)), *args)))
        return tasks

    @staticmethod
    def combine_residuals(results, rows: int) -> list[tuple]:
        """Per row, (r, prediction) from the results of ``residual_tasks``."""
        return list(results)

    def residuals_and_jacobian(self, theta, jacobian: str | None = None):
        """(r, J, prediction) at θ, with J = dr/dθ (m × n) from forward-mode autodiff
        (``jacobian="ad"``, the default) or from central differences with relative steps
        ``fd_step`` (``"fd"``: 2n + 1 runs in one vmapped batch). Autodiff is exact for the
        discrete run; in long, violent flows (tall columns) that derivative can be dominated by
        the run's chaotic sensitivity and no longer describe the trend over finite steps: then
        use "fd" (``check_jacobian`` compares the two)."""
        theta = self.as_theta(theta)
        if (jacobian or self.jacobian) == "ad":
            J, (r, pred) = self.functions.jacobian(theta, *self.arguments())
            return r, J, pred
        steps = self._fd_steps(theta)
        n = len(self.keys)
        eye = jnp.eye(n, dtype=self.dtype) * steps[None, :]
        batch = jnp.concatenate([theta[None, :], theta[None, :] + eye, theta[None, :] - eye])
        rs, preds = self.functions.batched(batch, *self.arguments())
        J = ((rs[1:n + 1] - rs[n + 1:]) / (2.0 * steps[:, None])).T
        pred = jax.tree.map(lambda a: a[0], preds)
        pred["status"] = jnp.bitwise_or.reduce(preds["status"])
        return rs[0], J, pred

    def in_metres(self, r) -> dict[str, np.ndarray]:
        """The weighted residuals ``r`` back in metres (model − data), by block: profile heights
        and front positions."""
        e = np.asarray(r, float) / self.row_scale
        if self.layout.front is not None:  # the front's rows are whitened (FrontTarget.correlation_time): undo it
            e = e.copy()
            e[self.blocks["front"]] = unwhiten_front(e[self.blocks["front"]], self.layout.front.phi)
        metres = e * self.layout.scales()
        return {name: metres[sl] for name, sl in self.blocks.items()}

    def _fd_steps(self, theta):
        span = jnp.asarray(self.bounds.upper, self.dtype) - jnp.asarray(self.bounds.lower, self.dtype)
        return self.fd_step * jnp.maximum(jnp.abs(theta), 0.01 * span)

    def check_jacobian(self, theta) -> dict[str, Any]:
        """Autodiff against central differences (relative step ``fd_step``) at θ: both Jacobians
        and, per key, the relative difference of their columns."""
        _, J_ad, _ = self.residuals_and_jacobian(theta, "ad")
        _, J_fd, _ = self.residuals_and_jacobian(theta, "fd")
        J_ad, J_fd = np.asarray(J_ad, float), np.asarray(J_fd, float)
        diff = np.linalg.norm(J_ad - J_fd, axis=0) / np.maximum(np.linalg.norm(J_fd, axis=0), 1e-300)
        return {"ad": J_ad, "fd": J_fd, "rel_diff": dict(zip(self.keys, diff.tolist()))}

    def value_and_grad(self, theta):
        """((loss, prediction), dloss/dθ) from reverse mode through the checkpointed rollout."""
        return self.functions.value_and_grad(self.as_theta(theta), *self.arguments())

    def loss(self, theta) -> float:
        r, _ = self.residuals(theta)
        return float(jnp.sum(r * r))

    def as_theta(self, theta, name: str = "theta"):
        """``theta`` as an array of the run's dtype, its shape checked against ``keys``."""
        theta = jnp.asarray(theta, self.dtype)
        if theta.shape != (len(self.keys),):
            raise ValueError(f"{name} must have shape ({len(self.keys)},) for keys {self.keys}, got {theta.shape}")
        return theta

    def initial(self) -> dict[str, float]:
        """The scene's values of the fitted keys."""
        return {k: float(getattr(self._base, k)) for k in self.keys}

    def expand(self, values: Mapping[str, float]) -> dict[str, float]:
        """Values by key as values of this objective's keys (``CompositeObjective.expand`` spreads
        a plain key over the experiments; here every key is its own)."""
        stray = [k for k in values if k not in self.keys]
        if stray:
            raise ValueError(f"{stray[0]!r} is not fitted (keys: {list(self.keys)})")
        return {k: float(v) for k, v in values.items()}

    def check_thetas(self, thetas, name: str = "thetas") -> None:
        """Raise ``ValueError`` unless every row of ``thetas`` (B, n), with the scene's values for
        the other keys, passes ``jaxmpm.validate_params`` (the rules ``python -m jaxmpm run --set``
        applies): a member with β < 0 or μ2 < μ1 is not a parameter set of the model, and a loss
        computed for it must not be reported. Names up to three offending rows."""
        thetas = np.asarray(thetas, float)
        if thetas.ndim == 1:
            thetas = thetas[None, :]
        if thetas.ndim != 2 or thetas.shape[1] != len(self.keys):
            raise ValueError(f"{name} must have shape (B, {len(self.keys)}) for keys {self.keys}, got {thetas.shape}")
        base = {k: np.full(thetas.shape[0], float(v)) for k, v in self._base.to_dict().items()}
        values = {**base, **{k: thetas[:, j] for j, k in enumerate(self.keys)}}
        try:
            validate_params(values)
            return
        except ValueError:
            pass
        bad = []
        for i in range(thetas.shape[0]):
            try:
                validate_params({k: v[i] for k, v in values.items()})
            except ValueError as err:
                bad.append((i, err))
                if len(bad) == 3:
                    break
        count = sum(1 for i in range(thetas.shape[0]) if not _valid({k: v[i] for k, v in values.items()}))
        rows = "; ".join(f"member {i} ({', '.join(f'{k} = {thetas[i, j]:g}' for j, k in enumerate(self.keys))}): "
                         f"{err}" for i, err in bad)
        what = "the member is" if thetas.shape[0] == 1 else f"{count} of {thetas.shape[0]} members are"
        raise ValueError(f"{name}: {what} not a valid parameter set: {rows}")

    def fingerprint(self) -> dict[str, Any]:
        """What this objective's loss and its optimiser steps depend on, as a JSON-able dict: the
        data's content (a hash; file names do not matter), the scene and its geometry, the fixed
        parameters, weights, smoothing, front threshold, bounds, dtype, the Jacobian's kind, the
        initial particles and the whole run configuration (hashed). Two objectives with equal
        fingerprints compute the same residuals; ``fit`` refuses to resume a history made for
        another one."""
        data = [a for p in self.layout.profiles for a in (p.x, p.h, [p.time])]
        if self.layout.front is not None:
            data += [self.layout.front.t, self.layout.front.x_front]
            if self.front.correlation_time is not None:  # (absent when None: older histories still match)
                data += [[float(self.front.correlation_time)]]
        info = self.scene.info
        config = json.dumps(self.config.to_dict(), sort_keys=True, default=str)
        return {
            "scene": self.scene.name, "data": _digest(*data), "keys": list(self.keys),
            "dx": float(self.config.grid.dx), "ppc": info.ppc, "sampling": info.sampling,
            "seed": info.seed, "dim": info.dim, "width": info.width,
            "slope_deg": info.slope_deg, "L": info.length, "H": info.height,
            "t_end": float(self.config.t_end),
            "fixed": {k: float(v) for k, v in self._base.to_dict().items() if k not in self.keys},
            "weights": {k: float(v) for k, v in self.weights.items()}, "sigma": self.sigma,
            **({"weighting": self.weighting} if self.weighting != "block" else {}),  # older files: "block"
            "front_threshold": self.front_threshold, "x_ref": self.x_ref, "mirror": self.mirror,
            "bounds": {k: [lo, hi] for k, lo, hi in zip(self.keys, self.bounds.lower, self.bounds.upper)},
            "dtype": np.dtype(self.dtype).name, "jacobian": self.jacobian, "fd_step": self.fd_step,
            "n_particles": int(self._state.x.shape[0]),
            "particles": _digest(self._state.x, self._state.vol0),
            "config": hashlib.sha256(config.encode()).hexdigest()[:16],
        }

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (scene, data sizes, weights), for history files."""
        return {"scene": self.scene.name, "keys": list(self.keys), "times": list(self.times),
                "n_profile": [int(p.x.size) for p in self.layout.profiles],
                "n_front": int(self.layout.front.t.size) if self.layout.front is not None else 0,
                "weights": self.weights, "weighting": self.weighting, "sigma": self.sigma,
                "front_threshold": self.front_threshold,
                "dx": self.config.grid.dx, "n_particles": int(self._state.x.shape[0]),
                "bounds": {k: [lo, hi] for k, lo, hi in zip(self.keys, self.bounds.lower, self.bounds.upper)},
                "bound_notes": list(self.bound_notes),
                "fixed": {k: float(v) for k, v in self._base.to_dict().items() if k not in self.keys}}


def _shared_layout(members, shared: tuple[str, ...], labels) -> tuple[tuple[str, ...], list[np.ndarray]]:
    """The composite's keys (the shared ones, then each member's own as ``key@label``) and where
    each member's keys sit among them."""
    labels = tuple(str(label) for label in (labels or ()))
    if len(labels) != len(members) or len(set(labels)) != len(labels) or not all(labels):
        raise ValueError(f"labels: one distinct, non-empty label per member is needed ({len(members)} members), "
                         f"got {list(labels)}")
    if len(set(shared)) != len(shared):
        raise ValueError(f"shared: a key is repeated in {list(shared)}")
    for i, m in enumerate(members):
        missing = [k for k in shared if k not in m.keys]
        if missing:
            raise ValueError(f"shared: {missing} are not fitted by members[{i}] ({labels[i]}: {list(m.keys)})")
    keys = list(shared)
    index = []
    for m, label in zip(members, labels):
        idx = []
        for k in m.keys:
            if k not in shared:
                keys.append(f"{k}@{label}")
            idx.append(keys.index(k if k in shared else f"{k}@{label}"))
        index.append(np.asarray(idx, int))
    return tuple(keys), index


class CompositeObjective:
    """Several objectives fitted together (e.g. one scene per aspect ratio): the residuals are
    concatenated, so the loss is the sum of the members' losses (a
    ``calibration.protocol.ObjectiveLike``).

    By default the members fit the same keys, one value each for all. ``shared`` (with
    ``labels``, one per member) lets keys differ by experiment: a key in ``shared`` is one value
    for every member; any other key a member fits is that member's own, named ``key@label`` in
    the composite's keys (``CompositeObjective.sharing``), and its residual blocks are named
    ``label/block`` (else ``i/block``). The members' Jacobians are scattered into the
    composite's columns; a member's column for another member's own key is zero."""

    def __init__(self, members: Sequence[Objective], shared: Sequence[str] | None = None,
                 labels: Sequence[str] | None = None):
        members = tuple(members)
        if not members:
            raise ValueError("members: at least one objective is needed")
        if shared is None:
            keys = members[0].keys
            for i, m in enumerate(members):
                if m.keys != keys:
                    raise ValueError(f"members[{i}] fits {m.keys}, members[0] fits {keys}; say which keys are "
                                     "shared (shared=, --shared) to fit the others per experiment")
            index = [np.arange(len(keys))] * len(members)
            labels = None
        else:
            keys, index = _shared_layout(members, tuple(shared), labels)
        self.members, self.keys, self.shared, self.labels = members, tuple(keys), shared, labels
        self._index = tuple(np.asarray(i, int) for i in index)  # member i's keys at these composite positions
        # The box every member accepts (their bounds differ only where a scene's μ1 or μ2 narrowed them).
        lower = np.full(len(self.keys), -np.inf)
        upper = np.full(len(self.keys), np.inf)
        for m, idx in zip(members, self._index):
            lower[idx] = np.maximum(lower[idx], m.bounds.lower)
            upper[idx] = np.minimum(upper[idx], m.bounds.upper)
        if np.any(lower >= upper):
            raise ValueError("members: their bounds do not overlap (each member's scene narrows mu1 or mu2 to keep "
                             "mu1 <= mu2); fit scenes with compatible friction coefficients")
        self.bounds = Bounds(self.keys, tuple(float(v) for v in lower), tuple(float(v) for v in upper))
        self.bound_notes = tuple(note for m in members for note in m.bound_notes)
        self.dtype = members[0].dtype
        offsets = np.cumsum([0] + [m.n_residuals for m in members])
        self.n_residuals = int(offsets[-1])
        self._prefix = tuple(labels) if labels is not None else tuple(str(i) for i in range(len(members)))
        self.blocks = {f"{self._prefix[i]}/{name}": slice(offsets[i] + s.start, offsets[i] + s.stop)
                       for i, m in enumerate(members) for name, s in m.blocks.items()}
        self.row_scale = np.concatenate([m.row_scale for m in members])
        #: The composite's Jacobians are forward-mode autodiff through the members' runs.
        self.jacobian = "ad"

    @classmethod
    def sharing(cls, members: Sequence[Objective], shared: Sequence[str], labels: Sequence[str]):
        """Members that share the keys in ``shared`` and fit the rest of their keys each for
        itself (named ``key@label``)."""
        return cls(members, shared=shared, labels=labels)

    def expand(self, values: Mapping[str, float]) -> dict[str, float]:
        """Values by plain key (``beta``) as values of the composite's keys: a shared key as it
        is, a member's own key (``beta@label``) from the plain one; a composite key passes."""
        out = {}
        for k, v in values.items():
            if k in self.keys:
                out[k] = float(v)
                continue
            own = [c for c in self.keys if c.split("@")[0] == k]
            if not own:
                raise ValueError(f"{k!r} is not fitted (keys: {list(self.keys)})")
            out.update({c: float(v) for c in own})
        return out

    def _member_theta(self, theta, i: int):
        """Member ``i``'s θ (or z) from the composite's: θ itself when every member fits the same
        keys, else its keys' entries (numpy stays numpy, a traced array stays traced)."""
        if self.shared is None:
            return theta
        idx = self._index[i]
        return theta[..., idx] if isinstance(theta, jax.Array) else np.asarray(theta)[..., idx]

    def _member_bounds(self, i: int) -> Bounds:
        if self.shared is None:
            return self.bounds
        idx = self._index[i]
        return Bounds(self.members[i].keys, tuple(self.bounds.lower[j] for j in idx),
                      tuple(self.bounds.upper[j] for j in idx))

    def _joined(self, outs) -> tuple:
        """The members' outputs, each ``(r, prediction)``, ``(r, J, prediction)`` or ``(r, J_z, J,
        prediction)``, as the composite's: the residuals concatenated, the Jacobians scattered into
        the composite's columns (``_scatter``), the predictions as ``{"status": every member's bits OR-ed,
        "members": [each member's]}``. numpy in, numpy out; anything else (traced) in jnp."""
        xp = np if all(isinstance(o[0], np.ndarray) for o in outs) else jnp
        preds = [o[-1] for o in outs]
        status = xp.bitwise_or.reduce(xp.stack([xp.asarray(p["status"]) for p in preds]))
        r = xp.concatenate([xp.asarray(o[0]) for o in outs])
        pred = {"status": status, "members": preds}
        return (r, *(self._scatter([o[j] for o in outs]) for j in range(1, len(outs[0]) - 1)), pred)

    def _scatter(self, jacobians):
        """The members' Jacobians (rows × their own keys) stacked as the composite's (rows ×
        keys), numpy in, numpy out."""
        xp = np if all(isinstance(J, np.ndarray) for J in jacobians) else jnp
        if self.shared is None:
            return xp.concatenate(jacobians)
        blocks = []
        for J, idx in zip(jacobians, self._index):
            full = np.zeros(J.shape[:-1] + (len(self.keys),), J.dtype)
            if xp is np:
                full[..., idx] = J
            else:
                full = jnp.zeros(J.shape[:-1] + (len(self.keys),), J.dtype).at[..., idx].set(J)
            blocks.append(full)
        return xp.concatenate(blocks)

    @property
    def dx(self) -> float:
        """The first member's grid spacing, m (the grid term coarsens every member by one ratio)."""
        return self.members[0].dx

    @property
    def seeded(self) -> bool:
        return all(m.seeded for m in self.members)

    def coarsened(self, ratio: float) -> CompositeObjective:
        """Every member on a grid ``ratio`` times coarser (``Objective.coarsened``)."""
        return CompositeObjective([m.coarsened(ratio) for m in self.members], self.shared, self.labels)

    def residuals_resampled(self, theta, seed: int):
        """The members' residuals at θ with every scene's particles drawn with ``seed``."""
        return self._joined([m.residuals_resampled(self._member_theta(theta, i), seed)
                             for i, m in enumerate(self.members)])

    @property
    def sampling_seed(self) -> None:
        """None: the members' particles are not one draw of one scene (``calibration.protocol``)."""
        return None

    def batched_jacobian_z(self) -> Callable:
        """``Z (k, n) -> (r, dr/dz, dr/dθ, prediction)`` stacked over the rows of Z (the
        composite's bounds): one jit(vmap(...)) of the members' concatenated runs, kept in
        ``calibration.observe.BATCHES`` by the composite's content (``content_key``)."""
        bounds = self.bounds

        def member(z):
            Jz, (r, pred) = jacobian_by_columns(lambda z_: self.residual_fn(bounds.to_physical(z_)), z)
            return r, Jz, Jz / bounds.jacobian_diag(z)[None, :], pred

        content = content_key(self)
        return BATCHES.get(None if content is None else ("search", content), lambda: jax.jit(jax.vmap(member)))

    def residual_fn(self, theta):
        """Pure, unjitted θ -> (r, prediction), the members' concatenated: for ``jax.vmap``."""
        return self._joined([m.residual_fn(self._member_theta(theta, i)) for i, m in enumerate(self.members)])

    def in_metres(self, r) -> dict[str, np.ndarray]:
        """The residuals in metres by block (``Objective.in_metres`` of each member)."""
        r = np.asarray(r, float)
        offsets = np.cumsum([0] + [m.n_residuals for m in self.members])
        return {f"{self._prefix[i]}/{name}": v for i, m in enumerate(self.members)
                for name, v in m.in_metres(r[offsets[i]:offsets[i + 1]]).items()}

    def residuals(self, theta):
        return self._joined([m.residuals(self._member_theta(theta, i)) for i, m in enumerate(self.members)])

    def residuals_and_jacobian_z(self, z):
        """(r, dr/dz, dr/dθ, prediction) at the unconstrained z of the composite's bounds (every
        member maps z with the composite's bounds, not its own)."""
        return self._joined([m.residuals_and_jacobian_z(self._member_theta(z, i), self._member_bounds(i))
                             for i, m in enumerate(self.members)])

    def column_tasks_z(self, z) -> list[tuple]:
        """Every member's forward-mode passes at z (the composite's bounds), members in order."""
        return [task for i, m in enumerate(self.members)
                for task in m.column_tasks_z(self._member_theta(z, i), self._member_bounds(i))]

    def combine_columns_z(self, results) -> tuple:
        starts = np.cumsum([0] + [len(idx) for idx in self._index])
        outs = [Objective.combine_columns_z(results[a:b]) for a, b in zip(starts[:-1], starts[1:])]
        return self._joined([(np.asarray(r), np.asarray(Jz), np.asarray(J), pred) for r, Jz, J, pred in outs])

    def residual_tasks(self, thetas, seeds=None) -> list[tuple]:
        return [task for i, m in enumerate(self.members)
                for task in m.residual_tasks(self._member_theta(thetas, i), seeds)]

    def combine_residuals(self, results, rows: int) -> list[tuple]:
        """Per row, the members' (r, prediction) of ``residual_tasks`` combined."""
        members = range(len(self.members))
        return [self._joined([(np.asarray(results[j * rows + i][0]), results[j * rows + i][1]) for j in members])
                for i in range(rows)]

    def residuals_and_jacobian(self, theta):
        return self._joined([m.residuals_and_jacobian(self._member_theta(theta, i))
                             for i, m in enumerate(self.members)])

    def value_and_grad(self, theta):
        outs = [m.value_and_grad(self._member_theta(theta, i)) for i, m in enumerate(self.members)]
        loss = sum(o[0][0] for o in outs)
        status = jnp.bitwise_or.reduce(jnp.stack([o[0][1]["status"] for o in outs]))
        if self.shared is None:
            return (loss, {"status": status}), sum(o[1] for o in outs)
        grad = jnp.zeros(len(self.keys), jnp.result_type(outs[0][1]))
        for (_, g), idx in zip(outs, self._index):
            grad = grad.at[idx].add(g)
        return (loss, {"status": status}), grad

    def loss(self, theta) -> float:
        return sum(m.loss(self._member_theta(theta, i)) for i, m in enumerate(self.members))

    def initial(self) -> dict[str, float]:
        """Each composite key's scene value (a shared key's from the first member fitting it)."""
        out = {}
        for m, idx in zip(self.members, self._index):
            values = m.initial()
            for k, j in zip(m.keys, idx):
                out.setdefault(self.keys[j], values[k])
        return {k: out[k] for k in self.keys}

    def check_thetas(self, thetas, name: str = "thetas") -> None:
        for i, member in enumerate(self.members):
            member.check_thetas(self._member_theta(thetas, i), name)

    def fingerprint(self) -> dict[str, Any]:
        out = {"members": [m.fingerprint() for m in self.members]}
        if self.shared is not None:
            out.update(shared=list(self.shared), labels=list(self.labels), keys=list(self.keys))
        return out

    def describe(self) -> dict[str, Any]:
        out = {"members": [m.describe() for m in self.members], "keys": list(self.keys)}
        if self.shared is not None:
            out.update(shared=list(self.shared), labels=list(self.labels))
        return out
