"""All five keys from several filmed collapses of one material: a twin, fitted from the command line.

    python docs/scripts/five_keys_twin.py data     # writes docs/five_keys/: 3 experiment files + CSVs
    python docs/scripts/five_keys_twin.py chute    # writes docs/five_keys/chute.toml + chute.csv
    python docs/scripts/five_keys_twin.py data --only column --fit beta,mu1 --no-start \
        --fit-cells 16 --data-cells 24 --seed 11 --out heldout   # the defaults' held-out check
    python -m calibration fit docs/five_keys/column.toml docs/five_keys/slope20.toml \\
        docs/five_keys/tall_slope20.toml --json --workers 2 --plot docs/five_keys/figs > fit.json

The material is S4's (coated beads: β = 0.25, μ1 = 0.382, μ2 = 0.643, I0 = 0.279, ξ = 50,
p_c0 = 500 Pa). Three experiments the designer ranks best among fast set-ups of that material
(docs/what_collapses_tell.md): the S4 column; the same column on a 20° slope; a column twice as
tall on the 20° slope. Each is "filmed": the profile at 0.05, 0.1, 0.2 and 0.5 s and the front at
ten times. The data are made on a grid 1.5 times finer than the fit's (L/18 against L/12) with
another particle draw, with noise of 2 % of each profile's peak where there is material (bare floor
reads zero) and 2 % of L on the front, so
that the fit meets the grid's error and the particles' as a real one would. Each file's [fit]
asks for all five keys from one start away from the truth.

``chute`` writes the designer's other half of its recommended set (docs/what_collapses_tell.md,
"Collapses and inclines in one design"): the same material's steady flows down a rough chute, a
flow-rule table (the depth-averaged velocity of the closed form at the truth, slopes 22–28°,
thicknesses 10–40 mm, 1 % noise, seed 0) in an incline experiment file (no start of its own: a
joint fit takes its start from --init).
"""

import argparse
import dataclasses
import json
import pathlib

import numpy as np

from calibration import FrontTarget, Objective, ProfileTarget
from calibration.data import FitSpec, FrontMeasurement, ProfileMeasurement, with_measurements
from jaxmpm import Experiment
from jaxmpm.scenes import S4_SIDE

ROOT = pathlib.Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "five_keys"
L = S4_SIDE
TRUTH = {"beta": 0.25, "mu1": 0.3818628674187188, "mu2": 0.6434683848584607, "I0": 0.279, "xi": 50.0}
INIT = {"beta": 0.18, "mu1": 0.42, "mu2": 0.58, "I0": 0.4, "xi": 40.0}
EXPERIMENTS = {  # label: changes to the S4 file
    "column": {},
    "slope20": {"slope": 20.0, "runout": 0.6},
    "tall_slope20": {"height": 2 * L, "slope": 20.0, "runout": 0.9},
}
PROFILE_TIMES = (0.05, 0.1, 0.2, 0.5)
FRONT_TIMES = tuple(np.round(np.linspace(0.05, 0.5, 10), 6))
NOISE = 0.02
FIT_CELLS, DATA_CELLS = 12, 18  # the fit's grid L/12, the data's 1.5 times finer


def base(changes, fit_dx: float) -> Experiment:
    """The S4 file with the twin's material, the fit's dx and ``changes``; a changed value's
    source says so instead of the S4 file's."""
    s4 = Experiment.from_toml(ROOT / "experiments_data" / "experiments" / "S4_cohesive_collapse.toml")
    changed = {"dx", "runout", *TRUTH, *changes}
    sources = {k: v for k, v in s4.sources.items() if k.split(".")[-1] not in changed}
    sources.update({f"{section}.{key}": {"source": "docs/scripts/five_keys_twin.py (the twin's choice)"}
                    for section, names in (("material", TRUTH), ("numerics", ("dx", "runout")),
                                           ("geometry", ("height", "slope")))
                    for key in names if key in changed})
    return s4.replace(material={**s4.material, **TRUTH}, dx=fit_dx, sources=sources, **changes)


