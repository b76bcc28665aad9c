"""Fits on a ladder of grids (``calibration.optim.ladder.grid_ladder``): every rung started from the
coarser one's point, the grid term from the fitted points, Richardson's extrapolation where three
grids converge with a believable order, the finest point with a wider term where they do not."""

import math
import types

import numpy as np
import pytest

from calibration.optim import ladder as ladder_module
from calibration.optim.fit import FitResult
from calibration.optim.ladder import Rung, _ladder_term, grid_ladder
from calibration.plots.fits import plot_ladder
from calibration.problem.bounds import Bounds

KEYS = ("beta", "mu1")
TRUTH = np.array([0.25, 0.38])
C = np.array([0.04, -0.03])  # the fit's grid error at dx = 1, times dx^p


class _Graded:
    """An objective with no runs whose fit at grid spacing h lands at TRUTH + C h^p (or, with
    ``alternate``, TRUTH + C h (−1)^level): what the ladder's stubbed fits return."""

    def __init__(self, dx=0.5, p=1.0, alternate=False, level=0, top=0.9):
        self.dx, self.p, self.alternate, self.level, self.top = dx, p, alternate, level, top
        self.keys = KEYS
        self.bounds = Bounds.create(KEYS, {"beta": (-0.5, top), "mu1": (0.05, 1.5)})
        self.blocks = {"profile": slice(0, 40)}
        self.row_scale = np.ones(40)
        self.jacobian = np.random.default_rng(0).standard_normal((40, 2))

    def coarsened(self, ratio):
        level = round(math.log(ratio) / math.log(1.5))
        return _Graded(self.dx * ratio, self.p, self.alternate, level, self.top)

    def landing(self):
        if self.alternate:
            return TRUTH + C * self.dx * (-1.0) ** self.level
        return TRUTH + C * self.dx ** self.p


def _stub_fits(monkeypatch, calls):
    def result(objective, init):
        calls.append((objective.dx, None if init is None else dict(init)))
        theta = objective.landing()
        return FitResult(keys=KEYS, theta=dict(zip(KEYS, map(float, theta))), loss=0.0, iterations=3, wall_s=0.1,
                         method="lm", converged=True, message="converged", history={}, residuals=np.zeros(40),
                         jacobian=objective.jacobian, prediction={}, verdict=types.SimpleNamespace(scatter=None))

    monkeypatch.setattr(ladder_module, "fit_from_starts", lambda obj, init, **kw: (result(obj, init), None))
    monkeypatch.setattr(ladder_module, "fit", lambda obj, init, **kw: result(obj, init))


def test_each_rung_starts_from_the_coarser_fit_and_three_converging_grids_extrapolate(monkeypatch, tmp_path):
    calls = []
    _stub_fits(monkeypatch, calls)
    found = grid_ladder(_Graded(p=1.4), {"beta": 0.1}, rungs=3, ratio=1.5, judge=ladder_module.JudgeOptions(
        noise=0.01, roundoff_samples=0, probe=False))
    dxs = [dx for dx, _ in calls]
    np.testing.assert_allclose(dxs, [0.5 * 2.25, 0.5 * 1.5, 0.5])  # coarsest first
    assert calls[0][1] == {"beta": 0.1}
    for (_, start), rung in zip(calls[1:], found.rungs[:-1]):
        assert start == rung.theta  # every finer rung from the coarser one's point
    assert found.extrapolated and found.grid.order == pytest.approx(1.4)
    np.testing.assert_allclose([found.point[k] for k in KEYS], TRUTH, atol=1e-12)  # exact for a pure power
    fine = TRUTH + C * 0.5 ** 1.4
    e21 = C * (0.75 ** 1.4 - 0.5 ** 1.4)
    np.testing.assert_allclose(found.grid.halfwidth, 1.25 * np.abs(e21) / (1.5 ** 1.4 - 1.0), rtol=1e-12)
    # The finest fit is judged with the ladder's term; the interval is its half-width about the point.
    assert found.fit.uncertainty.grid is found.grid
    half = 1.959963984540054 * found.fit.uncertainty.stderr
    for j, k in enumerate(KEYS):
        assert found.ci95[k] == pytest.approx((TRUTH[j] - half[j], TRUTH[j] + half[j]), rel=1e-12)
        assert found.fit.theta[k] == pytest.approx(fine[j])
        assert found.ci95[k][0] <= found.fit.theta[k] <= found.ci95[k][1]  # the finest point stays inside
    assert "Richardson" in found.statement
    out = found.to_json()
    assert out["extrapolated"] is True and [r["dx"] for r in out["rungs"]] == pytest.approx(dxs)
    drawn = plot_ladder(out, tmp_path / "ladder.png", truth=dict(zip(KEYS, TRUTH)))
    assert drawn.stat().st_size > 10_000


