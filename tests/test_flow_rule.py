"""Fitting μ1, μ2 and I0 to steady incline flows (a flow-rule table): the closed form against the
Bagnold profile, its Jacobian against differences, recovery of a twin from a start far away, the
shipped noisy twin's intervals, and every refusal naming what was wrong."""

import json
import math
import pathlib

import jax
import numpy as np
import pytest
from helpers import call_main

from calibration.cli.commands import main
from calibration.data.flow_rule import FlowRuleTable, load_flow_rule
from calibration.data.incline import load_incline
from calibration.problem.flow_rule import flow_rule_residuals
from calibration.studies.flow_rule import fit_flow_rule
from jaxmpm.datasets import dataset_path
from jaxmpm.params import DEFAULTS
from jaxmpm.scenes import S1_PARAMS, bagnold_velocity
from jaxmpm.scenes.incline import steady_velocity

MATERIAL = {**DEFAULTS, **S1_PARAMS}
TRUTH = {k: MATERIAL[k] for k in ("mu1", "mu2", "I0")}
SLOPES = np.repeat([22.0, 24.0, 26.0, 28.0, 30.0], 4)
THICK = np.tile([0.01, 0.02, 0.03, 0.04], 5)
FAR = {"mu1": 0.30, "mu2": 0.90, "I0": 0.80}
FIXED = {k: MATERIAL[k] for k in ("rho", "rho_s", "d")}


def velocities(theta=TRUTH, quantity="depth_averaged", slopes=SLOPES, h=THICK):
    p = {**MATERIAL, **theta}
    return np.asarray(steady_velocity(h, slopes, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"],
                                      quantity))


def table(u, quantity="depth_averaged", noise=None, slopes=SLOPES, h=THICK):
    return FlowRuleTable(slopes, h, u, quantity, "this test", False, experiment="twin", noise=noise)


@pytest.mark.parametrize("slope", [22.0, 26.0, 30.0])
def test_the_closed_form_is_the_bagnold_profile_at_its_surface_and_its_depth_average(slope):
    depth = 0.038
    z = np.linspace(0.0, depth, 20001)
    profile = bagnold_velocity(z, depth, slope, MATERIAL)
    surface = velocities(quantity="surface", slopes=slope, h=depth)
    mean = velocities(quantity="depth_averaged", slopes=slope, h=depth)
    np.testing.assert_allclose(surface, profile[-1], rtol=1e-12)
    np.testing.assert_allclose(mean, np.trapezoid(profile, z) / depth, rtol=1e-7)


def test_no_steady_flow_outside_the_friction_range_is_nan():
    slopes = np.array([math.degrees(math.atan(TRUTH["mu1"])) - 0.5, 25.0, math.degrees(math.atan(TRUTH["mu2"])) + 0.5])
    u = velocities(slopes=slopes, h=0.02)
    assert np.isnan(u[0]) and np.isfinite(u[1]) and u[1] > 0 and np.isnan(u[2])


def test_the_residuals_jacobian_matches_central_differences():
    data = table(velocities())
    keys = ("mu1", "mu2", "I0")
    residuals = flow_rule_residuals(data, keys, MATERIAL)
    theta = np.array([0.37, 0.66, 0.31])
    J = np.asarray(jax.jit(jax.jacfwd(residuals))(theta))
    step = 1e-6 * theta
    fd = np.stack([(np.asarray(residuals(theta + e)) - np.asarray(residuals(theta - e))) / (2 * e[i])
                   for i, e in enumerate(np.diag(step))], axis=1)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-10)
    assert np.all(np.isfinite(J))


def test_a_twin_is_recovered_from_a_start_far_away():
    result = fit_flow_rule(table(velocities()), init=FAR, values=FIXED)
    assert result.converged, result.message
    for key, value in TRUTH.items():
        assert result.theta[key] == pytest.approx(value, rel=1e-7), key
    assert result.start == FAR and result.iterations < 30


def test_a_surface_velocity_table_is_fitted_as_one():
    result = fit_flow_rule(table(velocities(quantity="surface"), "surface"), ("mu2", "I0"),
                           init={"mu2": 0.8, "I0": 0.5}, values=FIXED)
    assert result.theta == pytest.approx({"mu2": TRUTH["mu2"], "I0": TRUTH["I0"]}, rel=1e-7)


