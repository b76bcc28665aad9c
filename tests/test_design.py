"""``calibration.design.design`` and ``python -m calibration design``: what to measure, before measuring."""

import json

import numpy as np
import pytest

from calibration import Objective
from calibration.cli.commands import main
from calibration.design.design import Experiment, design, expected_halfwidths
from calibration.inference.noise import Z95
from jaxmpm import scenes

L = 0.089
KEYS = ("beta", "mu1")
TINY = ["--scene", "cohesive-collapse", "--dx", str(L / 4), "--t-end", "0.1"]


def _experiment(J, sigma, rows, label="main", weights=None):
    m = J.shape[0]
    weights = np.ones(m) if weights is None else weights
    return Experiment(label, None, rows, np.full(m, sigma), J, weights, None, None, None)


def test_expected_halfwidths_are_the_gauss_newton_ones_of_the_chosen_rows():
    rng = np.random.default_rng(1)
    J = rng.standard_normal((12, 2))
    rows = {"final": np.arange(0, 4), "profiles": np.arange(0, 8), "front": np.arange(8, 12),
            "top": np.arange(8, 12)}
    e = _experiment(J, 0.05, rows)
    for parts, chosen in ((((("main", "final"),)), np.arange(0, 4)),
                          ((("main", "profiles"), ("main", "front")), np.arange(12)),
                          ((("main", "final"), ("main", "profiles")), np.arange(8))):  # rows counted once
        hw, cov, data_only, weighted, cov_data = expected_halfwidths([e], parts)
        expected = np.linalg.inv(J[chosen].T @ J[chosen] / 0.05 ** 2)
        np.testing.assert_allclose(cov, expected, rtol=1e-10)
        np.testing.assert_allclose(hw, Z95 * np.sqrt(np.diag(expected)), rtol=1e-10)
        np.testing.assert_allclose(data_only, hw, rtol=1e-12)
        np.testing.assert_allclose(weighted, hw, rtol=1e-8)  # equal weights, equal noise: the bound
        np.testing.assert_array_equal(cov_data, cov)  # no draws, no grid: the data's share is all
    # A second experiment adds its Fisher information.
    J2 = rng.standard_normal((6, 2))
    e2 = _experiment(J2, 0.02, {"final": np.arange(6), "profiles": np.arange(6), "front": np.arange(0),
                                "top": np.arange(0)}, "tall")
    # Weights 1/σ² (each row by its own noise): the Fisher matrices add.
    optimal = np.linalg.inv(J[:4].T @ J[:4] / 0.05 ** 2 + J2.T @ J2 / 0.02 ** 2)
    e = _experiment(J, 0.05, rows, weights=np.full(12, 1 / 0.05 ** 2))
    e2 = _experiment(J2, 0.02, e2.rows, "tall", weights=np.full(6, 1 / 0.02 ** 2))
    _, cov, *_ = expected_halfwidths([e, e2], (("main", "final"), ("tall", "final")))
    np.testing.assert_allclose(cov, optimal, rtol=1e-8)
    # Other weights (the fit's: a block's weight shared by its rows): the sandwich, wider.
    e2 = _experiment(J2, 0.02, e2.rows, "tall", weights=np.full(6, 30.0))
    _, cov, *_ = expected_halfwidths([e, e2], (("main", "final"), ("tall", "final")))
    Jall, wall = np.concatenate([J[:4], J2]), np.concatenate([e.weights[:4], e2.weights])
    sall = np.concatenate([np.full(4, 0.05), np.full(6, 0.02)])
    A = Jall.T @ (wall[:, None] * Jall)
    B = Jall.T @ ((wall ** 2 * sall ** 2)[:, None] * Jall)
    np.testing.assert_allclose(cov, np.linalg.inv(A) @ B @ np.linalg.inv(A), rtol=1e-8)
    assert np.all(np.diag(cov) > np.diag(optimal))  # wider than the 1/σ²-weighted estimate


