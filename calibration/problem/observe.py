"""What a calibration run observes (``Observations``: where, when and how; no measured value),
and the whitening of a front's exponentially correlated residuals (``whiten_front``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from jaxmpm.observables import deposit_profile, front_from_profile, particle_volumes

__all__ = ["Observations", "unwhiten_front", "whiten_front"]


def _frozen(a) -> np.ndarray:
    a = np.array(a, float)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class Observations:
    """Where and when a run is observed.

    profile_x: the x points (m) of each profile; profile_times: the time (s) of each.
    front_times: the times (s) of the front (None: no front). front_points: the uniform x (m)
    on which the front's profile is read (``jaxmpm.observables.front_from_profile``).
    sigma: the profile kernel's width (m); front_threshold: the height (m) below which the
    deposit has ended; x_ref: where the front is measured from (m); mirror: the x (m) where
    the kernel is mirrored (None: nowhere); width: the channel width (m) of a 3D run (None in
    2D). Equal observations (by content) compile to the same functions."""

    profile_x: tuple[np.ndarray, ...]
    profile_times: tuple[float, ...]
    front_times: np.ndarray | None
    front_points: np.ndarray
    sigma: float
    front_threshold: float
    x_ref: float = 0.0
    mirror: float | None = None
    width: float | None = None

    def __post_init__(self):
        set_ = functools.partial(object.__setattr__, self)
        set_("profile_x", tuple(_frozen(x) for x in self.profile_x))
        set_("profile_times", tuple(float(t) for t in self.profile_times))
        set_("front_times", None if self.front_times is None else _frozen(self.front_times))
        set_("front_points", _frozen(self.front_points))
        if len(self.profile_x) != len(self.profile_times):
            raise ValueError(f"profile_times: {len(self.profile_times)} times for {len(self.profile_x)} profiles")
        if not self.profile_x and self.front_times is None:
            raise ValueError("observations: no profile and no front: nothing is observed")

    @property
    def times(self) -> tuple[float, ...]:
        """Every observation time, sorted, each once: the run's frame times."""
        front = () if self.front_times is None else tuple(float(t) for t in self.front_times)
        return tuple(sorted(set(self.profile_times) | set(front)))

    def _key(self):
        arrays = self.profile_x + ((self.front_times,) if self.front_times is not None else ()) + (self.front_points,)
        return (tuple((a.shape, a.tobytes()) for a in arrays), self.profile_times, self.front_times is None,
                self.sigma, self.front_threshold, self.x_ref, self.mirror, self.width)

    def __eq__(self, other):
        return isinstance(other, Observations) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    def observer(self) -> Callable:
        """``(state, params) -> {"h": heights at every profile's points, "front": front x}``."""
        x_all = np.concatenate(self.profile_x) if self.profile_x else np.zeros(1)
        sigma, thr, x_ref, mirror, width, xs_front = (self.sigma, self.front_threshold, self.x_ref, self.mirror,
                                                      self.width, self.front_points)

        def observe(state, params):
            vol = particle_volumes(state)
            dtype = state.x.dtype
            h = deposit_profile(state.x, vol, jnp.asarray(x_all, dtype), sigma, width=width, mirror=mirror)
            h_front = deposit_profile(state.x, vol, jnp.asarray(xs_front, dtype), sigma, width=width, mirror=mirror)
            return {"h": h, "front": front_from_profile(jnp.asarray(xs_front, dtype), h_front, thr, x_ref)}

        return observe


def whiten_front(e, phi):
    """The front residuals whitened for an exponentially correlated error (``FrontTarget``):
    w_0 = e_0, w_i = (e_i − φ_i e_{i−1}) / sqrt(1 − φ_i²); φ = 0 leaves e as it is. For
    corr(e_i, e_j) = Π φ between them (the Ornstein–Uhlenbeck covariance at any spacing),
    Σ w² = eᵀ C⁻¹ e exactly: C's inverse is tridiagonal, this is its Cholesky factor."""
    prev = jnp.concatenate([jnp.zeros_like(e[:1]), e[:-1]])
    return (e - phi * prev) / jnp.sqrt(1 - phi * phi)


def unwhiten_front(w, phi) -> np.ndarray:
    """``whiten_front``'s inverse (numpy): e_i = w_i sqrt(1 − φ_i²) + φ_i e_{i−1}."""
    w, phi = np.asarray(w, float), np.asarray(phi, float)
    e = np.empty_like(w)
    prev = 0.0
    for i in range(w.size):
        prev = e[i] = w[i] * math.sqrt(1.0 - phi[i] ** 2) + phi[i] * prev
    return e
