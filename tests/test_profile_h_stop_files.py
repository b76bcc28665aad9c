"""A velocity profile's table and an h_stop table, as files and in fits: the profile fitted as a
flow rule (its residuals' Jacobian against central differences, a 1 % twin recovered within its
intervals, a walled twin with μ_w), the h_stop table reported beside the fit and never fitted,
the incline file naming both, and every refusal naming the file, the row or the line."""

import json
import math

import jax
import numpy as np
import pytest
from helpers import call_main

from calibration.cli.args import h_stop_fields
from calibration.cli.commands import main
from calibration.data.flow_rule import FlowRuleTable, HStopTable, load_flow_rule, load_h_stop
from calibration.data.incline import load_incline
from calibration.problem.flow_rule import flow_rule_residuals
from calibration.studies.flow_rule import NO_H_STOP, fit_flow_rule, h_stop_report
from jaxmpm import SideWalls
from jaxmpm.datasets import dataset_path
from jaxmpm.params import DEFAULTS
from jaxmpm.scenes import S1_PARAMS
from jaxmpm.scenes.incline import steady_velocity

MATERIAL = {**DEFAULTS, **S1_PARAMS}
TRUTH = {k: MATERIAL[k] for k in ("mu1", "mu2", "I0")}
FIXED = {k: MATERIAL[k] for k in ("rho", "rho_s", "d")}
FAR = {"mu1": 0.36, "mu2": 0.75, "I0": 0.5}
# Five slopes between atan(mu1) = 20.9° and atan(mu2) = 32.8°, three thicknesses, four heights each.
SLOPES, THICK, SHARE = (a.ravel() for a in np.meshgrid([22.0, 24.0, 26.0, 28.0, 30.0], [0.01, 0.02, 0.04],
                                                       [0.25, 0.5, 0.75, 1.0], indexing="ij"))
HEIGHTS = SHARE * THICK


def profile(theta=TRUTH, walls=None, mu_w=None):
    p = {**MATERIAL, **theta}
    return np.asarray(steady_velocity(THICK, SLOPES, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"],
                                      "profile", walls, mu_w, height=HEIGHTS))


def table(u, noise=None, keep=slice(None)):
    return FlowRuleTable(SLOPES[keep], THICK[keep], u[keep], "profile", "this test", False, experiment="profile twin",
                         noise=noise, z=HEIGHTS[keep])


def test_the_profiles_residuals_jacobian_matches_central_differences():
    residuals = flow_rule_residuals(table(profile()), ("mu1", "mu2", "I0"), MATERIAL)
    theta = np.array([0.37, 0.66, 0.31])
    J = np.asarray(jax.jit(jax.jacfwd(residuals))(theta))
    step = 1e-6 * theta
    fd = np.stack([(np.asarray(residuals(theta + e)) - np.asarray(residuals(theta - e))) / (2 * e[i])
                   for i, e in enumerate(np.diag(step))], axis=1)
    assert np.all(np.isfinite(J))
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-10)


def test_a_noisy_profile_twin_is_recovered_within_its_intervals():
    """1 % noise (seed 0), stated in the table, from a start away from the truth. Over 100 seeds
    of a like design the 95 % intervals held the truth 96, 95 and 94 times (μ1, μ2, I0)."""
    u = profile() * (1.0 + 0.01 * np.random.default_rng(0).standard_normal(SLOPES.size))
    result = fit_flow_rule(table(u, noise=0.01), init=FAR, values=FIXED)
    assert result.converged, result.message
    for (lo, hi), key in zip(result.uncertainty.ci95, result.keys):
        assert lo < TRUTH[key] < hi, (key, lo, hi)
    out = result.to_json()
    json.dumps(out, allow_nan=False)
    assert out["data"]["quantity"] == "profile" and out["noise"] == {"velocity": 0.01} and "h_stop" not in out
    assert out["verdict"]["verdict"] == "a fit of the data"


