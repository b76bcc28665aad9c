"""The steady flow down a chute between side walls as a flow rule's model: the closed form against
Bagnold's (no drag), a fine quadrature and ``side_wall_velocity``, its derivatives against central
differences, a walled twin recovered (μ_w with it), and the incline file's and the command line's
side walls, with every refusal naming what was wrong."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import call_main

from calibration.cli.args import design_inclines
from calibration.cli.commands import main
from calibration.data.flow_rule import FlowRuleTable
from calibration.data.incline import load_incline
from calibration.problem.build import FitSetup
from calibration.problem.flow_rule import FlowRuleObjective
from calibration.studies.flow_rule import fit_flow_rule
from jaxmpm import SideWalls
from jaxmpm.params import DEFAULTS
from jaxmpm.scenes import S1_PARAMS
from jaxmpm.scenes.incline import G, side_wall_velocity, steady_velocity

MATERIAL = {**DEFAULTS, **S1_PARAMS}
TRUTH = {k: MATERIAL[k] for k in ("mu1", "mu2", "I0")}
FIXED = {k: MATERIAL[k] for k in ("rho", "rho_s", "d")}
SLOPES = np.repeat([22.0, 24.0, 26.0, 28.0], 4)
THICK = np.tile([0.01, 0.02, 0.03, 0.04], 4)
FAR = {"mu1": 0.36, "mu2": 0.75, "I0": 0.5}


def velocity(h, slope, quantity="depth_averaged", walls=None, mu_w=None, p=MATERIAL):
    return steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"], quantity, walls, mu_w)


def quadrature(h, slope, drag, quantity, points=100_001):
    """Simpson's rule on ζ = L s² (no sqrt endpoint left), L = min(h, ζ*)."""
    p, tan = MATERIAL, math.tan(math.radians(slope))
    length = min(h, (tan - p["mu1"]) / drag) if drag > 0 else h
    s = np.linspace(0.0, 1.0, points)
    zeta = length * s * s
    mu = tan - drag * zeta
    rate = (p["I0"] * (mu - p["mu1"]) / (p["mu2"] - mu)
            * np.sqrt(p["rho"] * G * math.cos(math.radians(slope)) * zeta / p["rho_s"]) / p["d"])
    f = rate * 2.0 * length * s * (1.0 if quantity == "surface" else zeta / h)
    return (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum()) * (s[1] - s[0]) / 3


@pytest.mark.parametrize("quantity", ["surface", "depth_averaged"])
def test_without_drag_the_walled_flow_is_bagnolds(quantity):
    free = np.asarray(velocity(THICK, SLOPES, quantity))
    no_drag = ((SideWalls(0.05, 0.0), None), (SideWalls(0.05, "mu_w"), 0.0), (SideWalls(0.05, 0.3, 0.0), None))
    for walls, mu_w in no_drag:
        np.testing.assert_allclose(np.asarray(velocity(THICK, SLOPES, quantity, walls, mu_w)), free, rtol=1e-13)
    bagnold = (2 / 3) * TRUTH["I0"] * (np.tan(np.radians(SLOPES)) - TRUTH["mu1"]) / (
        TRUTH["mu2"] - np.tan(np.radians(SLOPES))) * np.sqrt(MATERIAL["rho"] * G * np.cos(np.radians(SLOPES))
                                                             / MATERIAL["rho_s"]) / MATERIAL["d"] * THICK**1.5
    np.testing.assert_allclose(free, bagnold * (1.0 if quantity == "surface" else 0.6), rtol=1e-13)


@pytest.mark.parametrize("width", [0.01, 0.02, 0.05, 0.1, 1.0])
@pytest.mark.parametrize("slope", [21.0, 25.0, 28.0, 32.5])
def test_the_closed_form_is_the_integral_of_the_shear_rate(width, slope):
    """Against a 10^5-point Simpson rule, through both branches (series and arctan) and static bases."""
    walls = SideWalls(width, 0.3)
    for h in (0.002, 0.01, 0.04):
        for quantity in ("surface", "depth_averaged"):
            closed = float(velocity(h, slope, quantity, walls))
            assert closed == pytest.approx(quadrature(h, slope, 0.3 / width, quantity), rel=2e-14), (h, quantity)


