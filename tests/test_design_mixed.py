"""``design`` with incline experiments (flow-rule tables) beside collapses: sets that mix kinds."""

import json

import numpy as np
import pytest

from calibration import Objective
from calibration.cli.commands import main
from calibration.data.flow_rule import FlowRuleTable, load_flow_rule
from calibration.design.design import Experiment, _cost, design, expected_halfwidths
from calibration.design.inclines import incline_experiment
from calibration.inference.gridcheck import GCI_SAFETY, GRID_ORDER
from calibration.inference.noise import Z95
from jaxmpm import scenes
from jaxmpm.scenes.incline import steady_velocity

L = 0.089
KEYS = ("beta", "mu1", "mu2", "I0")
TWIN = "experiments_data/synthetic/flow_rule_twin.csv"
TINY = ["--scene", "cohesive-collapse", "--dx", str(L / 4), "--t-end", "0.1"]


def _table(slopes=(22.0, 26.0, 30.0), hs=(0.01, 0.03), noise=None):
    slope, h = np.meshgrid(slopes, hs, indexing="ij")
    return FlowRuleTable(slope.ravel(), h.ravel(), np.ones(slope.size), "depth_averaged", "a plan", False,
                         noise=noise)


def _collapse(J, sigma, weights, draws=None, coarse=None, ratio=None):
    m = J.shape[0]
    rows = {"final": np.arange(m), "profiles": np.arange(m), "front": np.arange(0), "top": np.arange(0)}
    return Experiment("main", None, rows, np.full(m, sigma), J, weights, draws, coarse, ratio)


def _incline(J, sigma, weights, closed_form=True, draws=None, coarse=None, ratio=None):
    m = J.shape[0]
    return Experiment("chute", None, {"flow_rule": np.arange(m)}, np.full(m, sigma), J, weights, draws, coarse,
                      ratio, closed_form=closed_form)


def test_an_inclines_rows_add_their_fisher_information_zero_columns_included():
    rng = np.random.default_rng(3)
    Jc = rng.standard_normal((10, 3))
    Ji = np.column_stack([np.zeros(6), rng.standard_normal((6, 2))])  # the flow rule does not see key 0
    c = _collapse(Jc, 0.05, np.full(10, 1 / 0.05 ** 2))
    i = _incline(Ji, 0.02, np.full(6, 1 / 0.02 ** 2))
    parts = (("main", "final"), ("chute", "flow_rule"))
    hw, cov, data_only, weighted, cov_data = expected_halfwidths([c, i], parts)
    expected = np.linalg.inv(Jc.T @ Jc / 0.05 ** 2 + Ji.T @ Ji / 0.02 ** 2)
    np.testing.assert_allclose(cov, expected, rtol=1e-9)
    np.testing.assert_allclose(hw, Z95 * np.sqrt(np.diag(expected)), rtol=1e-9)
    np.testing.assert_array_equal(cov_data, cov)  # a closed form adds no draw's or grid's share
    # The incline alone does not see key 0: an unbounded variance there, its own keys' as if alone.
    hw, cov, *_ = expected_halfwidths([c, i], (("chute", "flow_rule"),))
    assert hw[0] > 1e5 * hw[1:].max()
    np.testing.assert_allclose(cov[1:, 1:], np.linalg.inv(Ji[:, 1:].T @ Ji[:, 1:] / 0.02 ** 2), rtol=1e-9)
    # The fit's weights (relative velocities: row_scale 1) beside a collapse's: the sandwich.
    i = _incline(Ji, 0.02, np.ones(6))
    _, cov, *_ = expected_halfwidths([c, i], parts)
    J, w = np.concatenate([Jc, Ji]), np.concatenate([c.weights, i.weights])
    s = np.concatenate([np.full(10, 0.05), np.full(6, 0.02)])
    A, B = J.T @ (w[:, None] * J), J.T @ ((w * w * s * s)[:, None] * J)
    np.testing.assert_allclose(cov, np.linalg.inv(A) @ B @ np.linalg.inv(A), rtol=1e-8)


