"""Figures (matplotlib, the optional ``plot`` extra): the one module that draws.

The commands and the studies compute their data and hand it here; every function draws one
figure into ``path`` and returns ``path``.
"""

from __future__ import annotations

import numpy as np

from ..scenes import S1_DEPTH, S4_SIDE, bagnold_velocity, height_law, runout_law

__all__ = ["animate_avalanche", "animate_run", "plot_aspect_ratio", "plot_avalanche", "plot_bagnold",
           "plot_bagnold_from_rest", "plot_cohesion", "plot_convergence", "plot_obstacle_force", "plot_resolution",
           "plot_run", "plot_speed_accuracy", "plot_stress_path"]


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("figures need matplotlib: pip install 'jaxmpm[plot]'") from err
    return plt


def _save(fig, path, dpi):
    """Lay ``fig`` out, write it to ``path`` and close it; return ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


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


# ---- the validation studies (jaxmpm.studies.validation, jaxmpm.studies.fidelity) ----------------
def plot_bagnold(profiles, slopes, divisions, cases, params, path):
    """S1: the velocity profiles at each slope and resolution against the Bagnold profile, and the
    surface velocity's error against dx. ``profiles[(slope, division)] = (vx, z, depth)``."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(slopes) + 1, figsize=(4 * (len(slopes) + 1), 3.6))
    for ax, slope in zip(axes, slopes):
        for div in divisions:
            vx, y, h = profiles[(slope, div)]
            ax.plot(vx, y * 1e3, ".", ms=2, label=f"dx = h/{div}")
        z = np.linspace(0, h, 100)
        ax.plot(bagnold_velocity(z, h, slope, params), z * 1e3, "k-", lw=1.2, label="Bagnold (docs/model.md §6)")
        ax.set_title(f"θ = {slope:g}°")
        ax.set_xlabel("v (m/s)")
        ax.set_ylabel("height above bed (mm)")
    axes[0].legend(fontsize=7)
    ax = axes[-1]
    for slope in slopes:
        rows = [c for c in cases if c["slope_deg"] == slope]
        ax.loglog([c["dx"] for c in rows], [abs(c["rel_error"]) + 1e-6 for c in rows], "o-", label=f"{slope:g}°")
    ax.set_xlabel("dx (m)")
    ax.set_ylabel("|surface velocity error|")
    ax.legend(fontsize=7)
    return _save(fig, path, 90)


def plot_bagnold_from_rest(out, path):
    """S1 from rest (``out`` of ``bagnold_from_rest``): the binned velocity profile at several
    times against the Bagnold profile, and the surface velocity and profile error over time."""
    plt = _pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    z = np.asarray(out["z_bins"]) * 1e3
    shown = [s for s in out["snapshots"]][:: max(1, len(out["snapshots"]) // 6)]
    cmap = plt.get_cmap("viridis")
    for i, snap in enumerate(shown):
        prof = np.array([np.nan if v is None else v for v in snap["profile"]])
        a1.plot(prof, z, "-", color=cmap(i / max(1, len(shown) - 1)), label=f"t = {snap['t']:.1f} s")
    a1.plot(out["analytic"], z, "k--", lw=1.5, label="Bagnold (docs/model.md §6)")
    a1.set_xlabel("v (m/s)")
    a1.set_ylabel("height above bed (mm)")
    a1.set_title(f"S1, θ = {out['slope_deg']:g}° from rest, dx = h/{round(S1_DEPTH / out['dx'])}, {out['dtype']}"
                 + (f", XPIC({out['xpic']})" if out["xpic"] else ""), fontsize=9)
    a1.legend(fontsize=7)
    t = [s["t"] for s in out["snapshots"]]
    a2.plot(t, [s["surface_rel"] for s in out["snapshots"]], "o-", label="surface velocity / v_max")
    a2.plot(t, [s["profile_rel_error"] for s in out["snapshots"]], "s-", label="profile RMS error / v_max")
    a2.axhline(1.0, color="k", lw=0.6)
    a2.axhline(0.03, color="k", lw=0.6, ls=":")
    a2.set_xlabel("t (s)")
    a2.legend(fontsize=7)
    return _save(fig, path, 100)


def plot_convergence(xs, rows, profiles, sigma, t_end, path):
    """S3 over dx: the deposit profiles on ``xs`` (kernel width ``sigma``), and each run's
    differences to the finest run (the last row) against dx."""
    plt = _pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.6))
    for row, h in zip(rows, profiles):
        a1.plot(xs, h * 1e3, label=f"dx = {row['dx'] * 1e3:g} mm, {row['sampling']} ppc {row['ppc']:g}")
    a1.set_xlabel("x along the bed (m)")
    a1.set_ylabel(f"h (mm), kernel σ = {sigma * 1e3:g} mm")
    a1.legend(fontsize=7)
    a1.set_title(f"S3, θ = 10°, t = {t_end} s")
    coarse = rows[:-1]
    a2.loglog([r["dx"] for r in coarse], [max(r["front_diff"], 1e-6) for r in coarse], "o-", label="front (m)")
    a2.loglog([r["dx"] for r in coarse], [max(r["runout_diff"], 1e-6) for r in coarse], "^-",
              label="max-particle runout (m)")
    a2.loglog([r["dx"] for r in coarse], [r["profile_l2_rel"] for r in coarse], "s-", label="profile (rel. L2)")
    a2.set_xlabel("dx (m)")
    a2.set_ylabel("difference to the finest run")
    a2.legend(fontsize=7)
    return _save(fig, path, 90)


