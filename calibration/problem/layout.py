"""Where each residual comes from and how much it weighs: the rows of every profile and of the front
(``ResidualLayout``), built from the targets against one scene (``residual_layout``), and the
measured values as the pytree of arrays the pure residual functions take (``ResidualLayout.data``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .options import WEIGHTINGS
from .targets import FrontTarget, ProfileTarget, _check_array, _check_front_plausible, _check_profile_plausible

__all__ = ["ProfileBlock", "FrontBlock", "ResidualLayout", "residual_layout"]


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
        """The measured values and scales as the arrays the model functions take (``ModelFunctions``'
        ``data``), in ``dtype``."""
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


def _at_run_precision(t, dtype):
    """Observation time(s) rounded to the run's float type: the run lands exactly on its frame
    times in that type, so two times that differ only below its precision are one frame. (The
    caller caps them at t_end again: rounding may carry a time just past it.)"""
    rounded = np.asarray(np.asarray(t, float), jnp.dtype(dtype)).astype(float)
    return float(rounded) if rounded.ndim == 0 else rounded


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
