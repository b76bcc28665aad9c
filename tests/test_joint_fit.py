"""An incline's flow rule as an objective among the others: the package's fit of a
``FlowRuleObjective`` is the flow-rule fit, composites of closed forms fit and say they have no
grid, and (slow) a collapse fitted together with an incline recovers all four keys, with the
rate dependence the collapse alone leaves open fixed by the incline."""

import json

import numpy as np
import pytest
from helpers import ROOT, model_data, tiny_s4

from calibration import CompositeObjective, Objective, fit
from calibration.data import FlowRuleTable, dataset_path, load_flow_rule
from calibration.inference.gauss_newton import gauss_newton_uncertainty
from calibration.problem.flow_rule import FlowRuleObjective
from calibration.studies.flow_rule import fit_flow_rule
from jaxmpm.params import DEFAULTS
from jaxmpm.scenes.incline import steady_velocity

FIXED = {"rho": 1550.0, "rho_s": 2500.0, "d": 0.7e-3}
FAR = {"mu1": 0.30, "mu2": 0.90, "I0": 0.80}


def table(slopes, thicknesses, truth=DEFAULTS, material=FIXED):
    slope, h = (a.ravel() for a in np.meshgrid(slopes, thicknesses, indexing="ij"))
    u = np.asarray(steady_velocity(h, slope, truth["mu1"], truth["mu2"], truth["I0"], material["rho"],
                                   material["rho_s"], material["d"], "depth_averaged"))
    return FlowRuleTable(slope, h, u, "depth_averaged", "this test", False, experiment=f"{slopes[0]:g}-{slopes[-1]:g}")


def test_the_packages_fit_of_the_objective_is_the_flow_rule_fit_and_has_no_grid():
    data = load_flow_rule(dataset_path("synthetic/flow_rule_twin"))
    objective = FlowRuleObjective(data, values=FIXED)
    result = fit(objective, FAR, noise=0.02, grid_ratio=1.5, workers=1)
    study = fit_flow_rule(data, init=FAR, values=FIXED)
    assert result.theta == pytest.approx(study.theta, rel=1e-9)
    assert result.verdict.is_fit and result.uncertainty.grid is None
    assert "has no coarser grid" in result.uncertainty.grid_note
    json.dumps(result.to_json(), allow_nan=False)
    theta = np.array([0.37, 0.66, 0.31])
    r, J, _ = objective.residuals_and_jacobian(theta)
    assert np.all(np.isfinite(np.asarray(J))) and np.asarray(r).shape == (data.n,)
    # The worker task of one column is the Jacobian's column (a closed form computes it in place).
    z = objective.bounds.to_unconstrained(theta)
    fn, args = objective.column_task(z, np.array([0.0, 1.0, 0.0]), objective.bounds)
    r_task, _, dr, _ = fn(*args)
    np.testing.assert_allclose(dr, np.asarray(J)[:, 1], rtol=1e-10)
    np.testing.assert_allclose(r_task, np.asarray(r), rtol=1e-12)


def test_two_inclines_share_their_material_and_a_composite_of_closed_forms_has_no_grid():
    low = FlowRuleObjective(table((22.0, 24.0), (0.01, 0.02, 0.03)), values=FIXED)
    high = FlowRuleObjective(table((27.0, 29.0, 31.0), (0.01, 0.02)), values=FIXED)
    both = CompositeObjective([low, high])
    result = fit(both, FAR, workers=1)
    assert result.converged, result.message
    for key in ("mu1", "mu2", "I0"):
        assert result.theta[key] == pytest.approx(DEFAULTS[key], rel=1e-7), key
    with pytest.raises(NotImplementedError, match="no member has a grid"):
        both.coarsened(1.5)
    assert np.isnan(both.dx)


# 42 s cold, compiling NUTS around a flow rule; NUTS runs by default in tests/test_mcmc.py, the flow rule's fits
# here
@pytest.mark.slow
def test_the_posterior_of_a_flow_rule_samples_its_support():
    """NUTS reads μ1 and μ2 of every part to keep μ2 ≥ μ1; a flow rule's part has them too (the
    posterior of a joint fit with an incline raised AttributeError before its first draw)."""
    pytest.importorskip("blackjax")
    from calibration.inference.mcmc import nuts_posterior

    objective = FlowRuleObjective(table((22.0, 25.0, 28.0), (0.01, 0.02, 0.04)), values=FIXED)
    result = fit(objective, FAR, noise=0.01, workers=1)
    posterior = nuts_posterior(objective, result, chains=2, warmup=30, draws=60, noise=0.01)
    for key in objective.keys:  # a posterior about the fit, as wide as its standard error
        assert abs(posterior.mean[key] - result.theta[key]) < posterior.gn_stderr[key], key
        assert 0.5 < posterior.sd[key] / posterior.gn_stderr[key] < 2.0, key