def test_between_walls_a_profile_fixes_mu_w_with_the_rheology(tmp_path, monkeypatch):
    """A 5 cm chute (μ_w = 0.3): the rows in the static base (v = 0, which a relative residual
    cannot hold) are left out; the rest fix μ1, μ2, I0 and μ_w from a start away from all four.
    The figure draws the walled model through the data (it used to draw the wall-free one)."""
    import matplotlib.pyplot as plt

    from calibration.plots.flow_rule import plot_flow_rule

    walls = SideWalls(0.05, "mu_w")
    u = profile(walls=walls, mu_w=0.3)
    moving = u > 0
    assert 0 < (~moving).sum() < 20
    result = fit_flow_rule(table(u, keep=moving), ("mu1", "mu2", "I0", "mu_w"), init={**FAR, "mu_w": 0.2},
                           values=FIXED, side_walls=walls)
    assert result.converged, result.message
    assert result.theta == pytest.approx({**TRUTH, "mu_w": 0.3}, rel=1e-6)
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    assert plot_flow_rule(result, tmp_path).stat().st_size > 10_000
    lines = [line for line in figures[0].axes[0].lines if line.get_linestyle() == "-"]
    assert len(lines) == 15  # one per slope and thickness
    for line, (slope, h) in zip(lines, [(s, h) for s in np.unique(SLOPES) for h in np.unique(THICK)]):
        rows = moving & (SLOPES == slope) & (THICK == h)
        drawn = np.interp(SHARE[rows], line.get_ydata(), line.get_xdata())  # the line's u at the data's z/h
        np.testing.assert_allclose(drawn, u[rows], rtol=0.02, atol=0.01 * u[rows].max())


GOOD = "# source: a test\n# secondary: false\n# quantity: profile\nslope_deg,h_m,z_m,u_m_s\n25,0.02,0.01,0.2\n" \
       "25,0.02,0.02,0.3\n"


@pytest.mark.parametrize("text, message", [
    (GOOD.replace("0.02,0.02,0.3", "0.02,0.03,0.3"),
     r"z_m must be a height above the bed in \[0, h_m\]; row 2 has 0.03"),
    (GOOD.replace("0.02,0.01,0.2", "0.02,-0.01,0.2"), r"z_m must be a height above the bed in \[0, h_m\]; row 1 has"),
    (GOOD.replace("0.02,0.01,0.2", "0.02,0,0.2"), r"z_m must be > 0: at the bed \(z_m = 0\) the no-slip model's "
                                                   r"velocity is 0.*; row 1 has 0.0"),
    (GOOD.replace("slope_deg,h_m,z_m,u_m_s", "slope_deg,h_m,u_m_s").replace(",0.01,0.2", ",0.2").replace(
        ",0.02,0.3", ",0.3"), r"expected the columns slope_deg,h_m,z_m,u_m_s \(z_m: the height above the bed"),
    (GOOD.replace("quantity: profile", "quantity: surface"),
     r"expected the columns slope_deg,h_m,u_m_s; z_m \(a height above the bed\) belongs to a profile"),
    (GOOD.replace("0.2\n", "0\n"), r"u_m_s must be > 0 m/s; row 1 has 0.0"),
])
def test_a_bad_profile_table_is_refused_naming_the_file(tmp_path, text, message):
    path = tmp_path / "profile.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        load_flow_rule(path)
    assert str(path) in str(err.value)
    path.write_text(GOOD)
    loaded = load_flow_rule(path)
    assert loaded.quantity == "profile" and loaded.z.tolist() == [0.01, 0.02] and loaded.n == 2


def test_a_table_and_its_heights_go_together():
    with pytest.raises(ValueError, match="a profile .quantity: profile. needs the heights z above the bed"):
        FlowRuleTable([25.0], [0.02], [0.3], "profile", "a test", False)
    with pytest.raises(ValueError, match="heights z above the bed belong to a profile .quantity: profile., not to a "
                                         "surface table"):
        FlowRuleTable([25.0], [0.02], [0.3], "surface", "a test", False, z=[0.01])
    with pytest.raises(ValueError, match="slope_deg, h, u and z must be non-empty and of equal length"):
        FlowRuleTable([25.0, 26.0], [0.02, 0.02], [0.3, 0.4], "profile", "a test", False, z=[0.01])


# ---- h_stop ------------------------------------------------------------------------------------------------------
H_STOP = "# source: a test\n# secondary: true\nslope_deg,h_stop_m\n20,0.02\n22,0.008\n25,0.003\n"


@pytest.mark.parametrize("text, message", [
    (H_STOP.replace("22,0.008", "22,0"), r"h_stop_m must be > 0 m; row 2 has 0.0"),
    (H_STOP.replace("25,", "95,"), r"slope_deg must be in \(0, 90\) degrees; row 3 has 95.0"),
    (H_STOP.replace("# source: a test\n", ""), "the header has no 'source'"),
    (H_STOP.replace("# secondary: true\n", ""), "the header must say 'secondary: true' or 'secondary: false'"),
    (H_STOP.replace("h_stop_m", "h_m"), "expected the columns slope_deg,h_stop_m"),
])
def test_a_bad_h_stop_table_is_refused_naming_the_file(tmp_path, text, message):
    path = tmp_path / "hstop.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        load_h_stop(path)
    assert str(path) in str(err.value)
    path.write_text(H_STOP)
    assert load_h_stop(path).n == 3


