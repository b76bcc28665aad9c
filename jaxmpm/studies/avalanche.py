"""What avalanche engineers measure (docs/scenes.md S6), from an avalanche run's frames.

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
- the force on an obstacle at a station, two ways: the momentum flux ρ u² h through the station
  per unit width (kN/m), the standard design estimate of the force on a rigid wall normal to the
  flow, computed from the flow; and, where the scene has a simulated obstacle (``avalanche(...,
  obstacle=(x, height))``), the force the snow exerts on that wall, the change of its recorded
  impulse (``State.impulse``) between frames over the frame interval: the mean force over
  each interval, exact in momentum.

Peaks are over the frames only: a finer frame spacing catches sharper peaks.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

__all__ = ["PathFields", "avalanche_summary", "fields_header", "path_fields", "run_avalanche", "smooth_runout"]


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
    obstacle_force_kn_per_m: np.ndarray | None = None  # (T, 2) on the simulated obstacle (x: downstream), kN/m

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
            **({} if self.obstacle_force_kn_per_m is None else {
                "obstacle_force_max_kn_per_m": float(self.obstacle_force_kn_per_m[:, 0].max()),
                "obstacle_impulse_kn_s_per_m": float(np.sum(self.obstacle_force_kn_per_m[:, 0]
                                                            * np.diff(self.times, prepend=0.0)))}),
        }

    def columns(self) -> dict[str, np.ndarray]:
        """The fields along the path, for ``--profile-csv``."""
        return {"x_m": self.x, "z_m": self.z, "peak_thickness_m": self.peak_thickness,
                "peak_speed_m_per_s": self.peak_speed, "peak_pressure_kpa": self.peak_pressure_kpa,
                "deposit_m": self.deposit}


def path_fields(terrain, x, v, vol, times, rho: float, dx: float, threshold: float = 0.1,
                station: float | None = None, bin_width: float | None = None, impulse=None) -> PathFields:
    """The fields of the module docstring from frames ``x``, ``v`` (T, N, 2), reference volumes
    ``vol`` (N,) and frame ``times`` (T,), on ``terrain`` (a ``boundary.Terrain``); ``impulse``
    (T, 2): a simulated obstacle's impulse at the frames (from t = 0), for its force history."""
    x, v, vol, times = (np.asarray(a, float) for a in (x, v, vol, times))
    obstacle_force = None
    if impulse is not None:
        impulse = np.asarray(impulse, float)
        if impulse.shape != (len(times), 2):
            raise ValueError(f"impulse must be (frames, 2), got {impulse.shape}")
        obstacle_force = np.diff(impulse, axis=0, prepend=0.0) / np.diff(times, prepend=0.0)[:, None] / 1e3
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
                      float(threshold), obstacle_force)


