"""The side walls of a 2D channel outside the engine: ``[boundaries] side_walls`` in an experiment
file (read, checked, written back), ``jaxmpm.scenes.collapse(side_walls=)``, the named scenes and
``--side-walls WIDTH,FRICTION[,K]`` on both command lines. Scenes are built, never run."""

import importlib

import numpy as np
import pytest
from helpers import ROOT, S4_DATA, call_main, main_exit

import jaxmpm as jm
from calibration.data import read_measurements
from jaxmpm.__main__ import main as jaxmpm_main
from jaxmpm.experiment import Experiment, ExperimentError

SIMULATE_MODULE = importlib.import_module("jaxmpm.simulate")
S4_FILE = ROOT / "experiments_data" / "experiments" / "S4_cohesive_collapse.toml"
S4_TEXT = S4_FILE.read_text(encoding="utf-8")
GATE = 'gate_speed = { value = 50.0, source = "docs/scenes.md S4" }'
WALLS = 'side_walls = { width = "20 mm", friction = 0.25 }'
TINY = ["--dx", "0.02", "--t-end", "0.02", "--no-progress", "--json"]


def s4_text(side_walls: str | None = WALLS, geometry: str = "", numerics: str = "") -> str:
    """S4's file with a side_walls line after gate_speed, and lines added to [geometry] and [numerics]."""
    text = S4_TEXT.replace(GATE, GATE + ("\n" + side_walls if side_walls else ""))
    return text.replace("[geometry]\n", "[geometry]\n" + geometry).replace("[numerics]\n", "[numerics]\n" + numerics)


def s4_file(tmp_path, **kw):
    path = tmp_path / "s4_walls.toml"
    path.write_text(s4_text(**kw), encoding="utf-8")
    return path


def line_of(text: str, start: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if line.startswith(start))


# ---- the experiment file ---------------------------------------------------------------------------------
def test_s4_file_with_side_walls_builds_them():
    assert S4_TEXT.count(GATE) == 1
    e = Experiment.from_text(s4_text(), S4_FILE)
    assert e.side_walls == jm.SideWalls(0.02, 0.25, 1.0)
    assert e.builder_arguments()["side_walls"] == e.side_walls
    scene = e.scene()
    assert scene.config.side_walls == jm.SideWalls(0.02, 0.25)
    assert Experiment.from_text(S4_TEXT, S4_FILE).scene().config.side_walls is None


@pytest.mark.parametrize("entry, expected", [
    ('{ width = 0.03, friction = 0.1, lateral_pressure_ratio = 0.5 }', jm.SideWalls(0.03, 0.1, 0.5)),
    ('{ width = "2 cm", friction = 0 }', jm.SideWalls(0.02, 0.0)),
    ('{ width = { value = 20, unit = "mm", source = "flume drawing" }, friction = 0.25 }', jm.SideWalls(0.02, 0.25)),
])
def test_side_walls_values_and_round_trip(entry, expected):
    e = Experiment.from_text(s4_text("side_walls = " + entry), S4_FILE)
    assert e.side_walls == expected
    again = Experiment.from_text(e.to_toml(), S4_FILE)
    assert again == e and again.side_walls == expected
    assert "side_walls = {" in e.to_toml()


def test_side_walls_keep_their_source():
    entry = 'side_walls = { width = { value = 20, unit = "mm", source = "flume drawing" }, friction = 0.25 }'
    text = Experiment.from_text(s4_text(entry), S4_FILE).to_toml()
    assert 'source = "flume drawing"' in text
    assert "side_walls" not in Experiment.from_text(S4_TEXT, S4_FILE).to_toml()


