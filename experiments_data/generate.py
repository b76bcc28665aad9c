"""Regenerate the computed files of experiments_data/ (run from the repository root).

    python experiments_data/generate.py tables    # scaling_laws/*.csv, bagnold/*.csv, synthetic/flow_rule_twin.csv,
                                                  # synthetic/flow_profile_twin.csv, synthetic/h_stop_example.csv,
                                                  # examples/wpd_example.csv
    python experiments_data/generate.py profiles  # synthetic/S4_beta0.25.csv, S4_beta0.csv, S3_10deg.csv (~20 s)
    python experiments_data/generate.py front     # synthetic/S3_10deg_front.csv (one ~15 s run)

``tables`` only evaluates formulas (and reads synthetic/S4_beta0.25.csv for the WebPlotDigitizer
format example, so run ``profiles`` first on a fresh checkout). ``profiles`` runs exactly the
command lines recorded in each profile's ``source`` header. Nothing here is a measurement.
Tables are read and written with ``jaxmpm.tables`` (the project's one CSV format): the shipped
data depend on the engine alone, not on the calibration package built on it.
"""

from __future__ import annotations

import pathlib
import subprocess
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
A_VALUES = (0.5, 0.7, 1.0, 1.5, 2.0, 2.3, 3.0, 4.0, 6.0, 8.0)
SLOPES = (22.0, 24.0, 26.0, 28.0)
DEPTH = 0.038
KUMAR = "K. Kumar's PhD thesis (CC-BY-4.0), cited in docs/scenes.md S5; secondary: not read in the primary paper"
PROFILE_COMMANDS = (
    ("python -m jaxmpm run cohesive-collapse --set beta=0.25 --profile-csv experiments_data/synthetic/S4_beta0.25.csv"
    " --no-progress --json"),
    ("python -m jaxmpm run cohesive-collapse --set beta=0 --profile-csv experiments_data/synthetic/S4_beta0.csv"
    " --no-progress --json"),
    ("python -m jaxmpm run slope-collapse --slope 10 --profile-csv experiments_data/synthetic/S3_10deg.csv"
    " --no-progress --json"),
)


def _write(path: pathlib.Path, header: dict, names: tuple[str, ...], rows) -> None:
    """A table in the project's CSV format (``jaxmpm.tables.write_table``), 10 significant digits."""
    from jaxmpm.tables import write_table

    columns = np.array(list(rows), dtype=float).reshape(-1, len(names)).T
    write_table(path, dict(zip(names, columns)), header, fmt=".10g")
    print(f"wrote {path.relative_to(ROOT)}")


def scaling_laws() -> None:
    from jaxmpm.scenes import height_law, runout_law

    a = np.array(A_VALUES)
    _write(HERE / "scaling_laws" / "runout_glass_beads.csv", {
        "experiment": "quasi-2D granular column collapse on a horizontal floor, glass beads (Lajeunesse et al. 2005)",
        "secondary": True,
        "source": f"Lajeunesse et al. 2005, as quoted in {KUMAR}",
        "formula_runout": "dL/L0 = (L_f - L0)/L0 = 1.2 a for a <= 2.3; 1.9 a^(2/3) for a > 2.3",
        "formula_height": "H_f/L0 = a for a <= 0.7; a^(1/3) for a > 0.7",
        "note": "approximate laws; the quoted branches do not meet at the crossovers (2.76 vs 3.31 at a = 2.3, "
                "0.70 vs 0.89 at a = 0.7); samples at a crossover take the lower branch",
        "columns": {"a": "aspect ratio H0/L0", "dL_over_L0": "normalised runout", "Hf_over_L0": "normalised final "
                    "height"},
        "units": "dimensionless",
        "generated_by": "python experiments_data/generate.py tables (jaxmpm.scenes.runout_law, height_law)",
    }, ("a", "dL_over_L0", "Hf_over_L0"), zip(a, runout_law(a), height_law(a)))
    _write(HERE / "scaling_laws" / "runout_sand_lube2005.csv", {
        "experiment": "quasi-2D granular column collapse on a horizontal floor, rough sand (Lube et al. 2005)",
        "secondary": True,
        "source": f"Lube et al. 2005, as quoted in {KUMAR}",
        "formula_runout": "dL/L0 = (L_f - L0)/L0 = 1.6 a for a <= 2.3; 2.2 a^(2/3) for a > 2.3",
        "note": "approximate law; the crossover a = 2.3 is the glass-bead one (docs/scenes.md quotes no other); no "
                "final-height law is quoted for sand",
        "columns": {"a": "aspect ratio H0/L0", "dL_over_L0": "normalised runout"},
        "units": "dimensionless",
        "generated_by": "python experiments_data/generate.py tables (jaxmpm.scenes.runout_law(a, sand=True))",
    }, ("a", "dL_over_L0"), zip(a, runout_law(a, sand=True)))


