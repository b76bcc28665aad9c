"""Robust input for ``python -m calibration``: a resume that refuses a different problem, no history
replaced without --overwrite, swept members validated like ``run --set``, data checked against
the scene, outputs checked before the work and never lost after it, valid JSON only, messages
that name the command-line options. Through the real entry point (``calibration.__main__.main``)
on the tiny S4 scene (dx = L/6, 144 particles); cases that must be refused before any work run
with the model's evaluation replaced by a tripwire."""

import importlib
import json
import os
import pathlib
import shutil

import h5py
import numpy as np
import pytest
from helpers import ROOT, S4_DATA, TINY_FLAGS, call_main, strict_json, tiny_s4

from calibration import Bounds, fit, read_history
from calibration.batch.sweep import SweepResult, write_sweep
from calibration.cli.commands import main
from calibration.data.loaders import load_profile
from calibration.problem.composite import CompositeObjective
from calibration.problem.objective import Objective
from jaxmpm import LEFT_GRID
from jaxmpm.scenes import S4_SIDE

FIT_MODULE = importlib.import_module("calibration.optim.fit")
SWEEP_MODULE = importlib.import_module("calibration.batch.sweep")
SEARCH_MODULE = importlib.import_module("calibration.optim.search")
S4 = S4_DATA
WPD = ROOT / "experiments_data" / "examples" / "wpd_example.csv"
TINY = list(TINY_FLAGS)
FIT = ["fit", "--scene", "cohesive-collapse", "--fit", "beta"]
SWEEP = ["sweep", "--scene", "cohesive-collapse"]


def call(argv):
    """main(argv) with stdout captured: (exit code, stdout, stderr)."""
    return call_main(main, argv)


def refused(argv, message):
    code, _, err = call(argv)
    assert code == 2, err
    assert message in err, err
    return err


@pytest.fixture
def no_work(monkeypatch):
    """Any model evaluation (which compiles) fails the test: the error must come before it."""
    def tripwire(*args, **kwargs):
        raise AssertionError("the model was evaluated: the input should have been refused before")

    for name in ("residuals", "residuals_and_jacobian", "residuals_and_jacobian_z", "value_and_grad", "predict",
                 "residuals_resampled", "batched_jacobian_z"):
        monkeypatch.setattr(Objective, name, tripwire)
    monkeypatch.setattr(CompositeObjective, "batched_jacobian_z", tripwire)
    monkeypatch.setattr(SWEEP_MODULE, "compile_batch", tripwire)


def listing(folder):
    return sorted(str(p.relative_to(folder)) for p in pathlib.Path(folder).rglob("*"))


def read_only_folder(tmp_path):
    """A folder no one can write in: a chmod-ed one, or /proc for root (who ignores modes)."""
    if os.geteuid() != 0:
        folder = tmp_path / "locked"
        folder.mkdir()
        folder.chmod(0o555)
        return folder
    return pathlib.Path("/proc")


def write_csv(path, x, h, header=("# time_s: 0.5",), columns="x_m,h_m"):
    rows = "\n".join(f"{a:.9g},{b:.9g}" for a, b in zip(x, h))
    path.write_text("\n".join(header) + f"\n{columns}\n{rows}\n")
    return path


S4_X, S4_H = load_profile(S4).x, load_profile(S4).h