def test_the_shipped_noisy_twin_holds_its_truth_within_the_intervals():
    data = load_flow_rule(dataset_path("synthetic/flow_rule_twin"))
    assert data.noise == 0.02 and data.quantity == "depth_averaged" and data.n == 16
    truth = data.meta["parameters"]
    result = fit_flow_rule(data, init=FAR, values={k: truth[k] for k in ("rho", "rho_s", "d")})
    assert result.converged, result.message
    ci = result.uncertainty.ci95
    for (lo, hi), key in zip(ci, result.keys):
        assert lo < truth[key] < hi, (key, lo, hi, truth[key])
    out = result.to_json()
    json.dumps(out, allow_nan=False)
    assert out["data"]["slopes_deg"] == [22.0, 24.0, 26.0, 28.0] and out["noise"] == {"velocity": 0.02}
    assert out["verdict"]["verdict"] == "a fit of the data" and out["params"] == result.theta


def test_the_command_line_prints_the_fit_and_draws_it(tmp_path):
    code, out, err = call_main(main, ["flow-rule", dataset_path("synthetic/flow_rule_twin"), "--init", "mu1=0.3",
                                      "--init", "mu2=0.9", "--init", "I0=0.8", "--set", "d=0.0007",
                                      "--plot", tmp_path, "--json"])
    assert code == 0, err
    out = json.loads(out)
    assert out["converged"] and set(out["params"]) == {"mu1", "mu2", "I0"} and out["fixed"]["d"] == 0.0007
    assert out["figures"] == [str(tmp_path / "flow_rule.png")] and (tmp_path / "flow_rule.png").stat().st_size > 0


@pytest.mark.parametrize("kwargs, message", [
    ({"keys": ("mu1", "beta")}, "keys: a flow rule fits distinct keys among"),
    ({"init": {"xi": 1.0}}, r"init: \['xi'\] are not among the fitted keys"),
    ({"init": {"mu1": 0.45}}, "init: mu1 = 0.45 is not below tan 22°"),
    ({"init": {"mu2": 0.5}}, "init: mu2 = 0.5 is not above tan 30°"),
    ({"init": {"I0": 5.0}}, "init: I0 = 5.0 must lie strictly inside its bounds"),
])
def test_bad_fits_are_refused_naming_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        fit_flow_rule(table(velocities()), **kwargs)


def test_too_few_rows_for_the_keys_are_refused():
    few = table(velocities(slopes=np.array([24.0, 26.0]), h=np.array([0.02, 0.02])), slopes=np.array([24.0, 26.0]),
                h=np.array([0.02, 0.02]))
    with pytest.raises(ValueError, match="2 rows cannot fix 3 keys"):
        fit_flow_rule(few)


GOOD = "# source: a test\n# secondary: false\n# quantity: depth_averaged\nslope_deg,h_m,u_m_s\n25,0.02,0.3\n"


@pytest.mark.parametrize("text, message", [
    (GOOD.replace("u_m_s", "u"), "expected the columns slope_deg,h_m,u_m_s"),
    (GOOD.replace("# secondary: false\n", ""), "must say 'secondary: true' or 'secondary: false'"),
    (GOOD.replace("# source: a test\n", ""), "the header has no 'source'"),
    (GOOD.replace("depth_averaged", "mean"), "quantity must be one of"),
    (GOOD.replace("0.02,0.3", "-0.02,0.3"), "h_m must be > 0 m; row 1 has"),
    (GOOD.replace("25,", "95,"), r"slope_deg must be in \(0, 90\) degrees"),
    (GOOD.replace("# quantity", "# noise: lots\n# quantity"), "noise must be a number"),
    (GOOD.replace("# quantity", "# noise: 0\n# quantity"), "noise must be a relative standard deviation > 0"),
])
def test_a_bad_table_is_refused_naming_the_file(tmp_path, text, message):
    path = tmp_path / "rule.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        load_flow_rule(path)
    assert str(path) in str(err.value)
    assert load_flow_rule(_good(tmp_path)).n == 1


def _good(tmp_path):
    path = tmp_path / "good.csv"
    path.write_text(GOOD)
    return path


# ---- the incline experiment file ---------------------------------------------------------------------------------
TWIN_TOML = "synthetic/flow_rule_twin_experiment"


