"""Figures of a calibration: the fit against the data, the optimiser's history, a loss landscape
(or a loss curve, for a sweep over one key).

matplotlib is an optional dependency (the ``plot`` extra); it is imported only here.
"""

from __future__ import annotations

import pathlib

import numpy as np

from .protocol import ObjectiveLike

__all__ = ["fit_figures", "law_figures", "likelihood_figures", "plot_coverage", "plot_emulated", "plot_fit",
           "plot_grid_term", "plot_heldout", "plot_history", "plot_landscape", "plot_loss_curve", "plot_nuts",
           "plot_posterior_predictive", "plot_profile_likelihoods", "plot_runout_law", "sweep_figures",
           "twin_landscape_figure"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path, dpi: int) -> pathlib.Path:
    """Lay out, write and close ``fig``; the written path."""
    fig.tight_layout()
    path = pathlib.Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_fit(objective: ObjectiveLike, result, path, *, initial_prediction=None, truth_label: str = "data",
             title: str | None = None):
    """Modelled against measured profiles (one panel per profile time) and the front history."""
    plt = _plt()
    members = objective.members
    preds = result.prediction.get("members", [result.prediction]) if isinstance(result.prediction, dict) else [
        result.prediction]
    inits = None
    if initial_prediction is not None:
        inits = initial_prediction.get("members", [initial_prediction])
    panels = []
    for i, (obj, pred) in enumerate(zip(members, preds)):
        offset, obs, h_all = 0, obj.observations, np.asarray(obj.data["h"], float)
        for x, t in zip(obs.profile_x, obs.profile_times):
            sl = slice(offset, offset + x.size)
            offset += x.size
            init = None if inits is None else np.asarray(inits[i]["h"])[sl]
            panels.append(("profile", i, x, h_all[sl], np.asarray(pred["h"])[sl], init, t))
        if obs.front_times is not None:
            init = None if inits is None else np.asarray(inits[i]["front"])
            panels.append(("front", i, obs.front_times, np.asarray(obj.data["front"], float),
                           np.asarray(pred["front"]), init, None))
    n = len(panels)
    cols = min(n, 4)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.9 * rows), squeeze=False)
    for ax, (kind, i, x, data, model, init, t) in zip(axes.flat, panels):
        scale = 100.0  # cm
        if kind == "profile":
            ax.plot(x * scale, data * scale, "o", ms=3, color="0.3", label=truth_label)
            if init is not None:
                ax.plot(x * scale, init * scale, ":", color="tab:gray", label="start")
            ax.plot(x * scale, model * scale, "-", color="tab:red", label="fit")
            ax.set_xlabel("x (cm)")
            ax.set_ylabel("h (cm)")
            ax.set_title(f"profile at t = {t:.3g} s" + (f" [{i}]" if len(members) > 1 else ""), fontsize=9)
        else:
            ax.plot(x, data * scale, "o", ms=3, color="0.3", label=truth_label)
            if init is not None:
                ax.plot(x, init * scale, ":", color="tab:gray", label="start")
            ax.plot(x, model * scale, "-", color="tab:red", label="fit")
            ax.set_xlabel("t (s)")
            ax.set_ylabel("front x_f (cm)")
            ax.set_title("front position" + (f" [{i}]" if len(members) > 1 else ""), fontsize=9)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    params = ", ".join(f"{k} = {v:.4g}" for k, v in result.theta.items())
    fig.suptitle(title or f"fit: {params}", fontsize=10)
    return _save(plt, fig, path, dpi=110)


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
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
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
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path, dpi=110)


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
        ax.plot(mx, my, ls="none", label=label, mec=style.pop("mec", "k") if "mfc" not in style else style["color"],
                **style)
    if items:
        handles, labels = ax.get_legend_handles_labels()
        order = [labels.index(label) for (label, _), _ in items]
        ax.legend([handles[i] for i in order], [labels[i] for i in order], fontsize=8)
    if failed is not None and len(failed[0]):
        ax.plot(failed[0], failed[1], "kx", ms=6, label="failed run")
    if failed is not None and len(failed[0]) and not items:
        ax.legend(fontsize=8)
    ax.set_xlabel(key_x)
    ax.set_ylabel(key_y)
    ax.set_title(title or f"loss landscape over ({key_x}, {key_y})", fontsize=10)
    return _save(plt, fig, path, dpi=110)