def test_a_closed_forms_draws_and_grid_shift_count_as_zeros_beside_a_collapses():
    """When the collapse measured its draws and a coarse grid, a set with an incline has both
    shares, the incline's rows contributing zeros: the same as an incline that measured zeros."""
    rng = np.random.default_rng(4)
    Jc, Ji = rng.standard_normal((10, 3)), np.column_stack([np.zeros(6), rng.standard_normal((6, 2))])
    draws, coarse = 0.01 * rng.standard_normal((4, 10)), 0.02 * rng.standard_normal(10)
    c = _collapse(Jc, 0.05, np.full(10, 3.0), draws, coarse, 1.5)
    i = _incline(Ji, 0.02, np.ones(6))
    zeros = _incline(Ji, 0.02, np.ones(6), closed_form=False, draws=np.zeros((4, 6)), coarse=np.zeros(6), ratio=1.5)
    parts = (("main", "final"), ("chute", "flow_rule"))
    hw, cov, data_only, _, cov_data = expected_halfwidths([c, i], parts)
    hw0, cov0, *_ = expected_halfwidths([c, zeros], parts)
    np.testing.assert_allclose(cov, cov0, rtol=1e-12)
    assert np.all(hw > data_only * (1 + 1e-6))  # both shares were added
    # By hand: the grid's shift and the draws' spread, of the weighted rows.
    root = np.sqrt(np.concatenate([c.weights, i.weights]))
    J = np.concatenate([Jc, Ji]) * root[:, None]
    P = np.linalg.lstsq(J, (np.concatenate([draws, np.zeros((4, 6))], axis=1) * root).T, rcond=None)[0].T
    shift = -np.linalg.lstsq(J, np.concatenate([coarse, np.zeros(6)]) * root, rcond=None)[0]
    v = shift / np.linalg.norm(shift) * np.linalg.norm(GCI_SAFETY * np.abs(shift) / (1.5 ** GRID_ORDER - 1) / Z95)
    np.testing.assert_allclose(cov, cov_data + np.cov(P, rowvar=False, ddof=1) + np.outer(v, v), rtol=1e-9)
    # A set of the incline alone has neither share (nothing to measure), and no error.
    _, cov, _, _, cov_data = expected_halfwidths([c, i], (("chute", "flow_rule"),))
    np.testing.assert_array_equal(cov, cov_data)
    # A collapse that did not measure its draws: the share is unmeasured for the whole set.
    c = _collapse(Jc, 0.05, np.full(10, 3.0), None, None, None)
    _, cov, _, _, cov_data = expected_halfwidths([c, i], parts)
    np.testing.assert_array_equal(cov, cov_data)


def test_the_cost_convention_counts_an_inclines_slopes_and_its_set_up():
    slopes = {"chute": 4}
    assert _cost((("chute", "flow_rule"),), slopes) == 4.0
    assert _cost((("main", "final"), ("chute", "flow_rule")), slopes) == 1.0 + 4.0 + 1.0
    assert _cost((("main", "profiles"), ("main", "front"), ("chute", "flow_rule")), slopes) == 3.0 + 4.0 + 1.0
    assert _cost((("main", "final"), ("tall", "final"))) == 3.0  # collapses: as before


def test_the_inclines_jacobian_is_the_finite_difference_of_the_closed_forms_relative_residual():
    """In float64 (tests/conftest.py), against central differences of ``steady_velocity``."""
    assert np.asarray(steady_velocity(0.01, 25.0, 0.3, 0.6, 0.3, 1500.0, 2500.0, 1e-3)).dtype == np.float64
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1)
    table = _table(noise=0.03)
    values = {"beta": 0.25, "mu1": 0.37, "mu2": 0.66, "I0": 0.3}
    e = incline_experiment("chute", table, {"d": 0.7e-3}, scene.params, KEYS, values, 0.03, Experiment)
    rho, rho_s = float(scene.params.rho), float(scene.params.rho_s)

    def model(mu1, mu2, I0):
        return np.asarray(steady_velocity(table.h, table.slope_deg, mu1, mu2, I0, rho, rho_s, 0.7e-3, table.quantity))

    u = model(values["mu1"], values["mu2"], values["I0"])  # the data at θ: the model's own
    fd = np.zeros((table.n, len(KEYS)))
    for j, key in enumerate(KEYS[1:], start=1):
        step = 1e-6 * values[key]
        up, down = dict(values), dict(values)
        up[key] += step
        down[key] -= step
        fd[:, j] = (model(up["mu1"], up["mu2"], up["I0"]) / u - model(down["mu1"], down["mu2"], down["I0"]) / u) / (
            2 * step)
    np.testing.assert_allclose(e.J, fd, rtol=1e-7, atol=1e-9)
    np.testing.assert_array_equal(e.J[:, 0], 0.0)  # β: not a flow-rule key
    np.testing.assert_array_equal(e.noise_rows, 0.03)
    assert e.closed_form and e.rows["flow_rule"].tolist() == list(range(table.n))


def _tripwire(monkeypatch):
    def tripwire(*args, **kw):
        raise AssertionError("the model ran: the input should have been refused before")

    monkeypatch.setattr(Objective, "predict", tripwire)


