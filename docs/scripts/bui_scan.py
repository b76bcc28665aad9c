r"""Is the aluminium bars' fit (S7, Bui et al. 2008) the minimum of its loss? The loss of μ1 at
the default dx = H/16, on a 45-point scan from 0.26 to 0.48, for three particle draws (the
default jittered lattice with seeds 0, 1 and 2), against where LM stops from four starts.

    python docs/scripts/bui_scan.py          # about 7 minutes on two cores (three 45-run scans)
    python docs/scripts/bui_scan.py --plot   # the figure again from the JSON
    python docs/scripts/bui_scan.py --slopes # the loss's slope by forward mode and by central
                                             # differences of 1e-6 to 5e-3, float64 (3 minutes)
    python docs/scripts/bui_scan.py --ensemble # mu1 fitted to the three draws' summed loss (their mean),
                                             # from 0.30, 0.36 and 0.45 (11 minutes on one core)
    python docs/scripts/bui_scan.py --probed # the four fits again with the verdict's probe and its
                                             # restarts (the defaults since 2026-12-06; 10 minutes)

Writes docs/results/bui_scan.json and docs/figures/bui_scan.png. Each scan is ``python -m
calibration sweep --scene aluminium-bars --data experiments_data/bui2008/bui2008_final_surface.csv
--over mu1=0.26:0.48:45 --mode loop --seed S``; the fits are ``calibration fit --scene
aluminium-bars --data ... --fit mu1`` from the starts in ``STARTS`` (draw 0, LM's default model).
"""

import argparse
import json
import pathlib
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "docs" / "scripts"))
from lm_models import _json  # noqa: E402  (a command's JSON, kept in a file)

DATA = "experiments_data/bui2008/bui2008_final_surface.csv"
SEEDS = (0, 1, 2)
#: The fits' starts (``--init``; none: the default global search).
STARTS = {"0.30": ["--init", "mu1=0.30"], "0.36 (docs/real_data.md)": ["--init", "mu1=0.36"],
          "0.45": ["--init", "mu1=0.45"], "global search (the default)": []}


def scan(folder: pathlib.Path, seed: int) -> dict:
    out = _json(["-m", "calibration", "sweep", "--scene", "aluminium-bars", "--data", DATA, "--over",
                 "mu1=0.26:0.48:45", "--mode", "loop", "--seed", str(seed), "--no-progress", "--json"],
                folder / f"scan_seed{seed}.json")
    return {"mu1": np.asarray(out["thetas"], float)[:, 0].tolist(), "loss": out["loss"], "wall_s": out["wall_s"]}


def fit(folder: pathlib.Path, name: str, extra: list[str]) -> dict:
    out = _json(["-m", "calibration", "fit", "--scene", "aluminium-bars", "--data", DATA, "--fit", "mu1", *extra,
                 "--workers", "1", "--no-progress", "--json"], folder / f"fit_{name.split()[0]}.json")
    return {"mu1": out["params"]["mu1"], "loss": out["loss"], "ci95": out.get("ci95", {}).get("mu1"),
            "verdict": out["verdict"]["verdict"], "iterations": out["iterations"], "message": out["message"]}


def probed(folder: pathlib.Path, name: str, extra: list[str]) -> dict:
    """The fit from one of ``STARTS`` with today's defaults: the probe about the end point and up
    to two restarts from the lowest point it ran."""
    out = _json(["-m", "calibration", "fit", "--scene", "aluminium-bars", "--data", DATA, "--fit", "mu1", *extra,
                 "--workers", "1", "--no-progress", "--json"], folder / f"probed_{name.split()[0]}.json")
    probe = out.get("probe") or {}
    return {"mu1": out["params"]["mu1"], "loss": out["loss"], "ci95": out.get("ci95", {}).get("mu1"),
            "verdict": out["verdict"]["verdict"], "reasons": out["verdict"]["reasons"], "wall_s": out["wall_s"],
            "restarts": [{"ended": r["ended"]["mu1"], "probe_lowest": r["probe_lowest"]["mu1"],
                          "probe_rise": r["probe_rise"]} for r in out.get("restarts", [])],
            "probe_rise": probe.get("directions", [{}])[0].get("rise"), "next": out.get("next")}


def summarise(scans: dict) -> dict:
    mu = np.asarray(scans[0]["mu1"])
    losses = np.array([scans[s]["loss"] for s in SEEDS])
    mean = losses.mean(axis=0)
    lowest = {str(s): float(mu[np.argmin(losses[i])]) for i, s in enumerate(SEEDS)}
    near = np.abs(mu - mu[np.argmin(mean)]) <= 0.05  # a parabola through the mean about its lowest point
    a, b, _ = np.polyfit(mu[near], mean[near], 2)
    # The roughness: each draw's loss against a smooth fit of the three draws' mean (degree 6 over the scan).
    smooth = np.polyval(np.polyfit(mu, mean, 6), mu)
    rough = float(np.sqrt(np.mean((losses / smooth - 1) ** 2)))
    return {"lowest_by_seed": lowest, "lowest_of_mean": float(mu[np.argmin(mean)]),
            "parabola_minimum_of_mean": float(-b / (2 * a)), "roughness_rms_relative": rough}


