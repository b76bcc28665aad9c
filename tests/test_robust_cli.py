"""Robust input for ``python -m jaxmpm``: bad input refused before any compilation with a message
naming the option, outputs checked before the work (nothing left behind), valid JSON only, the
element test finite at its defaults, and no spurious step-budget bit when particles leave the
grid. Through the real entry point (``jaxmpm.__main__.main``) on tiny settings."""

import importlib
import json
import os
import pathlib

import numpy as np
import pytest
from helpers import strict_json

import jaxmpm as jm
from jaxmpm.__main__ import main
from jaxmpm.cli import json_safe

SIMULATE_MODULE = importlib.import_module("jaxmpm.simulate")  # jaxmpm.simulate is the function

TINY = ["--dx", "0.02", "--t-end", "0.02", "--no-progress", "--json"]


@pytest.fixture
def no_simulation(monkeypatch):
    """Fail the test if a run starts: the error must come before any compilation."""
    def refuse(*args, **kwargs):
        raise AssertionError("simulate was called: the input should have been refused before the run")

    monkeypatch.setattr(SIMULATE_MODULE, "simulate", refuse)


def refused(capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert message in err, err
    return err


def listing(folder):
    return sorted(str(p.relative_to(folder)) for p in pathlib.Path(folder).rglob("*"))


# ---- scene options -------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["--width", "0.05"], "--width applies to --dim 3"),  # a 2D run would ignore it
    (["--dx", "nan"], "--dx must be a finite number, got nan"),
    (["--t-end", "inf"], "--t-end must be a finite number, got inf"),
    (["--set", "beta=0.1", "--set", "beta=0.2"], "--set beta is given twice"),
    (["--set", "mu1=0.7"], "mu2 (the limiting friction) must be >= mu1"),  # default mu2 = tan 32.76 deg
])
def test_run_refuses_bad_scene_options(capsys, no_simulation, argv, message):
    refused(capsys, ["run", "cohesive-collapse", *TINY, *argv], message)


def test_slope_nan_names_the_slope(capsys, no_simulation):
    err = refused(capsys, ["run", "slope-collapse", *TINY, "--slope", "nan"], "--slope must be a finite number")
    assert "runout" not in err


# ---- output paths, checked before the run ---------------------------------------------------------
def read_only_folder(tmp_path):
    """A folder no one can write in: a chmod-ed one, or /proc for root (who ignores modes)."""
    if os.geteuid() != 0:
        folder = tmp_path / "locked"
        folder.mkdir()
        folder.chmod(0o555)
        return folder
    return pathlib.Path("/proc")


@pytest.mark.parametrize("case", ["missing-folder", "folder", "file-as-folder", "read-only", "plot-format",
                                  "gif-format", "gif-without-frames", "same-file"])
def test_output_paths_are_checked_before_the_run(capsys, no_simulation, tmp_path, case):
    (tmp_path / "a_file").write_text("keep me\n")
    (tmp_path / "a_folder").mkdir()
    argv, message = {
        "missing-folder": (["--out", str(tmp_path / "nope" / "run.h5")], "--out"),
        "folder": (["--profile-csv", str(tmp_path / "a_folder")], "is a folder"),
        "file-as-folder": (["--out", str(tmp_path / "a_file" / "run.h5")], "is a file, not a folder"),
        "read-only": (["--profile-csv", str(read_only_folder(tmp_path) / "p.csv")], "cannot write in the folder"),
        "plot-format": (["--plot", str(tmp_path / "fig.xyz")], "--plot"),
        "gif-format": (["--gif", str(tmp_path / "anim.mp4")], "must end in one of .gif"),
        "gif-without-frames": (["--gif", str(tmp_path / "anim.gif"), "--frames", "0"], "--frames must be >= 1"),
        "same-file": (["--out", str(tmp_path / "x"), "--profile-csv", str(tmp_path / "x")], "name the same file"),
    }[case]
    before = listing(tmp_path)
    err = refused(capsys, ["run", "cohesive-collapse", *TINY, *argv], message)
    if case == "missing-folder":
        assert "does not exist" in err
    assert listing(tmp_path) == before  # no output, no temporary file
    assert (tmp_path / "a_file").read_text() == "keep me\n"