def plot_loss_curve(xs, loss, key, path, *, best=None, title: str | None = None):
    """The loss of a sweep over one key (log scale); NaN (failed members) drawn as crosses on the
    axis; ``best``: the key's value at the lowest loss."""
    plt = _plt()
    xs, loss = np.asarray(xs, float), np.asarray(loss, float)
    order = np.argsort(xs)
    xs, loss = xs[order], loss[order]
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    ok = np.isfinite(loss) & (loss > 0)
    ax.semilogy(xs[ok], loss[ok], "o-", ms=4)
    if np.any(~np.isfinite(loss)):
        floor = float(np.min(loss[ok])) if ok.any() else 1.0
        ax.plot(xs[~np.isfinite(loss)], np.full(int((~np.isfinite(loss)).sum()), floor), "kx", ms=7, label="failed run")
        ax.legend(fontsize=8)
    if best is not None:
        ax.axvline(best, color="r", lw=1, ls="--")
    ax.set_xlabel(key)
    ax.set_ylabel("loss")
    ax.set_title(title or f"loss over {key}", fontsize=10)
    return _save(plt, fig, path, dpi=110)


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
    return _save(plt, fig, path, dpi=110)


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
    fig.suptitle(title or f"95 % intervals over {len(result.rows)} seeds, {100 * result.noise:.3g} % noise "
                 "(grey: true noise given; x: not a fit, no interval)", fontsize=10)
    return _save(plt, fig, path, dpi=120)


def plot_profile_likelihoods(profiles, path, *, truth=None, posterior=None):
    """One panel per ``calibration.likelihood.ProfileLikelihood``: Δχ² against the key's value
    with the Wilks 95 % level (3.84), the profile interval (shaded), the Gauss–Newton one (bars)
    and, from a ``GridPosterior``, its marginal (right axis); a 2D posterior adds a panel of its
    density (its grid points grey) and 95 % region with the fit's point."""
    from .likelihood import DELTA_CHI2_95

    plt = _plt()
    n = len(profiles) + (1 if posterior is not None and len(posterior.keys) == 2 else 0)
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), squeeze=False)
    for ax, prof in zip(axes[0], profiles):
        ax.plot(prof.values, prof.delta_chi2, "o-", color="C0", ms=3, label="profile likelihood")
        ax.axhline(DELTA_CHI2_95, color="0.5", lw=0.8, ls="--")
        lo, hi = prof.ci95
        if lo is not None and hi is not None:
            ax.axvspan(lo, hi, color="C0", alpha=0.12, label="profile 95 %")
        if prof.gn_ci95 is not None:
            ax.errorbar([prof.theta_hat], [DELTA_CHI2_95], xerr=[[prof.theta_hat - prof.gn_ci95[0]],
                        [prof.gn_ci95[1] - prof.theta_hat]], fmt="s", color="C3", capsize=3,
                        label="Gauss-Newton 95 %")
        if truth is not None and prof.key in truth:
            ax.axvline(truth[prof.key], color="k", lw=1, label="truth")
        if posterior is not None and prof.key in posterior.keys:
            twin = ax.twinx()
            twin.plot(*posterior.marginal(prof.key), color="C2", lw=1.2)
            twin.set_ylabel("posterior density", color="C2")
            twin.set_ylim(bottom=0)
        ax.set_xlabel(prof.key)
        ax.set_ylabel(r"$\Delta\chi^2$")
        ax.set_ylim(0, max(3 * DELTA_CHI2_95, 1.1 * float(np.nanmax(prof.delta_chi2[np.isfinite(prof.delta_chi2)]))
                           if np.any(np.isfinite(prof.delta_chi2)) else 3 * DELTA_CHI2_95))
        ax.legend(fontsize=7, loc="upper center")
    if n > len(profiles):
        ax = axes[0][-1]
        # The grid is structured (regular in the whitened coordinates): contour it as a curvilinear grid.
        a, b = (posterior.points[:, i].reshape(posterior.shape) for i in (0, 1))
        w = np.ma.masked_invalid(np.where(np.isfinite(posterior.chi2), posterior.weight, np.nan).reshape(
            posterior.shape))
        ax.contourf(a, b, w / w.max(), levels=12, cmap="Greens")
        dchi2 = np.ma.masked_invalid((posterior.chi2 - np.nanmin(posterior.chi2)).reshape(posterior.shape))
        ax.contour(a, b, dchi2, levels=[2 * np.log(1 / 0.05)], colors="k", linewidths=0.8)  # 95 % (2 dof)
        ax.plot(a.ravel(), b.ravel(), ".", color="0.6", ms=1)
        ax.plot(posterior.theta_hat[posterior.keys[0]], posterior.theta_hat[posterior.keys[1]], "r+", ms=10,
                label="fit")
        if truth is not None:
            ax.plot(truth.get(posterior.keys[0], np.nan), truth.get(posterior.keys[1], np.nan), "kx", label="truth")
        ax.set_xlabel(posterior.keys[0])
        ax.set_ylabel(posterior.keys[1])
        ax.set_title("posterior (flat prior), 95 % region", fontsize=9)
        ax.legend(fontsize=7)
    return _save(plt, fig, path, dpi=120)