@pytest.mark.parametrize("entry, message", [
    ('{ width = "-20 mm", friction = 0.25 }', "width must be > 0 m, got -0.02 m"),
    ('{ width = 0, friction = 0.25 }', "width must be > 0 m, got 0 m"),
    ('{ width = "20 mm", friction = -0.1 }', "friction must be >= 0 or \"mu_w\", got -0.1"),
    ('{ width = "20 mm", friction = 0.2, lateral_pressure_ratio = -1 }', "lateral_pressure_ratio must be >= 0"),
    ('{ width = "20 mm" }', "missing friction"),
    ('{ friction = 0.25 }', "missing width"),
    ('{ width = "20 mm", friction = 0.25, K = 1 }', "unknown entry 'K'; side_walls takes width, friction, "
                                                    "lateral_pressure_ratio"),
    ('{ width = "20 s", friction = 0.25 }', "width: unit 's' is not one of"),
    ('{ width = "20 mm", friction = "0.2 mm" }', "friction: unit 'mm' is not one of"),
    ('{ width = "wide", friction = 0.25 }', "width: expected a number or 'number unit'"),
    ('0.02', "expected a table { width = ..., friction = ..."),
])
def test_side_walls_refusals_name_file_line_and_key(entry, message):
    text = s4_text("side_walls = " + entry)
    with pytest.raises(ExperimentError) as err:
        Experiment.from_text(text, "walls.toml")
    prefix = f"walls.toml:{line_of(text, 'side_walls')}: [boundaries] side_walls: "
    assert str(err.value).startswith(prefix), str(err.value)
    assert message in str(err.value)


def test_side_walls_in_3d_are_the_channel_s_own_walls():
    """In 3D the key gives the friction of the channel's walls: its width must be the channel's
    (44.5 mm: eight cells of the file's dx, as a 3D channel must be a whole number of cells wide)."""
    text = s4_text(geometry='width = "44.5 mm"\n', numerics="dim = 3\n")
    with pytest.raises(ExperimentError) as err:
        Experiment.from_text(text, "walls.toml")
    assert str(err.value).startswith(f"walls.toml:{line_of(text, 'side_walls')}: [boundaries] side_walls: ")
    assert "in 3D the channel's own walls: its width must be [geometry] width (0.0445 m), got 0.02 m" in str(err.value)
    text = s4_text('side_walls = { width = "44.5 mm", friction = 0.3, lateral_pressure_ratio = 0.5 }',
                   geometry='width = "44.5 mm"\n', numerics="dim = 3\n")
    with pytest.raises(ExperimentError, match="in 3D the walls' normal stress is computed"):
        Experiment.from_text(text, "walls.toml")
    e = Experiment.from_text(s4_text('side_walls = { width = "44.5 mm", friction = 0.3 }',
                                     geometry='width = "44.5 mm"\n', numerics="dim = 3\n"), "walls.toml")
    assert e.side_walls == jm.SideWalls(0.0445, 0.3)


def test_width_in_a_2d_file_points_to_side_walls():
    text = s4_text(None, geometry='width = "50 mm"\n')
    with pytest.raises(ExperimentError) as err:
        Experiment.from_text(text, "walls.toml")
    message = str(err.value)
    assert message.startswith(f"walls.toml:{line_of(text, 'width')}: [geometry] width: applies to dim = 3 "
                              "(a 2D run has no width); set [numerics] dim = 3 or drop it")
    assert "[boundaries] side_walls = { width = ..., friction = ... }" in message


def test_python_side_walls_checked_like_the_file():
    e = Experiment.from_text(S4_TEXT, S4_FILE)
    with pytest.raises(ExperimentError, match=r"\[boundaries\] side_walls: must be a jaxmpm.SideWalls"):
        e.replace(side_walls=(0.02, 0.25))
    walls = e.replace(side_walls=jm.SideWalls(0.02, 0.25))
    with pytest.raises(ExperimentError, match=r"\[boundaries\] side_walls: in 3D the channel's own walls"):
        walls.with_options(dim=3, width=0.05)