# ---- one real fit, shared: its figure fails, its JSON and history must survive ----------------------
@pytest.fixture(scope="module")
def history(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fit")
    path = folder / "fit.h5"
    plots = importlib.import_module("calibration.plots.fits")
    with pytest.MonkeyPatch.context() as mp:
        def full_disk(*args, **kwargs):
            raise OSError(28, "No space left on device")

        mp.setattr(plots, "plot_fit", full_disk)
        code, out, err = call([*FIT, "--data", S4, "--init", "beta=0.2", "--steps", "1", "--grid-check", "0",
                               "--out", path,
                               "--plot", folder / "figs", *TINY])
    return {"path": path, "code": code, "out": out, "err": err, "folder": folder}


def test_a_failed_figure_keeps_the_json_and_the_history(history):
    assert history["code"] == 1, history["err"]
    out = strict_json(history["out"])
    assert "No space left on device" in out["output_errors"]["--plot"]
    assert set(out["params"]) == {"beta"} and out["iterations"] == 1
    assert read_history(history["path"])["history"]["loss"].size == 1


@pytest.mark.parametrize("change, message", [
    ("data", "data (--data/--front: their content)"),
    (["--dx", str(S4_SIDE / 5)], "dx (--dx): 0.0148"),
    (["--set", "pc0=400"], "fixed.pc0 (--set): 500.0 in the file, 400.0 now"),
    (["--weight-profile", "2"], "weights.profile (--weight-profile/--weight-front): 1.0 in the file, 2.0 now"),
    (["--t-end", "0.6"], "t_end (--t-end): 0.5 in the file, 0.6 now"),
    (["--jacobian", "fd"], "jacobian (--jacobian): 'ad' in the file, 'fd' now"),
])
def test_resume_refuses_a_different_problem(history, no_work, tmp_path, change, message):
    """A resume with other data or another objective-changing option used to
    mix two problems in one history; it is refused, naming what differs and its option."""
    data = S4
    extra = []
    if change == "data":
        data = write_csv(tmp_path / "other.csv", S4_X, 0.9 * S4_H)
    else:
        extra = change
    copy = tmp_path / "fit.h5"
    shutil.copy(history["path"], copy)
    before = copy.read_bytes()
    err = refused([*FIT, "--data", data, "--steps", "2", "--out", copy, "--resume", *TINY, *extra],
                  "holds a fit of a different problem")
    assert message in err
    assert copy.read_bytes() == before


def test_resume_accepts_the_same_data_under_another_name(history, tmp_path):
    copy, data = tmp_path / "fit.h5", tmp_path / "renamed.csv"
    shutil.copy(history["path"], copy)
    shutil.copy(S4, data)
    code, out, err = call([*FIT, "--data", data, "--steps", "1", "--out", copy, "--resume", *TINY])
    assert code == 0, err
    assert strict_json(out)["iterations"] == 1


@pytest.mark.parametrize("case, message", [
    ("misspelled", "does not exist, so there is nothing to resume"),
    ("empty", "is not a readable fit history"),
    ("truncated", "is not a readable fit history"),
    ("text", "is not a readable fit history"),
    ("foreign", "is not a fit history written by calibration.optim.fit (no attribute 'keys_json'"),
])
def test_resume_from_a_bad_file_is_refused_clearly(history, no_work, tmp_path, case, message):
    path = tmp_path / "fit.h5"
    if case == "empty":
        path.write_bytes(b"")
    elif case == "truncated":
        path.write_bytes(history["path"].read_bytes()[:3000])
    elif case == "text":
        path.write_text("x_m,h_m\n0,1\n")
    elif case == "foreign":  # e.g. a run's output
        with h5py.File(path, "w") as f:
            f.create_dataset("x", data=np.zeros(3))
    err = refused([*FIT, "--data", S4, "--out", path, "--resume", *TINY], message)
    assert "--resume" in err and str(path) in err
    assert "Traceback" not in err


def test_an_existing_history_is_not_replaced_without_overwrite(history, no_work, tmp_path):
    copy = tmp_path / "fit.h5"
    shutil.copy(history["path"], copy)
    before = copy.read_bytes()
    refused([*FIT, "--data", S4, "--out", copy, *TINY], "exists: pass --resume to continue the fit it holds, or "
            "--overwrite to replace it")
    refused([*SWEEP, "--data", S4, "--over", "beta=0.1:0.3:2", "--out", copy, *TINY], "exists: pass --overwrite")
    refused([*FIT, "--data", S4, "--out", copy, "--resume", "--overwrite", *TINY], "exclude each other")
    assert copy.read_bytes() == before


# ---- refused before any work ---------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    ([*FIT, "--data", S4, "--width", "0.05"], "--width applies to --dim 3"),
    (["fit", "--scene", "slope-collapse", "--fit", "beta", "--data", S4, "--slope", "nan"],
     "--slope must be a finite number, got nan"),
    ([*FIT, "--data", S4, "--weight-profile", "0"], "--weight-profile 0 gives the --data data no weight"),
    ([*FIT, "--data", S4, "--weight-front", "nan"], "--weight-front must be a finite number >= 0"),
    ([*FIT, "--data", S4, "--init", "beta=0.2", "--init", "beta=0.3"], "--init beta is given twice"),
    ([*FIT, "--data", S4, "--lr", "0"], "--lr must be a finite number > 0"),
    ([*SWEEP, "--data", S4, "--over", "beta=0.1:0.3:2", "--over", "beta=0.2:0.4:3"], "--over beta is given twice"),
    ([*SWEEP, "--data", S4, "--over", "beta=-0.2:0.2:5"],
     "--over: 2 of 5 members are not a valid parameter set: member 0 (beta = -0.2): beta must be >= 0"),
    ([*SWEEP, "--data", S4, "--over", "mu1=0.5:0.8:4"], "mu2 (the limiting friction) must be >= mu1"),
    ([*SWEEP, "--data", S4, "--over", "beta=0.1:0.3:2", "--over", "mu1=0.3:0.4:2", "--over", "xi=10:50:2",
      "--plot", "figs"], "--plot draws the loss over one or two swept keys, got 3"),
    ([*SWEEP, "--data", S4, "--over", "beta=0.1:0.3", "--over", "mu1=0.3:0.4", "--lhs", "4", "--plot", "figs"],
     "a Latin hypercube (--lhs) is none"),
    ([*SWEEP, "--data", S4, "--over", "beta=0.1:0.3:3", "--lhs", "4"], "a count n does not apply with --lhs"),
    (["twin", "--seed", "3"], "--sampling and --seed do not apply"),
    (["twin", "--fit", "beta", "--landscape", "3"], "--landscape needs at least two fitted keys"),
    (["law", "--law", str(ROOT / "experiments_data" / "scaling_laws" / "runout_glass_beads.csv"), "--test", "5"],
     "aspect ratios [5.0] are not in"),
    ([*FIT, "--data", S4, "--overwrite"], "--overwrite needs --out"),
])
def test_bad_options_are_refused_naming_the_option(no_work, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)  # "figs" would be created here if anything were drawn
    refused([*argv, *TINY], message)
    assert listing(tmp_path) == []