def test_grids_that_oscillate_or_show_an_unbelievable_order_are_not_extrapolated(monkeypatch):
    _stub_fits(monkeypatch, [])
    judge = ladder_module.JudgeOptions(noise=0.01, roundoff_samples=0, probe=False)
    swinging = grid_ladder(_Graded(alternate=True), rungs=3, judge=judge)
    assert not swinging.extrapolated and swinging.grid.order is None and "oscillate" in swinging.statement
    fine = TRUTH + C * 0.5
    assert [swinging.point[k] for k in KEYS] == pytest.approx(fine)
    e21, e32 = -2.5 * C * 0.5 * 1.5 / 1.5, C * 0.5 * (2.25 + 1.5)  # |θ(1.5 dx) − θ(dx)|, |θ(2.25 dx) − θ(1.5 dx)|
    np.testing.assert_allclose(swinging.grid.halfwidth, 3.0 * np.maximum(np.abs(e21), np.abs(e32)) / 0.5, rtol=1e-12)
    steep = grid_ladder(_Graded(p=3.0), rungs=3, judge=judge)
    assert not steep.extrapolated and "outside" in steep.statement and steep.grid.order == 2.0
    pinned = grid_ladder(_Graded(p=1.4, top=TRUTH[0] + C[0] * 1.125 ** 1.4), rungs=3, judge=judge)
    assert not pinned.extrapolated and "ended at a bound" in pinned.statement  # the coarsest rung's β
    assert pinned.rungs[0].at_bound == ("beta",) and pinned.grid.order == pytest.approx(1.4)
    two = grid_ladder(_Graded(p=1.0), rungs=2, judge=judge)
    assert not two.extrapolated and two.grid.shift2 is None
    np.testing.assert_allclose(two.grid.halfwidth, 3.0 * np.abs(C * 0.25) / 0.5, rtol=1e-12)


def test_the_ladder_term_reads_fitted_points_not_a_step():
    rungs = tuple(Rung(dx, dict(zip(KEYS, TRUTH + C * dx)), 0.0, True, 1, 1.0) for dx in (2.25, 1.5, 1.0))
    grid, point, said = _ladder_term(rungs, KEYS, 1.5, None)
    assert grid.order == pytest.approx(1.0) and "order 1" in said
    np.testing.assert_allclose(point, TRUTH, atol=1e-12)
    np.testing.assert_allclose(grid.shift, C * 0.5, rtol=1e-12)
    np.testing.assert_allclose(grid.shift2, C * 1.25, rtol=1e-12)
    assert grid.wall_s == 2.0  # the coarser rungs' cost


@pytest.mark.parametrize("kwargs, match", [({"rungs": 4}, "rungs must be one of"), ({"rungs": 1}, "rungs"),
                                           ({"ratio": 1.0}, "grid_ratio"), ({"starts": 0}, "starts")])
def test_bad_ladder_options_are_refused_before_any_fit(kwargs, match, monkeypatch):
    calls = []
    _stub_fits(monkeypatch, calls)
    with pytest.raises(ValueError, match=match):
        grid_ladder(_Graded(), **kwargs)
    assert calls == []


def test_an_objective_with_no_grid_is_refused():
    class _Closed(_Graded):
        def coarsened(self, ratio):
            raise NotImplementedError("a closed form")

    with pytest.raises(ValueError, match="no coarser grid"):
        grid_ladder(_Closed())


@pytest.mark.slow  # 3 fits of tiny S4 compiled at two grids (about 40 s on one core)
def test_the_command_line_ladder_fits_each_rung_from_the_coarser_point(tmp_path, capsys):
    import json
    import pathlib

    from calibration.cli.commands import main

    data = pathlib.Path(__file__).resolve().parents[1] / "experiments_data" / "synthetic" / "S4_beta0.25.csv"
    dx = 0.089 / 6
    code = main(["fit", "--scene", "cohesive-collapse", "--data", str(data), "--fit", "beta,mu1", "--init", "beta=0.2",
                 "--init", "mu1=0.4", "--dx", str(dx), "--set", "pc0=500", "--set", "xi=50", "--grid-ladder", "2",
                 "--steps", "6", "--no-progress", "--json", "--workers", "1"])
    out = json.loads(capsys.readouterr().out)
    assert code in (0, 1)
    rungs = out["ladder"]["rungs"]
    assert [r["dx"] for r in rungs] == pytest.approx([1.5 * dx, dx])
    assert out["params"] == pytest.approx(rungs[-1]["theta"])  # the report is the finest fit's
    assert out["start"] == pytest.approx(rungs[0]["theta"]) or rungs[0]["at_bound"]  # started at the coarse point
    assert out["grid"]["method"].startswith("fits at two grids")
    shift = {k: rungs[0]["theta"][k] - rungs[1]["theta"][k] for k in ("beta", "mu1")}
    assert out["grid"]["shift"] == pytest.approx(shift)
    assert out["search"]["starts"] == 1