# ---- the Python API ----------------------------------------------------------------------------------
def test_collapse_takes_side_walls_as_a_term_in_2d_and_as_the_walls_in_3d():
    walls = jm.SideWalls(0.02, 0.25, 0.8)
    kw = dict(dx=0.01, runout=0.1, t_end=0.01)
    scene = jm.scenes.collapse("c", 0.05, 0.05, side_walls=walls, **kw)
    assert scene.config.side_walls == walls
    assert scene.remake(dx=0.0125).config.side_walls == walls  # a variant keeps them
    assert jm.scenes.collapse("c", 0.05, 0.05, **kw).config.side_walls is None
    with pytest.raises(ValueError, match="side_walls in 3D gives the friction of the channel's own walls: its width"):
        jm.scenes.collapse("c", 0.05, 0.05, dim=3, width=0.05, side_walls=walls, **kw)
    with pytest.raises(ValueError, match="and its lateral_pressure_ratio 1 \\(got 0.8"):
        jm.scenes.collapse("c", 0.05, 0.05, dim=3, width=0.05, side_walls=jm.SideWalls(0.05, 0.25, 0.8), **kw)
    scene = jm.scenes.collapse("c", 0.05, 0.05, dim=3, width=0.05, side_walls=jm.SideWalls(0.05, 0.25), **kw)
    assert scene.config.side_walls is None
    sides = [w for w in scene.config.walls if w.normal[2] != 0.0]
    assert len(sides) == 2 and all(w.kind == "separable" and w.friction == 0.25 for w in sides)
    plain = jm.scenes.collapse("c", 0.05, 0.05, dim=3, width=0.05, **kw)
    assert all(w.friction == 0.0 for w in plain.config.walls if w.normal[2] != 0.0)
    with pytest.raises(ValueError, match="side_walls must be a jaxmpm.SideWalls or None, got tuple"):
        jm.scenes.collapse("c", 0.05, 0.05, side_walls=(0.02, 0.25), **kw)


@pytest.mark.parametrize("name", ["gates-collapse", "cohesive-collapse", "aspect-ratio"])
def test_named_collapses_pass_side_walls(name):
    walls = jm.SideWalls(0.02, 0.25)
    scene = jm.scenes.build_scene(name, dx=0.012, t_end=0.01, side_walls=walls)
    assert scene.config.side_walls == walls
    assert jm.scenes.named_experiment(name, side_walls=walls).side_walls == walls


def test_named_scenes_refuse_side_walls_where_they_do_not_apply():
    walls = jm.SideWalls(0.02, 0.25)
    with pytest.raises(ValueError, match="--side-walls applies to the collapses, not elastic-block"):
        jm.scenes.build_scene("elastic-block", side_walls=walls)
    with pytest.raises(ValueError, match="in 3D the channel's own walls: its width must be"):
        jm.scenes.named_experiment("cohesive-collapse", dim=3, width=0.05, side_walls=walls)


# ---- python -m jaxmpm run ---------------------------------------------------------------------------------
class _Built(Exception):
    """Raised by the stand-in for ``simulate``, carrying the scene's config."""


@pytest.fixture
def built(monkeypatch):
    """Stop the run at ``simulate``, handing over the config that it was given."""
    def stop(config, *args, **kwargs):
        raise _Built(config)

    monkeypatch.setattr(SIMULATE_MODULE, "simulate", stop)


def run_config(argv):
    with pytest.raises(_Built) as exc:
        jaxmpm_main(["run", *argv])
    return exc.value.args[0]


def refused(capsys, argv, message):
    code, err = main_exit("jaxmpm", argv, capsys)
    assert code == 2, err
    assert message in err, err
    return err


