"""Figures (matplotlib, the optional ``plot`` extra)."""

from __future__ import annotations

import numpy as np

__all__ = ["animate_avalanche", "plot_avalanche", "plot_stress_path"]


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("figures need matplotlib: pip install 'jaxmpm[plot]'") from err
    return plt


def plot_stress_path(history, params, path, title=""):
    """The (p, q) stress path over the initial and final yield surfaces and the critical-state
    line q = μ1 p̄ (and q = μ2 p̄, the rate-dependent limit)."""
    plt = _pyplot()
    p, q, pc = (np.asarray(a) for a in (history.p, history.q, history.pc))
    beta, mu1, mu2 = float(params.beta), float(params.mu1), float(params.mu2)
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for k, (label, style) in ((0, ("yield surface, start", ":")), (-1, ("yield surface, end", "-"))):
        ps = np.linspace(-beta * pc[k], pc[k], 200)
        ax.plot(ps, mu1 * np.sqrt(np.maximum((pc[k] - ps) * (ps + beta * pc[k]), 0)), "k" + style, lw=1, label=label)
    p_line = np.linspace(-beta * pc.max(), max(pc.max(), p.max()), 2)
    ax.plot(p_line, mu1 * (p_line + beta * pc[-1]), "C2--", lw=1, label="critical state q = μ1 p̄")
    ax.plot(p_line, mu2 * (p_line + beta * pc[-1]), "C3--", lw=1, label="q = μ2 p̄")
    ax.plot(p, q, "C0-", lw=2, label="stress path")
    ax.plot(p[-1], q[-1], "C0o")
    ax.set_xlabel("p (Pa)")
    ax.set_ylabel("q (Pa)")
    ax.set_ylim(bottom=0)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_run(scene, result, path, profile=None):
    """The final deposit (particles coloured by pressure) over the initial column outline, and
    the deposit profile h(x) if given."""
    plt = _pyplot()
    x = np.asarray(result.state.x)
    from ..materials.base import invariants

    p = np.asarray(invariants(result.state.tau)[0])
    fig, ax = plt.subplots(figsize=(8, 3.2))
    info = scene.info
    if info.wall_gap is not None and info.wall_gap <= 2 * info.dx:  # a body that starts on the bed (not a drop)
        x0, x1, H = info.front0 - info.length, info.front0, info.height
        ax.plot([x0, x0, x1, x1], [0, H, H, 0], "k:", lw=1, label="initial column")
    # 1st-99th percentile colour range: a few particles pressed on a wall would wash the map out
    art = ax.scatter(x[:, 0], x[:, 1], s=2, c=p, cmap="viridis", lw=0, vmin=min(0.0, float(np.percentile(p, 1))),
                     vmax=float(np.percentile(p, 99)))
    fig.colorbar(art, ax=ax, label="p (Pa)", shrink=0.8)
    if profile is not None:
        ax.plot(profile[0], profile[1], "C3-", lw=1.5, label="deposit profile h(x)")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x along the bed (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{scene.name}, t = {float(result.state.t):.3f} s, status {result.status}")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def animate_run(scene, result, path, fps=15):
    """A GIF of the particle positions at the frame times (needs frames with positions)."""
    plt = _pyplot()
    from matplotlib.animation import FuncAnimation, PillowWriter

    if result.frames is None or "x" not in result.frames:
        raise ValueError("the run has no frames with positions: pass --frames N")
    xs = np.asarray(result.frames["x"])
    fig, ax = plt.subplots(figsize=(8, 3))
    lo, hi = xs.min(axis=(0, 1)), xs.max(axis=(0, 1))
    ax.set_xlim(lo[0] - 0.01, hi[0] + 0.01)
    ax.set_ylim(min(lo[1], 0) - 0.005, hi[1] + 0.01)
    ax.set_aspect("equal")
    ax.axhline(0, color="k", lw=0.8)
    art = ax.scatter(xs[0, :, 0], xs[0, :, 1], s=2, lw=0)
    title = ax.set_title("")

    def draw(k):
        art.set_offsets(xs[k, :, :2])
        title.set_text(f"{scene.name}, t = {result.frame_times[k]:.3f} s")
        return art, title

    FuncAnimation(fig, draw, frames=len(xs), blit=False).save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path


def plot_avalanche(fields, path, title="S6 avalanche", n_times=6):
    """The avalanche in three panels: the terrain with the front at several times and the
    runout; the flow thickness along the path at those times; the peak thickness, speed and
    pressure along the path (``fields`` from ``jaxmpm.studies.avalanche.path_fields``)."""
    plt = _pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(9, 9), sharex=True, constrained_layout=True)
    picks = np.unique(np.linspace(0, len(fields.times) - 1, n_times).round().astype(int))
    colours = plt.cm.viridis(np.linspace(0, 1, len(picks)))
    ax = axes[0]
    ax.plot(fields.x, fields.z, "k-", lw=1, label="terrain")
    for k, c in zip(picks, colours):
        if np.isfinite(fields.front[k]):
            ax.plot(fields.front[k], np.interp(fields.front[k], fields.x, fields.z), "o", color=c,
                    label=f"front, t = {fields.times[k]:.0f} s")
    if np.isfinite(fields.runout_x):
        ax.axvline(fields.runout_x, color="r", ls="--", lw=1, label=f"runout x = {fields.runout_x:.0f} m")
    ax.set_ylabel("z (m)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(title, fontsize=10)
    ax = axes[1]
    for k, c in zip(picks, colours):
        ax.plot(fields.x, fields.thickness[k], color=c, lw=1, label=f"t = {fields.times[k]:.0f} s")
    ax.plot(fields.x, fields.deposit, "k-", lw=1.5, label="deposit (last frame)")
    ax.axhline(fields.threshold, color="grey", lw=0.8, ls=":")
    ax.set_ylabel("flow thickness (m)")
    ax.legend(fontsize=7, ncol=3)
    ax = axes[2]
    ax.plot(fields.x, fields.peak_thickness, "k-", lw=1, label="peak thickness (m)")
    ax.plot(fields.x, fields.peak_speed, "b-", lw=1, label="peak speed (m/s)")
    twin = ax.twinx()
    twin.plot(fields.x, fields.peak_pressure_kpa, "r-", lw=1, label="peak pressure ρu² (kPa)")
    twin.set_ylabel("pressure (kPa)", color="r")
    ax.axvline(fields.station, color="grey", lw=0.8, ls="--")
    ax.set_xlabel("x along the path (m)")
    ax.set_ylabel("thickness (m), speed (m/s)")
    lines = ax.get_lines()[:2] + twin.get_lines()
    ax.legend(lines, [ln.get_label() for ln in lines], fontsize=7, loc="upper left")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def animate_avalanche(fields, path, fps=10):
    """A GIF of the flow thickness along the path over the frames, with the terrain's elevation."""
    plt = _pyplot()
    from matplotlib.animation import FuncAnimation, PillowWriter

    fig, ax = plt.subplots(figsize=(9, 3), constrained_layout=True)
    ax.set_xlim(fields.x[0], fields.x[-1])
    ax.set_ylim(0, 1.1 * max(float(fields.thickness.max()), fields.threshold))
    ax.set_xlabel("x along the path (m)")
    ax.set_ylabel("flow thickness (m)")
    (line,) = ax.plot(fields.x, fields.thickness[0], "b-", lw=1)
    title = ax.set_title("")

    def draw(k):
        line.set_ydata(fields.thickness[k])
        title.set_text(f"S6 avalanche, t = {fields.times[k]:.1f} s, front x = {fields.front[k]:.0f} m")
        return line, title

    FuncAnimation(fig, draw, frames=len(fields.times), blit=False).save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