@pytest.mark.parametrize("kwargs, match", [
    ({"inclines": {"main": _table()}}, r"inclines: the label 'main' is already"),
    ({"inclines": {"tall": _table()}, "variants": {"tall": {"height": 0.178}}}, r"label 'tall' is already"),
    ({"inclines": {"steep": _table(slopes=(26.0, 34.0))}}, r"inclines\['steep'\]: .*no steady flow.*mu2"),
    ({"inclines": {"gentle": _table(slopes=(20.0, 26.0))}}, r"inclines\['gentle'\]: .*no steady flow.*mu1"),
    ({"inclines": {"chute": "rule.csv"}}, r"inclines\['chute'\] must be a FlowRuleTable"),
    ({"inclines": {"chute": (_table(), {"rho": -1.0})}}, r"inclines\['chute'\]: the material"),
    ({"inclines": {"chute": _table()}, "sets": [("x", [("main", "flow_rule")])]}, r"names \('main', 'flow_rule'\)"),
    ({"inclines": {"chute": _table()}, "sets": [("x", [("chute", "final")])]}, r"names \('chute', 'final'\)"),
    ({"inclines": {"chute": _table()}, "sets": [("x", [("chute", "flow_rule")], -1)]}, "a cost is a finite"),
    ({"noise": {"velocity": 0.0}}, r"noise\['velocity'\] must be a positive"),
])
def test_bad_inclines_are_refused_before_any_run(kwargs, match, monkeypatch):
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1)
    _tripwire(monkeypatch)
    with pytest.raises(ValueError, match=match):
        design(scene, KEYS, {"beta": 0.25}, **kwargs)


def test_an_inclines_noise_is_the_given_velocity_noise_else_its_tables_else_two_percent():
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1)
    values = {"beta": 0.25, "mu1": 0.37, "mu2": 0.66, "I0": 0.3}
    from calibration.design.inclines import incline_sigma

    assert incline_sigma(_table(noise=0.03), {"velocity": 0.01}, given=True) == 0.01
    assert incline_sigma(_table(noise=0.03), {"velocity": 0.02}, given=False) == 0.03
    assert incline_sigma(_table(), {"velocity": 0.02}, given=False) == 0.02
    # A design with no flow-rule key: the incline's rows are all zeros (it adds nothing).
    e = incline_experiment("chute", _table(), {}, scene.params, ("beta", "xi"), {"beta": 0.25, "xi": 50.0}, 0.02,
                           Experiment)
    assert e.objective is None and e.J.shape == (6, 2) and not np.any(e.J)
    assert incline_experiment("c", _table(), {}, scene.params, KEYS, values, 0.02, Experiment).J[:, 1:].all()


# ---- one tiny S4 design with the shipped twin table (about 20 s: slow; the incline's rows, Jacobian, ------
# ---- costs and refusals are checked by default above, and a collapse's design in tests/test_design.py) --
@pytest.fixture(scope="module")
def mixed():
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1, dtype="float32")  # as the command line builds it
    table = load_flow_rule(TWIN)
    return design(scene, KEYS, {"beta": 0.25}, noise={"profile": 0.01, "front": 0.01, "top": 0.01}, tolerance=0.1,
                  inclines={"flow_rule_twin": table})


@pytest.mark.slow
def test_a_collapse_and_an_incline_constrain_every_key_better_than_either_alone(mixed):
    by_name = {c.name: c for c in mixed.candidates}
    collapse, incline = by_name["final profile"], by_name["incline flow_rule_twin"]
    joint = by_name["final profile + incline flow_rule_twin"]
    mu2, I0 = KEYS.index("mu2"), KEYS.index("I0")
    assert max(collapse.relative[mu2], collapse.relative[I0]) > mixed.tolerance  # the collapse alone cannot
    for name in [c.name for c in mixed.candidates if "incline" not in c.name]:
        assert max(by_name[name].relative[mu2], by_name[name].relative[I0]) > mixed.tolerance, name
    assert incline.relative[KEYS.index("beta")] > 1e3  # the incline alone does not see β
    for alone in (collapse, incline):
        assert np.all(joint.halfwidth <= alone.halfwidth * (1 + 1e-9)), alone.name
        assert np.all(joint.halfwidth_weighted <= alone.halfwidth_weighted * (1 + 1e-9)), alone.name
    assert joint.halfwidth[mu2] < 1e-2 * collapse.halfwidth[mu2] and joint.halfwidth[I0] < 1e-2 * collapse.halfwidth[I0]
    assert joint.meets and mixed.recommended is joint  # the cheapest set that meets 10 %
    assert joint.cost == 1 + 4 + 1 and incline.cost == 4  # four slopes, a second set-up
    assert mixed.experiments == ("main", "flow_rule_twin")
    assert mixed.noise["velocity@flow_rule_twin"] == 0.02 and "velocity" not in mixed.noise  # the table's
    out = mixed.to_json()
    json.dumps(out, allow_nan=False)
    assert {"incline flow_rule_twin", "final profile + incline flow_rule_twin",
            "profiles in time + front + incline flow_rule_twin"} <= {c["name"] for c in out["candidates"]}


