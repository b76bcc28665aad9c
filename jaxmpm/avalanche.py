"""What avalanche engineers measure (docs/scenes.md S6, issue 13), from an avalanche run's frames.

The fields are sampled on bins along x (``bin_width``, default 4 dx: a bin holds about 2 ppc
particle columns, so that the thickness is not aliased by the particle spacing) and on the
run's frame times:

- flow thickness h(x, t): the snow's area in the bin (2D: volume per unit width, at the release
  density: the particles' reference volumes) over the bin's length along the terrain, that is
  area · cos θ / Δx with θ the terrain's local angle; it is the thickness normal to the slope;
- flow speed u(x, t): the magnitude of the bin's mass-weighted mean velocity;
- pressure ρ u² (the AvaFrame convention), in kPa, with ρ the snow's density;
- the front x_f(t): the farthest bin whose thickness exceeds ``threshold`` (0.1 m), and its speed
  by central differences over the frames;
- ``runout_x``: the farthest x where the peak (over the frames) flow thickness exceeded the
  threshold, the ISeeSnow comparison's definition;
- the deposit: h(x) at the last frame;
- the force on an obstacle at a station: the momentum flux ρ u² h through the station per unit
  width (kN/m), the standard design estimate of the force on a rigid wall normal to the flow. It
  is computed from the flow, not from a simulated obstacle (none is modelled).

Peaks are over the frames only: a finer frame spacing catches sharper peaks.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["PathFields", "path_fields"]


@dataclasses.dataclass(frozen=True)
class PathFields:
    x: np.ndarray  # (B,) bin centres, m
    z: np.ndarray  # (B,) terrain elevation there, m
    times: np.ndarray  # (T,) frame times, s
    thickness: np.ndarray  # (T, B) flow thickness normal to the slope, m
    speed: np.ndarray  # (T, B) flow speed, m/s
    pressure_kpa: np.ndarray  # (T, B) ρ u², kPa
    front: np.ndarray  # (T,) front position, m (NaN where no bin reaches the threshold)
    front_speed: np.ndarray  # (T,) its speed, m/s
    station: float  # obstacle station x, m
    force_kn_per_m: np.ndarray  # (T,) ρ u² h at the station, kN/m
    threshold: float

    @property
    def peak_thickness(self) -> np.ndarray:
        return self.thickness.max(axis=0)

    @property
    def peak_speed(self) -> np.ndarray:
        return self.speed.max(axis=0)

    @property
    def peak_pressure_kpa(self) -> np.ndarray:
        return self.pressure_kpa.max(axis=0)

    @property
    def deposit(self) -> np.ndarray:
        return self.thickness[-1]

    @property
    def runout_x(self) -> float:
        hit = np.flatnonzero(self.peak_thickness > self.threshold)
        return float(self.x[hit[-1]]) if hit.size else float("nan")

    def summary(self) -> dict:
        finite = np.isfinite(self.front_speed)
        return {
            "runout_x": self.runout_x,
            "front_speed_max": float(np.max(self.front_speed[finite])) if finite.any() else None,
            "peak_pressure_max_kpa": float(self.peak_pressure_kpa.max()),
            "peak_thickness_max": float(self.peak_thickness.max()),
            "peak_speed_max": float(self.peak_speed.max()),
            "front_final": float(self.front[-1]) if np.isfinite(self.front[-1]) else None,
            "deposit_max": float(self.deposit.max()),
            "station_x": self.station,
            "force_max_kn_per_m": float(self.force_kn_per_m.max()),
            "threshold_m": self.threshold,
        }

    def columns(self) -> dict[str, np.ndarray]:
        """The fields along the path, for ``--profile-csv``."""
        return {"x_m": self.x, "z_m": self.z, "peak_thickness_m": self.peak_thickness,
                "peak_speed_m_per_s": self.peak_speed, "peak_pressure_kpa": self.peak_pressure_kpa,
                "deposit_m": self.deposit}


def path_fields(terrain, x, v, vol, times, rho: float, dx: float, threshold: float = 0.1,
                station: float | None = None, bin_width: float | None = None) -> PathFields:
    """The fields of the module docstring from frames ``x``, ``v`` (T, N, 2), reference volumes
    ``vol`` (N,) and frame ``times`` (T,), on ``terrain`` (a ``boundary.Terrain``)."""
    x, v, vol, times = (np.asarray(a, float) for a in (x, v, vol, times))
    if x.ndim != 3 or x.shape[-1] != 2 or v.shape != x.shape or vol.shape != x.shape[1:2]:
        raise ValueError(f"x and v must be (frames, particles, 2) and vol (particles,), got {x.shape}, {v.shape}, "
                         f"{vol.shape}")
    dx = 4.0 * dx if bin_width is None else float(bin_width)
    if not (np.isfinite(dx) and dx > 0):
        raise ValueError(f"bin_width must be > 0, got {bin_width!r}")
    finite = np.isfinite(x[..., 0])
    lo = np.floor(np.min(x[..., 0][finite]) / dx) * dx
    hi = np.ceil(np.max(x[..., 0][finite]) / dx) * dx + dx
    edges = np.arange(lo, hi + 0.5 * dx, dx)
    centres = 0.5 * (edges[1:] + edges[:-1])
    z, slope = terrain._evaluate(centres)
    cos = 1.0 / np.sqrt(1.0 + slope * slope)
    n_bins = len(centres)
    thickness = np.zeros((len(times), n_bins))
    speed = np.zeros_like(thickness)
    for k in range(len(times)):
        ok = finite[k]
        b = np.clip(np.searchsorted(edges, x[k, ok, 0], side="right") - 1, 0, n_bins - 1)
        area = np.bincount(b, weights=vol[ok], minlength=n_bins)
        mom = np.stack([np.bincount(b, weights=vol[ok] * v[k, ok, a], minlength=n_bins) for a in range(2)])
        thickness[k] = area * cos / dx
        with np.errstate(invalid="ignore", divide="ignore"):
            speed[k] = np.where(area > 0, np.hypot(*mom) / area, 0.0)
    pressure = rho * speed**2 / 1e3
    front = np.full(len(times), np.nan)
    for k in range(len(times)):
        hit = np.flatnonzero(thickness[k] > threshold)
        if hit.size:
            front[k] = centres[hit[-1]]
    front_speed = np.gradient(front, times) if len(times) > 1 else np.full(1, np.nan)
    if station is None:  # half way along the reach of the flow
        station = 0.5 * (lo + hi)
    j = int(np.clip(np.searchsorted(edges, station, side="right") - 1, 0, n_bins - 1))
    force = rho * speed[:, j] ** 2 * thickness[:, j] / 1e3
    return PathFields(centres, z, times, thickness, speed, pressure, front, front_speed, float(station), force,
                      float(threshold))
