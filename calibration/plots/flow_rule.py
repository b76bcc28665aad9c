"""The figure of a flow-rule fit: the table's velocities against thickness, slope by slope, with
the fitted model's lines (``calibration.studies.flow_rule``)."""

from __future__ import annotations

import pathlib
import types

import numpy as np

from jaxmpm.precision import x64
from jaxmpm.scenes.incline import steady_velocity

__all__ = ["plot_flow_rule", "plot_flow_rule_member"]


def plot_flow_rule_member(objective, theta, path, result) -> pathlib.Path:
    """The table of ``objective`` (a ``FlowRuleObjective`` in a joint fit) against the model at its
    keys' values ``theta`` (an array in its keys' order), titled with ``result``'s (a fit's) end;
    written to ``path``."""
    theta = np.asarray(theta, float)
    member = types.SimpleNamespace(table=objective.table, material=objective.material,
                                   theta=dict(zip(objective.keys, theta.tolist())),
                                   residuals=np.asarray(objective.residuals(theta)[0], float),
                                   message=result.message, iterations=result.iterations)
    return plot_flow_rule(member, pathlib.Path(path).parent, pathlib.Path(path).name)


def plot_flow_rule(result, directory, name: str = "flow_rule.png") -> pathlib.Path:
    """Draw ``result`` (a ``FlowRuleResult``): u/sqrt(g h) against h/d at each slope, the data as
    points and the fit as lines, and each row's relative residual beside it; written to
    ``directory``/``name`` (the folder made if missing), whose path it returns."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table, p = result.table, {**result.material, **result.theta}
    d, g = p["d"], 9.81
    fig, (ax, res) = plt.subplots(1, 2, figsize=(10, 4.2), gridspec_kw={"width_ratios": [3, 2]})
    colours = plt.cm.viridis(np.linspace(0.0, 0.9, table.slopes.size))
    for colour, slope in zip(colours, table.slopes):
        rows = table.slope_deg == slope
        h = table.h[rows]
        ax.plot(h / d, table.u[rows] / np.sqrt(g * h), "o", color=colour, label=f"{slope:g}°")
        line = np.linspace(0.0, 1.05 * h.max(), 50)
        with x64():
            u = np.asarray(steady_velocity(line, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], d,
                                           table.quantity))
        with np.errstate(invalid="ignore", divide="ignore"):
            ax.plot(line / d, u / np.sqrt(g * line), "-", color=colour)
        res.plot(table.h[rows] / d, 100 * result.residuals[rows], "o", color=colour)
    what = "depth-averaged" if table.quantity == "depth_averaged" else "surface"
    fitted = ", ".join(f"{k} = {v:.4g}" for k, v in result.theta.items())
    fig.suptitle(table.experiment, fontsize=9)
    ax.set(xlabel="h / d", ylabel=f"{what} u / sqrt(g h)")
    ax.set_title(fitted, fontsize=9)
    ax.legend(title="slope", fontsize=8)
    res.axhline(0.0, color="0.5", lw=0.8)
    res.set(xlabel="h / d", ylabel="model / data − 1 (%)")
    res.set_title(f"{result.message.split(':')[0]} after {result.iterations} iterations", fontsize=9)
    fig.tight_layout()
    path = pathlib.Path(directory) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