def test_run_flag_sets_the_side_walls(built, tmp_path):
    config = run_config(["cohesive-collapse", *TINY, "--side-walls", "0.02,0.25"])
    assert config.side_walls == jm.SideWalls(0.02, 0.25, 1.0)
    config = run_config(["gates-collapse", *TINY, "--side-walls", "0.03, 0.1, 0.5"])
    assert config.side_walls == jm.SideWalls(0.03, 0.1, 0.5)
    assert run_config(["cohesive-collapse", *TINY]).side_walls is None
    # an experiment file's side walls, and the flag over them
    path = s4_file(tmp_path)
    assert run_config([str(path), *TINY]).side_walls == jm.SideWalls(0.02, 0.25)
    assert run_config([str(path), *TINY, "--side-walls", "0.05,0.4"]).side_walls == jm.SideWalls(0.05, 0.4)


@pytest.mark.parametrize("value, message", [
    ("0.02", "argument --side-walls: expected WIDTH,FRICTION[,K]"),
    ("0.02,0.25,1,2", "argument --side-walls: expected WIDTH,FRICTION[,K]"),
    ("wide,0.25", "argument --side-walls: expected WIDTH,FRICTION[,K]"),
    ("0.02,nan", "argument --side-walls: expected WIDTH,FRICTION[,K]"),
    ("-0.02,0.25", "argument --side-walls: the width must be > 0 m, got -0.02"),
    ("0,0.25", "argument --side-walls: the width must be > 0 m, got 0"),
    ("0.02,-0.1", "argument --side-walls: the friction must be >= 0, got -0.1"),
    ("0.02,0.1,-1", "argument --side-walls: the K must be >= 0, got -1"),
])
def test_run_refuses_bad_side_walls(capsys, built, value, message):
    refused(capsys, ["run", "cohesive-collapse", *TINY, f"--side-walls={value}"], message)


def test_run_refuses_side_walls_where_they_do_not_apply(capsys, built, tmp_path):
    refused(capsys, ["run", "cohesive-collapse", *TINY, "--dim", "3", "--width", "0.06", "--side-walls", "0.02,0.25"],
            "in 3D the channel's own walls: its width must be")
    refused(capsys, ["run", "elastic-block", *TINY, "--side-walls", "0.02,0.25"],
            "--side-walls applies to the collapses, not elastic-block")
    refused(capsys, ["run", "avalanche", "--side-walls", "0.02,0.25"],
            "--side-walls does not apply to the avalanche scene")
    refused(capsys, ["run", "cohesive-collapse", *TINY, "--width", "0.05"], "--width applies to --dim 3")
    # a 3D file refuses the flag
    path = s4_file(tmp_path, side_walls=None, geometry='width = "44.5 mm"\n', numerics="dim = 3\n")
    refused(capsys, ["run", str(path), "--dx", "0.011125", *TINY[2:], "--side-walls", "0.02,0.25"],
            "in 3D the channel's own walls: its width must be")


# ---- python -m calibration fit / sweep ----------------------------------------------------------------------
def calibration_call(argv):
    from calibration.cli import main

    code, _, err = call_main(main, argv)
    return code, err


@pytest.mark.parametrize("command", ["fit", "sweep"])
def test_calibration_flag_sets_the_side_walls(command, tmp_path):
    from calibration.cli import build_parser
    from calibration.cli.args import experiments_of
    from calibration.cli.checks import check_args

    extra = ["--fit", "beta"] if command == "fit" else ["--over", "beta=0:0.5:3"]
    args = build_parser().parse_args([command, "--scene", "cohesive-collapse", "--data", str(S4_DATA), *extra,
                                      "--side-walls", "0.02,0.25,0.9"])
    check_args(args)
    (experiment,) = experiments_of(args)
    assert experiment.side_walls == jm.SideWalls(0.02, 0.25, 0.9)
    assert experiment.scene().config.side_walls == experiment.side_walls
    args = build_parser().parse_args([command, str(s4_file(tmp_path)), "--data", str(S4_DATA), *extra])
    check_args(args)
    (experiment,) = experiments_of(args)
    assert experiment.side_walls == jm.SideWalls(0.02, 0.25)


