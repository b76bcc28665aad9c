"""S7, the aluminium-bar collapse of Bui et al. (2008): the scene's documented set-up, a short run
from the command line with its /initial state, and the shipped measured surface."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

import jaxmpm as jm
from calibration import Objective, read_measurements
from calibration.data.loaders import load_profile
from jaxmpm.datasets import dataset_path, list_datasets
from jaxmpm.scenes import S7_PARAMS, aluminium_bars, build_scene

DATA_NAME = "bui2008/bui2008_final_surface"


def test_scene_has_the_documented_geometry_and_parameters():
    scene = aluminium_bars()
    config, state, params = scene
    assert scene.name == "aluminium-bars"
    assert (scene.info.length, scene.info.height, scene.info.slope_deg, scene.info.dim) == (0.2, 0.1, 0.0, 2)
    assert config.grid.dx == 0.1 / 16 and config.t_end == 1.0 and state.n_particles == 4608
    # the column [0, L] x [0, H], half a cell above the no-slip floor, in front of the back wall
    x = np.asarray(state.x)
    np.testing.assert_allclose(x[:, 1].min(), 0.501 * config.grid.dx, rtol=1e-12)
    assert 0.0 < x[:, 0].min() and x[:, 0].max() < 0.2 and x[:, 1].max() < 0.1 + 0.501 * config.grid.dx
    np.testing.assert_allclose(float(np.sum(state.vol0)), 0.2 * 0.1, rtol=1e-12)
    # rough floor = no-slip; a slip-free (separable, frictionless) back wall; no gate: the front is free
    kinds = {(w.normal, w.kind, w.friction) for w in config.walls}
    assert kinds == {((0.0, 1.0), "no-slip", 0.0), ((1.0, 0.0), "separable", 0.0)}
    assert not any(w.moving for w in config.walls)
    # the grid holds the measured deposit (to x = 0.442 m) with room for a longer runout
    x_hi = config.grid.origin[0] + config.grid.cells[0] * config.grid.dx
    assert x_hi > 0.55
    # the material: cohesionless, mu1 = tan 19.8 deg, and the sourced choices of S7_PARAMS
    got = params.to_dict()
    assert math.isclose(got["mu1"], math.tan(math.radians(19.8)), rel_tol=1e-12) and got["beta"] == 0.0
    for key, value in S7_PARAMS.items():
        assert math.isclose(got[key], value, rel_tol=1e-12), key
    # the command line's builder is the same scene, and parameters can be overridden
    same = build_scene("aluminium-bars")
    np.testing.assert_array_equal(np.asarray(same.state.x), x)
    assert same.params.to_dict() == got and same.config == config
    assert build_scene("aluminium-bars", values={"mu1": 0.3}).params.to_dict()["mu1"] == 0.3


def test_experiment_file_agrees_with_the_builder():
    from jaxmpm.experiment import shipped_experiment

    experiment = shipped_experiment("aluminium-bars")
    got = aluminium_bars().params.to_dict()
    for key in jm.MATERIAL_KEYS:
        assert math.isclose(got[key], experiment.material[key], rel_tol=1e-12), key
    assert experiment.sources["material.mu1"]["expression"] == "tan(19.8 deg)"
    # what was not measured says so
    for key in ("rho", "E", "nu", "d", "mu2", "I0", "pc0", "xi"):
        assert "modelling choice" in experiment.sources[f"material.{key}"]["note"], key
    assert "modelling choice" not in experiment.sources["material.beta"].get("note", "")
    # the measured deposit is the file's profile
    measured = read_measurements(experiment).profiles
    assert [p.file.resolve() for p in measured] == [dataset_path("bui2008/bui2008_final_surface").resolve()]


def test_short_cli_run_writes_the_initial_state(tmp_path):
    """A coarse, short run: no status flags, and /initial holds the scene's initial particles
    (in the same order as /final) beside /final."""
    path = tmp_path / "s7.h5"
    out = subprocess.run([sys.executable, "-m", "jaxmpm", "run", "aluminium-bars", "--dx", "0.02", "--t-end", "0.05",
                          "--out", str(path), "--json", "--no-progress"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["status"] == 0 and summary["status_text"] == [] and summary["scene"] == "aluminium-bars"
    data = jm.io.read_h5(path)
    assert data["attrs"]["status"] == 0 and data["attrs"]["scene"] == "aluminium-bars"
    scene = build_scene("aluminium-bars", dx=0.02, t_end=0.05, dtype="float32")
    initial, final = data["initial"], data["final"]
    np.testing.assert_array_equal(initial["x"], np.asarray(scene.state.x))
    assert set(initial) == set(final) >= {"x", "v", "p", "q", "vol", "pc", "eps_v_p"}
    np.testing.assert_array_equal(initial["v"], 0.0)
    np.testing.assert_array_equal(initial["vol"], np.asarray(scene.state.vol0))
    assert final["x"].shape == initial["x"].shape
    assert 0.0 < np.max(np.linalg.norm(final["x"] - initial["x"], axis=1)) < 0.05  # it moved, a little, in 0.05 s


def test_shipped_surface_loads_with_its_provenance_and_licence():
    info = list_datasets()[DATA_NAME]
    assert info.kind == "measured" and not info.synthetic
    assert "GPL-3.0" in info.licence and "Bui" in info.source and "Wyser" in info.source
    profile = load_profile(dataset_path(DATA_NAME))
    assert not profile.synthetic and profile.time_s is None and profile.n == 23
    assert profile.experiment.startswith("Bui, Fukagawa, Sako & Ohno (2008)") and "1537-1570" in profile.experiment
    assert profile.meta["time_s_text"].startswith("final deposit")
    assert "Wyser" in profile.meta["digitised by"] and "7caea56" in profile.meta["digitised by"]
    assert "GPL-3.0" in profile.meta["licence"] and "friction angle 19.8 deg" in profile.meta[
        "set-up as reported with these data"]
    np.testing.assert_allclose((profile.x[0], profile.x[-1], profile.h.max()), (0.000123, 0.442348, 0.099282))
    # the header travels verbatim with the data
    lines = dataset_path(DATA_NAME).read_text().splitlines()
    assert lines[0].startswith("# experiment: Bui, Fukagawa, Sako & Ohno (2008)")
    assert any(line.startswith("# licence: the digitised file is distributed in a GPL-3.0 repository")
               for line in lines)


def test_objective_accepts_the_shipped_surface():
    profile = load_profile(dataset_path(DATA_NAME))
    objective = Objective(build_scene("aluminium-bars"), ("mu1",), profile=profile)
    assert objective.times == (1.0,) and objective.n_residuals == profile.n  # "final deposit": the end of the run
    with pytest.raises(ValueError, match="outside the scene's grid"):  # the plausibility checks still bite
        Objective(aluminium_bars(runout=0.1), ("mu1",), profile=profile)


@pytest.mark.parametrize("kwargs, message", [
    ({"dx": -0.01}, "dx must be > 0, got -0.01"),
    ({"dx": float("nan")}, "dx must be > 0, got nan"),
    ({"t_end": 0.0}, "t_end must be > 0, got 0.0"),
    ({"ppc": 2.5}, "ppc must be a positive integer for jitter sampling, got 2.5"),
    ({"dim": 3}, "width .* is required when dim=3"),
    ({"mu1": -0.1}, "mu1 must be >= 0"),
    ({"sampling": "hex"}, "sampling must be one of"),
])
def test_bad_input_is_refused_before_anything_compiles(kwargs, message, monkeypatch):
    def no_compile(*args, **kw):
        raise AssertionError("compiled before validating")

    # init_state is where the particles become JAX arrays, after every check of the builder
    monkeypatch.setattr(sys.modules["jaxmpm.scenes.collapse"], "init_state", no_compile)
    with pytest.raises(ValueError, match=message):
        aluminium_bars(**kwargs)
    with pytest.raises(ValueError, match="--slope applies to slope-collapse, not aluminium-bars"):
        build_scene("aluminium-bars", slope=10.0)


def test_cli_refuses_a_negative_dx(tmp_path):
    out = subprocess.run([sys.executable, "-m", "jaxmpm", "run", "aluminium-bars", "--dx", "-0.01"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 2 and "dx must be > 0 m, got -0.01" in out.stderr