@pytest.mark.parametrize("kwargs, match", [
    ({"tolerance": 0.0}, "tolerance"),
    ({"times": [0.5]}, "times must increase strictly within"),
    ({"times": []}, "times must be a non-empty"),
    ({"noise": {"height": 0.01}}, "noise: unknown kind"),
    ({"noise": -0.1}, "must be a positive fraction"),
    ({"variants": {"tall": {"beta": 0.3}}}, "material parameters"),
    ({"variants": {"tall": {"heigth": 0.2}}}, "not arguments of the collapse builder"),
    ({"variants": {"main": {"height": 0.2}}}, "'main' names the scene"),
    ({"sampling_seeds": 1}, "sampling_seeds"),
    ({"grid_ratio": 0.5}, "grid_ratio"),
    ({"theta": {"xi": 10.0}}, "not among the keys"),
    ({"sets": [("x", [("other", "final")])]}, "experiments are"),
])
def test_bad_input_is_refused_before_any_run(kwargs, match, monkeypatch):
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1)

    def tripwire(*args, **kw):
        raise AssertionError("the model ran: the input should have been refused before")

    monkeypatch.setattr(Objective, "predict", tripwire)
    theta = kwargs.pop("theta", None)
    with pytest.raises(ValueError, match=match):
        design(scene, KEYS, theta, **kwargs)


@pytest.fixture(scope="module")
def tiny():
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.1, dtype="float32")  # as the command line builds it
    return design(scene, KEYS, {"beta": 0.25}, noise=0.02, tolerance=0.5)


def test_more_observations_never_widen_the_datas_bound(tiny):
    """The noise-weighted half-widths (the data's Cramér–Rao bound) can only shrink as rows are
    added; the library's fit, which weighs each block as a whole, need not (the sandwich)."""
    by_name = {c.name: c for c in tiny.candidates}
    final = by_name["final profile"].halfwidth_weighted
    for name in ("final profile + front", "final profile + top height", "profiles in time",
                 "profiles in time + front", "profiles in time + front + top"):
        assert np.all(by_name[name].halfwidth_weighted <= final * (1 + 1e-9)), name
        assert np.all(by_name[name].halfwidth_data >= by_name[name].halfwidth_weighted * (1 - 1e-9)), name
    assert np.all(by_name["profiles in time + front"].halfwidth_weighted
                  <= by_name["profiles in time"].halfwidth_weighted * (1 + 1e-9))
    np.testing.assert_allclose(final, by_name["final profile"].halfwidth_data, rtol=1e-8)  # one block
    # Candidates come by cost; the recommendation is the cheapest that meets the tolerance.
    costs = [c.cost for c in tiny.candidates]
    assert costs == sorted(costs) and costs[0] == 1.0
    meeting = [c for c in tiny.candidates if c.meets]
    assert tiny.recommended is (meeting[0] if meeting else None)
    out = tiny.to_json()
    json.dumps(out, allow_nan=False)
    assert out["experiments"] == ["main"] and out["candidates"][0]["name"] == "final profile"
    assert out["notes"] == []  # nothing asked for went unmeasured


def test_the_command_line_prints_the_candidates_and_draws_the_regions(tiny, capsys, tmp_path):
    figure = tmp_path / "design.png"
    code = main(["design", *TINY, "--fit", "beta,mu1", "--at", "beta=0.25", "--tolerance", "0.5", "--grid-check", "0",
                 "--workers", "1", "--json", "--plot", str(figure)])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and figure.stat().st_size > 10_000
    # The same candidates as the library call with the same settings (float32 runs, one process).
    ours = {c["name"]: c["halfwidth95"] for c in out["candidates"]}
    for c in tiny.candidates:
        np.testing.assert_allclose([ours[c.name][k] for k in KEYS], c.halfwidth, rtol=1e-6)


@pytest.mark.parametrize("argv, message", [
    (["--fit", "beta", "--plot", "x.png"], "--plot draws the first two keys"),
    (["--fit", "beta,mu1", "--variant", "tall"], "--variant expects LABEL:key=value"),
    (["--fit", "beta,mu1", "--variant", "a:height=0.1", "--variant", "a:height=0.2"], "given twice"),
    (["--fit", "beta,mu1", "--times", "0.05,0.2"], "times must increase strictly within"),
])
def test_command_line_errors_name_the_option(argv, message, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["design", *TINY, *argv])
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_the_command_line_prints_the_librarys_ranking_as_text(tiny, capsys):
    """Without --json, ``design`` prints ``DesignResult.lines()`` of the library's call."""
    code = main(["design", *TINY, "--fit", "beta,mu1", "--at", "beta=0.25", "--tolerance", "0.5", "--grid-check", "0",
                 "--workers", "1"])
    text = capsys.readouterr().out
    assert code == 0 and text.splitlines() == tiny.lines()
    assert text.splitlines()[len(tiny.candidates)] == tiny.statement