def plot_heldout(heldout, path, *, title: str | None = None):
    """The held-out data against the fitted model's prediction and its 95 % band, by block."""
    plt = _plt()
    names = list(heldout.blocks)
    fig, axes = plt.subplots(1, len(names), figsize=(4.6 * len(names), 3.2), squeeze=False)
    for ax, name in zip(axes[0], names):
        b = heldout.blocks[name]
        front = name == "front"
        x = b["at"] if front else 100 * b["at"]
        ax.fill_between(x, 100 * (b["predicted"] - b["band"]), 100 * (b["predicted"] + b["band"]), color="C0",
                        alpha=0.25, label="prediction 95 %")
        ax.plot(x, 100 * b["predicted"], color="C0", label="predicted")
        ax.plot(x, 100 * b["data"], "k.", ms=3, label="held-out data")
        ax.set_xlabel("t (s)" if front else "x (cm)")
        ax.set_ylabel("front x (cm)" if front else f"{name}: h (cm)")
        ax.set_title(f"{name}: RMS {1000 * heldout.rms[name]:.2g} mm, {100 * heldout.inside[name]:.0f} % inside",
                     fontsize=9)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path, dpi=120)


def plot_nuts(posterior, path, *, grid=None, truth=None):
    """A ``calibration.mcmc.McmcPosterior``: the traces of every chain (top row) and each key's
    marginal histogram with the Gauss–Newton normal and, from a ``GridPosterior`` of the same
    target, the quadrature's marginal (bottom row); two keys add the draws over the grid
    posterior's 95 % region."""
    plt = _plt()
    keys = posterior.keys
    pair = len(keys) == 2
    cols = len(keys) + (1 if pair else 0)
    fig, axes = plt.subplots(2, cols, figsize=(4.2 * cols, 6.0), squeeze=False)
    for j, key in enumerate(keys):
        ax = axes[0][j]
        for c in range(posterior.chains):
            ax.plot(posterior.draws[c, :, j], lw=0.7, label=f"chain {c + 1}")
        ax.set_xlabel("draw (after warm-up)")
        ax.set_ylabel(key)
        ax.set_title(f"R-hat {posterior.rhat[key]:.3f}, ESS bulk {posterior.ess_bulk[key]:.0f}, "
                     f"tail {posterior.ess_tail[key]:.0f}", fontsize=9)
        ax = axes[1][j]
        x = posterior.flat()[:, j]
        ax.hist(x, bins=min(30, max(8, x.size // 12)), density=True, color="C0", alpha=0.45, label="NUTS draws")
        lo, hi = ax.get_xlim()
        span = np.linspace(lo, hi, 200)
        mu, se = posterior.theta_hat[key], posterior.gn_stderr[key]
        ax.plot(span, np.exp(-0.5 * ((span - mu) / se) ** 2) / (se * np.sqrt(2 * np.pi)), color="C3",
                label="Gauss-Newton")
        if grid is not None and key in grid.keys:
            ax.plot(*grid.marginal(key), color="C2", label="grid quadrature")
        if truth is not None and key in truth:
            ax.axvline(truth[key], color="k", lw=1, label="truth")
        ax.set_xlabel(key)
        ax.set_ylabel("posterior density")
        ax.set_title(f"mean {posterior.mean[key]:.4g}, sd {posterior.sd[key]:.2g} "
                     f"(GN se {se:.2g})", fontsize=9)
        ax.legend(fontsize=7)
    axes[0][0].legend(fontsize=7)
    if pair:
        ax = axes[1][-1]
        if grid is not None and grid.keys == keys:
            a, b = (grid.points[:, i].reshape(grid.shape) for i in (0, 1))
            dchi2 = np.ma.masked_invalid((grid.chi2 - np.nanmin(grid.chi2)).reshape(grid.shape))
            ax.contour(a, b, dchi2, levels=[2 * np.log(1 / 0.05)], colors="C2", linewidths=1.0)
        flat = posterior.flat()
        ax.plot(flat[:, 0], flat[:, 1], ".", ms=2, alpha=0.6, color="C0")
        ax.plot(posterior.theta_hat[keys[0]], posterior.theta_hat[keys[1]], "r+", ms=10, label="fit")
        if truth is not None:
            ax.plot(truth.get(keys[0], np.nan), truth.get(keys[1], np.nan), "kx", label="truth")
        ax.set_xlabel(keys[0])
        ax.set_ylabel(keys[1])
        ax.set_title("draws; grid posterior's 95 % region (green)", fontsize=9)
        ax.legend(fontsize=7)
        axes[0][-1].axis("off")
        div = sum(posterior.divergences)
        axes[0][-1].text(0.0, 0.5, f"{posterior.chains} chains x {posterior.draws.shape[1]} draws\n"
                         f"(warm-up {posterior.warmup})\ndivergences {div}\nleapfrog steps/draw "
                         f"{np.mean(posterior.steps):.1f}\n{posterior.gradient_evaluations} Jacobians, "
                         f"{posterior.wall_s / 60:.0f} min", fontsize=9, va="center")
    return _save(plt, fig, path, dpi=120)


def plot_emulated(posterior, path, *, truth=None, reference=None, title: str | None = None):
    """A ``calibration.emulator.EmulatedPosterior`` as a corner plot: on the diagonal each key's
    marginal, the emulator's NUTS draws (grey) against the model's posterior (the checked draws
    weighted, blue), with ``reference`` posteriors' means ± sd ({label: (mean, sd) by key}, e.g.
    NUTS on the model) beside them; below it the checked draws of every pair, sized by their
    importance weight; the diagnostics in the corner above."""
    plt = _plt()
    keys = posterior.keys
    k = len(keys)
    thetas, log_w = posterior.checks
    from .emulator import psis

    w = np.exp(psis(log_w)[0])
    flat = posterior.emulated.flat()
    fig, axes = plt.subplots(k, k, figsize=(2.3 * k + 1.2, 2.3 * k + 0.6), squeeze=False)
    for i in range(k):
        for j in range(k):
            ax = axes[i][j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                bins = np.linspace(*np.quantile(flat[:, i], [0.001, 0.999]), 31)
                ax.hist(flat[:, i], bins=bins, density=True, color="0.7", label="emulator's NUTS")
                ax.hist(thetas[:, i], bins=bins, weights=w, density=True, histtype="step", lw=1.5, color="C0",
                        label="model's (weighted)")
                for n, (label, ref) in enumerate((reference or {}).items()):
                    if keys[i] in ref:
                        mu, sd = ref[keys[i]]
                        y = ax.get_ylim()[1] * (0.9 - 0.1 * n)
                        ax.errorbar([mu], [y], xerr=[sd], fmt="o", ms=3, color=f"C{n + 2}", label=label)
                if truth is not None and keys[i] in truth:
                    ax.axvline(truth[keys[i]], color="k", lw=1, label="truth")
                ax.set_yticks([])
                ax.set_title(f"{keys[i]}: {posterior.mean[keys[i]]:.3g} ± {posterior.sd[keys[i]]:.2g}", fontsize=8)
            else:
                ax.scatter(thetas[:, j], thetas[:, i], s=4 + 400 * w, alpha=0.5, color="C0", lw=0)
                if truth is not None and keys[i] in truth and keys[j] in truth:
                    ax.plot(truth[keys[j]], truth[keys[i]], "kx", ms=7)
            if i == k - 1:
                ax.set_xlabel(keys[j])
            if j == 0 and i > 0:
                ax.set_ylabel(keys[i])
            ax.tick_params(labelsize=7)
    em = posterior.emulated
    text = (f"{posterior.jacobians} model Jacobians, {posterior.runs} runs, {posterior.wall_s / 60:.0f} min\n"
            f"emulator's chains: R-hat max {max(em.rhat.values()):.3f}, ESS min {min(em.ess_bulk.values()):.0f}\n"
            f"importance: Pareto k {posterior.pareto_k:.2f}, ESS {posterior.ess_importance:.0f}"
            f"{', failed runs ' + str(posterior.failed_checks) if posterior.failed_checks else ''}\n"
            f"{'converged' if posterior.converged else 'NOT converged'}")
    if k > 1:  # the empty corner above the diagonal: the legend and the diagnostics
        handles, labels = axes[0][0].get_legend_handles_labels()
        info = axes[0][k - 1]
        info.legend(handles, labels, fontsize=7, loc="upper right", frameon=False)
        info.text(1.0, 0.0, text, fontsize=7, ha="right", va="bottom", transform=info.transAxes)
    else:
        axes[0][0].legend(fontsize=6)
        axes[0][0].set_xlabel(text, fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path, dpi=110)


def plot_grid_term(posterior, path, *, truth=None, title: str | None = None):
    """An ``EmulatedPosterior``'s grid term, one panel per key: the 95 % interval of the data
    (thick) and with the grid term (thin) about the mean, the same posterior's means on the
    coarser grids (``grid_posteriors``, with their own intervals) at their dx, and ``truth``: how
    far the answer still moves with the grid, against what the data fix."""
    plt = _plt()
    if posterior.grid is None:
        raise ValueError("posterior: carries no grid term (emulated_posterior(grid_ratio=...))")
    keys = posterior.keys
    fig, axes = plt.subplots(1, len(keys), figsize=(2.4 * len(keys) + 0.6, 3.2), squeeze=False)
    levels = [(posterior.grid.dx, posterior.mean, posterior.ci95)] + [
        (g["dx"], g["mean"], g["ci95"]) for g in posterior.grid_posteriors]
    fine_dx = posterior.grid.dx
    for ax, k in zip(axes[0], keys):
        for n, (dx, mean, ci) in enumerate(levels):
            y = dx / fine_dx
            ax.plot(ci[k], [y, y], color="C0" if n == 0 else "0.5", lw=4, solid_capstyle="butt",
                    label="data's 95 %" if n == 0 else ("coarser grids' 95 %" if n == 1 else None))
            ax.plot([mean[k]], [y], "o", color="C0" if n == 0 else "0.3", ms=4)
        lo, hi = posterior.ci95_with_grid[k]
        ax.plot([lo, hi], [0.8, 0.8], color="C3", lw=1.5, marker="|", ms=8, label="with the grid term")
        ax.plot([levels[i][1][k] for i in range(len(levels))], [lv[0] / fine_dx for lv in levels], ":", color="0.4")
        if truth is not None and k in truth:
            ax.axvline(truth[k], color="k", lw=1, label="truth")
        ax.set_title(k + ("" if posterior.grid_converged[k] else " (grid > data)"), fontsize=9)
        ax.set_ylim(0.6, max(lv[0] for lv in levels) / fine_dx + 0.3)
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("dx / the fit's dx")
    axes[0][0].legend(fontsize=6, loc="upper left")
    if title:
        fig.suptitle(title, fontsize=9)
    return _save(plt, fig, path, dpi=110)


def plot_posterior_predictive(predictive, path, *, title: str | None = None, split: float | None = None):
    """``calibration.mcmc.posterior_predictive``: by block, the measured values against the
    draws' predictions (their 5–95 % band and median) and the measurement noise (±2σ about the
    median, dashed); ``split``: an x (m) drawn as the line between fitted and held-out data."""
    plt = _plt()
    names = list(predictive["blocks"])
    fig, axes = plt.subplots(1, len(names), figsize=(5.6 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        b = predictive["blocks"][name]
        front = name == "front"
        x = b["at"] if front else 100 * b["at"]
        pred = b["predicted"] if front else 100 * b["predicted"]
        lo, med, hi = np.percentile(pred, [5, 50, 95], axis=0)
        ax.fill_between(x, lo, hi, color="C0", alpha=0.3, label=f"{pred.shape[0]} draws, 5-95 %")
        ax.plot(x, med, color="C0", label="median")
        sigma = predictive["noise"].get(name)
        if sigma is not None and not front:
            scale = 100 * np.max(np.abs(b["data"]))  # the profile's noise is relative to its peak
            ax.plot(x, med + 2 * sigma * scale, "C0--", lw=0.7, label="median ± 2 noise sd")
            ax.plot(x, med - 2 * sigma * scale, "C0--", lw=0.7)
        ax.plot(x, b["data"] if front else 100 * b["data"], "k.", ms=3, label="data")
        if split is not None and not front:
            ax.axvline(100 * split, color="0.4", lw=0.8, ls=":", label="fitted | held out")
        ax.set_xlabel("t (s)" if front else "x (cm)")
        ax.set_ylabel("front x (m)" if front else "h (cm)")
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path, dpi=120)


def plot_design(result, path, *, title: str | None = None, data_only: bool = False):
    """The expected 95 % ellipses of the first two keys for the candidate sets of
    ``calibration.design`` (at most eight: the narrowest of each cost, then the recommended one),
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
    for i, c in enumerate(chosen[:8]):
        cov = (c.cov_data if data_only else c.cov)[:2, :2]
        evals, evecs = np.linalg.eigh(cov)
        xy = (evecs * np.sqrt(np.maximum(evals, 0.0))) @ circle * radius + theta[:2, None]
        style = "-" if c is result.recommended else "--"
        ax.plot(xy[0], xy[1], style, color=f"C{i}", lw=2 if c is result.recommended else 1.2,
                label=f"{c.name} (cost {c.cost:g})" + (": recommended" if c is result.recommended else ""))
    tol = result.tolerance * np.abs(theta[:2])
    ax.plot(theta[0] + tol[0] * np.array([-1, 1, 1, -1, -1]), theta[1] + tol[1] * np.array([-1, -1, 1, 1, -1]),
            ":", color="k", lw=1, label=f"±{100 * result.tolerance:g} %")
    ax.plot(theta[0], theta[1], "k+", ms=10)
    ax.set(xlabel=keys[0], ylabel=keys[1] if len(keys) > 1 else "",
           title=title or f"expected 95 % regions of ({keys[0]}, {keys[1]}) before measuring")
    ax.legend(fontsize=7, loc="best")
    return _save(plt, fig, path, 120)


# ---- the figure sets of the command line's studies ----------------------------------------------
def _folder(directory) -> pathlib.Path:
    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    return d


def fit_figures(directory, objective, result, *, prefix: str = "fit", truth=None, initial=None) -> list[str]:
    """A fit's figures in ``directory`` (made if missing): ``PREFIX_profiles.png`` (``plot_fit``)
    and ``PREFIX_history.png`` (``plot_history``, ``truth`` drawn where given); their paths."""
    d = _folder(directory)
    figs = [plot_fit(objective, result, d / f"{prefix}_profiles.png", initial_prediction=initial),
            plot_history(result.history, result.keys, d / f"{prefix}_history.png", truth=truth)]
    return [str(f) for f in figs]


def likelihood_figures(directory, profiles, *, posterior=None) -> list[str]:
    """A fit's profile likelihoods (and its grid posterior, where given) as
    ``fit_likelihood.png`` in ``directory`` (``plot_profile_likelihoods``); its path in a list."""
    return [str(plot_profile_likelihoods(profiles, pathlib.Path(directory) / "fit_likelihood.png",
                                         posterior=posterior))]


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
    failed = list(result.failed)
    fx = np.asarray(result.thetas)[failed, 0] if failed else np.zeros(0)
    fy = np.asarray(result.thetas)[failed, 1] if failed else np.zeros(0)
    marks = {"lowest": (best[keys[0]], best[keys[1]])} if best else None
    return [str(plot_landscape(xs, ys, loss, keys[0], keys[1], d / "landscape.png", marks=marks, failed=(fx, fy)))]


def twin_landscape_figure(directory, landscape) -> pathlib.Path:
    """A twin's loss landscape (``calibration.twin.TwinLandscape``) as ``twin_landscape.png`` in
    ``directory``, the truth, the start and the fit marked; its path."""
    kx, ky = landscape.keys
    xs, ys, loss = landscape.grid()
    return plot_landscape(xs, ys, loss, kx, ky, pathlib.Path(directory) / "twin_landscape.png",
                          marks=landscape.marks, title=f"twin loss over ({kx}, {ky}), others at truth")


def law_figures(directory, result, law) -> list[str]:
    """A runout-law fit's figures (``calibration.scaling.LawResult``) in ``directory`` (made if
    missing): ``law_runout.png`` (``plot_runout_law`` against ``law``) and ``law_history.png``;
    their paths."""
    d = _folder(directory)
    return [str(plot_runout_law(result.to_json()["cases"], d / "law_runout.png", law=law, title=result.law)),
            str(plot_history(result.fit.history, result.fit.keys, d / "law_history.png"))]