# ---- JSON ------------------------------------------------------------------------------------------
def test_json_safe_replaces_non_finite_numbers_and_names_them():
    obj = {"loss": float("nan"), "stderr": {"beta": np.inf, "mu1": 0.1}, "x": np.array([1.0, -np.inf]), "n": 3}
    safe, bad = json_safe(obj)
    assert safe == {"loss": None, "stderr": {"beta": None, "mu1": 0.1}, "x": [1.0, None], "n": 3}
    assert bad == ["loss", "stderr.beta", "x[1]"]
    json.dumps(safe, allow_nan=False)


# ---- the element test --------------------------------------------------------------------------------
@pytest.mark.parametrize("extra", [[], ["--pressure", "0"], ["--pressure", "1"], ["--pressure", "100"]])
def test_element_triaxial_is_finite_at_its_defaults(capsys, extra):
    """The default (p = p_c0/2) and the 0 Pa, 1 Pa and p = p_c0 starts, with the default 2000
    steps and with 20 (large steps, where the old plain-Newton lateral control diverged)."""
    for steps in ("2000", "20"):
        code = main(["element", "triaxial", "--json", "--steps", steps, *extra])
        out = strict_json(capsys.readouterr().out)
        assert code == 0, out
        assert all(np.isfinite(v) for v in out.values()), out
        assert out["p"] > 0 and out["q"] > 0


def test_element_refuses_a_start_beyond_the_yield_surface(capsys):
    refused(capsys, ["element", "triaxial", "--pressure", "1000", "--json"],
            "pressure = 1000 Pa exceeds the compressive strength pc0 = 100 Pa")


def test_element_exits_non_zero_with_null_on_a_non_finite_result(capsys, monkeypatch):
    import jaxmpm.studies.element

    real = jaxmpm.studies.element.element_test

    def broken(*args, **kwargs):
        history = real(*args, **kwargs)
        p = np.array(history.p)
        p[7:] = np.nan
        return type(history)(**{**vars(history), "p": p})

    monkeypatch.setattr(jaxmpm.studies.element, "element_test", broken)
    code = main(["element", "isotropic", "--json", "--steps", "20"])
    out = strict_json(capsys.readouterr().out)
    assert code == 1
    assert out["p"] is None and out["nonfinite"] == ["p"] and "first at step 7" in out["error"]


# ---- status bits ----------------------------------------------------------------------------------------
# 13 s: a run to t = 1 s on the command line; the engine's LEFT_GRID and BUDGET bits are checked by default
@pytest.mark.slow  # (tests/test_engine.py)
def test_no_spurious_budget_bit_when_particles_leave_the_grid(capsys):
    """Frictionless, soft material spreads off the grid. The command line (block by block, stopping
    on the fatal bit) used to report LEFT_GRID | BUDGET | EDGE = 25 where ``simulate()`` gives no
    BUDGET bit: the budget did not run out, the run was stopped."""
    argv = ["--dx", "0.02", "--t-end", "1.0", "--set", "mu1=0", "--set", "mu2=0", "--set", "E=1e5"]
    code = main(["run", "cohesive-collapse", *argv, "--no-progress", "--json"])
    out = strict_json(capsys.readouterr().out)
    assert code == 1
    assert out["status"] & jm.LEFT_GRID and not out["status"] & jm.BUDGET, out["status_text"]
    assert out["n_steps"] < 1000
    scene = jm.scenes.build_scene("cohesive-collapse", dx=0.02, t_end=1.0, dtype="float32",
                                  values={"mu1": 0.0, "mu2": 0.0, "E": 1e5})
    plain = jm.simulate(*scene, throw=False)
    assert plain.status & jm.LEFT_GRID and not plain.status & jm.BUDGET