def plot_aspect_ratio(rows, path):
    """S5: runout and final height over L0 against the scaling laws (secondary)."""
    plt = _pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6))
    a = np.array([r["a"] for r in rows])
    fine = np.linspace(0.3, 10, 200)
    a1.loglog(a, [r["runout_over_L0"] for r in rows], "o", label="jaxmpm")
    a1.loglog(fine, runout_law(fine), "k-", label="glass beads (secondary)")
    a1.loglog(fine, runout_law(fine, sand=True), "k--", label="sand, Lube 2005 (secondary)")
    a1.set_xlabel("a = H0/L0")
    a1.set_ylabel("ΔL/L0")
    a1.legend(fontsize=7)
    a2.loglog(a, [r["height_over_L0"] for r in rows], "o", label="jaxmpm")
    a2.loglog(fine, height_law(fine), "k-", label="glass beads (secondary)")
    a2.set_xlabel("a = H0/L0")
    a2.set_ylabel("H_f/L0")
    a2.legend(fontsize=7)
    return _save(fig, path, 90)


def plot_cohesion(shown, path):
    """S4 deposits side by side, particles coloured by pressure: ``shown`` is a list of
    ``(beta, x, p)``."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for ax, (beta, x, p) in zip(axes, shown):
        ax.plot([0, 0, S4_SIDE, S4_SIDE], [0, S4_SIDE, S4_SIDE, 0], "k:", lw=1)
        # colour range from the 1st to the 99th percentile: a few particles pressed against a
        # wall carry p an order of magnitude above the rest and would wash the map out
        art = ax.scatter(x[:, 0], x[:, 1], c=p, s=2, lw=0, vmin=min(0.0, float(np.percentile(p, 1))),
                         vmax=float(np.percentile(p, 99)))
        fig.colorbar(art, ax=ax, label="p (Pa)", shrink=0.8)
        ax.set_aspect("equal")
        ax.set_title(f"S4, β = {beta}, t = 0.5 s")
    axes[-1].set_xlabel("x (m)")
    return _save(fig, path, 90)


def plot_speed_accuracy(rows, path):
    """S3 speed against accuracy: each run's front and profile errors against its run time, the
    Pareto front (``row["pareto"]``) in red."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, key, label in ((axes[0], "front_rel_error", "front error (h < 3 mm)"),
                           (axes[1], "profile_rel_error", "deposit profile error (rel. L2)")):
        for r in rows:
            marker = {"aflip": "o", "apic": "s", "pic": "^"}[r["transfer"]]
            ax.loglog(r["wall_s"], max(r[key], 1e-4), marker, color="C3" if r["pareto"] else "C0", ms=7)
            ax.annotate(f"{r['dx'] * 1e3:g}mm {r['transfer']} {r['sampling'][:3]} ppc{r['ppc']:g}"
                        + (f" xpic{r['xpic']}" if r["xpic"] else "")
                        + (" f64" if r["dtype"] == "float64" else "")
                        + (f" cfl{r['cfl']}" if r["cfl"] != 0.5 else ""),
                        (r["wall_s"], max(r[key], 1e-4)), fontsize=5.5, xytext=(3, 3), textcoords="offset points")
        for level in (0.01, 0.02, 0.05):
            ax.axhline(level, color="k", lw=0.6, ls=":")
        ax.set_xlabel("run time on 2 CPU cores (s), compilation apart")
        ax.set_ylabel(label)
    axes[0].set_title("o AFLIP  s APIC  ^ PIC;  red: Pareto front (front error)", fontsize=9)
    return _save(fig, path, 110)