def make_data(seed: int = 7, fit_cells: int = FIT_CELLS, data_cells: int = DATA_CELLS, out: pathlib.Path = OUT,
              labels=tuple(EXPERIMENTS), fit_keys=tuple(TRUTH), start: bool = True):
    """The experiment files and their data in ``out``: the ``labels`` of ``EXPERIMENTS``, each
    file's [fit] asking for ``fit_keys`` (from ``INIT`` if ``start``, else a global search)."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(2026)
    keys = tuple(TRUTH)
    theta = np.array([TRUTH[k] for k in keys])
    for label in labels:
        changes = EXPERIMENTS[label]
        experiment = base(changes, L / fit_cells).replace(name=f"five-keys-{label}", title=f"S4's material, {label}")
        data_scene = experiment.replace(dx=L / data_cells, seed=seed).scene()
        grid = data_scene.config.grid
        xs = np.linspace(0.0, 0.95 * (grid.origin[0] + grid.cells[0] * grid.dx), 80)
        ones = np.ones_like(xs)
        model = Objective(data_scene, keys, profile=[ProfileTarget(xs, ones, t) for t in PROFILE_TIMES],
                          front=FrontTarget(np.asarray(FRONT_TIMES), np.ones(len(FRONT_TIMES))), check_data=False)
        _, pred = model.residuals(theta)
        if int(pred["status"]):
            raise SystemExit(f"{label}: the true run failed (status {int(pred['status'])})")
        h = np.asarray(pred["h"], float).reshape(len(PROFILE_TIMES), xs.size)
        front = np.asarray(pred["front"], float) + NOISE * L * rng.standard_normal(len(FRONT_TIMES))
        header = [f"# experiment: five-keys-{label} (synthetic, docs/scripts/five_keys_twin.py)", "# synthetic: true",
                  f"# truth: {json.dumps(TRUTH)}",
                  f"# made at dx = L/{data_cells} = {L / data_cells:.6g} m, particle seed {seed}"]
        profiles = []
        for t, row in zip(PROFILE_TIMES, h):
            # Noise where there is material; bare floor reads zero (a photo shows no deposit there).
            material = row > 0.01 * row.max()
            noisy = np.where(material, np.maximum(row + NOISE * row.max() * rng.standard_normal(row.shape), 0.0), 0.0)
            name = f"{label}_t{t:g}.csv"
            (out / name).write_text("\n".join(header + [f"# time_s: {t}", f"# noise: {100 * NOISE:g} % of the peak",
                                                        "x_m,h_m"]
                                              + [f"{x:.5f},{y:.6f}" for x, y in zip(xs, noisy)]) + "\n")
            profiles.append(ProfileMeasurement(out / name, time=t))
        (out / f"{label}_front.csv").write_text("\n".join(
            header + [f"# noise: {100 * NOISE:g} % of L", "t_s,xf_m"]
            + [f"{t:.4f},{x:.5f}" for t, x in zip(FRONT_TIMES, front)]) + "\n")
        path = out / f"{label}.toml"
        experiment = with_measurements(
            dataclasses.replace(experiment, path=path), profiles=tuple(profiles),
            front=FrontMeasurement(out / f"{label}_front.csv"),
            fit=FitSpec(keys=tuple(fit_keys), init={k: INIT[k] for k in fit_keys} if start else {}))
        path.write_text(f"# {label}: a filmed collapse of S4's material, synthetic (docs/scripts/five_keys_twin.py)\n"
                        + experiment.to_toml())
        print(f"{label}: {data_scene.state.n_particles} particles in the data's run; wrote {path.name}")


CHUTE_SLOPES, CHUTE_DEPTHS, CHUTE_NOISE = (22.0, 24.0, 26.0, 28.0), (0.01, 0.02, 0.03, 0.04), 0.01


def make_chute(out: pathlib.Path = OUT) -> None:
    """docs/five_keys/chute.csv and chute.toml (see the module docstring)."""
    from jaxmpm.precision import x64
    from jaxmpm.scenes.incline import steady_velocity

    material = base({}, L / FIT_CELLS).material
    slope, h = (a.ravel() for a in np.meshgrid(CHUTE_SLOPES, CHUTE_DEPTHS, indexing="ij"))
    with x64():
        u = np.asarray(steady_velocity(h, slope, TRUTH["mu1"], TRUTH["mu2"], TRUTH["I0"], material["rho"],
                                       material["rho_s"], material["d"], "depth_averaged"))
    u = u * (1.0 + CHUTE_NOISE * np.random.default_rng(0).standard_normal(u.size))
    truth = {k: TRUTH[k] for k in ("mu1", "mu2", "I0")}
    header = ["# experiment: five-keys-chute (synthetic twin, docs/scripts/five_keys_twin.py chute)",
              "# synthetic: true", f"# truth: {json.dumps(truth)}",
              "# source: python docs/scripts/five_keys_twin.py chute",
              "# secondary: false", "# quantity: depth_averaged", f"# noise: {CHUTE_NOISE}", "slope_deg,h_m,u_m_s"]
    (out / "chute.csv").write_text("\n".join(header + [f"{a:g},{b:g},{c:.6g}" for a, b, c in zip(slope, h, u)]) + "\n")
    lines = ["# chute: steady flows of S4's material down a rough chute, synthetic (docs/scripts/five_keys_twin.py)",
             "format = 1", "", "[experiment]", 'kind = "incline"', 'name = "five-keys-chute"',
             'title = "S4\'s material, steady layers on a rough chute at 22-28 degrees"',
             'source = "python docs/scripts/five_keys_twin.py chute"', "", "[material]"]
    lines += [f'{k} = {{ value = {material[k]!r}, source = "as docs/five_keys/column.toml" }}'
              for k in ("rho", "rho_s", "d")]
    lines += ["", "[flow_rule]", 'file = "chute.csv"', "", "[fit]", 'keys = ["mu1", "mu2", "I0"]']
    (out / "chute.toml").write_text("\n".join(lines) + "\n")
    print(f"chute: {u.size} rows; wrote chute.toml and chute.csv")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("what", choices=("data", "chute"))
    parser.add_argument("--seed", type=int, default=7, help="the data's particle draw")
    parser.add_argument("--fit-cells", type=int, default=FIT_CELLS, help="the files' dx = L/N (default 12)")
    parser.add_argument("--data-cells", type=int, default=DATA_CELLS, help="the data's dx = L/N (default 18)")
    parser.add_argument("--only", default=",".join(EXPERIMENTS), help="the experiments to write (default: all)")
    parser.add_argument("--fit", default=",".join(TRUTH), help="the keys each [fit] asks for (default: all five)")
    parser.add_argument("--no-start", action="store_true", help="no [fit] init: the fit searches globally")
    parser.add_argument("--out", type=pathlib.Path, default=OUT, help="the folder (default docs/five_keys)")
    args = parser.parse_args()
    if args.what == "chute":
        return make_chute(args.out)
    make_data(args.seed, args.fit_cells, args.data_cells, args.out, tuple(args.only.split(",")),
              tuple(args.fit.split(",")), not args.no_start)


if __name__ == "__main__":
    main()