def slopes(points=(0.30, 0.335), steps=(1e-6, 1e-4, 1e-3, 5e-3)) -> list[dict]:
    """dL/dμ1 by forward mode and by central differences of each step, in float64, for draw 0:
    whether LM's slope is the run's (it is, to the smallest step) and how rough the loss is."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import calibration as cal
    from jaxmpm.scenes import build_scene

    objective = cal.Objective(build_scene("aluminium-bars", dtype="float64"), ("mu1",),
                              profile=cal.load_profile(str(ROOT / DATA)))
    out = []
    for mu1 in points:
        r, J, _ = objective.residuals_and_jacobian(np.array([mu1]))
        row = {"mu1": mu1, "loss": float(np.sum(np.asarray(r) ** 2)),
               "forward_mode": float(2 * np.asarray(r) @ np.asarray(J)[:, 0]), "central": {}}
        for h in steps:
            up, down = objective.loss(np.array([mu1 + h])), objective.loss(np.array([mu1 - h]))
            row["central"][f"{h:g}"] = float((up - down) / (2 * h))
        print(json.dumps(row), flush=True)
        out.append(row)
    return out


def ensemble(folder: pathlib.Path) -> dict:
    """μ1 fitted to the three draws at once (a joint fit of the shipped S7 file with ``seed`` set,
    μ1 shared: the sum of the draws' losses), from each start: does the draws' mean loss, less
    rough, take LM to its minimum?"""
    shipped = (ROOT / "experiments_data/experiments/S7_aluminium_bars.toml").read_text()
    files = []
    for seed in SEEDS:
        text = shipped.replace('file = "../bui2008/', f'file = "{ROOT}/experiments_data/bui2008/')
        text = text.replace('name = "aluminium-bars"', f'name = "bars_draw{seed}"')
        seed_line = f'seed = {{ value = {seed}, source = "the particle draw" }}'
        text = text.replace("\ntransfer = ", f"\n{seed_line}\ntransfer = ")
        files.append(folder / f"draw{seed}.toml")
        files[-1].write_text(text)
    out = {}
    for start in ("0.30", "0.36", "0.45"):
        fit = _json(["-m", "calibration", "fit", *map(str, files), "--fit", "mu1", "--shared", "mu1", "--init",
                     f"mu1={start}", "--workers", "1", "--roundoff-samples", "0", "--grid-check", "0", "--no-progress",
                     "--json"], folder / f"ensemble_{start}.json")
        out[start] = {"mu1": fit["params"]["mu1"], "iterations": fit["iterations"], "message": fit["message"],
                      "verdict": fit["verdict"]["verdict"]}
        print(start, json.dumps(out[start]), flush=True)
    return out


def plot(summary: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(12, 4.6))
    for seed, color in zip(SEEDS, ("C0", "C1", "C2")):
        s = summary["scans"][str(seed)]
        ax.plot(s["mu1"], s["loss"], ".-", color=color, lw=0.8, ms=3, label=f"loss scan, particle draw {seed}")
    for (name, f), marker in zip(summary["fits"].items(), "osD^"):
        ax.plot([f["mu1"]], [f["loss"]], marker, color="k", mfc="none", ms=8,
                label=f"LM from {name}: {f['mu1']:.3f} ({f['verdict']})")
    for (name, f), marker in zip(summary.get("probed", {}).items(), "osD^"):
        ax.plot([f["mu1"]], [f["loss"]], marker, color="C3", ms=6,
                label=f"with the probe, from {name}: {f['mu1']:.3f} ({f['verdict']}, "
                      f"{len(f['restarts'])} restart{'' if len(f['restarts']) == 1 else 's'})")
    ax.axvline(summary["summary"]["parabola_minimum_of_mean"], color="0.4", ls="--", lw=0.8,
               label=f"parabola through the draws' mean: {summary['summary']['parabola_minimum_of_mean']:.3f}")
    ax.set(xlabel="μ1", ylabel="loss (sum of squared residuals)", yscale="log",
           title="Bui et al. (2008) bars at dx = H/16: the loss against μ1")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), framealpha=0.9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="/tmp/bui_scan")
    parser.add_argument("--plot", action="store_true")
    parser.add_argument("--slopes", action="store_true", help="only the slopes, added to the results' JSON")
    parser.add_argument("--ensemble", action="store_true", help="only the fits to the three draws at once, added")
    parser.add_argument("--probed", action="store_true", help="only the fits with the probe and its restarts, added")
    args = parser.parse_args(argv)
    results, figure = ROOT / "docs/results/bui_scan.json", ROOT / "docs/figures/bui_scan.png"
    if args.slopes or args.ensemble or args.probed:
        out = json.loads(results.read_text())
        if args.probed:
            folder = pathlib.Path(args.out)
            folder.mkdir(parents=True, exist_ok=True)
            with ThreadPoolExecutor(2) as pool:
                out["probed"] = dict(zip(STARTS, pool.map(lambda n: probed(folder, n, STARTS[n]), STARTS)))
            for name, f in out["probed"].items():
                print(name, json.dumps(f), flush=True)
        if args.slopes:
            out["slopes"] = slopes()
        if args.ensemble:
            folder = pathlib.Path(args.out)
            folder.mkdir(parents=True, exist_ok=True)
            out["ensemble"] = ensemble(folder)
        results.write_text(json.dumps(out, indent=1) + "\n")
        return
    if not args.plot:
        folder = pathlib.Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        with ThreadPoolExecutor(2) as pool:
            scans = dict(zip(SEEDS, pool.map(lambda s: scan(folder, s), SEEDS)))
            fits = dict(zip(STARTS, pool.map(lambda n: fit(folder, n, STARTS[n]), STARTS)))
        out = {"note": __doc__.split("\n\n")[0], "scans": {str(s): v for s, v in scans.items()}, "fits": fits,
               "summary": summarise(scans)}
        results.write_text(json.dumps(out, indent=1) + "\n")
    out = json.loads(results.read_text())
    print(json.dumps(out["summary"], indent=1))
    for name, f in out["fits"].items():
        print(f"from {name}: {f['mu1']:.4f} loss {f['loss']:.3g} {f['verdict']} {f['ci95']} ({f['iterations']} it)")
    plot(out, figure)


if __name__ == "__main__":
    main()