@pytest.mark.parametrize("case", ["fit-out-missing-folder", "fit-out-folder", "fit-plot-is-a-file",
                                  "sweep-out-read-only", "sweep-plot-under-a-file", "law-out-missing-folder"])
def test_output_paths_are_checked_before_the_work(no_work, tmp_path, case):
    (tmp_path / "a_file").write_text("keep me\n")
    sweep = [*SWEEP, "--data", S4, "--over", "beta=0.1:0.3:2"]
    argv, message = {
        "fit-out-missing-folder": ([*FIT, "--data", S4, "--out", tmp_path / "nope" / "f.h5"], "does not exist"),
        "fit-out-folder": ([*FIT, "--data", S4, "--out", tmp_path], "is a folder"),
        "fit-plot-is-a-file": ([*FIT, "--data", S4, "--plot", tmp_path / "a_file"], "is a file; give a folder"),
        "sweep-out-read-only": ([*sweep, "--out", read_only_folder(tmp_path) / "s.h5"], "cannot write in the folder"),
        "sweep-plot-under-a-file": ([*sweep, "--plot", tmp_path / "a_file" / "figs"], "which is a file"),
        "law-out-missing-folder": (["law", "--out", tmp_path / "nope" / "law.h5"], "does not exist"),
    }[case]
    before = listing(tmp_path)
    option = "--plot" if "plot" in case else "--out"
    err = refused([*argv, *TINY] if argv[0] != "law" else [*argv, "--json"], message)
    assert option in err
    assert listing(tmp_path) == before and (tmp_path / "a_file").read_text() == "keep me\n"


# ---- data that cannot come from the scene --------------------------------------------------------------
@pytest.mark.parametrize("case, message", [
    ("mm-labelled-m", "x the height of scene cohesive-collapse's column"),
    ("m-labelled-mm", "is only"),
    ("x-far-away", "all its points"),
    ("x-partly-off-grid", "point(s) with material"),
    ("too-much-material", "more material than the scene has"),
    ("beyond-float32", "values beyond the range of float32"),
    ("failed-run", "written by a run that failed (status 1: a particle left the grid"),
    ("front-off-grid", "lies outside the scene's grid"),
])
def test_implausible_data_are_refused_naming_the_file(no_work, tmp_path, case, message):
    path = tmp_path / f"{case}.csv"
    option = "--data"
    if case == "mm-labelled-m":
        write_csv(path, 1000 * S4_X, 1000 * S4_H)
    elif case == "m-labelled-mm":
        write_csv(path, S4_X, S4_H, columns="x_mm,h_mm")
    elif case == "x-far-away":
        write_csv(path, S4_X + 5.0, S4_H)
    elif case == "x-partly-off-grid":
        write_csv(path, S4_X + 0.3, S4_H)
    elif case == "too-much-material":
        write_csv(path, np.linspace(0.0, 0.39, 40), np.full(40, 0.08))
    elif case == "beyond-float32":
        write_csv(path, S4_X, S4_H * 1e40)
    elif case == "failed-run":
        write_csv(path, S4_X, S4_H, header=("# time_s: 0.5", "# status: 1"))
    else:
        option = "--front"
        path.write_text("t_s,xf_m\n0.1,0.12\n0.2,0.15\n0.5,1.0\n")
    err = refused([*FIT, option, path, "--t-end", "0.5", *TINY], message)
    assert str(path) in err