@pytest.mark.parametrize("argv, message", [
    (["--side-walls=0.02,-0.25"], "argument --side-walls: the friction must be >= 0"),
    (["--side-walls=-1,0.25"], "argument --side-walls: the width must be > 0 m"),
    (["--side-walls", "0.02;0.25"], "argument --side-walls: expected WIDTH,FRICTION[,K]"),
    (["--dim", "3", "--width", "0.05", "--side-walls", "0.02,0.25"], "in 3D the channel's own walls"),
])
def test_calibration_refuses_bad_side_walls(argv, message):
    code, err = calibration_call(["fit", "--scene", "cohesive-collapse", "--data", S4_DATA, "--fit", "beta", *argv])
    assert code == 2, err
    assert message in err, err


def test_calibration_design_takes_and_twin_refuses_side_walls():
    from calibration.cli import build_parser
    from calibration.cli.checks import check_args
    from jaxmpm.cli import scene_from_args

    args = build_parser().parse_args(["design", "--scene", "cohesive-collapse", "--fit", "beta", "--dx", "0.012",
                                      "--side-walls", "0.02,0.25"])
    check_args(args)
    assert scene_from_args(args).config.side_walls == jm.SideWalls(0.02, 0.25)
    code, err = calibration_call(["twin", "--quick", "--side-walls", "0.02,0.25"])
    assert code == 2, err
    assert "--width and --side-walls do not apply" in err, err


def test_runout_law_puts_every_column_in_the_channel():
    from calibration.cli import build_parser
    from calibration.studies.scaling import runout_objective

    args = build_parser().parse_args(["law", "--side-walls", "0.1,0.3"])
    assert args.side_walls == jm.SideWalls(0.1, 0.3)
    assert build_parser().parse_args(["law"]).side_walls is None
    walls = jm.SideWalls(0.1, 0.3, 0.8)
    objective = runout_objective(2.0, ("mu1",), dx=0.0125, side_walls=walls)
    assert objective.scene.config.side_walls == walls
    assert runout_objective(2.0, ("mu1",), dx=0.0125).scene.config.side_walls is None
    code, err = calibration_call(["law", "--side-walls", "0.1,-0.3", "--json"])
    assert code == 2 and "argument --side-walls: the friction must be >= 0" in err, err


def test_a_3d_file_must_fit_a_whole_number_of_cells_across(tmp_path):
    text = s4_text(side_walls=None, geometry='width = "50 mm"\n', numerics="dim = 3\n")
    with pytest.raises(ExperimentError) as err:
        Experiment.from_text(text, "walls.toml")
    assert str(err.value).startswith(f"walls.toml:{line_of(text, 'dx')}: [numerics] dx: must fit a whole number of "
                                     "cells across the 3D channel"), str(err.value)
    assert ("width 0.05 m is 8.989 cells of dx = 0.0055625 m: a 3D channel's walls stand on node rows, so the width "
            "must be a whole number of cells; use dx = width/8 = 0.00625 m or width/9 = 0.00555556 m") in str(err.value)


def test_a_3d_channel_must_be_a_whole_number_of_cells_wide():
    """The walls act on grid nodes: between two node rows a wall would act at the row behind it and
    the channel would be wider than asked, so the builder refuses and names two spacings that fit."""
    with pytest.raises(ValueError, match=r"width = 0.05 m is 12.5 cells of dx = 0.004 m: .* use dx = width/12 = "
                                         r"0.00416667 m or width/13 = 0.00384615 m"):
        jm.scenes.collapse("c", 0.05, 0.05, dx=0.004, dim=3, width=0.05, t_end=0.01, runout=0.05)
    scene = jm.scenes.collapse("c", 0.05, 0.05, dx=0.05 / 12, dim=3, width=0.05, t_end=0.01, runout=0.05)
    nodes_z = scene.config.grid.origin[2] + scene.config.grid.dx * np.arange(scene.config.grid.cells[2] + 1)
    assert np.isclose(nodes_z, 0.0, atol=1e-12).any() and np.isclose(nodes_z, 0.05, atol=1e-12).any()


