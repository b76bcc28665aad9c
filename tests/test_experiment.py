"""Experiment files (jaxmpm.experiment, docs/experiments.md): the shipped scenes are experiment files
equal to their builders; a user's collapse runs and fits from one file as from the equivalent Python
set-up; every bad input is one line naming the file, the line and the key, before anything compiles."""

import json
import math
import pathlib

import numpy as np
import pytest
from helpers import main_exit
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxmpm.experiment import SHIPPED_EXPERIMENTS, Experiment, ExperimentError, shipped_experiment
from jaxmpm.scenes import (
    S4_SIDE,
    aluminium_bars,
    aspect_ratio_collapse,
    cohesive_collapse,
    collapse,
    gates_collapse,
    slope_collapse,
)

BUILDERS = {"gates-collapse": gates_collapse, "slope-collapse": slope_collapse,
            "cohesive-collapse": cohesive_collapse, "aspect-ratio": aspect_ratio_collapse,
            "aluminium-bars": aluminium_bars}

# A collapse none of the named scenes describes: another column, slope, gate speed and cohesion.
USER_TOML = """\
# a user's experiment
[experiment]
name = "tall-cohesive"

[geometry]
length = "60 mm"
height = "90 mm"
slope = 5

[boundaries]
gate = "front"
gate_lift_time = "60 ms"

[material]
beta = 0.15
pc0 = { value = 0.4, unit = "kPa", source = "shear-box test" }
xi = 50
d = "0.8 mm"

[numerics]
dx = "15 mm"
t_end = "0.1 s"
"""
# The same set-up written in Python.
USER_PYTHON = dict(name="tall-cohesive", length=0.06, height=0.09, dx=0.015, slope_deg=5.0, front_gate_speed=1.5,
                   runout=1.6 * 1.2 * (0.09 / 0.06) * 0.06 * (1 + 5 / 8) + 4 * 0.015, t_end=0.1, beta=0.15,
                   pc0=400.0, xi=50.0, d=0.8e-3)


def _same_scene(a, b, info=True):
    assert a.name == b.name
    assert a.config == b.config
    for field in ("x", "v", "F", "vol0"):
        np.testing.assert_array_equal(np.asarray(getattr(a.state, field)), np.asarray(getattr(b.state, field)))
    assert a.params.to_dict() == b.params.to_dict()
    if info:
        assert a.info == b.info


@pytest.mark.parametrize("name", sorted(SHIPPED_EXPERIMENTS))
def test_shipped_experiments_build_the_named_scenes(name):
    experiment = shipped_experiment(name)
    # S5's builder also records the aspect ratio it was asked for; the geometry is the same.
    _same_scene(experiment.scene(), BUILDERS[name](), info=name != "aspect-ratio")
    assert "docs/scenes.md" in experiment.sources["geometry.height"]["source"]
    # Written and read back: the same experiment, sources kept.
    again = Experiment.from_text(experiment.to_toml(), experiment.path)
    assert again == experiment and again.sources == experiment.sources


def test_named_shortcut_with_options_equals_builder():
    from jaxmpm.scenes import build_scene

    _same_scene(build_scene("cohesive-collapse", dx=S4_SIDE / 8, ppc=2, t_end=0.2, values={"beta": 0.2}, seed=3),
                cohesive_collapse(beta=0.2, dx=S4_SIDE / 8, ppc=2, t_end=0.2, seed=3))


def test_user_experiment_equals_python_set_up(tmp_path):
    path = tmp_path / "tall.toml"
    path.write_text(USER_TOML)
    experiment = Experiment.from_toml(path)
    assert experiment.gate_speed == pytest.approx(1.5) and experiment.material["pc0"] == 400.0
    assert experiment.sources["material.pc0"] == {"source": "shear-box test", "unit": "kPa"}
    _same_scene(experiment.scene(), collapse(**USER_PYTHON))
    assert experiment.scene().experiment == experiment


_main = main_exit