# ---- loader messages name the command-line options -----------------------------------------------------
def test_loader_hints_name_the_command_line_options(no_work, tmp_path, monkeypatch):
    refused([*FIT, "--data", WPD, *TINY], "--units m|cm|mm")
    clicks = tmp_path / "clicks.csv"
    clicks.write_text("20,79.4\n10,84.5\n40,68.6\n")
    refused([*FIT, "--data", clicks, "--units", "mm", *TINY], "--sort")
    noisy = tmp_path / "noisy.csv"
    noisy.write_text("10,84.5\n20,79.4\n40,-0.01\n")
    refused([*FIT, "--data", noisy, "--units", "mm", *TINY], "--clip-noise")

    # The options reach the loader: with --sort and --clip-noise the files load and the fit starts.
    def started(*args, **kwargs):
        raise ValueError("fit reached")

    monkeypatch.setattr(FIT_MODULE, "fit", started)
    monkeypatch.setattr(SEARCH_MODULE, "search", started)  # without --init, a fit is a global search
    for path, option in ((clicks, "--sort"), (noisy, "--clip-noise")):
        refused([*FIT, "--data", path, "--units", "mm", "--t-end", "0.5", option, *TINY], "fit reached")


# ---- a sweep over one key: a curve, an atomic --out ----------------------------------------------------
# 21 s cold; the command line's sweep, its figure and --out run by default (tests/test_calibration_cli.py)
@pytest.mark.slow
def test_sweep_over_one_key_draws_its_loss_and_writes_out(tmp_path):
    out = tmp_path / "sweep.h5"
    code, stdout, err = call([*SWEEP, "--data", S4, "--over", "beta=0.1:0.3:2", "--out", out,
                              "--plot", tmp_path / "figs", *TINY])
    assert code == 0, err
    result = strict_json(stdout)
    assert result["out"] == str(out) and result["failed"] == []
    assert pathlib.Path(result["figures"][0]).name == "loss.png"
    assert pathlib.Path(result["figures"][0]).stat().st_size > 5_000
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["keys_json"]) == ["beta"] and f["loss"].shape == (2,)
    assert listing(tmp_path) == ["figs", "figs/loss.png", "sweep.h5"]  # no temporary file