def bagnold() -> None:
    from jaxmpm.params import DEFAULTS
    from jaxmpm.scenes import S1_PARAMS, bagnold_velocity

    params = {**DEFAULTS, **S1_PARAMS}
    used = {k: params[k] for k in ("rho", "rho_s", "d", "mu1", "mu2", "I0")}
    z = np.linspace(0.0, DEPTH, 21)
    rows, surface = [], {}
    for slope in SLOPES:
        v = bagnold_velocity(z, DEPTH, slope, params)
        surface[f"{slope:g}"] = round(float(v[-1]), 6)
        rows += [(slope, zi, vi) for zi, vi in zip(z, v)]
    _write(HERE / "bagnold" / "bagnold_profiles.csv", {
        "experiment": "S1 steady uniform flow down an inclined plane: Bagnold velocity profile (analytic)",
        "analytic": True,
        "synthetic": False,
        "source": "docs/model.md section 6, evaluated with jaxmpm.scenes.incline.bagnold_velocity",
        "formula": "v(z) = (2/3) I_theta sqrt(rho g cos(theta) / rho_s) / d * (h^(3/2) - (h - z)^(3/2)), "
                   "I_theta = I0 (tan(theta) - mu1) / (mu2 - tan(theta))",
        "parameters": {**used, "g": 9.81, "h_m": DEPTH},
        "parameter_sources": "docs/scenes.md S1 (rho, rho_s, d, mu1 = tan 20.9 deg, mu2 = tan 32.76 deg, I0, h)",
        "surface_velocity_m_per_s": surface,
        "columns": {"slope_deg": "bed angle theta, degrees", "z_m": "height above the bed, m",
                    "v_m_per_s": "downslope velocity, m/s"},
        "generated_by": "python experiments_data/generate.py tables",
    }, ("slope_deg", "z_m", "v_m_per_s"), rows)


def flow_rule_twin() -> None:
    """A synthetic flow-rule table: the depth-averaged velocity of the steady flow (docs/model.md
    section 6) of S1's material at S1's slopes and four thicknesses, with 2 % Gaussian noise
    (seed 0); what ``python -m calibration flow-rule`` fits in the docs and tests."""
    from jaxmpm.params import DEFAULTS
    from jaxmpm.precision import x64
    from jaxmpm.scenes import S1_PARAMS
    from jaxmpm.scenes.incline import steady_velocity

    p = {**DEFAULTS, **S1_PARAMS}
    slope, h = (a.ravel() for a in np.meshgrid(SLOPES, (0.01, 0.02, 0.03, 0.04), indexing="ij"))
    with x64():
        u = np.asarray(steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"],
                                       "depth_averaged"))
    u = u * (1.0 + 0.02 * np.random.default_rng(0).standard_normal(u.size))
    _write(HERE / "synthetic" / "flow_rule_twin.csv", {
        "experiment": "steady flows down a rough incline, S1's glass beads (synthetic twin, not a measurement)",
        "synthetic": True,
        "secondary": False,
        "quantity": "depth_averaged",
        "noise": 0.02,
        "source": "docs/model.md section 6 (jaxmpm.scenes.incline.steady_velocity) at S1's material, "
                  "times 1 + 0.02 N(0, 1) (numpy default_rng(0))",
        "parameters": {k: p[k] for k in ("rho", "rho_s", "d", "mu1", "mu2", "I0")},
        "parameter_sources": "docs/scenes.md S1 (rho, rho_s, d, mu1 = tan 20.9 deg, mu2 = tan 32.76 deg, I0, slopes)",
        "columns": {"slope_deg": "bed angle, degrees", "h_m": "layer thickness, m",
                    "u_m_s": "depth-averaged downslope velocity, m/s"},
        "generated_by": "python experiments_data/generate.py tables",
    }, ("slope_deg", "h_m", "u_m_s"), zip(slope, h, u))