# ---- the walls' friction as the parameter mu_w (fitted) -------------------------------------------------------
MU_W_WALLS = 'side_walls = { width = "20 mm", friction = "mu_w" }'


def with_material(text: str, line: str) -> str:
    return text.replace("[material]\n", "[material]\n" + line + "\n")


def test_a_file_s_side_walls_may_take_the_parameter_mu_w():
    """friction = "mu_w": the walls read Params.mu_w ([material] mu_w, a fit's start), so that
    [fit] keys may hold mu_w; written back as it was read."""
    text = with_material(s4_text(MU_W_WALLS), "mu_w = 0.3")
    e = Experiment.from_text(text, S4_FILE)
    assert e.side_walls == jm.SideWalls(0.02, "mu_w")
    scene = e.scene()
    assert scene.config.reads_mu_w and float(scene.params.mu_w) == 0.3
    assert Experiment.from_text(e.to_toml(), S4_FILE) == e
    fitted = text + '\n[fit]\nkeys = ["beta", "mu_w"]\n'
    assert read_measurements(Experiment.from_text(fitted, S4_FILE)).fit.keys == ("beta", "mu_w")


@pytest.mark.parametrize("walls, material, fit, at, message", [
    (MU_W_WALLS, None, None, "[material]",
     "[material] mu_w: missing: the side walls' friction is the parameter mu_w"),
    (WALLS, None, '["beta", "mu_w"]', "keys", "[fit] keys: mu_w is read by no boundary"),
    ('side_walls = { width = "20 mm", friction = "mu" }', None, None, "side_walls",
     "friction: expected a number or 'number unit' or the parameter 'mu_w', got 'mu'"),
    ('side_walls = { width = "20 mm", friction = { value = "mu_w", unit = "-" } }', "mu_w = 0.3", None, "side_walls",
     "the parameter 'mu_w' takes no unit"),
])
def test_mu_w_walls_refusals_name_file_line_and_key(walls, material, fit, at, message):
    text = s4_text(walls)
    if material:
        text = with_material(text, material)
    if fit:
        text += f"\n[fit]\nkeys = {fit}\n"
    with pytest.raises(ExperimentError) as err:
        read_measurements(Experiment.from_text(text, "walls.toml"))  # [fit] is calibration's to read
    assert str(err.value).startswith(f"walls.toml:{line_of(text, at)}: "), str(err.value)
    assert message in str(err.value), str(err.value)


def test_the_flag_and_the_objective_take_mu_w_walls():
    from calibration import Objective, load_profile
    from calibration.cli import build_parser
    from calibration.cli.args import experiments_of
    from calibration.cli.checks import check_args

    args = build_parser().parse_args(["fit", "--scene", "cohesive-collapse", "--data", str(S4_DATA), "--fit",
                                      "mu1,mu_w", "--side-walls", "0.02,mu_w,0.8", "--set", "mu_w=0.3"])
    check_args(args)
    (experiment,) = experiments_of(args)
    assert experiment.side_walls == jm.SideWalls(0.02, "mu_w", 0.8)
    scene = experiment.scene()
    assert scene.config.reads_mu_w and float(scene.params.mu_w) == pytest.approx(0.3, rel=1e-7)  # float32
    profile = load_profile(S4_DATA)
    assert Objective(scene, ("mu1", "mu_w"), profile=profile).keys == ("mu1", "mu_w")
    plain = jm.scenes.cohesive_collapse(dx=0.02, t_end=0.5, side_walls=jm.SideWalls(0.02, 0.25))
    with pytest.raises(ValueError, match="keys: mu_w is read by no boundary of the scene"):
        Objective(plain, ("mu1", "mu_w"), profile=profile)