@pytest.mark.parametrize("width, slope", [(0.02, 22.0), (0.02, 28.0), (0.05, 25.0), (0.1, 28.0)])
def test_side_wall_velocitys_trapezoid_converges_to_the_closed_form(width, slope):
    walls, h = SideWalls(width, 0.3), 0.03
    surface, mean = (float(velocity(h, slope, q, walls)) for q in ("surface", "depth_averaged"))
    gaps = []
    for points in (4001, 16001):
        z = np.linspace(0.0, h, points)
        profile, stop = side_wall_velocity(z, h, slope, MATERIAL, walls, points=points)
        gaps.append(abs(profile[-1] / surface - 1))
        assert np.trapezoid(profile, z) / h == pytest.approx(mean, rel=2e-5)
    assert stop == pytest.approx(width * (math.tan(math.radians(slope)) - TRUTH["mu1"]) / 0.3, rel=1e-12)
    assert gaps[0] < 5e-4 and gaps[1] < gaps[0] / 4  # the trapezoid's h^1.5 error at the sqrt endpoint


@pytest.mark.parametrize("quantity", ["surface", "depth_averaged"])
def test_the_derivatives_match_central_differences_and_are_finite_without_drag(quantity):
    walls = SideWalls(0.05, "mu_w")
    h, slope = jnp.array([0.002, 0.01, 0.02, 0.04, 0.01]), jnp.array([22.0, 24.0, 26.0, 28.0, 31.5])

    @jax.jit
    def f(theta):
        mu1, mu2, I0, mu_w = theta
        return steady_velocity(h, slope, mu1, mu2, I0, MATERIAL["rho"], MATERIAL["rho_s"], MATERIAL["d"], quantity,
                               walls, mu_w)

    jacfwd, jacrev = jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f))
    for mu_w in (0.05, 0.3, 1.0):
        theta = np.array([TRUTH["mu1"], TRUTH["mu2"], TRUTH["I0"], mu_w])
        forward, reverse = np.asarray(jacfwd(theta)), np.asarray(jacrev(theta))
        step = 1e-6 * theta
        fd = np.stack([(np.asarray(f(theta + e)) - np.asarray(f(theta - e))) / (2 * e[i])
                       for i, e in enumerate(np.diag(step))], axis=1)
        np.testing.assert_allclose(forward, fd, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-15)
    theta, eps = np.array([TRUTH["mu1"], TRUTH["mu2"], TRUTH["I0"], 0.0]), 1e-6
    at_zero = np.asarray(jacfwd(theta))
    one_sided = (-3 * np.asarray(f(theta)) + 4 * np.asarray(f(theta + [0, 0, 0, eps]))
                 - np.asarray(f(theta + [0, 0, 0, 2 * eps]))) / (2 * eps)
    assert np.all(np.isfinite(at_zero)) and np.all(np.isfinite(np.asarray(jacrev(theta))))
    np.testing.assert_allclose(at_zero[:, 3], one_sided, rtol=1e-5)
    assert np.all(at_zero[:, 3] < 0)  # friction on the walls slows the flow


def test_it_vmaps_and_is_nan_where_no_flow_is_steady():
    walls = SideWalls(0.05, "mu_w")
    batch = jax.jit(jax.vmap(lambda m: velocity(0.02, 25.0, "surface", walls, m)))(jnp.array([0.0, 0.2, 0.4]))
    assert np.all(np.diff(np.asarray(batch)) < 0)
    np.testing.assert_allclose(np.asarray(batch), [float(velocity(0.02, 25.0, "surface", walls, m)) for m in
                                                   (0.0, 0.2, 0.4)], rtol=1e-14)
    slopes = np.array([math.degrees(math.atan(TRUTH["mu1"])) - 0.5, 25.0, math.degrees(math.atan(TRUTH["mu2"])) + 0.5])
    u = np.asarray(velocity(0.02, slopes, walls=SideWalls(0.05, 0.3)))
    assert np.isnan(u[0]) and np.isfinite(u[1]) and np.isnan(u[2])
    with pytest.raises(ValueError, match="mu_w: the side walls' friction is the parameter mu_w"):
        velocity(0.02, 25.0, walls=walls)


# ---- the objective and the fit -------------------------------------------------------------------------------------
def twin(width, friction=0.3, noise=None):
    u = np.asarray(velocity(THICK, SLOPES, walls=SideWalls(width, friction)))
    return FlowRuleTable(SLOPES, THICK, u, "depth_averaged", "this test", False, experiment="walled twin", noise=noise)


def test_a_walled_twin_is_recovered_and_the_walls_are_recorded():
    walls = SideWalls(0.05, 0.3)
    result = fit_flow_rule(twin(0.05), init=FAR, values=FIXED, side_walls=walls)
    assert result.converged and result.theta == pytest.approx(TRUTH, rel=1e-7)
    out = result.to_json()
    assert out["side_walls"] == {"width": 0.05, "friction": 0.3, "lateral_pressure_ratio": 1.0}
    wall_free = fit_flow_rule(twin(0.05, noise=0.01), init=FAR, values=FIXED)
    assert wall_free.fit.verdict.to_dict()["verdict"] == "not a fit of the data"


