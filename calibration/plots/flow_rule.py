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
    member = types.SimpleNamespace(table=objective.table, material=objective.material, side_walls=objective.side_walls,
                                   theta=dict(zip(objective.keys, theta.tolist())),
                                   residuals=np.asarray(objective.residuals(theta)[0], float),
                                   message=result.message, iterations=result.iterations)
    return plot_flow_rule(member, pathlib.Path(path).parent, pathlib.Path(path).name)


def plot_flow_rule(result, directory, name: str = "flow_rule.png") -> pathlib.Path:
    """Draw ``result`` (a ``FlowRuleResult``): u/sqrt(g h) against h/d at each slope (a profile's
    table: the height z/h against u, one line per slope and thickness), the data as points and
    the fit as lines, and each row's relative residual beside it; written to
    ``directory``/``name`` (the folder made if missing), whose path it returns."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table, p = result.table, {**result.material, **result.theta}
    p["side_walls"] = getattr(result, "side_walls", None)  # the model between the chute's walls, as fitted
    fig, (ax, res) = plt.subplots(1, 2, figsize=(10, 4.2), gridspec_kw={"width_ratios": [3, 2]})
    colours = plt.cm.viridis(np.linspace(0.0, 0.9, table.slopes.size))
    draw = _draw_profile if table.quantity == "profile" else _draw_flow_rule
    for colour, slope in zip(colours, table.slopes):
        rows = table.slope_deg == slope
        draw(ax, table, rows, slope, p, colour)
        along = table.z[rows] / table.h[rows] if table.quantity == "profile" else table.h[rows] / p["d"]
        res.plot(along, 100 * result.residuals[rows], "o", color=colour)
    fitted = ", ".join(f"{k} = {v:.4g}" for k, v in result.theta.items())
    fig.suptitle(table.experiment, fontsize=9)
    ax.set_title(fitted, fontsize=9)
    ax.legend(title="slope", fontsize=8)
    res.axhline(0.0, color="0.5", lw=0.8)
    res.set(xlabel="z / h" if table.quantity == "profile" else "h / d", ylabel="model / data − 1 (%)")
    res.set_title(f"{result.message.split(':')[0]} after {result.iterations} iterations", fontsize=9)
    fig.tight_layout()
    path = pathlib.Path(directory) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _model(p, h, slope, quantity, height=None):
    walls = p["side_walls"]
    mu_w = p["mu_w"] if walls is not None and walls.friction == "mu_w" else None
    with x64():
        return np.asarray(steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"], quantity,
                                          walls, mu_w, height=height))


def _draw_flow_rule(ax, table, rows, slope, p, colour) -> None:
    """One slope of a flow-rule table: u/sqrt(g h) against h/d, the data and the model."""
    d, g, h = p["d"], 9.81, table.h[rows]
    ax.plot(h / d, table.u[rows] / np.sqrt(g * h), "o", color=colour, label=f"{slope:g}°")
    line = np.linspace(0.0, 1.05 * h.max(), 50)
    u = _model(p, line, slope, table.quantity)
    with np.errstate(invalid="ignore", divide="ignore"):
        ax.plot(line / d, u / np.sqrt(g * line), "-", color=colour)
    what = "depth-averaged" if table.quantity == "depth_averaged" else "surface"
    ax.set(xlabel="h / d", ylabel=f"{what} u / sqrt(g h)")


def _draw_profile(ax, table, rows, slope, p, colour) -> None:
    """One slope of a profile's table: z/h against u, the data and the model, one line per thickness."""
    for k, h in enumerate(np.unique(table.h[rows])):
        at = rows & (table.h == h)
        ax.plot(table.u[at], table.z[at] / h, "o", color=colour, label=f"{slope:g}°" if k == 0 else None)
        line = np.linspace(0.0, h, 50)
        ax.plot(_model(p, h, slope, "profile", line), line / h, "-", color=colour)
    ax.set(xlabel="u (m/s)", ylabel="z / h")
