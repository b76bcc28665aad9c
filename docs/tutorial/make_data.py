"""The tutorial's stand-in measurements (docs/tutorial.md): column.toml's collapse at a hidden
truth, run on a grid twice as fine as the fit's and with another particle draw, with noise: 1 % of
the peak height on the deposit (a photo, digitised) and 1 mm on the front (a video at 20 frames
a second). Files in millimetres and milliseconds, as a digitiser writes them. And the same beads'
steady flows down a rough chute (chute.toml's flow-rule table, chute.csv): the depth-averaged
velocity of the steady μ(I) flow at the same truth, four slopes and four thicknesses, 1 % noise.

    python docs/tutorial/make_data.py          # writes docs/tutorial/deposit.csv and front.csv
    python docs/tutorial/make_data.py chute    # writes docs/tutorial/chute.csv
"""

import json
import pathlib
import sys

import numpy as np

from calibration import FrontTarget, Objective, ProfileTarget
from jaxmpm import Experiment

HERE = pathlib.Path(__file__).resolve().parent
TRUTH = {"beta": 0.2, "mu1": 0.42}  # what the tutorial's fit should find
CHUTE_TRUTH = {"mu1": 0.42, "mu2": 0.6434683848584607, "I0": 0.279}  # μ2, I0: the model's defaults
CHUTE_SLOPES, CHUTE_DEPTHS, NOISE_VELOCITY = (24.0, 26.0, 28.0, 30.0), (0.005, 0.01, 0.015, 0.02), 0.01
FRONT_TIMES = np.arange(0.05, 0.401, 0.05)
NOISE_PROFILE, NOISE_FRONT = 0.01, 1e-3


def main():
    experiment = Experiment.from_toml(HERE / "column.toml").with_options(dx=0.0035, seed=7)
    scene = experiment.scene()
    keys = tuple(TRUTH)
    theta = np.array([TRUTH[k] for k in keys])
    xs = np.linspace(0.0, 0.25, 60)
    model = Objective(scene, keys, profile=[ProfileTarget(xs, np.ones_like(xs), experiment.t_end)],
                      front=FrontTarget(FRONT_TIMES, np.ones_like(FRONT_TIMES)), check_data=False)
    _, pred = model.residuals(theta)
    if int(pred["status"]):
        raise SystemExit(f"the true run failed (status {int(pred['status'])})")
    rng = np.random.default_rng(2026)
    h = np.asarray(pred["h"], float)
    h = np.maximum(h + NOISE_PROFILE * h.max() * rng.standard_normal(h.shape), 0.0)
    front = np.asarray(pred["front"], float) + NOISE_FRONT * rng.standard_normal(FRONT_TIMES.shape)
    keep = xs <= 1.1 * xs[np.flatnonzero(h > 0.01 * h.max())[-1]]  # the deposit and a little beyond
    header = ["# experiment: tutorial-column (synthetic stand-in, docs/tutorial/make_data.py)",
              "# synthetic: true", f"# truth: {json.dumps(TRUTH)}", "# source: python docs/tutorial/make_data.py"]
    (HERE / "deposit.csv").write_text("\n".join(
        header + [f"# time_s: {experiment.t_end}", "# noise: 1 % of the peak height", "x_mm,h_mm"]
        + [f"{1e3 * x:.2f},{1e3 * y:.2f}" for x, y in zip(xs[keep], h[keep])]) + "\n")
    (HERE / "front.csv").write_text("\n".join(
        header + ["# noise: 1 mm", "t_s,xf_mm"] + [f"{t:.3f},{1e3 * x:.2f}" for t, x in zip(FRONT_TIMES, front)])
        + "\n")


def chute():
    """chute.csv: the depth-averaged velocity (docs/model.md §6, ``steady_velocity``) of column.toml's
    beads (its ρ, ρ_s, d) at ``CHUTE_TRUTH``, times 1 + 1 % N(0, 1) (seed 2026), in mm and m/s."""
    from jaxmpm.precision import x64
    from jaxmpm.scenes.incline import steady_velocity

    material = Experiment.from_toml(HERE / "column.toml").material
    slope, h = (a.ravel() for a in np.meshgrid(CHUTE_SLOPES, CHUTE_DEPTHS, indexing="ij"))
    with x64():
        u = np.asarray(steady_velocity(h, slope, CHUTE_TRUTH["mu1"], CHUTE_TRUTH["mu2"], CHUTE_TRUTH["I0"],
                                       material["rho"], material["rho_s"], material["d"], "depth_averaged"))
    u = u * (1.0 + NOISE_VELOCITY * np.random.default_rng(2026).standard_normal(u.size))
    header = ["# experiment: tutorial-chute (synthetic stand-in, docs/tutorial/make_data.py)", "# synthetic: true",
              f"# truth: {json.dumps(CHUTE_TRUTH)}", "# source: python docs/tutorial/make_data.py chute",
              "# secondary: false", "# quantity: depth_averaged", f"# noise: {NOISE_VELOCITY}", "slope_deg,h_m,u_m_s"]
    (HERE / "chute.csv").write_text("\n".join(header + [f"{a:g},{b:g},{c:.5g}" for a, b, c in zip(slope, h, u)])
                                    + "\n")


if __name__ == "__main__":
    chute() if sys.argv[1:] == ["chute"] else main()