@pytest.mark.slow  # 20 s: a four-key fit of a collapse's runs; the objective's own fit runs by default
def test_a_collapse_and_an_incline_fitted_together_fix_the_rate_dependence():
    keys = ("beta", "mu1", "mu2", "I0")
    scene = tiny_s4()
    truth = np.array([0.25] + [float(getattr(scene.params, k)) for k in keys[1:]])
    profile, front = model_data(scene, keys, truth, np.linspace(0.0, 0.16, 17), (0.05, 0.1))
    collapse = Objective(scene, keys, profile=profile, front=front)
    material = {k: float(getattr(scene.params, k)) for k in ("rho", "rho_s", "d")}
    incline = FlowRuleObjective(table((22.0, 24.0, 26.0, 28.0, 30.0), (0.01, 0.02, 0.03),
                                      dict(zip(keys, truth)), material), values=material)
    joint = CompositeObjective.sharing([collapse, incline], shared=("mu1", "mu2", "I0"),
                                       labels=("collapse", "incline"))
    assert joint.keys == ("mu1", "mu2", "I0", "beta@collapse")
    result = fit(joint, {"beta@collapse": 0.18, "mu1": 0.36, "mu2": 0.75, "I0": 0.5}, steps=30, noise=0.01,
                 workers=1)
    assert result.converged and result.verdict.is_fit, result.message
    got = np.array([result.theta[k] for k in ("beta@collapse", "mu1", "mu2", "I0")])
    np.testing.assert_allclose(got, truth, rtol=1e-8)
    # The collapse alone, at the same noise, leaves μ2 and I0 open; the incline fixes them.
    r, J, _ = collapse.residuals_and_jacobian(truth)
    alone = gauss_newton_uncertainty(np.asarray(J), np.asarray(r), keys, truth, collapse.blocks, collapse.row_scale,
                                     noise=0.01)
    joint_se = dict(zip(result.keys, result.uncertainty.stderr))
    for key, se_alone in zip(keys, alone.stderr):
        name = "beta@collapse" if key == "beta" else key
        assert joint_se[name] < se_alone, (key, joint_se[name], se_alone)
    assert alone.stderr[3] > 1.0 and joint_se["I0"] < 0.01  # I0: unknown from the collapse, to 1 % jointly


def test_a_block_the_noise_does_not_name_is_estimated_and_the_source_says_which():
    from calibration.inference.noise import block_noise, structural_noise

    rng = np.random.default_rng(3)
    r = np.concatenate([0.03 * rng.standard_normal(40), 0.01 * rng.standard_normal(16)])
    blocks = {"column/profile": slice(0, 40), "chute/velocity": slice(40, 56)}
    sigma, counts, source = block_noise(r, np.ones(56), blocks, {"chute/velocity": 0.01})
    assert sigma["chute/velocity"] == 0.01 and counts["chute/velocity"] == 0
    assert (sigma["column/profile"], counts["column/profile"]) == structural_noise(r[:40])
    assert source == "given for chute/velocity; estimated from the residuals' second differences for the others"
    assert block_noise(r, np.ones(56), blocks, 0.02)[2] == "given"
    assert block_noise(r, np.ones(56), blocks, None)[2] == "estimated from the residuals' second differences"


def test_a_joint_fit_takes_each_tables_stated_noise_for_its_block(tmp_path):
    """``FitSetup.stated_noise``: an incline table's header noise, under its block's name in the
    objective (alone: "velocity"; beside another experiment: "label/velocity"); a collapse states
    none, so its blocks are estimated. (Before, a joint fit estimated the table's noise from its
    residuals too, and a lucky draw narrowed the intervals past the truth.)"""
    from calibration.data.incline import load_incline
    from calibration.problem.build import FitSetup
    from jaxmpm import Experiment

    twin = load_incline(dataset_path("synthetic/flow_rule_twin_experiment"))
    assert FitSetup((twin,), ("mu1", "mu2", "I0")).stated_noise() == {"velocity": 0.02}
    column = Experiment.from_toml(ROOT / "docs" / "five_keys" / "column.toml")
    chute = load_incline(ROOT / "docs" / "five_keys" / "chute.toml")
    setup = FitSetup((column, chute), ("beta", "mu1", "mu2", "I0"), shared=("mu1", "mu2", "I0"),
                     labels=("column", "chute"))
    assert setup.stated_noise() == {"chute/velocity": 0.01}
    assert "chute/velocity" in setup.objective().blocks
