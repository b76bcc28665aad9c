"""Does a flow rule's calibrated μ1, μ2, I0 move with the chute's width? Twin flow-rule tables from
the steady flow between side walls (``steady_velocity(side_walls=)``) of S1's glass beads in chutes
2, 5 and 10 cm wide (and 20, 50, 100 cm; μ_w = 0.3, K = 1), 22-28°, 10-40 mm, 1 % noise (seed 0), each fitted with the
wall-free model and with the walls; then μ_w fitted with the rheology from one width and from two;
and the closed form's accuracy against a 10^5-point quadrature (docs/incline_fits.md, "A chute
with side walls").

    python docs/scripts/chute_width.py [--json docs/results/chute_width.json] [--figure docs/figures/chute_width.png]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from calibration import CompositeObjective, FlowRuleObjective, fit
from calibration.data.flow_rule import FlowRuleTable
from calibration.studies.flow_rule import fit_flow_rule
from jaxmpm import SideWalls
from jaxmpm.params import DEFAULTS
from jaxmpm.precision import x64
from jaxmpm.scenes import S1_PARAMS
from jaxmpm.scenes.incline import G, side_wall_velocity, steady_velocity

MATERIAL = {**DEFAULTS, **S1_PARAMS}
KEYS = ("mu1", "mu2", "I0")
TRUTH = {k: MATERIAL[k] for k in KEYS}
FIXED = {k: MATERIAL[k] for k in ("rho", "rho_s", "d")}
WIDTHS = (0.02, 0.05, 0.10)
WIDER = (0.2, 0.5, 1.0)  # where the wall-free model starts to pass for a fit
MU_W, K = 0.3, 1.0
SLOPES, THICKNESSES = (22.0, 24.0, 26.0, 28.0), (0.01, 0.02, 0.03, 0.04)
NOISE, SEED = 0.01, 0
START = {"mu1": 0.36, "mu2": 0.75, "I0": 0.5}


def velocities(h, slope, quantity, walls, mu_w=None, p=MATERIAL):
    with x64():
        return np.asarray(steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"],
                                          quantity, walls, mu_w))


def stop_depth(width, slope):
    """ζ* = W (tan θ − μ1) / (μ_w K): the flow stops below it."""
    return width * (np.tan(np.radians(slope)) - TRUTH["mu1"]) / (MU_W * K)


# ---- the closed form's accuracy -----------------------------------------------------------------------------------
def reference(h, slope, drag, quantity, points=100_001):
    """Simpson's rule on ζ = L s² (s in [0, 1]: no sqrt endpoint), ``points`` points."""
    p, tan = MATERIAL, math.tan(math.radians(slope))
    top = (tan - p["mu1"]) / drag if drag > 0 else math.inf
    length = min(h, top)
    s = np.linspace(0.0, 1.0, points)
    zeta = length * s * s
    mu = tan - drag * zeta
    rate = p["I0"] * (mu - p["mu1"]) / (p["mu2"] - mu) * np.sqrt(p["rho"] * G * math.cos(math.radians(slope))
                                                                 * zeta / p["rho_s"]) / p["d"]
    f = rate * 2.0 * length * s * (1.0 if quantity == "surface" else zeta / h)
    return float((f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum()) * (s[1] - s[0]) / 3)


def gauss_legendre(h, slope, drag, quantity, n):
    """The same integral by n-point Gauss–Legendre on s in [−1, 1] (the integrand is even in s)."""
    p, tan = MATERIAL, math.tan(math.radians(slope))
    length = min(h, (tan - p["mu1"]) / drag) if drag > 0 else h
    s, w = np.polynomial.legendre.leggauss(n)
    zeta = length * s * s
    mu = tan - drag * zeta
    rate = p["I0"] * (mu - p["mu1"]) / (p["mu2"] - mu) * np.sqrt(p["rho"] * G * math.cos(math.radians(slope))
                                                                 * zeta / p["rho_s"]) / p["d"]
    f = rate * 2.0 * length * np.abs(s) * (1.0 if quantity == "surface" else zeta / h)
    return float(0.5 * np.sum(w * f))