def test_the_shipped_incline_file_is_fitted_as_its_table_with_its_material():
    experiment = load_incline(dataset_path(TWIN_TOML))
    assert experiment.keys == ("mu1", "mu2", "I0") and experiment.init == FAR
    assert experiment.material["d"] == pytest.approx(0.7e-3) and experiment.sources["material.d"]["unit"] == "mm"
    code, out, err = call_main(main, ["flow-rule", dataset_path(TWIN_TOML), "--json"])
    assert code == 0, err
    out = json.loads(out)
    assert out["start"] == FAR and out["fixed"]["d"] == pytest.approx(0.7e-3) and out["converged"]
    table = load_flow_rule(experiment.table_file)
    direct = fit_flow_rule(table, init=FAR, values=experiment.material)
    assert out["params"] == pytest.approx(direct.theta, rel=1e-12)


INCLINE = ('format = 1\n[experiment]\nkind = "incline"\n[material]\nd = "0.7 mm"\n[flow_rule]\nfile = "rule.csv"\n'
           '[fit]\nkeys = ["mu2", "I0"]\n')


@pytest.mark.parametrize("edit, message", [
    (('kind = "incline"', 'kind = "chute"'), ':3: [experiment] kind: must be "incline" in an incline file'),
    (('d = "0.7 mm"', 'nu = 0.7'), ":5: [material] nu: nu must be in (-1, 0.5)"),
    (('file = "rule.csv"', 'file = "gone.csv"'), ":7: [flow_rule] file: no such file:"),
    (('keys = ["mu2", "I0"]', 'keys = ["beta"]'), ":9: [fit] keys: a flow rule fits distinct keys among"),
    (('keys = ["mu2", "I0"]\n', 'keys = ["mu2", "I0"]\ninit = { mu1 = 0.3 }\n'),
     ":10: [fit] init: ['mu1'] are not among the fitted keys"),
    (("[fit]", "[numerics]\ndx = 0.01\n[fit]"), ":8: [numerics]: unknown section or key"),
])
def test_a_bad_incline_file_is_refused_at_its_line(tmp_path, edit, message):
    (tmp_path / "rule.csv").write_text(GOOD)
    path = tmp_path / "chute.toml"
    path.write_text(INCLINE.replace(*edit))
    code, out, err = call_main(main, ["flow-rule", path, "--json"])
    assert code == 2 and out == "" and f"{path}{message}" in err, err
    path.write_text(INCLINE)
    assert load_incline(path).keys == ("mu2", "I0")


def test_the_engine_refuses_an_incline_file_and_says_what_fits_it(tmp_path):
    from jaxmpm.experiment import Experiment, ExperimentError

    path = tmp_path / "chute.toml"
    path.write_text(INCLINE)
    with pytest.raises(ExperimentError, match=r"chute.toml:3: \[experiment\] kind: this file describes a collapse; "
                                              r"got kind = 'incline' \(steady flows down an incline: fitted by "
                                              r"`python -m calibration flow-rule FILE`"):
        Experiment.from_toml(path)


def test_a_joint_fits_figures_draw_its_incline(tmp_path):
    """``fit_figures`` of a fit holding a flow-rule table (here alone; beside a collapse in a joint
    fit, whose profiles panel skips it): the history and the table against the model at the fit's
    values. It used to raise, so that `calibration fit collapse.toml incline.toml --plot` printed
    a traceback and no JSON."""
    from calibration import FlowRuleObjective, fit
    from calibration.plots.fits import fit_figures

    objective = FlowRuleObjective(load_flow_rule(dataset_path("synthetic/flow_rule_twin")))
    result = fit(objective, {"mu1": 0.35, "mu2": 0.7, "I0": 0.3}, steps=3, uncertainty=False)
    figures = fit_figures(tmp_path / "figs", objective, result)
    assert [pathlib.Path(f).name for f in figures] == ["fit_history.png", "fit_flow_rule.png"]
    assert all(pathlib.Path(f).stat().st_size > 10_000 for f in figures)


def test_an_output_step_that_fails_in_any_way_keeps_the_work():
    """``guard``: an output step's failure, a defect included (the figure bug above was an
    AttributeError, which used to escape and lose a finished fit's JSON), is reported under its
    option and returns None."""
    from calibration.cli.args import guard

    def broken():
        raise AttributeError("'FlowRuleObjective' object has no attribute 'observations'")

    errors = {}
    assert guard(errors, "--plot", broken) is None
    assert errors == {"--plot": "AttributeError: 'FlowRuleObjective' object has no attribute 'observations'"}
    assert guard(errors, "--out", lambda: "written") == "written" and "--out" not in errors
