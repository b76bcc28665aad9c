"""Figures of fits, sweeps and studies: profiles against data, histories, landscapes, the runout law,
coverage and designs. matplotlib is imported only when a figure is drawn (the ``plot`` extra).
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..problem.flow_rule import FlowRuleObjective
from ..problem.protocol import ObjectiveLike
from .flow_rule import plot_flow_rule_member

__all__ = [
    "plot_fit", "plot_history", "plot_landscape", "plot_loss_curve", "plot_runout_law", "plot_coverage",
    "plot_ladder", "fit_figures", "sweep_figures", "twin_landscape_figure", "law_figures",
]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path, dpi: int, title: str | None = None) -> pathlib.Path:
    """Title (where given), lay out, write and close ``fig``; the written path."""
    import matplotlib.pyplot as plt

    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = pathlib.Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_fit(objective: ObjectiveLike, result, path, *, title: str | None = None):
    """Modelled against measured profiles (one panel per profile time) and the front history."""
    plt = _plt()
    members = [part for part, _, _ in objective.parts]
    preds = result.prediction.get("members", [result.prediction]) if isinstance(result.prediction, dict) else [
        result.prediction]
    panels = []  # (member, x or t, data, model, the profile's time or None for the front)
    for i, (obj, pred) in enumerate(zip(members, preds)):
        if isinstance(obj, FlowRuleObjective):
            continue  # a closed form's table (an incline): its own figure (fit_figures)
        offset, obs, h_all = 0, obj.observations, np.asarray(obj.data["h"], float)
        for x, t in zip(obs.profile_x, obs.profile_times):
            sl = slice(offset, offset + x.size)
            offset += x.size
            panels.append((i, x, h_all[sl], np.asarray(pred["h"])[sl], t))
        if obs.front_times is not None:
            panels.append((i, obs.front_times, np.asarray(obj.data["front"], float), np.asarray(pred["front"]), None))
    n = len(panels)
    cols = min(n, 4)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.9 * rows), squeeze=False)
    for ax, (i, x, data, model, t) in zip(axes.flat, panels):
        front = t is None
        x = x if front else 100 * x  # lengths in cm
        ax.plot(x, 100 * data, "o", ms=3, color="0.3", label="data")
        ax.plot(x, 100 * model, "-", color="tab:red", label="fit")
        ax.set(xlabel="t (s)" if front else "x (cm)", ylabel="front x_f (cm)" if front else "h (cm)")
        what = "front position" if front else f"profile at t = {t:.3g} s"
        ax.set_title(what + (f" [{i}]" if len(members) > 1 else ""), fontsize=9)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    params = ", ".join(f"{k} = {v:.4g}" for k, v in result.theta.items())
    return _save(fig, path, dpi=110, title=title or f"fit: {params}")


def plot_history(history, keys, path, *, truth=None, title: str | None = None):
    """Loss (log scale) and each parameter against iteration; rejected LM trials hollow."""
    plt = _plt()
    loss = np.asarray(history["loss"])
    theta = np.asarray(history["theta"])
    accepted = np.asarray(history["accepted"], bool)
    it = np.arange(loss.size)
    n = len(keys)
    fig, axes = plt.subplots(1, n + 1, figsize=(3.2 * (n + 1), 2.8))
    ax = axes[0]
    ax.semilogy(it[accepted], loss[accepted], "o-", ms=3, color="tab:blue", label="accepted")
    if (~accepted).any():
        ax.semilogy(it[~accepted], loss[~accepted], "o", ms=4, mfc="none", color="tab:gray", label="rejected")
        ax.legend(fontsize=8)
    ax.set(xlabel="iteration", ylabel="loss")
    ax.grid(alpha=0.3)
    for j, key in enumerate(keys):
        ax = axes[j + 1]
        ax.plot(it[accepted], theta[accepted, j], "o-", ms=3, color="tab:red")
        if truth is not None and key in truth:
            ax.axhline(truth[key], color="k", ls="--", lw=1, label="true")
            ax.legend(fontsize=8)
        ax.set_xlabel("iteration")
        ax.set_title(key, fontsize=10)
        ax.grid(alpha=0.3)
    return _save(fig, path, dpi=110, title=title)


def plot_landscape(xs, ys, loss, key_x, key_y, path, *, marks=None, failed=None, title: str | None = None):
    """log10 loss over a grid of two parameters (``loss[j, i]`` at ``(xs[i], ys[j])``, as
    ``SweepResult.landscape`` returns it); ``marks``: {label: (x, y)} points to draw;
    ``failed``: (x, y) arrays of members whose runs failed (drawn as crosses)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.0, 4.0))
    z = np.log10(np.asarray(loss, float))
    cs = ax.contourf(xs, ys, z, levels=20, cmap="viridis")
    fig.colorbar(cs, ax=ax, label="log10 loss")
    styles = ({"marker": "*", "color": "r", "ms": 12}, {"marker": "^", "color": "w", "ms": 9},
              {"marker": "o", "color": "w", "mfc": "none", "ms": 14, "mew": 2}, {"marker": "s", "color": "m", "ms": 8})
    items = list(zip((marks or {}).items(), styles))
    for (label, (mx, my)), style in reversed(items):  # the first mark (the truth) on top
        ax.plot(mx, my, ls="none", label=label, mec=style["color"] if "mfc" in style else "k", **style)
    if items:
        handles, labels = ax.get_legend_handles_labels()
        order = [labels.index(label) for (label, _), _ in items]
        ax.legend([handles[i] for i in order], [labels[i] for i in order], fontsize=8)
    if failed is not None and len(failed[0]):
        ax.plot(failed[0], failed[1], "kx", ms=6, label="failed run")
        if not items:
            ax.legend(fontsize=8)
    ax.set(xlabel=key_x, ylabel=key_y)
    ax.set_title(title or f"loss landscape over ({key_x}, {key_y})", fontsize=10)
    return _save(fig, path, dpi=110)