def test_mu_w_is_fitted_with_the_rheology_between_walls_that_read_it():
    walls = SideWalls(0.05, "mu_w")
    result = fit_flow_rule(twin(0.05), ("mu1", "mu2", "I0", "mu_w"), init={**FAR, "mu_w": 0.2}, values=FIXED,
                           side_walls=walls)
    assert result.converged and result.theta == pytest.approx({**TRUTH, "mu_w": 0.3}, rel=1e-6)
    fixed = fit_flow_rule(twin(0.05), init=FAR, values={**FIXED, "mu_w": 0.3}, side_walls=walls).to_json()
    assert fixed["fixed"]["mu_w"] == 0.3 and fixed["params"] == pytest.approx(TRUTH, rel=1e-7)


@pytest.mark.parametrize("walls, values, message", [
    (None, {}, r"keys: a flow rule fits distinct keys among \['mu1', 'mu2', 'I0'\].*this chute has no side walls"),
    (SideWalls(0.05, 0.3), {}, "mu_w is the side walls' friction.*these walls' friction is a number"),
])
def test_mu_w_is_refused_where_no_wall_reads_it(walls, values, message):
    with pytest.raises(ValueError, match=message):
        FlowRuleObjective(twin(0.05), ("mu1", "mu_w"), values=values, side_walls=walls)


def test_walls_that_read_mu_w_need_its_value():
    with pytest.raises(ValueError, match=r"values: the side walls' friction is the parameter mu_w"):
        FlowRuleObjective(twin(0.05), values=FIXED, side_walls=SideWalls(0.05, "mu_w"))
    with pytest.raises(ValueError, match="side_walls must be a jaxmpm.SideWalls or None, got dict"):
        FlowRuleObjective(twin(0.05), side_walls={"width": 0.05})


# ---- the incline file and the command line --------------------------------------------------------------------------
INCLINE = ('format = 1\n[experiment]\nkind = "incline"\n[material]\nd = "0.7 mm"\nrho = 1550.0\nrho_s = 2500.0\n'
           'mu_w = 0.2\n[flow_rule]\nfile = "rule.csv"\n[boundaries]\nside_walls = { width = "5 cm", friction = 0.3 }\n'
           '[fit]\nkeys = ["mu1", "mu2", "I0"]\ninit = { mu1 = 0.36, mu2 = 0.75, I0 = 0.5 }\n')


def write_twin(tmp_path, width=0.05):
    from jaxmpm.tables import write_table

    table = twin(width)
    path = tmp_path / "rule.csv"
    write_table(path, {"slope_deg": table.slope_deg, "h_m": table.h, "u_m_s": table.u},
                {"source": "a test", "secondary": False, "quantity": "depth_averaged"}, fmt=".17g")
    return path


def test_an_incline_files_side_walls_are_read_and_fitted(tmp_path):
    write_twin(tmp_path)
    path = tmp_path / "chute.toml"
    path.write_text(INCLINE)
    experiment = load_incline(path)
    assert experiment.side_walls == SideWalls(0.05, 0.3)
    code, out, err = call_main(main, ["flow-rule", path, "--json"])
    assert code == 0, err
    out = json.loads(out)
    assert out["side_walls"]["width"] == 0.05 and out["params"] == pytest.approx(TRUTH, rel=1e-6)
    path.write_text(INCLINE.replace("friction = 0.3", 'friction = "mu_w"').replace('"I0"]', '"I0", "mu_w"]'))
    code, out, err = call_main(main, ["flow-rule", path, "--init", "mu_w=0.2", "--json"])
    assert code == 0, err
    assert json.loads(out)["params"] == pytest.approx({**TRUTH, "mu_w": 0.3}, rel=1e-6)


def test_the_joint_fit_builds_the_incline_with_its_walls(tmp_path):
    write_twin(tmp_path)
    path = tmp_path / "chute.toml"
    path.write_text(INCLINE)
    setup = FitSetup((load_incline(path),), ("mu1", "mu2", "I0"), dtype="float64")
    again = FitSetup.from_json(json.loads(json.dumps(setup.to_json())))
    for objective in (setup.objective(), again.objective()):
        assert objective.side_walls == SideWalls(0.05, 0.3)
        np.testing.assert_allclose(np.asarray(objective.residuals(list(TRUTH.values()))[0]), 0.0, atol=1e-12)
    ((table, material, walls),) = design_inclines([str(path)]).values()  # the designer plans with the walls
    assert walls == SideWalls(0.05, 0.3) and material["mu_w"] == 0.2 and table.n == 16