def plot_obstacle_force(open_path, obstacle, dx, path):
    """S6 with an obstacle: the force on the simulated wall against the open path's momentum flux
    at the station, and the deposits near it with and without the wall (``PathFields`` both)."""
    plt = _pyplot()
    fig, (top, low) = plt.subplots(2, 1, figsize=(8, 6))
    t = obstacle.times
    top.step(t, obstacle.obstacle_force_kn_per_m[:, 0], where="pre", color="k",
             label="simulated 5 m wall: its impulse's change over each 1 s frame")
    top.plot(t, open_path.force_kn_per_m, "r--", label="open path: momentum flux ρu²h through the station")
    top.set_xlabel("t (s)")
    top.set_ylabel(f"force at x = {obstacle.station:g} m (kN/m)")
    top.set_xlim(t[np.argmax(obstacle.obstacle_force_kn_per_m[:, 0] > 0)] - 5, t[-1])
    top.legend(fontsize=8)
    top.set_title(f"S6, dry snow, dx = {dx:g} m: the force on an obstacle", fontsize=10)
    near = (open_path.x > obstacle.station - 400) & (open_path.x < obstacle.station + 500)
    low.plot(open_path.x[near], open_path.deposit[near], "r--", label="deposit, open path")
    near = (obstacle.x > obstacle.station - 400) & (obstacle.x < obstacle.station + 500)
    low.plot(obstacle.x[near], obstacle.deposit[near], "k-", label="deposit, with the wall")
    low.axvline(obstacle.station, color="grey", lw=3, alpha=0.5, label="wall")
    low.set_xlabel("x along the path (m)")
    low.set_ylabel("deposit thickness (m, at release density)")
    low.legend(fontsize=8)
    return _save(fig, path, 110)


def plot_resolution(out, path):
    """The resolution study (``out`` of ``analyse_resolution``): the worst scalar error and the
    profile error of every run against its cost (particle-steps)."""
    plt = _pyplot()
    names, sigma = list(out["scenes"]), out["sigma_m"]
    fig, axes = plt.subplots(2, len(names), figsize=(6.5 * len(names), 8), squeeze=False)
    markers = {"lattice": "o", "jitter": "s", "poisson": "^"}
    colors = {2.0: "C0", 2.45: "C1", 3.0: "C2", 4.0: "C3"}
    for col, name in enumerate(names):
        data = out["scenes"][name]
        for row, (label, value) in enumerate((
                ("worst scalar error (" + ", ".join(data["scalars"]) + ")",
                 lambda r, data=data: max(abs(r["error"][k]) for k in data["scalars"])),  # used in this iteration
                (f"deposit profile error (rel. L2, σ = {sigma * 1e3:g} mm)", lambda r: r["error"]["profile"]))):
            ax = axes[row, col]
            for r in data["runs"]:
                cost, err = r["particle_steps"], max(value(r), 1e-4)
                ax.loglog(cost, err, markers[r["sampling"]], color=colors.get(float(r["ppc"]), "C4"), ms=6,
                          mfc="none" if r["seed"] else None)
                ax.annotate(f"{r['dx'] * 1e3:.2g}", (cost, err), fontsize=6, xytext=(3, 2), textcoords="offset points")
            for level in (0.01, 0.02, 0.05):
                ax.axhline(level, color="k", lw=0.6, ls=":")
            ax.set_xlabel("cost: particle-steps of the run")
            ax.set_ylabel(label, fontsize=8)
        ref = data["reference"]
        axes[0, col].set_title(f"{name} against {ref['sampling']} ppc {ref['ppc']:g}, dx {ref['dx'] * 1e3:.2g} mm "
                               f"(mean of seeds {ref['seeds']})\no lattice, s jitter, ^ Poisson; colour: ppc 2, 2.45, "
                               "3, 4; open: seeds > 0; label: dx (mm)", fontsize=8)
    return _save(fig, path, 100)