def test_the_h_stop_block_says_where_the_model_flows_and_that_it_fits_no_h_stop():
    h_stop = HStopTable([20.0, 22.0, 25.0], [0.02, 0.008, 0.003], "a test", True, path="hstop.csv")
    mu1 = math.tan(math.radians(21.0))
    block = h_stop_report(h_stop, mu1)
    json.dumps(block, allow_nan=False)
    assert block["fitted"] is False and block["why"] == NO_H_STOP and "does not predict h_stop" in block["why"]
    assert block["threshold_deg"] == pytest.approx(21.0, rel=1e-12) and block["slopes_deg"] == [20.0, 25.0]
    assert [r["model_flows"] for r in block["rows"]] == [False, True, True]
    assert block["rows"][1] == {"slope_deg": 22.0, "h_stop_m": 0.008, "model_flows": True}
    assert block["reading"].startswith("atan(mu1) = 21 deg lies among the h_stop slopes (20-25 deg): the model "
                                       "flows at any thickness at 2 of the 3 rows' slopes")
    assert block["mu1"] == mu1 and block["mu1_fitted"] and block["path"] == "hstop.csv" and block["secondary"]
    assert "below every h_stop slope" in h_stop_report(h_stop, 0.3)["reading"]
    none = h_stop_report(h_stop, 0.5, fitted=False)
    assert "at or above every h_stop slope" in none["reading"] and not none["mu1_fitted"]
    assert not any(r["model_flows"] for r in none["rows"])


def test_a_fit_reports_its_h_stop_table_and_cannot_fit_it():
    u = profile()
    h_stop = HStopTable([20.0, 22.0, 25.0], [0.02, 0.008, 0.003], "a test", True)
    result = fit_flow_rule(table(u), ("mu2", "I0"), init={"mu2": 0.8, "I0": 0.5}, values=FIXED, h_stop=h_stop)
    block = result.to_json()["h_stop"]
    assert block == h_stop_report(h_stop, TRUTH["mu1"], fitted=False)  # mu1 held at its value
    with pytest.raises(ValueError, match="keys: a flow rule fits distinct keys among .* \\(h_stop is not a parameter: "
                                         "the local mu\\(I\\) model does not predict it"):
        fit_flow_rule(table(u), ("mu1", "h_stop"), values=FIXED)
    with pytest.raises(ValueError, match="h_stop must be an HStopTable .calibration.data.load_h_stop. or None, "
                                         "got str"):
        fit_flow_rule(table(u), values=FIXED, h_stop="hstop.csv")


# ---- the incline file --------------------------------------------------------------------------------------------
INCLINE = ('format = 1\n[experiment]\nkind = "incline"\n[material]\nd = "0.7 mm"\n[flow_rule]\nfile = "profile.csv"\n'
           '[h_stop]\nfile = "hstop.csv"\n[fit]\nkeys = ["mu2", "I0"]\n')


@pytest.mark.parametrize("edit, message", [
    (('file = "hstop.csv"', 'file = "gone.csv"'), ":9: [h_stop] file: no such file:"),
    (('file = "hstop.csv"', 'fit = true'), ":9: [h_stop] fit: unknown key; [h_stop] takes file"),
    (('file = "hstop.csv"\n', ''), ":8: [h_stop] file: missing: the h_stop table's CSV file (slope_deg,h_stop_m)"),
    (('keys = ["mu2", "I0"]', 'keys = ["mu2", "h_stop"]'), ":11: [fit] keys: a flow rule fits distinct keys among"),
])
def test_a_bad_h_stop_section_is_refused_at_its_line(tmp_path, edit, message):
    (tmp_path / "profile.csv").write_text(GOOD)
    (tmp_path / "hstop.csv").write_text(H_STOP)
    path = tmp_path / "chute.toml"
    path.write_text(INCLINE.replace(*edit))
    code, out, err = call_main(main, ["flow-rule", path, "--json"])
    assert code == 2 and out == "" and f"{path}{message}" in err, err
    path.write_text(INCLINE)
    assert load_incline(path).h_stop_file == tmp_path / "hstop.csv"