def plot_loss_curve(xs, loss, key, path, *, best=None, title: str | None = None):
    """The loss of a sweep over one key (log scale); NaN (failed members) drawn as crosses on the
    axis; ``best``: the key's value at the lowest loss."""
    plt = _plt()
    xs, loss = np.asarray(xs, float), np.asarray(loss, float)
    order = np.argsort(xs)
    xs, loss = xs[order], loss[order]
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    ok = np.isfinite(loss) & (loss > 0)
    failed = ~np.isfinite(loss)
    ax.semilogy(xs[ok], loss[ok], "o-", ms=4)
    if failed.any():
        floor = float(np.min(loss[ok])) if ok.any() else 1.0
        ax.plot(xs[failed], np.full(int(failed.sum()), floor), "kx", ms=7, label="failed run")
        ax.legend(fontsize=8)
    if best is not None:
        ax.axvline(best, color="r", lw=1, ls="--")
    ax.set(xlabel=key, ylabel="loss")
    ax.set_title(title or f"loss over {key}", fontsize=10)
    return _save(fig, path, dpi=110)


def plot_runout_law(cases, path, *, law, title: str | None = None):
    """Normalised runout ΔL/L0 against aspect ratio: the law, the model before and after the fit;
    filled markers for the aspect ratios used in the fit, hollow for the predicted ones."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.0, 3.8))
    a = np.array([c["a"] for c in cases])
    grid = np.geomspace(a.min() * 0.8, a.max() * 1.2, 200)
    try:
        ax.loglog(grid, law(grid), "k-", lw=1, label="scaling law (secondary)")
    except ValueError:  # a tabulated law: only its points
        order = np.argsort(a)
        ax.loglog(a[order], np.array([c["law"] for c in cases])[order], "k+--", lw=1, label="scaling law (table)")
    used = np.array([c["used_in_fit"] for c in cases])
    start = np.array([c["model_start"] for c in cases])
    fitted = np.array([c["model_fit"] for c in cases])
    ax.loglog(a, start, "s", color="tab:gray", mfc="none", label="model, start")
    ax.loglog(a[used], fitted[used], "o", color="tab:red", label="model, fitted (used in fit)")
    if (~used).any():
        ax.loglog(a[~used], fitted[~used], "o", color="tab:red", mfc="none", ms=8, label="model, fitted (predicted)")
    ax.set_xlabel("aspect ratio a = H0/L0")
    ax.set_ylabel("ΔL/L0")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(title or "runout against aspect ratio", fontsize=10)
    return _save(fig, path, dpi=110)


def plot_coverage(result, path, *, title: str | None = None):
    """Every seed's fitted value and 95 % interval (estimated noise; the given-noise interval
    faint behind it) against the truth, one panel per key, misses in red."""
    plt = _plt()
    keys = result.keys
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 0.22 * len(result.rows) + 1.8), squeeze=False)
    for ax, k in zip(axes[0], keys):
        truth = result.truth[k]
        for i, row in enumerate(result.rows):
            value = row.theta[k]
            if row.ci95_given is not None:
                lo, hi = row.ci95_given[k]
                ax.plot([lo, hi], [i, i], color="0.75", lw=5, solid_capstyle="butt")
            if row.ci95 is None:
                ax.plot(value, i, "x", color="tab:orange")
                continue
            lo, hi = row.ci95[k]
            color = "tab:blue" if lo <= truth <= hi else "tab:red"
            ax.plot([lo, hi], [i, i], color=color, lw=1.8)
            ax.plot(value, i, "o", color=color, ms=3.5)
        ax.axvline(truth, color="k", lw=1, ls="--")
        rate = result.rate(k)
        ax.set_title(f"{k}: {rate['hits']}/{rate['of']} intervals hold the truth", fontsize=10)
        ax.set_xlabel(k)
        ax.set_yticks(range(len(result.rows)))
        ax.set_yticklabels([str(r.seed) for r in result.rows], fontsize=7)
    axes[0][0].set_ylabel("noise seed")
    title = title or (f"95 % intervals over {len(result.rows)} seeds, {100 * result.noise:.3g} % noise (grey: true "
                      "noise given; x: not a fit, no interval)")
    return _save(fig, path, dpi=120, title=title)


def plot_design(result, path, *, title: str | None = None, data_only: bool = False):
    """The expected 95 % ellipses of the first two keys for the candidate sets of
    ``calibration.design.design`` (at most eight: the narrowest of each cost, then the recommended one),
    centred on θ, with the tolerance as a dotted box. ``data_only``: the data's share alone
    (without the particle draw's and the grid's)."""
    plt = _plt()
    keys, theta = result.keys, result.theta
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    def widest(c):  # the candidate's largest relative half-width, of what is drawn
        return float(np.max((c.halfwidth_data if data_only else c.halfwidth) / np.maximum(np.abs(theta), 1e-12)))

    chosen = [min((c for c in result.candidates if c.cost == cost), key=widest)
              for cost in sorted({c.cost for c in result.candidates})]
    if result.recommended is not None and result.recommended not in chosen:
        chosen.append(result.recommended)
    t = np.linspace(0.0, 2.0 * np.pi, 200)
    circle = np.stack([np.cos(t), np.sin(t)])
    radius = np.sqrt(5.991)  # the 95 % quantile of chi-square with two degrees of freedom
    tol = result.tolerance * np.abs(theta[:2])
    regions = []
    for c in chosen[:8]:
        evals, evecs = np.linalg.eigh((c.cov_data if data_only else c.cov)[:2, :2])
        regions.append((evecs * np.sqrt(np.maximum(evals, 0.0))) @ circle * radius)
    # The window: every region within twice |θ| of it (a key a set does not see, e.g. β from an
    # incline alone, has a region of thousands of |θ|: drawn, but beyond the axes, and said so).
    span = np.abs(np.stack(regions)).max(axis=2)  # (regions, 2) half-extents
    shown = span[np.all(span <= 2.0 * np.abs(theta[:2]), axis=1)]
    window = np.maximum(1.5 * tol, shown.max(axis=0) if shown.size else 2.0 * tol)
    for i, (c, xy, extent) in enumerate(zip(chosen, regions, span)):
        beyond = " (beyond the axes)" if np.any(extent > 1.001 * window) else ""
        style = "-" if c is result.recommended else "--"
        ax.plot(xy[0] + theta[0], xy[1] + theta[1], style, color=f"C{i}", lw=2 if c is result.recommended else 1.2,
                label=f"{c.name} (cost {c.cost:g})" + (": recommended" if c is result.recommended else "") + beyond)
    ax.set(xlim=(theta[0] - 1.05 * window[0], theta[0] + 1.05 * window[0]),
           ylim=(theta[1] - 1.05 * window[1], theta[1] + 1.05 * window[1]))
    ax.plot(theta[0] + tol[0] * np.array([-1, 1, 1, -1, -1]), theta[1] + tol[1] * np.array([-1, -1, 1, 1, -1]),
            ":", color="k", lw=1, label=f"±{100 * result.tolerance:g} %")
    ax.plot(theta[0], theta[1], "k+", ms=10)
    ax.set(xlabel=keys[0], ylabel=keys[1] if len(keys) > 1 else "",
           title=title or f"expected 95 % regions of ({keys[0]}, {keys[1]}) before measuring")
    ax.legend(fontsize=7, loc="best")
    return _save(fig, path, dpi=120)


# ---- the figure sets of the command line's studies ----------------------------------------------
def plot_ladder(ladder, path, *, truth=None, title: str | None = None):
    """A ladder of fits (``LadderResult.to_json()``, as the fit's JSON holds it under "ladder"),
    one panel per key: each rung's fitted value against its dx, the reported point with its 95 %
    interval where there is one (at dx = 0 where it is Richardson's extrapolation, else the finest
    fit's at its dx), the power law the three rungs fix where they converge, and ``truth``
    ({key: value}) where given."""
    plt = _plt()
    keys, rungs, ci95 = list(ladder["point"]), ladder["rungs"], ladder["ci95"]
    extrapolated = ladder["extrapolated"]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 3.2), squeeze=False)
    dx = np.array([r["dx"] for r in rungs]) * 1e3
    for ax, k in zip(axes[0], keys):
        values = np.array([r["theta"][k] for r in rungs])
        ax.plot(dx, values, "o-", color="C0", label="fit at each grid")
        point = ladder["point"][k]
        at = 0.0 if extrapolated else dx[-1]  # a point not extrapolated stays at its grid
        if extrapolated:
            h = np.linspace(0.0, dx.max(), 50)
            p = ladder["grid"]["order_observed"]
            ax.plot(h, point + (values[-1] - point) * (h / dx[-1]) ** p, ":", color="C0", lw=1,
                    label=f"θ* + C dx^{p:.2g}")
        if ci95 is not None:
            lo, hi = ci95[k]
            ax.errorbar([at], [point], yerr=[[point - lo], [hi - point]], fmt="none", ecolor="C3", capsize=4)
        what = "extrapolated to dx = 0" if extrapolated else "finest fit (not extrapolated)"
        ax.plot([at], [point], "*", color="C3", ms=11,
                label=what + (", 95 % interval" if ci95 is not None else ", no interval: not a fit"))
        if truth is not None and k in truth:
            ax.axhline(truth[k], color="k", ls="--", lw=1, label="truth")
        ax.set_xlabel("dx (mm)")
        ax.set_ylabel(k)
        ax.set_xlim(left=-0.05 * dx.max())
    axes[0][0].legend(fontsize=7)
    return _save(fig, path, 130, title or f"Fits on {len(dx)} grids, ratio {ladder['ratio']:g}")


def _folder(directory) -> pathlib.Path:
    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    return d


def fit_figures(directory, objective, result, *, prefix: str = "fit", truth=None) -> list[str]:
    """A fit's figures in ``directory`` (made if missing): ``PREFIX_profiles.png`` (``plot_fit``)
    and ``PREFIX_history.png`` (``plot_history``, ``truth`` drawn where given); their paths."""
    d = _folder(directory)
    figs = [plot_fit(objective, result, d / f"{prefix}_profiles.png")] if not all(
        isinstance(member, FlowRuleObjective) for member, _, _ in objective.parts) else []
    figs.append(plot_history(result.history, result.keys, d / f"{prefix}_history.png", truth=truth))
    theta = np.array([result.theta[k] for k in result.keys])
    inclines = [(member, index) for member, index, _ in objective.parts if isinstance(member, FlowRuleObjective)]
    for n, (member, index) in enumerate(inclines):  # an incline in a joint fit: its table against the model
        name = f"{prefix}_flow_rule.png" if len(inclines) == 1 else f"{prefix}_flow_rule_{n + 1}.png"
        figs.append(plot_flow_rule_member(member, theta[np.asarray(index)], d / name, result))
    return [str(f) for f in figs]


def sweep_figures(directory, result, keys) -> list[str]:
    """A sweep's figure in ``directory`` (made if missing): ``loss.png``, the loss over one swept
    key, or ``landscape.png``, the landscape over the first two (a grid), with the lowest member
    and the failed ones marked; its path in a list."""
    d = _folder(directory)
    best = result.best() if result.ok.any() else None
    if len(keys) == 1:
        return [str(plot_loss_curve(result.thetas[:, 0], result.loss, keys[0], d / "loss.png",
                                    best=best[keys[0]] if best else None))]
    xs, ys, loss = result.landscape(keys[0], keys[1])
    failed = np.asarray(result.thetas)[list(result.failed)]
    marks = {"lowest": (best[keys[0]], best[keys[1]])} if best else None
    return [str(plot_landscape(xs, ys, loss, keys[0], keys[1], d / "landscape.png", marks=marks,
                               failed=(failed[:, 0], failed[:, 1])))]


def twin_landscape_figure(directory, landscape) -> pathlib.Path:
    """A twin's loss landscape (``calibration.studies.twin.TwinLandscape``) as ``twin_landscape.png`` in
    ``directory``, the truth, the start and the fit marked; its path."""
    kx, ky = landscape.keys
    xs, ys, loss = landscape.grid()
    return plot_landscape(xs, ys, loss, kx, ky, pathlib.Path(directory) / "twin_landscape.png",
                          marks=landscape.marks, title=f"twin loss over ({kx}, {ky}), others at truth")


def law_figures(directory, result, law) -> list[str]:
    """A runout-law fit's figures (``calibration.studies.scaling.LawResult``) in ``directory`` (made if
    missing): ``law_runout.png`` (``plot_runout_law`` against ``law``) and ``law_history.png``;
    their paths."""
    d = _folder(directory)
    walls = result.side_walls
    friction = None if walls is None else (walls.friction if isinstance(walls.friction, str) else f"{walls.friction:g}")
    title = result.law if walls is None else (f"{result.law}\nchannel {walls.width * 100:g} cm wide, wall friction "
                                              f"{friction}, K = {walls.lateral_pressure_ratio:g}")
    return [str(plot_runout_law(result.to_json()["cases"], d / "law_runout.png", law=law, title=title)),
            str(plot_history(result.fit.history, result.fit.keys, d / "law_history.png"))]