def flow_profile_twin() -> None:
    """A synthetic velocity profile's table: the velocity v(z) = U_s(h) − U_s(h − z) of the steady
    flow (docs/model.md section 6) of S1's material at four slopes, two thicknesses and five
    heights each, with 1 % Gaussian noise (seed 0); the example of docs/incline_fits.md "A velocity
    profile, and h_stop"."""
    from jaxmpm.params import DEFAULTS
    from jaxmpm.precision import x64
    from jaxmpm.scenes import S1_PARAMS
    from jaxmpm.scenes.incline import steady_velocity

    p = {**DEFAULTS, **S1_PARAMS}
    slope, h, share = (a.ravel() for a in np.meshgrid((22.0, 25.0, 28.0, 31.0), (0.01, 0.03),
                                                      (0.2, 0.4, 0.6, 0.8, 1.0), indexing="ij"))
    z = share * h
    with x64():
        u = np.asarray(steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"],
                                       "profile", height=z))
    u = u * (1.0 + 0.01 * np.random.default_rng(0).standard_normal(u.size))
    _write(HERE / "synthetic" / "flow_profile_twin.csv", {
        "experiment": "velocity profiles of steady flows down a rough incline, S1's glass beads (synthetic twin, "
                      "not a measurement)",
        "synthetic": True,
        "secondary": False,
        "quantity": "profile",
        "noise": 0.01,
        "source": "docs/model.md section 6 (jaxmpm.scenes.incline.steady_velocity, quantity profile) at S1's "
                  "material, times 1 + 0.01 N(0, 1) (numpy default_rng(0))",
        "parameters": {k: p[k] for k in ("rho", "rho_s", "d", "mu1", "mu2", "I0")},
        "parameter_sources": "docs/scenes.md S1 (rho, rho_s, d, mu1 = tan 20.9 deg, mu2 = tan 32.76 deg, I0)",
        "columns": {"slope_deg": "bed angle, degrees", "h_m": "layer thickness, m",
                    "z_m": "height above the bed, m", "u_m_s": "downslope velocity at that height, m/s"},
        "generated_by": "python experiments_data/generate.py tables",
    }, ("slope_deg", "h_m", "z_m", "u_m_s"), zip(slope, h, z, u))