def test_the_designer_plans_a_walled_chute_with_the_walled_flow():
    """An incline plan with side walls whose friction is "mu_w": its Jacobian (μ1, μ2, I0, μ_w and a
    key it does not see, β) is the central difference of the walled closed form's relative
    velocities (float64), and μ_w's column is not zero."""
    from calibration.design.design import Experiment
    from calibration.design.inclines import incline_experiment, incline_plans
    from jaxmpm import Params

    walls, keys = SideWalls(0.05, "mu_w"), ("beta", "mu1", "mu2", "I0", "mu_w")
    plain = twin(0.05)  # a plan: its velocities are not used
    ((table, material, got),) = incline_plans({"chute": (plain, {}, walls)}, ["main"]).values()
    assert got == walls
    values = {"beta": 0.25, **TRUTH, "mu_w": 0.3}
    experiment = incline_experiment("chute", table, {**FIXED, **material}, Params.create(**FIXED), keys, values, 0.01,
                                    Experiment, walls)

    def relative(p):
        model = steady_velocity(table.h, table.slope_deg, p["mu1"], p["mu2"], p["I0"], *FIXED.values(),
                                table.quantity, walls, p["mu_w"])
        at = steady_velocity(table.h, table.slope_deg, *TRUTH.values(), *FIXED.values(), table.quantity, walls, 0.3)
        return np.asarray(model) / np.asarray(at) - 1.0

    for i, key in enumerate(keys):
        h = 1e-6 * values[key]
        fd = (relative({**values, key: values[key] + h}) - relative({**values, key: values[key] - h})) / (2 * h)
        np.testing.assert_allclose(experiment.J[:, i], fd, rtol=1e-6, atol=1e-9, err_msg=key)
    assert np.all(experiment.J[:, 0] == 0.0) and np.all(np.abs(experiment.J[:, 4]) > 0)


@pytest.mark.parametrize("edit, message", [
    ([('width = "5 cm", ', "")], ":12: [boundaries] side_walls: missing width"),
    ([("friction = 0.3", "friction = -0.3")], ":12: [boundaries] side_walls: friction must be >= 0"),
    ([("friction = 0.3", "friction = 0.3, roughness = 1")], ":12: [boundaries] side_walls: unknown entry 'roughness'"),
    ([("mu_w = 0.2\n", ""), ("friction = 0.3", 'friction = "mu_w"')],
     ": [material] mu_w: missing: the side walls' friction is the parameter mu_w"),
    ([('"I0"]', '"I0", "mu_w"]')], ":14: [fit] keys: a flow rule fits distinct keys among"),
])
def test_a_bad_side_wall_entry_is_refused_at_its_line(tmp_path, edit, message):
    write_twin(tmp_path)
    path = tmp_path / "chute.toml"
    text = INCLINE
    for old, new in edit:
        text = text.replace(old, new)
    path.write_text(text)
    code, out, err = call_main(main, ["flow-rule", path, "--json"])
    assert code == 2 and out == "" and message in err and str(path) in err, err


def test_the_side_walls_flag_fits_a_table_between_walls(tmp_path):
    rule = write_twin(tmp_path, width=0.1)
    init = ["--init", "mu1=0.36", "--init", "mu2=0.75", "--init", "I0=0.5", "--set", "d=0.0007"]
    code, out, err = call_main(main, ["flow-rule", rule, *init, "--side-walls", "0.1,0.3", "--json"])
    assert code == 0, err
    out = json.loads(out)
    assert out["side_walls"] == {"width": 0.1, "friction": 0.3, "lateral_pressure_ratio": 1.0}
    assert out["params"] == pytest.approx(TRUTH, rel=1e-6)
    code, out, err = call_main(main, ["flow-rule", rule, *init, "--side-walls", "0.1,mu_w", "--json"])
    assert code == 2 and "--side-walls: the walls' friction is the parameter mu_w; give its value with --set" in err
    code, out, err = call_main(main, ["flow-rule", rule, *init, "--side-walls", "0.1,-1", "--json"])
    assert code == 2 and "the friction must be >= 0" in err
    path = tmp_path / "chute.toml"  # the flag wins over the file's walls (5 cm there)
    path.write_text(INCLINE)
    code, out, err = call_main(main, ["flow-rule", path, "--side-walls", "0.1,0.3", "--json"])
    assert code == 0 and json.loads(out)["params"] == pytest.approx(TRUTH, rel=1e-6), err
