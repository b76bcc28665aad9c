"""The tutorial's stand-in measurements (docs/tutorial.md): column.toml's collapse at a hidden
truth, run on a grid twice as fine as the fit's and with another particle draw, with noise: 1 % of
the peak height on the deposit (a photo, digitised) and 1 mm on the front (a video at 20 frames
a second). Files in millimetres and milliseconds, as a digitiser writes them.

    python docs/tutorial/make_data.py      # writes docs/tutorial/deposit.csv and front.csv
"""

import json
import pathlib

import numpy as np

from calibration import FrontTarget, Objective, ProfileTarget
from jaxmpm import Experiment

HERE = pathlib.Path(__file__).resolve().parent
TRUTH = {"beta": 0.2, "mu1": 0.42}  # what the tutorial's fit should find
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


if __name__ == "__main__":
    main()