@pytest.mark.slow
def test_the_designs_incline_alone_is_the_finite_difference_fisher_of_the_table(mixed):
    """The incline-alone candidate's μ1, μ2, I0 half-widths are those of the finite-difference
    Jacobian of the table's relative residuals (float64 closed form) at 2 % noise."""
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1)
    table = load_flow_rule(TWIN)
    p = {k: float(getattr(scene.params, k)) for k in ("mu1", "mu2", "I0", "rho", "rho_s", "d")}

    def model(q):
        return np.asarray(steady_velocity(table.h, table.slope_deg, q["mu1"], q["mu2"], q["I0"], q["rho"],
                                          q["rho_s"], q["d"], table.quantity))

    u = model(p)
    J = np.zeros((table.n, 3))
    for j, key in enumerate(("mu1", "mu2", "I0")):
        step = 1e-6 * p[key]
        J[:, j] = (model({**p, key: p[key] + step}) - model({**p, key: p[key] - step})) / u / (2 * step)
    expected = Z95 * np.sqrt(np.diag(np.linalg.inv(J.T @ J / 0.02 ** 2)))
    incline = next(c for c in mixed.candidates if c.name == "incline flow_rule_twin")
    np.testing.assert_allclose(incline.halfwidth[1:], expected, rtol=1e-6)


@pytest.mark.slow
def test_the_command_line_ranks_the_mixed_candidates(mixed, capsys):
    # The same design through the command line: under 1 s after ``mixed`` (the runs are compiled).
    code = main(["design", *TINY, "--fit", ",".join(KEYS), "--at", "beta=0.25", "--noise", "0.01", "--grid-check", "0",
                 "--workers", "1", "--incline", TWIN, "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["experiments"] == ["main", "flow_rule_twin"]
    ours = {c["name"]: c for c in out["candidates"]}
    assert out["recommended"]["name"] == "final profile + incline flow_rule_twin"
    for c in mixed.candidates:
        np.testing.assert_allclose([ours[c.name]["halfwidth95"][k] for k in KEYS], c.halfwidth, rtol=1e-6)
        assert ours[c.name]["cost"] == c.cost


@pytest.mark.parametrize("argv, message", [
    (["--incline", "no/such/rule.csv"], "--incline no/such/rule.csv: "),
    (["--incline", "tests/test_design_mixed.py"], "--incline tests/test_design_mixed.py: "),
    (["--incline", TWIN, "--incline", "experiments_data/synthetic/flow_rule_twin.toml"], "two files are labelled"),
])
def test_command_line_inclines_are_refused_naming_the_option(argv, message, capsys, monkeypatch):
    _tripwire(monkeypatch)
    with pytest.raises(SystemExit) as stop:
        main(["design", *TINY, "--fit", ",".join(KEYS), *argv])
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_the_design_figure_keeps_its_axes_on_the_sets_that_see_both_keys(tmp_path, monkeypatch):
    """An incline alone does not see β: its region is thousands of |β| wide. It is drawn but left
    beyond the axes, and its legend says so, so that the collapses' regions stay readable."""
    from types import SimpleNamespace

    import calibration.plots.fits as fits

    def candidate(name, cost, sd):
        cov = np.diag(np.square(sd))
        return SimpleNamespace(name=name, cost=cost, cov=cov, cov_data=cov, halfwidth=1.96 * np.asarray(sd),
                               halfwidth_data=1.96 * np.asarray(sd))

    collapse, incline = candidate("final profile", 1.0, [0.03, 0.01]), candidate("incline", 4.0, [1e3, 1e-4])
    result = SimpleNamespace(keys=("beta", "mu1"), theta=np.array([0.25, 0.38]), tolerance=0.1,
                             candidates=(collapse, incline), recommended=None)
    seen = {}
    monkeypatch.setattr(fits, "_save", lambda fig, path, dpi: seen.setdefault("fig", fig) and path)
    fits.plot_design(result, tmp_path / "design.png")
    ax = seen["fig"].axes[0]
    low, high = ax.get_xlim()
    assert 0.25 - 0.2 < low < 0.25 - 0.03 * 2.4 and 0.25 + 0.03 * 2.4 < high < 0.25 + 0.2  # the collapse's region
    labels = [line.get_label() for line in ax.get_lines()]
    assert "incline (cost 4) (beyond the axes)" in labels and "final profile (cost 1)" in labels