def h_stop_example() -> None:
    """An illustrative h_stop table (no model here predicts h_stop, so nothing makes a twin of
    one): Pouliquen's (1999) form h_stop = L (tan θ2 − tan θ) / (tan θ − tan θ1) at S1's θ1 and θ2,
    with L = 2 d chosen for illustration only."""
    from jaxmpm.params import DEFAULTS
    from jaxmpm.scenes import S1_PARAMS

    p = {**DEFAULTS, **S1_PARAMS}
    slope = np.array([22.0, 24.0, 26.0, 28.0, 30.0])
    tan, length = np.tan(np.radians(slope)), 2.0 * p["d"]
    h_stop = length * (p["mu2"] - tan) / (tan - p["mu1"])
    _write(HERE / "synthetic" / "h_stop_example.csv", {
        "experiment": "h_stop of S1's glass beads, an illustration (synthetic, not a measurement)",
        "synthetic": True,
        "secondary": True,
        "source": "the form of Pouliquen (1999), h_stop = L (tan theta2 - tan theta) / (tan theta - tan theta1), at "
                  "S1's mu1 = tan theta1 and mu2 = tan theta2 with L = 2 d = 1.4 mm, chosen for illustration (the "
                  "published L was not read in a primary source here): not data to draw conclusions from",
        "columns": {"slope_deg": "bed angle, degrees", "h_stop_m": "thickness at which a layer stops, m"},
        "generated_by": "python experiments_data/generate.py tables",
    }, ("slope_deg", "h_stop_m"), zip(slope, h_stop))


def wpd_example() -> None:
    from jaxmpm.tables import PROFILE_COLUMNS, read_columns

    header, columns = read_columns(HERE / "synthetic" / "S4_beta0.25.csv", required=PROFILE_COLUMNS)
    if header.get("units", "m") != "m":
        raise SystemExit(f"synthetic/S4_beta0.25.csv: expected a profile in metres, got units = {header['units']!r}")
    x, h = (columns[name] for name in PROFILE_COLUMNS)
    x_mm = np.array([10.0, 20.0, 40.0, 60.0, 80.0, 100.0, 120.0, 140.0, 160.0])
    h_mm = np.round(np.interp(x_mm * 1e-3, x, h) * 1e3, 1)
    path = HERE / "examples" / "wpd_example.csv"
    path.write_text("".join(f"{x:.1f},{h:.1f}\n" for x, h in zip(x_mm, h_mm)))
    print(f"wrote {path.relative_to(ROOT)}")


def profiles() -> None:
    for command in PROFILE_COMMANDS:
        argv = [sys.executable, *command.split()[1:]]
        print(command)
        subprocess.run(argv, cwd=ROOT, check=True)


def front() -> None:
    """Front position of the synthetic S3 run at 10 degrees (the CLI's slope-collapse: dx = 0.01 m,
    float32), as the largest particle x at 20 frames (t > 0: a fit's front data start after the
    release; the initial front L is in the header's scene)."""
    import jax.numpy as jnp

    from jaxmpm import __version__, scenes, simulate
    from jaxmpm.tables import FRONT_COLUMNS, write_table

    scene = scenes.slope_collapse(10.0, dx=0.01, frames=20)
    config, state, params = scene
    result = simulate(config, state, params, observer=lambda s, p: {"front": jnp.max(s.x[:, 0])}, throw=False)
    t = np.asarray(result.frame_times, float)
    xf = np.asarray(result.frames["front"], float)
    # A front history's header (what calibration's front-history loader reads): its fields, then the run's facts.
    header = {"experiment": f"slope-collapse 10 deg front position (synthetic, jaxmpm {__version__})", "units": "m",
              "source": "python experiments_data/generate.py front", "synthetic": True,
              "front_definition": "largest particle x (along the bed, from the back wall) at each frame",
              "parameters": params.to_dict(), "scene": scene.info.to_dict(), "status": int(result.status)}
    write_table(HERE / "synthetic" / "S3_10deg_front.csv", dict(zip(FRONT_COLUMNS, (t, xf))), header)
    print("wrote experiments_data/synthetic/S3_10deg_front.csv")


if __name__ == "__main__":
    what = sys.argv[1:] or ["tables"]
    for item in what:
        if item == "tables":
            scaling_laws()
            bagnold()
            flow_rule_twin()
            flow_profile_twin()
            h_stop_example()
            wpd_example()
        elif item == "profiles":
            profiles()
        elif item == "front":
            front()
        else:
            raise SystemExit(f"unknown target {item!r}; use tables, profiles or front")
