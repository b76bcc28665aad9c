"""Figures of the checks beyond Gauss–Newton: profile likelihoods, held-out predictions, NUTS and
emulated posteriors, their grid terms and posterior predictions.
"""

from __future__ import annotations

import numpy as np

from .fits import _folder, _plt, _save

__all__ = [
    "plot_profile_likelihoods", "plot_heldout", "plot_nuts", "plot_emulated", "plot_grid_term",
    "plot_posterior_predictive", "likelihood_figures",
]


def plot_profile_likelihoods(profiles, path, *, truth=None, posterior=None):
    """One panel per ``calibration.inference.likelihood.ProfileLikelihood``: Δχ² against the key's value
    with the Wilks 95 % level (3.84), the profile interval (shaded), the Gauss–Newton one (bars)
    and, from a ``GridPosterior``, its marginal (right axis); a 2D posterior adds a panel of its
    density (its grid points grey) and 95 % region with the fit's point."""
    from ..inference.likelihood import DELTA_CHI2_95

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
        ax.set(xlabel=prof.key, ylabel=r"$\Delta\chi^2$")
        finite = prof.delta_chi2[np.isfinite(prof.delta_chi2)]
        ax.set_ylim(0, max(3 * DELTA_CHI2_95, 1.1 * float(finite.max()) if finite.size else 0.0))
        ax.legend(fontsize=7, loc="upper center")
    if n > len(profiles):
        ax = axes[0][-1]
        a, b = _region95(ax, posterior, color="k", lw=0.8)
        w = np.ma.masked_invalid(np.where(np.isfinite(posterior.chi2), posterior.weight, np.nan).reshape(
            posterior.shape))
        ax.contourf(a, b, w / w.max(), levels=12, cmap="Greens")
        ax.plot(a.ravel(), b.ravel(), ".", color="0.6", ms=1)
        _mark_pair(ax, posterior.keys, posterior.theta_hat, truth)
        ax.set_title("posterior (flat prior), 95 % region", fontsize=9)
    return _save(fig, path, dpi=120)


def _region95(ax, grid, *, color, lw):
    """The 95 % region (2 dof) of a two-key ``GridPosterior`` contoured on ``ax``; the grid's
    coordinates (it is regular in the whitened coordinates: a curvilinear grid here)."""
    a, b = (grid.points[:, i].reshape(grid.shape) for i in (0, 1))
    dchi2 = np.ma.masked_invalid((grid.chi2 - np.nanmin(grid.chi2)).reshape(grid.shape))
    ax.contour(a, b, dchi2, levels=[2 * np.log(1 / 0.05)], colors=color, linewidths=lw)
    return a, b


def _mark_pair(ax, keys, theta_hat, truth) -> None:
    """The fit's point (and ``truth``'s, where given) on a panel of two keys, axes labelled."""
    ax.plot(theta_hat[keys[0]], theta_hat[keys[1]], "r+", ms=10, label="fit")
    if truth is not None:
        ax.plot(truth.get(keys[0], np.nan), truth.get(keys[1], np.nan), "kx", label="truth")
    ax.set(xlabel=keys[0], ylabel=keys[1])
    ax.legend(fontsize=7)


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
        ax.set(xlabel="t (s)" if front else "x (cm)", ylabel="front x (cm)" if front else f"{name}: h (cm)")
        ax.set_title(f"{name}: RMS {1000 * heldout.rms[name]:.2g} mm, {100 * heldout.inside[name]:.0f} % inside",
                     fontsize=9)
        ax.legend(fontsize=7)
    return _save(fig, path, dpi=120, title=title)


def plot_nuts(posterior, path, *, grid=None, truth=None):
    """A ``calibration.inference.mcmc.McmcPosterior``: the traces of every chain (top row) and each key's
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
        ax.set(xlabel="draw (after warm-up)", ylabel=key)
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
        ax.set(xlabel=key, ylabel="posterior density")
        ax.set_title(f"mean {posterior.mean[key]:.4g}, sd {posterior.sd[key]:.2g} "
                     f"(GN se {se:.2g})", fontsize=9)
        ax.legend(fontsize=7)
    axes[0][0].legend(fontsize=7)
    if pair:
        ax = axes[1][-1]
        if grid is not None and grid.keys == keys:
            _region95(ax, grid, color="C2", lw=1.0)
        flat = posterior.flat()
        ax.plot(flat[:, 0], flat[:, 1], ".", ms=2, alpha=0.6, color="C0")
        _mark_pair(ax, keys, posterior.theta_hat, truth)
        ax.set_title("draws; grid posterior's 95 % region (green)", fontsize=9)
        axes[0][-1].axis("off")
        div = sum(posterior.divergences)
        axes[0][-1].text(0.0, 0.5, f"{posterior.chains} chains x {posterior.draws.shape[1]} draws\n"
                         f"(warm-up {posterior.warmup})\ndivergences {div}\nleapfrog steps/draw "
                         f"{np.mean(posterior.steps):.1f}\n{posterior.gradient_evaluations} Jacobians, "
                         f"{posterior.wall_s / 60:.0f} min", fontsize=9, va="center")
    return _save(fig, path, dpi=120)


def plot_emulated(posterior, path, *, truth=None, reference=None, title: str | None = None):
    """A ``calibration.inference.emulator.EmulatedPosterior`` as a corner plot: on the diagonal each key's
    marginal, the emulator's NUTS draws (grey) against the model's posterior (the checked draws
    weighted, blue), with ``reference`` posteriors' means ± sd ({label: (mean, sd) by key}, e.g.
    NUTS on the model) beside them; below it the checked draws of every pair, sized by their
    importance weight; the diagnostics in the corner above."""
    plt = _plt()
    keys = posterior.keys
    k = len(keys)
    thetas, log_w = posterior.checks
    from ..inference.surrogates import psis

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
    return _save(fig, path, dpi=110, title=title)


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
        ax.locator_params(axis="x", nbins=4)  # a key fixed to 0.1 % has long tick labels
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("dx / the fit's dx")
    axes[0][0].legend(fontsize=6, loc="upper left")
    if title:
        fig.suptitle(title, fontsize=9)
    return _save(fig, path, dpi=110)


def plot_posterior_predictive(predictive, path, *, title: str | None = None, split: float | None = None):
    """``calibration.inference.mcmc.posterior_predictive``: by block, the measured values against the
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
        ax.set(xlabel="t (s)" if front else "x (cm)", ylabel="front x (m)" if front else "h (cm)")
        ax.legend(fontsize=7)
    return _save(fig, path, dpi=120, title=title)


def likelihood_figures(directory, profiles, *, posterior=None, nuts=None, emulated=None) -> list[str]:
    """The figures of a fit's posterior checks in ``directory``, their paths: the profile
    likelihoods with the grid posterior (``fit_likelihood.png``, where there are profiles), NUTS's
    traces and marginals (``posterior_nuts.png``), the emulated posterior's corner plot
    (``posterior_emulated.png``) and its grid term (``posterior_grid_term.png``, where measured)."""
    folder, paths = _folder(directory), []
    if profiles:
        paths.append(plot_profile_likelihoods(profiles, folder / "fit_likelihood.png", posterior=posterior))
    if nuts is not None:
        paths.append(plot_nuts(nuts, folder / "posterior_nuts.png", grid=posterior))
    if emulated is not None:
        paths.append(plot_emulated(emulated, folder / "posterior_emulated.png"))
        if emulated.grid is not None:
            paths.append(plot_grid_term(emulated, folder / "posterior_grid_term.png"))
    return [str(p) for p in paths]