def test_a_bad_h_stop_table_is_refused_before_a_joint_fit_runs(tmp_path):
    (tmp_path / "profile.csv").write_text(GOOD)
    (tmp_path / "hstop.csv").write_text(H_STOP.replace("22,0.008", "22,-1"))
    path = tmp_path / "chute.toml"
    path.write_text(INCLINE)
    code, out, err = call_main(main, ["fit", path, "--fit", "mu2,I0", "--json", "--no-progress"])
    assert code == 2 and out == "" and f"{tmp_path / 'hstop.csv'}: h_stop_m must be > 0 m; row 2 has -1.0" in err, err


SHIPPED = "synthetic/flow_profile_twin_experiment"


def test_the_shipped_profile_file_is_fitted_with_its_h_stop_reported():
    experiment = load_incline(dataset_path(SHIPPED))
    data = load_flow_rule(experiment.table_file)
    assert data.quantity == "profile" and data.noise == 0.01 and experiment.h_stop_file.is_file()
    code, out, err = call_main(main, ["flow-rule", dataset_path(SHIPPED), "--json"])
    assert code == 0, err
    out = json.loads(out)
    truth = data.meta["parameters"]
    assert out["converged"] and out["verdict"]["verdict"] == "a fit of the data" and out["start"] == FAR
    for key, (lo, hi) in out["ci95"].items():
        assert lo < truth[key] < hi, (key, lo, hi)
    block = out["h_stop"]
    assert block["fitted"] is False and block["mu1"] == out["params"]["mu1"] and len(block["rows"]) == 5
    assert all(r["model_flows"] for r in block["rows"]) and block["slopes_deg"] == [22.0, 30.0]


def test_a_joint_fits_h_stop_blocks_read_each_inclines_mu1():
    """``calibration fit``'s blocks: by the incline file's name, at its own "mu1@NAME", the shared
    "mu1", or its material's μ1 where none is fitted."""
    experiment = load_incline(dataset_path(SHIPPED))
    tables = {"chute": (load_h_stop(experiment.h_stop_file), experiment.material)}
    own = h_stop_fields(tables, {"mu1@chute": 0.6, "mu1": 0.3})["h_stop"]["chute"]
    assert own["mu1"] == 0.6 and own["mu1_fitted"] and not any(r["model_flows"] for r in own["rows"])
    assert h_stop_fields(tables, {"mu1": 0.3, "I0": 0.3})["h_stop"]["chute"]["mu1"] == 0.3
    held = h_stop_fields(tables, {"mu2": 0.6})["h_stop"]["chute"]
    assert held["mu1"] == DEFAULTS["mu1"] and not held["mu1_fitted"]
    assert h_stop_fields({}, {"mu1": 0.3}) == {}
    # A flow rule and a profile of one chute: two incline files fitted together, each with its own noise.
    code, out, err = call_main(main, ["fit", dataset_path("synthetic/flow_rule_twin_experiment"), dataset_path(SHIPPED),
                                      "--init", "mu1=0.36", "--init", "mu2=0.75", "--init", "I0=0.5", "--dtype",
                                      "float64", "--json", "--no-progress"])
    assert code == 0, err
    out = json.loads(out)
    assert out["converged"] and out["noise"] == {"0/velocity": 0.02, "1/velocity": 0.01}
    assert list(out["h_stop"]) == ["flow_profile_twin"] and out["h_stop"]["flow_profile_twin"]["mu1"] == out["params"][
        "mu1"]


def test_a_designs_profile_jacobian_is_the_finite_difference_of_its_relative_residual():
    """``design --incline`` with a profile's table plans on the profile (its heights kept), in
    float64 against central differences of ``steady_velocity(..., "profile")``."""
    from calibration.design.design import Experiment
    from calibration.design.inclines import incline_experiment
    from jaxmpm import Params

    plan = table(np.ones(SLOPES.size), noise=0.01)
    values = {"mu1": 0.37, "mu2": 0.66, "I0": 0.3}
    e = incline_experiment("chute", plan, FIXED, Params.create(**MATERIAL), ("mu1", "mu2", "I0"), values, 0.01,
                           Experiment)
    u = profile(values)
    fd = np.stack([(profile({**values, key: values[key] * (1 + 1e-6)}) - profile({**values, key: values[key] *
                                                                                   (1 - 1e-6)})) / u
                   / (2e-6 * values[key]) for key in values], axis=1)
    np.testing.assert_allclose(e.J, fd, rtol=1e-6, atol=1e-9)