@pytest.mark.slow  # 25 s; an experiment file's objective is built by default (tests/test_tutorial.py)
def test_user_experiment_runs_and_fits_from_the_file_as_from_python(tmp_path, capsys):
    """The command line on the file against the library on the Python set-up: the same run
    (and its HDF5 records the experiment) and the same fit."""
    import jax

    from calibration import Objective, fit, load_profile
    from jaxmpm import simulate
    from jaxmpm.__main__ import main as run_main
    from jaxmpm.io import read_h5

    path = tmp_path / "tall.toml"
    path.write_text(USER_TOML)
    h5, csv = tmp_path / "run.h5", tmp_path / "deposit.csv"
    assert run_main(["run", str(path), "--json", "--no-progress", "--out", str(h5), "--profile-csv", str(csv)]) == 0
    summary = json.loads(capsys.readouterr().out)
    python = simulate(*collapse(**USER_PYTHON, dtype="float32"), throw=False)
    x = np.asarray(python.state.x)
    assert summary["n_steps"] == int(python.state.steps)
    assert summary["x_max"] == float(x[:, 0].max()) and summary["y_max"] == float(x[:, 1].max())
    assert summary["runout"] == pytest.approx(float(x[:, 0].max()) - 0.06, abs=1e-8)
    assert Experiment.from_h5(h5) == Experiment.from_toml(path).replace(dtype="float32")  # as it ran
    assert read_h5(h5)["attrs"]["scene"] == "tall-cohesive"

    # The fit: the file names the data and what to fit; Python builds the same objective.
    path.write_text(USER_TOML + '\n[[profile]]\nfile = "deposit.csv"\n\n[fit]\nkeys = ["beta"]\n'
                    'init = { beta = 0.1 }\n')
    from calibration.cli.commands import main as calibration_main

    assert calibration_main(["fit", str(path), "--json", "--no-progress", "--workers", "1", "--steps", "2",
                             "--roundoff-samples", "0", "--grid-check", "0"]) in (0, 1)
    cli = json.loads(capsys.readouterr().out)
    assert cli["experiments"] == [str(path)] and cli["search"]["starts"] == 1
    objective = Objective(collapse(**USER_PYTHON, dtype="float32"), ("beta",), profile=[load_profile(csv)])
    from_file = Objective.from_experiment(Experiment.from_toml(path).replace(dtype="float32"))
    assert from_file.fingerprint() == objective.fingerprint() and from_file.keys == ("beta",)
    ours = fit(objective, {"beta": 0.1}, steps=2, progress=False, roundoff_samples=0)
    assert cli["params"]["beta"] == pytest.approx(ours.theta["beta"], rel=1e-6)
    assert cli["loss"] == pytest.approx(ours.loss, rel=1e-5)
    jax.clear_caches()


def test_several_experiments_make_one_joint_objective(tmp_path):
    import argparse

    from calibration.cli.args import experiments_of, fit_request, setup_of
    from calibration.cli.parser import build_parser
    from calibration.problem.composite import CompositeObjective

    for name, slope in (("a", 0), ("b", 8)):
        (tmp_path / f"{name}.toml").write_text(USER_TOML.replace("slope = 5", f"slope = {slope}")
                                               + f'\n[[profile]]\nfile = "{name}.csv"\n[fit]\nkeys = ["mu1"]\n')
        (tmp_path / f"{name}.csv").write_text("# units: m\n# time_s: 0.1\nx_m,h_m\n0,0.05\n0.05,0.04\n0.1,0\n")
    args = build_parser().parse_args(["fit", str(tmp_path / "a.toml"), str(tmp_path / "b.toml")])
    assert isinstance(args, argparse.Namespace)
    experiments = experiments_of(args)
    request = fit_request(args, experiments)
    assert request.keys == ("mu1",) and request.init == {} and request.noise is None
    objective = setup_of(args, request.keys).objective()
    assert isinstance(objective, CompositeObjective) and len(objective.members) == 2
    assert [m.scene.info.slope_deg for m in objective.members] == [0.0, 8.0]
    coarse = objective.coarsened(1.5)  # the grid term of a joint fit coarsens every member
    assert [m.dx for m in coarse.members] == pytest.approx([0.0225, 0.0225])


# -- bad input: one line naming the file, the line and the key, through the real main() ---------------

