"""Figures (matplotlib, the optional ``plot`` extra)."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_stress_path"]


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