def smooth_runout(x, vol0, terrain, xs, threshold: float = 0.1, width: float | None = None,
                  sharpness: float | None = None, length: float | None = None):
    """A differentiable runout of particles at ``x`` (N, 2) with reference volumes ``vol0`` (N,),
    on the evenly spaced evaluation points ``xs`` (M,), which must reach past the deposit.

    h(s) is the thickness normal to the terrain from a Gaussian kernel of ``width`` (default:
    4 × the spacing of ``xs``), and g(h) a logistic step from 0 (bare ground) to 1 centred on
    ``threshold`` with width ``sharpness`` (default threshold / 4). Counted from the far end,
    C(s) = ∫_s g ds' is the length of ground beyond s covered thicker than the threshold, and
    the runout is where C reaches about ``length`` (default ``width``):

        R = xs[0] + length + ∫ (1 − exp(−C(s)/length)) ds,

    which for a deposit with a sharp front at R0 (g = 1 behind it, 0 beyond) is R0 up to
    e^{−(R0 − xs[0])/length}: the ``runout_x`` rule of ``PathFields`` on a smooth field. Gaps in
    the deposit behind the front do not matter; a stray particle ahead of it, far thinner than
    the threshold, adds its small g to C over the whole distance between: R grows by about that
    g-length × distance / ``length``. Written in jax.numpy: it can be differentiated with
    respect to ``x``."""
    import jax.numpy as jnp

    xs_np = np.asarray(xs, float)  # concrete: the points are part of the definition, not traced
    if xs_np.ndim != 1 or len(xs_np) < 2 or not np.all(np.diff(xs_np) > 0):
        raise ValueError(f"xs must be at least two increasing points, got shape {xs_np.shape}")
    step = float(xs_np[1] - xs_np[0])
    if not np.allclose(np.diff(xs_np), step, rtol=1e-6):
        raise ValueError("xs must be evenly spaced")
    width = 4.0 * step if width is None else float(width)
    sharpness = 0.25 * threshold if sharpness is None else float(sharpness)
    length = width if length is None else float(length)
    _, slope = terrain._evaluate(xs_np)
    cos = jnp.asarray(1.0 / np.sqrt(1.0 + slope * slope), x.dtype)
    xs = jnp.asarray(xs_np, x.dtype)
    d = (xs[:, None] - x[None, :, 0]) / width
    h = cos * jnp.sum(vol0 * jnp.exp(-0.5 * d * d), axis=1) / (width * math.sqrt(2.0 * math.pi))
    # g shifted and scaled so that bare ground (h = 0) counts exactly 0 and a thick deposit 1
    floor = 1.0 / (1.0 + math.exp(threshold / sharpness))
    g = (jax.nn.sigmoid((h - threshold) / sharpness) - floor) / (1.0 - floor)
    beyond = step * (jnp.cumsum(g[::-1])[::-1] - 0.5 * g)  # C at each point (midpoint rule)
    return xs[0] - 0.5 * step + length + step * jnp.sum(1.0 - jnp.exp(-beyond / length))


def _observer(state, params):
    return {"x": state.x, "v": state.v, "impulse": state.impulse}


def run_avalanche(scene, station: float | None = None, progress: bool = False, threshold: float = 0.1):
    """Run an S6 ``scene`` (``jaxmpm.scenes.avalanche``) and return ``(result, fields)``: the
    ``simulate`` result (``throw=False``: its status says whether the run is trusted; timed) and
    the ``PathFields`` on its frames. ``station`` defaults to the obstacle's where the scene has
    one, else half way along the flow's reach."""
    from ..scenes.avalanche import OBSTACLE
    from ..simulate import simulate

    config, state, params = scene
    result = simulate(config, state, params, observer=_observer, throw=False, progress=progress, timed=not progress)
    has_obstacle = len(config.walls) > OBSTACLE
    if station is None and has_obstacle:
        station = float(config.walls[OBSTACLE].point[0])
    fields = path_fields(config.walls[0], result.frames["x"], result.frames["v"], state.vol0,
                         np.asarray(config.frame_times), float(params.rho), config.grid.dx, threshold=threshold,
                         station=station, impulse=result.frames["impulse"][:, OBSTACLE] if has_obstacle else None)
    return result, fields


def avalanche_summary(scene, result, fields: PathFields, snow: str) -> dict:
    """What an S6 run ended with (``run_avalanche``'s ``result`` and ``fields``): sizes, the
    fields' summary, the basal friction, the status and its meaning, the timings; what
    ``python -m jaxmpm run avalanche`` prints."""
    from ..state import describe_status

    config, state, params = scene
    return {"scene": "avalanche", "snow": snow, "n_particles": int(state.n_particles),
            "n_steps": int(result.state.steps), "dx": config.grid.dx, "t_end": config.t_end,
            "grid_nodes_dense": config.grid.n_nodes, "active_nodes": config.active_nodes,
            **fields.summary(), "mu_w": float(params.mu_w), "status": result.status,
            "status_text": describe_status(result.status), "compile_s": round(result.compile_s, 3),
            "run_s": round(result.run_s, 3)}


def fields_header(scene, result, fields: PathFields, source: str) -> dict:
    """The header of the fields along the path as CSV (``tables.write_table`` of
    ``fields.columns()``): a synthetic table made by ``source`` (the command that ran it)."""
    from .._version import __version__

    return {"experiment": f"avalanche (synthetic, jaxmpm {__version__})", "units": "m, m/s, kPa",
            "synthetic": True, "source": source, "t_end_s": scene.config.t_end, "peaks": "over the frames",
            "summary": fields.summary(), "status": result.status}