def accuracy() -> dict:
    """The closed form's largest relative error against the 10^5-point reference over chutes 1 cm
    to 1 m and wall-free, 21-32.5°, 2-40 mm, both quantities; what Gauss–Legendre would need; and
    the gap to ``side_wall_velocity`` (trapezoid, 4001 points)."""
    cases = [(h, slope, MU_W * K / w if w else 0.0, q) for w in (0.01, 0.02, 0.05, 0.1, 1.0, None)
             for slope in (21.0, 22.0, 25.0, 28.0, 31.0, 32.5) for h in (0.002, 0.01, 0.04)
             for q in ("surface", "depth_averaged")]
    refs = [reference(*c) for c in cases]
    closed = [float(velocities(h, slope, q, SideWalls(MU_W * K / a if a else 1.0, MU_W if a else 0.0, K)))
              for h, slope, a, q in cases]
    gl = {n: max(abs(gauss_legendre(*c, n) / r - 1) for c, r in zip(cases, refs)) for n in (4, 8, 16, 32, 64, 128)}
    gap = {}
    for w in WIDTHS:
        walls, h = SideWalls(w, MU_W, K), 0.03
        z = np.linspace(0.0, h, 4001)
        for slope in (22.0, 28.0):
            profile, _ = side_wall_velocity(z, h, slope, MATERIAL, walls)
            gap[f"W={w:g} m, {slope:g} deg"] = float(velocities(h, slope, "surface", walls) / profile[-1] - 1)
    return {"cases": len(cases), "closed_form_max_rel_error": max(abs(c / r - 1) for c, r in zip(closed, refs)),
            "gauss_legendre_max_rel_error": {str(n): e for n, e in gl.items()},
            "side_wall_velocity_4001_surface_rel_gap": gap}


# ---- the twin -----------------------------------------------------------------------------------------------------
def twin_table(width, to_bed_only: bool, noise: float = NOISE):
    """The table at ``width``: every (slope, thickness) of the plan, or only those whose flow
    reaches the bed (h < ζ*); with 1 % noise drawn for the whole plan (seed 0: the same 16 draws
    at every width)."""
    slope, h = (a.ravel() for a in np.meshgrid(SLOPES, THICKNESSES, indexing="ij"))
    u = velocities(h, slope, "depth_averaged", SideWalls(width, MU_W, K))
    u = u * (1.0 + noise * np.random.default_rng(SEED).standard_normal(u.size))
    keep = h < stop_depth(width, slope) if to_bed_only else np.ones(h.size, bool)
    dropped = [[float(a), float(b)] for a, b in zip(slope[~keep], h[~keep])]
    if keep.sum() <= len(KEYS):
        return None, dropped
    return FlowRuleTable(slope[keep], h[keep], u[keep], "depth_averaged", "chute-width twin", False,
                         experiment=f"S1 beads, W = {width:g} m", noise=NOISE), dropped


def summary(result, truth) -> dict:
    """A fit (a ``FitResult``) as JSON: its point, its 95 % intervals where it gives them (none
    where its verdict is "not a fit of the data"), the truth and the verdict."""
    verdict = result.verdict.to_dict()
    ci = {}
    if result.uncertainty is not None and result.uncertainty.ci95 is not None:
        ci = {k: [float(lo), float(hi)] for k, (lo, hi) in zip(result.keys, result.uncertainty.ci95)
              if lo is not None and hi is not None}
    return {"params": dict(result.theta), "ci95": ci, "truth": truth, "verdict": verdict["verdict"],
            "reasons": verdict.get("reasons", []), "iterations": int(result.iterations),
            "truth_inside_ci95": {k: bool(lo <= truth[k] <= hi) for k, (lo, hi) in ci.items()}}


def twins() -> dict:
    out = {}
    for variant, to_bed in (("all_rows", False), ("to_the_bed", True)):
        rows = {}
        for width in WIDTHS + WIDER:
            table, dropped = twin_table(width, to_bed)
            row = {"rows": 0 if table is None else table.n, "dropped": dropped,
                   "stop_depth_mm": {f"{s:g}": 1e3 * float(stop_depth(width, s)) for s in SLOPES}}
            if table is not None:
                for model, walls in (("wall_free", None), ("walls", SideWalls(width, MU_W, K))):
                    row[model] = summary(fit_flow_rule(table, KEYS, init=START, values=FIXED,
                                                       side_walls=walls).fit, TRUTH)
                exact = twin_table(width, to_bed, noise=0.0)[0]  # the same rows without noise: any bias is here
                fitted = fit_flow_rule(exact, KEYS, init=START, values=FIXED, side_walls=SideWalls(width, MU_W, K))
                row["walls_noise_free_rel_error"] = {k: fitted.theta[k] / TRUTH[k] - 1 for k in KEYS}
            rows[f"{width:g}"] = row
        out[variant] = rows
    return out