BAD = [
    # (change to USER_TOML, the message's expected parts)
    (("xi = 50", "xi = 50\npc = 3"), ("tall.toml:18:", "[material] pc: unknown key")),
    (("[numerics]", "[numeric]"), ("tall.toml:", "numeric", "unknown section or key")),
    (('length = "60 mm"\n', ""), ("tall.toml:5:", "[geometry] length: missing")),
    (('t_end = "0.1 s"\n', ""), ("tall.toml:", "[numerics] t_end: missing")),
    (('height = "90 mm"', 'height = "90 kg"'), ("tall.toml:7:", "[geometry] height: unit 'kg' is not one of")),
    (('d = "0.8 mm"', 'd = "0.8 kPa"'), ("tall.toml:", "[material] d: unit 'kPa'")),
    (("xi = 50", 'xi = "fifty"'), ("tall.toml:", "[material] xi: expected a number or 'number unit'")),
    (("slope = 5", "slope = true"), ("tall.toml:8:", "[geometry] slope: expected a number")),
    (('gate = "front"', 'gate = "side"'), ("tall.toml:", "[boundaries] gate: must be one of")),
    (('gate_lift_time = "60 ms"\n', ""), ("tall.toml:", "[boundaries] gate_speed: missing")),
    (('gate_lift_time = "60 ms"', 'gate_lift_time = "60 ms"\ngate_speed = 1'),
     ("tall.toml:", "gate_lift_time: give gate_speed or gate_lift_time, not both")),
    (('dx = "15 mm"', 'dx = "10 cm"'), ("tall.toml:21:", "[numerics] dx: must be at most the column's thinnest side")),
    (('length = "60 mm"', 'length = "0.1 mm"'), ("tall.toml:", "[numerics] dx: must be at most the column's")),
    (('dx = "15 mm"', "dx = -0.01"), ("tall.toml:21:", "[numerics] dx: must be > 0")),
    (("slope = 5", "slope = 5\nwidth = 0.1"), ("tall.toml:", "[geometry] width: applies to dim = 3")),
    (('gate = "front"', 'gate = "front"\nfloor_friction = 0.3'), ("tall.toml:", "floor_friction: a no-slip floor")),
    (("[numerics]", "[numerics]\nppc = 2.5"), ("tall.toml:", "[numerics] ppc: must be a positive integer")),
    # The parameter table's rules and relation, at the key's line (they were refused later, by
    # Params.create, without the file, the line or the key).
    (("xi = 50", "xi = 50\nnu = 0.5"), ("tall.toml:18:", "[material] nu: must be in (-1, 0.5), got 0.5")),
    (("xi = 50", "xi = 50\nE = -1"), ("tall.toml:18:", "[material] E: must be > 0, got -1.0")),
    (("xi = 50", "xi = 50\nmu1 = 0.6\nmu2 = 0.5"),
     ("tall.toml:19:", "[material] mu2: must be >= mu1 (mu2 is the limiting friction), got mu1 = 0.6 and mu2 = 0.5")),
    (("xi = 50", "xi = 50\nmu2 = 0.3"),  # below the default mu1 = tan 20.9 deg
     ("tall.toml:18:", "[material] mu2: must be >= mu1", "mu1 = 0.38186", "(the default) and mu2 = 0.3")),
    (("xi = 50", "xi = 50\nmu1 = 0.7"),  # above the default mu2: reported where mu2 would stand
     ("tall.toml:14:", "[material] mu2: must be >= mu1", "mu1 = 0.7 and mu2 = 0.64", "(the default)")),
    (("xi = 50", "xi = 50\nphi = 30"),
     ("tall.toml:18:", "[material] phi: unknown key; [material] takes E [Pa], nu [-]")),
    (('gate = "front"', 'gate = "front"\nfloor = "slip-stick"\nfloor_friction = -0.1'),
     ("tall.toml:13:", "[boundaries] floor_friction: must be >= 0, got -0.1 (the floor's mu_w)")),
    # Each choice from the list of the module that owns it: flip was accepted here and refused by Config.
    (('t_end = "0.1 s"', 't_end = "0.1 s"\ntransfer = "flip"'),
     ("tall.toml:23:", "[numerics] transfer: must be one of ('pic', 'apic', 'aflip'), got 'flip'")),
    (('gate = "front"', 'gate = "front"\nfloor = "rough"'),
     ("tall.toml:12:", "[boundaries] floor: must be one of ('no-slip', 'slip-stick', 'separable'), got 'rough'")),
    (('t_end = "0.1 s"', 't_end = "0.1 s"\ndtype = "float16"'),
     ("tall.toml:23:", "[numerics] dtype: must be one of ('float32', 'float64'), got 'float16'")),
    # A measurement file that is not there (the run went on and exited 0).
    (('t_end = "0.1 s"\n', 't_end = "0.1 s"\n\n[[profile]]\nfile = "missing.csv"\n'),
     ("tall.toml:25:", "[[profile]] #1 file: no such file: ", "missing.csv")),
    (('t_end = "0.1 s"\n', 't_end = "0.1 s"\n\n[front]\nfile = "gone.csv"\n'),
     ("tall.toml:25:", "[front] file: no such file: ", "gone.csv")),
    (("[experiment]", "[experiment\n"), ("tall.toml: not valid TOML",)),
]


