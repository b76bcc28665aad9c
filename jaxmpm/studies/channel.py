"""Channel studies (docs/validation.md §8): the side walls of a 2D channel against the analytic
steady flow between them.

``side_walls``: S1's strip (docs/scenes.md) at two slopes between walls at two widths, started
on the analytic profile of ``jaxmpm.scenes.incline.side_wall_velocity`` at the critical state, as
the Bagnold study starts on its own: the run shows whether the scheme holds the profile and the
depth ζ* below which the walls stop the flow.
"""

from __future__ import annotations

import pathlib

import jax
import numpy as np

from .. import scenes
from ..boundary import SideWalls
from ..scenes import S1_DEPTH
from ..scenes.incline import side_wall_velocity
from ..simulate import simulate

__all__ = ["side_walls"]

#: The threshold, as a fraction of the surface velocity, below which a particle counts as at rest
#: when the depth of the flowing layer is read off a profile (the analytic one read the same way).
AT_REST = 0.02


def _observer(state, params):
    return {"vx": state.v[:, 0], "y": state.x[:, 1]}


def _flowing_depth(v, z, depth, v_surface):
    """How deep below the surface the particles move faster than ``AT_REST`` of ``v_surface``."""
    moving = np.asarray(z)[np.asarray(v) > AT_REST * v_surface]
    return float(depth - moving.min()) if moving.size else 0.0


def side_walls(quick=False, plot_dir=None, slopes=(25.0, 28.0), widths=(0.05, 0.1), friction=0.3,
               division=None, t_end=None) -> dict:
    """S1 between side walls ``widths`` apart (μ_w = ``friction``, K = 1) at each of ``slopes``:
    the surface velocity (the top row of particles) and the profile (RMS over the particles, over
    the analytic surface velocity) at t_end against the analytic solution, and the depth of the
    flowing layer read off both profiles the same way (``AT_REST``) beside the analytic ζ*."""
    division = division or (8 if quick else 16)
    t_end = (0.3 if quick else 1.0) if t_end is None else t_end
    cases, shown = [], {}
    for slope in slopes:
        for width in widths:
            walls = SideWalls(width, friction)
            scene = scenes.incline(slope, dx=S1_DEPTH / division, t_end=t_end, frames=1, critical_start=True,
                                   side_walls=walls)
            result = simulate(*scene, observer=_observer, throw=False)
            vx = np.asarray(result.frames["vx"][-1])
            z = np.asarray(result.frames["y"][-1]) - scene.info.wall_gap
            analytic, stop = side_wall_velocity(z, S1_DEPTH, slope, scene.params, walls)
            v_max = float(side_wall_velocity(S1_DEPTH, S1_DEPTH, slope, scene.params, walls)[0])
            top = np.argsort(z)[-scene.config.grid.cells[0] * scene.info.ppc:]
            fine = np.linspace(0.0, S1_DEPTH, 2001)
            cases.append({
                "slope_deg": slope, "width": width, "friction": friction, "dx": scene.info.dx,
                "v_surface": float(vx[top].mean()), "v_surface_analytic": float(analytic[top].mean()),
                "rel_error": float(vx[top].mean() / analytic[top].mean() - 1.0),
                "profile_rel_error": float(np.sqrt(np.mean((vx - analytic) ** 2)) / v_max),
                "stop_depth_analytic": float(min(stop, S1_DEPTH)),
                "flowing_depth": _flowing_depth(vx, z, S1_DEPTH, v_max),
                "flowing_depth_analytic": _flowing_depth(side_wall_velocity(fine, S1_DEPTH, slope, scene.params,
                                                                            walls)[0], fine, S1_DEPTH, v_max),
                "v_surface_without_walls": float(scenes.bagnold_velocity(S1_DEPTH, S1_DEPTH, slope, scene.params)),
                "status": result.status,
            })
            cases[-1]["flowing_depth_rel_error"] = cases[-1]["flowing_depth"] / cases[-1]["flowing_depth_analytic"] - 1
            shown[(slope, width)] = (vx, z, scene.params, walls)
    out = {"study": "side-walls", "t_end": t_end, "division": division, "at_rest": AT_REST,
           "dtype": str(jax.numpy.zeros(()).dtype), "cases": cases}
    if plot_dir:
        _plot(shown, cases, pathlib.Path(plot_dir) / "side_walls.png")
    return out


def _plot(shown, cases, path):
    from .plots import _pyplot, _save

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(shown), figsize=(3.4 * len(shown), 3.8), sharey=True)
    for ax, ((slope, width), (vx, z, params, walls)), case in zip(np.atleast_1d(axes), shown.items(), cases):
        ax.plot(vx, z * 1e3, ".", ms=2, label=f"jaxmpm, dx = {case['dx'] * 1e3:.2g} mm")
        fine = np.linspace(0.0, S1_DEPTH, 200)
        ax.plot(side_wall_velocity(fine, S1_DEPTH, slope, params, walls)[0], fine * 1e3, "k-", lw=1.2,
                label="analytic, with walls")
        if case["stop_depth_analytic"] < S1_DEPTH:
            ax.axhline((S1_DEPTH - case["stop_depth_analytic"]) * 1e3, color="k", ls=":", lw=0.8, label="ζ*")
        ax.set_title(f"θ = {slope:g}°, W = {width * 100:g} cm, μ_w = {walls.friction:g}", fontsize=9)
        ax.set_xlabel("v (m/s)")
    np.atleast_1d(axes)[0].set_ylabel("height above bed (mm)")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    return _save(fig, path, 100)