def with_mu_w(widths) -> dict:
    """(μ1, μ2, I0, μ_w) fitted to the all-rows tables of ``widths`` together (one composite)."""
    keys = (*KEYS, "mu_w")
    with x64():
        members = [FlowRuleObjective(twin_table(w, False)[0], keys, values=FIXED, dtype="float64",
                                     side_walls=SideWalls(w, "mu_w", K)) for w in widths]
        objective = members[0] if len(members) == 1 else CompositeObjective(members)
        result = fit(objective, {**START, "mu_w": 0.2}, noise=NOISE, workers=1)
    out = summary(result, {**TRUTH, "mu_w": MU_W})
    corr = np.asarray(result.uncertainty.corr) if result.uncertainty is not None else None
    out["corr_mu_w"] = None if corr is None else dict(zip(keys, corr[-1].tolist()))
    return out


def figure(out, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.8))
    for ax, key in zip(axes, ("mu2", "I0")):
        ax.axhline(TRUTH[key], color="0.3", lw=1.0, label="truth")
        for variant, marker, shift in (("all_rows", "o", 0.0), ("to_the_bed", "s", 0.15)):
            for model, colour, dx in (("wall_free", "tab:red", -0.3), ("walls", "tab:blue", 0.3)):
                for w, row in out["twins"][variant].items():
                    if model not in row:
                        continue
                    fit_ = row[model]
                    x = 100 * float(w) * (1.0 + 0.06 * (dx + shift))
                    value, ci = fit_["params"][key], fit_["ci95"].get(key)
                    filled = fit_["verdict"] == "a fit of the data"
                    kw = dict(color=colour, marker=marker, mfc=colour if filled else "none", ls="none")
                    if ci:
                        ax.errorbar([x], [value], yerr=[[value - ci[0]], [ci[1] - value]], capsize=3, **kw)
                    else:
                        ax.plot([x], [value], **kw)
        ax.set(xlabel="chute width W (cm)", ylabel=key, xscale="log")
        ax.set_xticks([100 * w for w in WIDTHS + WIDER], [f"{100 * w:g}" for w in WIDTHS + WIDER])
    handles = [plt.Line2D([], [], color=c, marker="o", ls="none", label=lab)
               for c, lab in (("tab:red", "wall-free model"), ("tab:blue", "model with walls"))]
    handles += [plt.Line2D([], [], color="k", marker=m, ls="none", mfc="none", label=lab)
                for m, lab in (("o", "all 16 rows"), ("s", "rows flowing to the bed"))]
    axes[0].set_yscale("log")
    axes[1].set_yscale("log")
    axes[1].legend(handles=handles, fontsize=8, loc="best")
    fig.suptitle("Flow-rule fits of twins in chutes of width W (μ_w = 0.3, K = 1); open: not a fit of the data",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", default=None)
    parser.add_argument("--figure", default=None)
    args = parser.parse_args()
    start = time.perf_counter()
    out = {"material": {k: MATERIAL[k] for k in ("rho", "rho_s", "d", *KEYS)},
           "walls": {"mu_w": MU_W, "K": K, "widths_m": list(WIDTHS + WIDER)}, "slopes_deg": list(SLOPES),
           "thicknesses_m": list(THICKNESSES), "noise": NOISE, "seed": SEED, "start": START,
           "accuracy": accuracy(), "twins": twins(),
           "mu_w_fits": {"+".join(f"{w:g}" for w in ws): with_mu_w(ws)
                         for ws in ((0.02,), (0.05,), (0.10,), (0.02, 0.10), (0.05, 0.10))}}
    out["wall_s"] = time.perf_counter() - start
    text = json.dumps(out, indent=1, allow_nan=False)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    if args.figure:
        figure(out, args.figure)
    print(text)


if __name__ == "__main__":
    main()
