"""Physical bounds on the fitted parameters, kept by a smooth reparametrisation.

An optimiser works on unconstrained numbers z; the physical value is
θ = lo + (hi − lo) · sigmoid(z), which stays strictly inside (lo, hi) for every finite z and is
smooth, so no step can leave the admissible range and no gradient is clipped. The bounds below
are wide physical limits, not priors: a fitted value that ends near a bound is reported as such.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import PARAMS

__all__ = [
    "FIT_KEYS", "START_MARGIN", "MAX_STEP", "DEFAULT_BOUNDS", "physical", "unconstrained", "dphysical_dz",
    "log_jacobian", "Bounds",
]


#: The calibration targets of docs/model.md §4.
FIT_KEYS = ("beta", "mu1", "mu2", "I0", "xi")


#: Where a start the user did not choose moves when it lies on a bound: this fraction of the
#: range inside it.
START_MARGIN = 0.05

#: The longest step in any z an optimiser or a profile's refit takes: a step of 2 in z moves θ
#: across most of its range (the logistic's slope is at most 1/4 of it).
MAX_STEP = 2.0


#: Physical limits (lo, hi) of every key that may be fitted: ``jaxmpm.PARAMS``' ``fit_bounds`` (β:
#: tensile/compressive strength ratio, dry 0 … strongly cohesive; μ1, μ2: tan 3° … tan 63°; I0: the
#: inertial number's scale; ξ: hardening rate; μ_w: the walls' and terrain's Coulomb friction).
DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {k: s.fit_bounds for k, s in PARAMS.items() if s.fit_bounds}


def physical(z, lower, upper):
    """θ = lower + (upper − lower) sigmoid(z), elementwise (traceable)."""
    return lower + (upper - lower) * jax.nn.sigmoid(z)


def unconstrained(theta, lower, upper) -> np.ndarray:
    """z = logit((θ − lower) / (upper − lower)) (numpy; θ strictly inside, unchecked)."""
    u = (np.asarray(theta, float) - lower) / (np.asarray(upper, float) - lower)
    return np.log(u) - np.log1p(-u)


def dphysical_dz(z, lower, upper):
    """dθ/dz = (upper − lower) s (1 − s), s = sigmoid(z), elementwise (traceable)."""
    s = jax.nn.sigmoid(z)
    return (upper - lower) * s * (1.0 - s)


def log_jacobian(z, lower, upper):
    """log |dθ/dz| summed over the keys: the density of a flat prior in θ sampled in z."""
    return jnp.sum(jnp.log(dphysical_dz(z, lower, upper)))


@dataclasses.dataclass(frozen=True)
class Bounds:
    """Bounds for an ordered tuple of parameter keys, and the map between θ and z."""

    keys: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]

    @classmethod
    def create(cls, keys: Sequence[str], overrides: Mapping[str, tuple[float, float]] | None = None) -> Bounds:
        keys = tuple(keys)
        if not keys:
            raise ValueError("keys: at least one parameter must be fitted")
        if len(set(keys)) != len(keys):
            raise ValueError(f"keys: repeated parameter in {keys}")
        table = {**DEFAULT_BOUNDS, **dict(overrides or {})}
        unknown = [k for k in keys if k not in table]
        if unknown:
            raise ValueError(f"keys: no bounds known for {unknown}; pass bounds={{key: (lo, hi)}}")
        lower, upper = [], []
        for k in keys:
            lo, hi = (float(v) for v in table[k])
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"bounds[{k!r}] must be finite with lo < hi, got ({lo}, {hi})")
            lower.append(lo)
            upper.append(hi)
        return cls(keys, tuple(lower), tuple(upper))

    @property
    def n(self) -> int:
        return len(self.keys)

    def _arrays(self, like):
        dtype = jnp.result_type(like)
        return jnp.asarray(self.lower, dtype), jnp.asarray(self.upper, dtype)

    def to_physical(self, z):
        """θ = lo + (hi − lo) sigmoid(z) (``physical``)."""
        return physical(z, *self._arrays(z))

    def to_unconstrained(self, theta):
        """The inverse map (``unconstrained``); ``theta`` must lie strictly inside the bounds."""
        theta = np.asarray(theta, float)
        self.check(theta, "theta")
        return unconstrained(theta, np.asarray(self.lower), np.asarray(self.upper))

    def jacobian_diag(self, z):
        """dθ/dz, elementwise (``dphysical_dz``)."""
        return dphysical_dz(z, *self._arrays(z))

    def log_jacobian(self, z):
        """log |dθ/dz| summed (``log_jacobian``)."""
        return log_jacobian(z, *self._arrays(z))

    def check(self, theta, name: str = "init") -> None:
        theta = np.asarray(theta, float)
        for k, v, lo, hi in zip(self.keys, theta, self.lower, self.upper):
            if not (math.isfinite(v) and lo < v < hi):
                raise ValueError(f"{name}: {k} = {float(v)!r} must lie strictly inside its bounds ({lo}, {hi})")

    def move_inside(self, theta, margin: float = START_MARGIN) -> tuple[np.ndarray, dict[str, tuple[float, float]]]:
        """θ with every value on, outside or within ``near_bound`` of a bound moved to ``margin``
        of the range inside that bound (β = 0 on (0, 1) becomes 0.05); returns the new θ and
        ``{key: (old, new)}`` for what moved. For starts the user did not choose (scene values)."""
        theta = np.array(theta, float)
        near = set(self.near_bound(theta))  # also every value on or outside a bound
        moved = {}
        for i, (k, v, lo, hi) in enumerate(zip(self.keys, theta, self.lower, self.upper)):
            if k in near or not math.isfinite(v):
                new = hi - margin * (hi - lo) if v > 0.5 * (lo + hi) else lo + margin * (hi - lo)
                moved[k] = (float(v), float(new))
                theta[i] = new
        return theta, moved

    def near_bound(self, theta, rel: float = 1e-3) -> list[str]:
        """Keys whose value sits within ``rel`` of the bound range of a bound."""
        theta = np.asarray(theta, float)
        return [k for k, v, lo, hi in zip(self.keys, theta, self.lower, self.upper)
                if min(v - lo, hi - v) < rel * (hi - lo)]