@pytest.mark.parametrize("change, parts", BAD)
def test_bad_experiment_files_fail_before_compiling(change, parts, tmp_path, capsys):
    path = tmp_path / "tall.toml"
    path.write_text(USER_TOML.replace(*change))
    code, err = _main("jaxmpm", ["run", str(path)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    for part in parts:
        assert part in err, err
    with pytest.raises(ExperimentError):
        Experiment.from_toml(path)



def test_each_choice_is_the_list_of_the_module_that_owns_it():
    """An experiment file accepts what the engine accepts: one list of each choice, read from
    its owner (the file's own copy of the transfers listed a FLIP that Config refuses)."""
    from jaxmpm import _experiment_checks as checks
    from jaxmpm.cli import add_scene_arguments
    from jaxmpm.config import TRANSFERS
    from jaxmpm.precision import DTYPES
    from jaxmpm.sampling import SAMPLINGS
    from jaxmpm.scenes.collapse import FLOORS

    assert (checks.TRANSFERS, checks.SAMPLINGS, checks.DTYPES, checks.FLOORS) == (TRANSFERS, SAMPLINGS, DTYPES, FLOORS)
    assert checks.TRANSFERS is TRANSFERS and checks.SAMPLINGS is SAMPLINGS and checks.DTYPES is DTYPES
    assert checks.FLOORS is FLOORS and "flip" not in TRANSFERS
    import argparse

    parser = argparse.ArgumentParser()
    add_scene_arguments(parser)
    choices = {a.dest: a.choices for a in parser._actions}
    assert choices["sampling"] is SAMPLINGS and choices["dtype"] is DTYPES
    with pytest.raises(ValueError, match=r"floor must be one of \('no-slip', 'slip-stick', 'separable'\)"):
        collapse(**{**USER_PYTHON, "floor": "rough"})


def test_measurement_files_are_checked_where_the_experiment_is_read(tmp_path):
    """A file naming a measurement that is not there is refused when it is read; a run's HDF5
    file re-made elsewhere names the file it recorded, and ``check_files=False`` gives the set-up
    alone (all a run needs) with the recorded paths kept."""
    import h5py

    path = tmp_path / "tall.toml"
    text = USER_TOML + '\n[[profile]]\nfile = "deposit.csv"\n'
    path.write_text(text)
    with pytest.raises(ExperimentError, match=r"tall.toml:25: \[\[profile\]\] #1 file: no such file: .*deposit.csv$"):
        Experiment.from_toml(path)
    with pytest.raises(ExperimentError, match="no such file"):
        Experiment.from_text(text, path)
    unchecked = Experiment.from_toml(path, check_files=False)
    assert unchecked.measurements["profile"][0]["file"] == tmp_path / "deposit.csv"
    (tmp_path / "deposit.csv").write_text("# units: m\n# time_s: 0.1\nx_m,h_m\n0,0.05\n0.05,0.04\n0.1,0\n")
    experiment = Experiment.from_toml(path)
    assert experiment == unchecked
    h5 = tmp_path / "run.h5"
    with h5py.File(h5, "w") as f:  # what Scene.run_attrs records of a run
        f.attrs["experiment_toml"] = experiment.to_toml()
        f.attrs["experiment_path"] = str(path.resolve())
    assert Experiment.from_h5(h5) == experiment
    (tmp_path / "deposit.csv").unlink()  # the data moved after the run
    with pytest.raises(ExperimentError, match=r"\[\[profile\]\] #1 file: no such file: .*deposit.csv"):
        Experiment.from_h5(h5)
    again = Experiment.from_h5(h5, check_files=False)
    assert again == experiment and again.scene().config == experiment.scene().config


def test_a_command_line_value_names_itself_not_the_file(tmp_path, capsys):
    """A --set value that breaks a rule is the option's error (the file's own values were
    checked when it was read), in the words of Params.create."""
    path = tmp_path / "tall.toml"
    path.write_text(USER_TOML)
    code, err = _main("jaxmpm", ["run", str(path), "--set", "nu=0.7"], capsys)
    assert code == 2 and "nu must be in (-1, 0.5), got 0.7" in err and "tall.toml" not in err
    code, err = _main("jaxmpm", ["run", str(path), "--set", "mu2=0.2"], capsys)
    assert code == 2 and "mu2 (the limiting friction) must be >= mu1" in err

def test_bad_data_and_fit_requests(tmp_path, capsys):
    path = tmp_path / "tall.toml"
    # A measurement that does not exist, and one that does not match the geometry.
    path.write_text(USER_TOML + '\n[[profile]]\nfile = "missing.csv"\n[fit]\nkeys = ["beta"]\n')
    code, err = _main("calibration", ["fit", str(path)], capsys)
    assert code == 2 and "missing.csv" in err
    (tmp_path / "far.csv").write_text("# units: m\n# time_s: 0.1\nx_m,h_m\n5,0.05\n5.1,0.04\n5.2,0\n")
    path.write_text(USER_TOML + '\n[[profile]]\nfile = "far.csv"\n[fit]\nkeys = ["beta"]\n')
    code, err = _main("calibration", ["fit", str(path)], capsys)
    assert code == 2 and "far.csv" in err
    path.write_text(USER_TOML + '\n[[profile]]\nfile = "far.csv"\n')
    code, err = _main("calibration", ["fit", str(path)], capsys)
    assert code == 2 and "--fit is required" in err
    code, err = _main("calibration", ["fit", str(path), "--scene", "cohesive-collapse", "--fit", "beta"], capsys)
    assert code == 2 and "not both" in err
    path.write_text(USER_TOML + '\n[fit]\nkeys = ["beta", "gamma"]\n')
    code, err = _main("calibration", ["fit", str(path)], capsys)
    assert code == 2 and "[fit] keys: unknown parameter(s) ['gamma']" in err
    # --shared: several files, and keys among the fitted ones.
    path.write_text(USER_TOML + '\n[[profile]]\nfile = "far.csv"\n[fit]\nkeys = ["beta", "mu1"]\n')
    code, err = _main("calibration", ["fit", str(path), "--shared", "mu1"], capsys)
    assert code == 2 and "--shared needs two experiment files or more" in err
    code, err = _main("calibration", ["fit", str(path), str(path), "--fit", "beta,mu1", "--shared", "xi"], capsys)
    assert code == 2 and "--shared xi: not among the fitted keys" in err
    code, err = _main("calibration", ["fit", str(path), str(path), "--shared", ","], capsys)
    assert code == 2 and "--shared: expected comma-separated parameter names" in err
    # A command-line option that does not fit the file names the option.
    path.write_text(USER_TOML)
    code, err = _main("jaxmpm", ["run", str(path), "--dx", "1"], capsys)
    assert code == 2 and "--dx must be at most the column's thinnest side (0.06 m)" in err
    code, err = _main("jaxmpm", ["run", str(path), "--aspect", "2"], capsys)
    assert code == 2 and "--aspect applies to the aspect-ratio scene" in err


# -- property tests of the parser ---------------------------------------------------------------------

_KEYS = ["length", "height", "slope", "width", "gate", "gate_speed", "floor", "back_wall", "beta", "pc0", "dx", "t_end",
         "ppc", "seed", "dim", "frames", "unknown", "file", "keys"]
_SECTIONS = ["experiment", "geometry", "boundaries", "material", "numerics", "fit", "front", "bogus"]
_VALUES = st.one_of(st.integers(-5, 5), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
                    st.text(max_size=8), st.sampled_from(['"60 mm"', '"1 s"', '"2 kPa"', '"x m"']),
                    st.lists(st.integers(0, 3), max_size=2))


def _literal(value):
    if isinstance(value, str) and value.startswith('"'):
        return value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    return str(value).replace("'", '"')


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.dictionaries(st.sampled_from(_SECTIONS),
                       st.dictionaries(st.sampled_from(_KEYS), _VALUES, max_size=4), max_size=6))
def test_parser_fuzz_gives_an_experiment_or_one_clear_error(document):
    text = "\n".join(f"[{section}]\n" + "\n".join(f"{k} = {_literal(v)}" for k, v in table.items())
                     for section, table in document.items())
    try:
        experiment = Experiment.from_text(text, pathlib.Path("fuzz.toml"))
    except ExperimentError as err:
        assert str(err).startswith("fuzz.toml") and "\n" not in str(err).strip()
    else:
        assert Experiment.from_text(experiment.to_toml(), pathlib.Path("fuzz.toml")) == experiment


@settings(max_examples=60, deadline=None)
@given(length=st.floats(0.02, 1.0), aspect=st.floats(0.3, 3.0), slope=st.floats(-20, 30),
       gate=st.sampled_from(["none", "front"]), speed=st.floats(0.1, 100), beta=st.floats(0, 1),
       dx_cells=st.integers(2, 20), t_end=st.floats(0.01, 3))
def test_to_toml_round_trips(length, aspect, slope, gate, speed, beta, dx_cells, t_end):
    height = aspect * length
    experiment = Experiment(name="p", length=length, height=height, t_end=t_end, slope=slope, gate=gate,
                            gate_speed=speed if gate != "none" else None, material={"beta": beta},
                            dx=min(length, height) / dx_cells)
    assert Experiment.from_text(experiment.to_toml()) == experiment