def test_write_sweep_is_atomic(tmp_path, monkeypatch):
    result = SweepResult(keys=("beta",), thetas=np.array([[0.1], [0.2]]), loss=np.array([1.0, np.nan]),
                         status=np.array([0, LEFT_GRID]), residuals=np.zeros((2, 3)), predictions=None,
                         failed=np.array([1]), mode="vmap", chunk=2, n_devices=1, wall_s=0.0, compile_s=0.0)
    path = tmp_path / "s.h5"
    write_sweep(path, result)
    before = path.read_bytes()
    real = h5py.Group.create_dataset

    def fail_on_residuals(self, name, *args, **kwargs):
        if name == "residuals":
            raise OSError("disk full")
        return real(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", fail_on_residuals)
    with pytest.raises(OSError, match="disk full"):
        write_sweep(path, result)
    assert path.read_bytes() == before and listing(tmp_path) == ["s.h5"]


# ---- the library's rules, on a closed-form objective (no rollout to compile) ----------------------------
class LinearObjective:
    """r = A θ - b: enough of an Objective for ``fit`` (bounds, residuals and Jacobians, a
    fingerprint, or none with ``fingerprint=False``: an objective that cannot be checked on a
    resume); ``status`` is what every evaluation reports."""

    keys = ("beta",)
    bound_notes = ()
    jacobian = "ad"
    A = np.array([[1.0], [2.0], [3.0]])

    def __init__(self, b=0.3, status=0, fingerprint=True):
        self.bounds = Bounds.create(self.keys)
        self.b, self.status, self.fingerprinted = b, status, fingerprint
        self.blocks, self.row_scale = {"profile": slice(0, 3)}, np.ones(3)

    def initial(self):
        return {"beta": 0.5}

    def check_thetas(self, thetas, name="thetas"):
        """Every θ inside the bounds is a parameter set of the toy."""

    def residuals(self, theta):
        return self.A @ np.asarray(theta) - self.b * self.A[:, 0], {"status": np.asarray(self.status)}

    def residuals_and_jacobian(self, theta):
        r, pred = self.residuals(theta)
        return r, self.A, pred

    def residuals_and_jacobian_z(self, z):
        r, J, pred = self.residuals_and_jacobian(self.bounds.to_physical(np.asarray(z)))
        return r, J * np.asarray(self.bounds.jacobian_diag(np.asarray(z)))[None, :], J, pred

    def describe(self):
        return {"b": self.b}

    def fingerprint(self):
        return {"data": f"b={self.b}", "dx": 0.1} if self.fingerprinted else None


def test_fit_overwrite_resume_and_fingerprint_rules(tmp_path):
    path = tmp_path / "f.h5"
    first = fit(LinearObjective(), steps=2, out=path, uncertainty=False)
    assert first.iterations == 2
    with pytest.raises(ValueError, match="exists .*resume=True \\(--resume\\).*overwrite=True \\(--overwrite\\)"):
        fit(LinearObjective(), steps=2, out=path)
    replaced = fit(LinearObjective(b=0.4), steps=1, out=path, overwrite=True, uncertainty=False)
    assert read_history(path)["history"]["loss"].size == 1 and replaced.iterations == 1
    with pytest.raises(ValueError, match=r"data \(--data/--front: their content\): 'b=0.4' in the file, 'b=0.3' now"):
        fit(LinearObjective(b=0.3), steps=3, out=path, resume=True)
    resumed = fit(LinearObjective(b=0.4), steps=3, out=path, resume=True, uncertainty=False)
    assert resumed.iterations >= 2
    with pytest.raises(ValueError, match="does not exist: there is nothing to resume"):
        fit(LinearObjective(), steps=2, out=tmp_path / "typo.h5", resume=True)
    # A history without a fingerprint (an older file, or an objective without one) cannot be checked.
    fit(LinearObjective(fingerprint=False), steps=1, out=tmp_path / "old.h5", uncertainty=False)
    with pytest.raises(ValueError, match="does not record the problem it was made for"):
        fit(LinearObjective(), steps=2, out=tmp_path / "old.h5", resume=True)


def test_a_failed_start_names_its_status():
    with pytest.raises(ValueError, match="init: the run at the initial parameters fails \\(status 1: a particle "
                                         "left the grid"):
        fit(LinearObjective(status=LEFT_GRID), steps=2)


def test_objective_refuses_a_zero_weight_and_invalid_starts():
    scene = tiny_s4(t_end=0.5)
    from calibration.problem.targets import ProfileTarget

    target = ProfileTarget(S4_X, S4_H, 0.5, source="S4.csv")
    with pytest.raises(ValueError, match=r"weights\['profile'\] is 0"):
        Objective(scene, ("beta",), profile=target, weights={"profile": 0.0})
    objective = Objective(scene, ("mu1",), profile=target)
    # With mu2 fixed, mu1 <= mu2 is a bound: every point the optimiser can reach keeps it.
    mu2 = float(scene.params.mu2)
    assert objective.bounds.upper == (pytest.approx(mu2),) and "lowered to the scene's mu2" in objective.bound_notes[0]
    with pytest.raises(ValueError, match="init: mu1 = 0.7 must lie strictly inside its bounds .*mu1's upper bound 2 "
                                         "lowered to the scene's mu2"):
        fit(objective, {"mu1": 0.7}, steps=1)
    # With both fitted, the rule is checked per point.
    both = Objective(scene, ("mu1", "mu2"), profile=target)
    assert both.bounds.upper == (2.0, 2.0) and not both.bound_notes
    with pytest.raises(ValueError, match="init: the member is not a valid parameter set: member 0 \\(mu1 = 0.7, "
                                         "mu2 = 0.6\\): mu2 \\(the limiting friction\\) must be >= mu1"):
        fit(both, {"mu1": 0.7, "mu2": 0.6}, steps=1)
