r"""Roughness of the loss along the β–μ1 valley: docs/results/valley_roughness.json
and docs/figures/calibration_valley_roughness.png.

S4 with p_c0 = 500 Pa, ξ = 50, dx = L/8, one final profile (50 points) of the first far twin
(β = 0.1, μ1 = 0.3; docs/results/calibration_twins_far.json). Each configuration fits its own
noise-free twin (its own prediction at the truth), so every curve has its minimum at the truth;
the loss is evaluated along the valley's floor direction (Δμ1 = −0.24 Δβ, the data's worst-fixed
combination there) at two spacings: Δβ = 0.005 over [0.02, 0.30] and Δβ = 2e-4 over ±0.004.
Roughness: the rms of the loss about a local quadratic (Savitzky–Golay, 7 points), in χ² units of
a 2 % noise on the 50 points. Run from the repository root, on the twin's profile made as in docs/calibration.md:

    python -m jaxmpm run cohesive-collapse --dx 0.011125 --set pc0=500 --set xi=50 --set beta=0.1 \
        --set mu1=0.30 --profile-csv twin.csv
    python docs/scripts/valley_roughness.py twin.csv     # about 15 minutes on 2 cores
    python docs/scripts/valley_roughness.py --plot-only  # the figure from the saved JSON
"""

import json
import pathlib
import sys
import time

import numpy as np
from scipy.signal import savgol_filter

import calibration as cal
from calibration.problem.composite import CompositeObjective
from jaxmpm.scenes import S4_SIDE, build_scene

ROOT = pathlib.Path(__file__).resolve().parents[2]
DX, VALUES, KEYS, TRUTH = S4_SIDE / 8, {"pc0": 500.0, "xi": 50.0}, ("beta", "mu1"), np.array([0.1, 0.3])
SIGMA_NOISE, SLOPE = 0.02, -0.24
CONFIGS = {
    "default (jittered 3 × 3, kernel = spacing)": {},
    "kernel width × 2": {"sigma_factor": 2.0},
    "4 × 4 particles per cell": {"ppc": 4},
    "ensemble of 4 sampling seeds": {"seeds": 4},
}


def objective(cfg, profile):
    if "seeds" in cfg:
        return CompositeObjective([cal.Objective(build_scene("cohesive-collapse", dx=DX, values=VALUES, seed=s), KEYS,
                                                 profile=profile) for s in range(cfg["seeds"])])
    scene = build_scene("cohesive-collapse", dx=DX, values=VALUES, ppc=cfg.get("ppc"))
    sigma = cfg["sigma_factor"] * DX / scene.info.ppc if "sigma_factor" in cfg else None
    return cal.Objective(scene, KEYS, profile=profile, sigma=sigma)


def roughness(loss, members, m):
    smooth = savgol_filter(loss, 7, 2)
    return float(np.sqrt(np.mean((loss - smooth)[3:-3] ** 2))) * m / SIGMA_NOISE ** 2 / members


def main(twin_csv):
    data = cal.load_profile(twin_csv)
    out = {}
    for name, cfg in CONFIGS.items():
        probe = objective(cfg, data)
        members = getattr(probe, "members", (probe,))
        # This configuration's own noise-free twin: its prediction at the truth on the data's x.
        h = np.mean([np.asarray(m.residuals(TRUTH)[1]["h"], float) for m in members], axis=0)
        obj = objective(cfg, cal.ProfileTarget(np.asarray(data.x), h, data.time_s))
        t0, res = time.perf_counter(), {}
        for label, ts in (("wide", np.linspace(-0.08, 0.2, 57)), ("zoom", np.linspace(-0.004, 0.004, 41))):
            loss = np.array([obj.loss(TRUTH + t * np.array([1.0, SLOPE])) for t in ts])
            res[label] = {"t": ts.tolist(), "loss": loss.tolist(),
                          "roughness_chi2": roughness(loss, len(members), np.asarray(data.x).size)}
            print(name, label, f"roughness {res[label]['roughness_chi2']:.3g} chi2", flush=True)
        res.update(wall_s=time.perf_counter() - t0, members=len(members),
                   particles=sum(int(m.scene.state.x.shape[0]) for m in members),
                   min_loss=float(min(res["wide"]["loss"])))
        out[name] = res
    (ROOT / "docs" / "results" / "valley_roughness.json").write_text(json.dumps(out, indent=1))
    plot(out)


def plot(out):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, res in out.items():
        for ax, label in zip(axes, ("wide", "zoom")):
            t, loss = np.array(res[label]["t"]), np.array(res[label]["loss"])
            chi2 = loss * 50 / SIGMA_NOISE ** 2 / res["members"]
            ax.plot(TRUTH[0] + t, chi2 - chi2.min(), ".-", ms=3,
                    label=f"{name}: roughness {res[label]['roughness_chi2']:.2g} χ²")
    axes[0].set_yscale("symlog", linthresh=1.0)  # linear below 1, logarithmic above
    for ax, title in zip(axes, ("along the valley floor, Δβ = 0.005", "near the truth, Δβ = 2e-4 (linear)")):
        ax.axvline(TRUTH[0], color="k", lw=0.8, ls="--")
        ax.set_xlabel("β (μ1 = 0.3 − 0.24 (β − 0.1))")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("χ² − its minimum, at 2 % noise (50 points)")
    fig.suptitle("S4 twin (β 0.1, μ1 0.3), dx = L/8: the loss along the β–μ1 valley", fontsize=10)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "figures" / "calibration_valley_roughness.png", dpi=120)


if __name__ == "__main__":
    if sys.argv[1:] == ["--plot-only"]:
        plot(json.loads((ROOT / "docs" / "results" / "valley_roughness.json").read_text()))
    else:
        main(sys.argv[1])
