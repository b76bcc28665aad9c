"""The library calls behind ``python -m calibration``: each builds, runs or reports what the
command does (its objective, its fit, its sweep, its checks beyond Gauss–Newton, its law, its
ranking, its figures), checked against the command where a small case allows."""

import json
import pathlib
from types import SimpleNamespace

import numpy as np
import pytest

from calibration.batch.sweep import SweepResult, grid_points, latin_hypercube, sweep, sweep_points
from calibration.cli import args as cli
from calibration.cli.commands import main
from calibration.cli.parser import build_parser
from calibration.data.loaders import load_profile
from calibration.data.measurements import check_run_status, load_data
from calibration.design.design import Candidate, DesignResult
from calibration.inference.options import JudgeOptions
from calibration.optim.options import FitOptions
from calibration.optim.report import PosteriorOptions, posterior_checks
from calibration.plots import fits as plots
from calibration.problem.build import member_objective, objective_of
from calibration.problem.options import DataOptions
from calibration.studies.scaling import named_law
from jaxmpm import SideWalls, scenes
from jaxmpm.scenes import runout_law

ROOT = pathlib.Path(__file__).resolve().parents[1]
S4 = str(ROOT / "experiments_data" / "synthetic" / "S4_beta0.25.csv")
DX = 0.089 / 6
TINY = ["--dx", str(DX), "--no-progress", "--json"]


def test_objective_of_is_the_objective_the_command_line_fits():
    """A named scene with a profile: the command line's objective (run to the data's time, the
    profile weighed 2) is the library's from the scene, the data and ``DataOptions``."""
    args = build_parser().parse_args(["fit", "--scene", "cohesive-collapse", "--data", S4, "--fit", "beta,mu1",
                                      "--weight-profile", "2", "--weighting", "row", *TINY])
    cli_objective = cli.setup_of(args, ("beta", "mu1")).objective()
    scene = cli_objective.scene
    data = load_data([S4])
    assert scene.config.t_end == pytest.approx(0.5) and len(data[0]) == 1 and data[1] is None
    ours = objective_of([scenes.cohesive_collapse(dx=DX, t_end=0.5, dtype="float32")], ("beta", "mu1"), [data],
                        DataOptions(weight_profile=2.0, weighting="row"))
    assert ours.fingerprint() == cli_objective.fingerprint()
    assert ours.weights["profile"] == 2.0 and ours.weighting == "row"
    with pytest.raises(ValueError, match="one \\(profiles, front\\) pair per source"):
        objective_of([scene, scene], ("beta",), [data])


def test_member_objective_sets_the_fronts_correlation_time(tmp_path):
    front = tmp_path / "front.csv"
    front.write_text("t_s,xf_m\n0.05,0.095\n0.1,0.11\n0.2,0.14\n")
    _, history = load_data([], front)
    scene = scenes.cohesive_collapse(dx=DX, t_end=0.2, dtype="float32")
    plain = member_objective(scene, ("beta",), [], history)
    correlated = member_objective(scene, ("beta",), [], history, DataOptions(front_correlation_time=0.05))
    assert plain.front.correlation_time is None and correlated.front.correlation_time == 0.05
    assert plain.weights == {"profile": 1.0, "front": 1.0}


def test_load_data_refuses_a_failed_runs_file(tmp_path):
    profiles, front = load_data([S4])
    np.testing.assert_array_equal(profiles[0].h, load_profile(S4).h)
    failed = tmp_path / "failed.csv"
    failed.write_text("# time_s: 0.5\n# status: 1\nx_m,h_m\n0,0.05\n0.05,0.04\n0.1,0\n")
    with pytest.raises(ValueError, match="written by a run that failed \\(status 1: a particle left the grid"):
        load_data([failed])
    check_run_status([None, *profiles])  # nothing recorded, nothing refused


def test_fit_from_starts_runs_one_start_a_search_or_two_stages(monkeypatch):
    """The dispatch of ``fit``'s starts: one start is ``calibration.optim.fit.fit`` with the history
    options; more are ``search`` (or ``coarse_to_fine`` with a coarse objective) with the fit's
    steps and the judging options, the best point returned with the search."""
    import importlib

    fit_module = importlib.import_module("calibration.optim.fit")
    search_module = importlib.import_module("calibration.optim.search")
    calls = []

    fitted, best = SimpleNamespace(verdict=None), SimpleNamespace(verdict=None)

    def fake_fit(objective, init, **kw):
        calls.append(("fit", init, kw))
        return fitted

    def fake_search(name):
        def run(*args, **kw):
            calls.append((name, args, kw))
            return SimpleNamespace(best=best)
        return run

    monkeypatch.setattr(fit_module, "fit", fake_fit)
    monkeypatch.setattr(search_module, "search", fake_search("search"))
    monkeypatch.setattr(search_module, "coarse_to_fine", fake_search("coarse_to_fine"))
    options, judge = FitOptions(steps=7, lm_model="adaptive"), JudgeOptions(roundoff_samples=0, grid_ratio=1.5)
    assert search_module.fit_from_starts("obj", {"beta": 0.2}, options=options, judge=judge, out="f.h5",
                                         resume=True, meta={"a": 1}) == (fitted, None)
    name, init, kw = calls[-1]
    assert name == "fit" and init == {"beta": 0.2} and kw["options"] is options and kw["judge"] is judge
    assert kw["out"] == "f.h5" and kw["resume"] and kw["meta"] == {"a": 1}
    result, found = search_module.fit_from_starts("obj", {}, starts=3, options=options, judge=judge, seed=4)
    name, args, kw = calls[-1]
    assert (name, args, result, found.best) == ("search", ("obj", 3), best, best)
    assert kw["steps"] == 7 and kw["seed"] == 4 and kw["init"] is None and kw["grid_ratio"] == 1.5
    assert kw["roundoff_samples"] == 0 and kw["lm_model"] == "adaptive"
    search_module.fit_from_starts("obj", None, starts=3, coarse="coarse", refine=5, options=options, judge=judge)
    name, args, kw = calls[-1]
    assert name == "coarse_to_fine" and args == ("obj", "coarse", 3) and kw["refine"] == 5 and kw["steps"] == 7
    with pytest.raises(ValueError, match="starts must be an integer >= 1, got 0"):
        search_module.fit_from_starts("obj", starts=0)


def _probed(theta, passed, lowest=None):
    probe = SimpleNamespace(passed=passed, lowest=lowest, lowest_rise=-5.0)
    return SimpleNamespace(keys=("mu1",), theta={"mu1": theta}, loss=theta, wall_s=1.0, restarts=[],
                           verdict=SimpleNamespace(probe=probe))


@pytest.mark.parametrize("restarts", [0, 1, 2])
def test_a_fit_whose_probe_finds_a_lower_loss_starts_again_from_it(monkeypatch, restarts):
    """``fit_from_starts``' restarts: from the probe's lowest point, until a probe passes or
    ``restarts`` are spent; the last fit is the answer, and it lists the ones before it."""
    import importlib

    fit_module = importlib.import_module("calibration.optim.fit")
    search_module = importlib.import_module("calibration.optim.search")
    ends = iter([_probed(0.30, False, [0.32]), _probed(0.325, False, [0.335]), _probed(0.337, True)])
    starts = []

    def fake_fit(objective, init, **kw):
        starts.append(init)
        assert "out" not in kw or init == {"mu1": 0.36}  # a restart keeps no history of its own
        return next(ends)

    monkeypatch.setattr(fit_module, "fit", fake_fit)
    result, _ = search_module.fit_from_starts("obj", {"mu1": 0.36}, options=FitOptions(restarts=restarts),
                                              judge=JudgeOptions())
    assert starts == [{"mu1": 0.36}, {"mu1": 0.32}, {"mu1": 0.335}][:restarts + 1]
    assert result.theta["mu1"] == (0.30, 0.325, 0.337)[restarts]
    assert [r["ended"]["mu1"] for r in result.restarts] == [0.30, 0.325][:restarts]
    assert result.wall_s == restarts + 1  # the walls of the fits before it added


def test_lm_model_is_checked_and_a_history_without_it_resumes_as_gauss_newton():
    with pytest.raises(ValueError, match="lm_model must be one of"):
        FitOptions(lm_model="secant")
    saved = {k: v for k, v in FitOptions().to_json().items() if k != "lm_model"}  # a file from before the field
    assert FitOptions(lm_model="gauss-newton").differences(saved) == []
    assert FitOptions().differences(saved) == [
        "lm_model: 'adaptive' now, 'gauss-newton' in the file (written before it was recorded)"]


def test_posterior_checks_say_why_they_are_skipped():
    result = SimpleNamespace(uncertainty=None, keys=("beta",))
    assert posterior_checks(None, result, PosteriorOptions()).report == {}
    skipped = posterior_checks(None, result, PosteriorOptions(profiles=5))
    assert skipped.report == {"profile_likelihood_skipped": "the point is not a fit of the data: no interval to "
                                                            "scan around"}
    assert skipped.profiles == [] and skipped.posterior is None
    three = SimpleNamespace(uncertainty=SimpleNamespace(withheld=False), keys=("beta", "mu1", "xi"))
    assert posterior_checks(None, three, PosteriorOptions(posterior=5)).report == {
        "posterior_skipped": "3 keys: the grid posterior is for one or two"}


def test_sweep_points_are_the_grid_or_the_latin_hypercube():
    over = {"beta": (0.1, 0.3, 3), "mu1": (0.35, 0.45, 2)}
    keys, thetas = sweep_points(over)
    expected = grid_points({"beta": (0.1, 0.3), "mu1": (0.35, 0.45)}, {"beta": 3, "mu1": 2})
    assert keys == expected[0] and thetas.shape == (6, 2)
    np.testing.assert_array_equal(thetas, expected[1])
    keys, thetas = sweep_points(over, lhs=4, seed=2)
    np.testing.assert_array_equal(thetas, latin_hypercube({"beta": (0.1, 0.3), "mu1": (0.35, 0.45)}, 4, seed=2)[1])


# 10 s: the sweep command end to end stays in the default suite (tests/test_calibration_cli.py).
@pytest.mark.slow
def test_the_sweep_command_prints_the_library_sweep(capsys, tmp_path):
    """``sweep --over beta=0.1:0.3:2`` prints the losses of the library's sweep of the same
    objective over the same points (a coarse grid, 0.1 s)."""
    dx, data = 0.089 / 4, tmp_path / "early.csv"
    data.write_text("# units: m\n# time_s: 0.1\nx_m,h_m\n0,0.08\n0.05,0.06\n0.1,0.01\n0.15,0\n")
    assert main(["sweep", "--scene", "cohesive-collapse", "--data", str(data), "--over", "beta=0.1:0.3:2", "--dx",
                 str(dx), "--no-progress", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    keys, thetas = sweep_points(cli.parse_over(["beta=0.1:0.3:2"]))
    objective = objective_of([scenes.cohesive_collapse(dx=dx, t_end=0.1, dtype="float32")], keys,
                             [load_data([data])])
    ours = sweep(objective, thetas)
    assert out["n_members"] == ours.n == 2 and "residuals" not in out and np.all(np.isfinite(ours.loss))
    np.testing.assert_allclose(out["loss"], ours.loss, rtol=1e-6)


def test_named_law_is_the_table_or_a_published_law():
    law, label = named_law()
    assert law is runout_law and label == "glass beads (Lajeunesse et al. 2005, secondary)"
    sand, label = named_law(sand=True)
    assert label == "sand (Lube et al. 2005, secondary)"
    assert sand(np.array([2.0]))[0] == pytest.approx(runout_law(np.array([2.0]), sand=True)[0])
    path = ROOT / "experiments_data" / "scaling_laws" / "runout_glass_beads.csv"
    table, label = named_law(path)
    assert "secondary" in label or "primary" in label
    assert callable(table)


def _candidate(name, relative, cost, meets):
    r = np.asarray(relative, float)
    return Candidate(name, (), cost, 0.5 * r, r, np.eye(2), meets, 0.5 * r, 0.25 * r, np.eye(2))


def test_the_design_ranking_as_text():
    """One line per candidate by cost, the recommended one starred, then the statement and the
    notes: what ``design`` prints without --json."""
    cheap, better = _candidate("final profile", [0.4, 0.2], 1.0, False), _candidate("+ front", [0.05, 0.02], 2, True)
    result = DesignResult(("beta", "mu1"), np.array([0.5, 0.5]), {"profile": 0.02}, 0.1, (cheap, better), better,
                          ("main",), 0.0, notes=("the grid's share was not measured",))
    lines = result.lines()
    assert len(lines) == 4 and lines[2] == result.statement
    assert lines[0].startswith("  cost 1  final profile: beta ±40 % (data alone ±40 %, noise-weighted ±20 %)")
    assert lines[1].startswith("* cost 2  + front: ")
    assert lines[3] == "note: the grid's share was not measured"


def test_sweep_figures_draw_a_curve_or_a_landscape(tmp_path):
    pytest.importorskip("matplotlib")

    def result(thetas, keys):
        n = len(thetas)
        loss = np.linspace(1.0, 2.0, n)
        return SweepResult(keys=keys, thetas=np.asarray(thetas, float), loss=loss, status=np.zeros(n, np.int64),
                           residuals=np.zeros((n, 2)), predictions=None, failed=np.zeros(0, np.int64), mode="loop",
                           chunk=1, n_devices=1, wall_s=0.0, compile_s=0.0)

    one = plots.sweep_figures(tmp_path / "one", result([[0.1], [0.2], [0.3]], ("beta",)), ("beta",))
    keys, thetas = grid_points({"beta": (0.1, 0.3), "mu1": (0.35, 0.45)}, 3)
    two = plots.sweep_figures(tmp_path / "two", result(thetas, keys), keys)
    assert [pathlib.Path(f).name for f in one + two] == ["loss.png", "landscape.png"]
    assert all(pathlib.Path(f).stat().st_size > 5_000 for f in one + two)


def test_the_twin_landscape_and_law_figures(tmp_path):
    """The figure sets of ``twin --landscape --plot`` and ``law --plot``, from stand-in results."""
    pytest.importorskip("matplotlib")
    from calibration.studies.twin import TwinLandscape

    keys, thetas = grid_points({"beta": (0.1, 0.3), "mu1": (0.35, 0.45)}, 3)
    swept = SweepResult(keys=keys, thetas=thetas, loss=np.linspace(1.0, 2.0, 9), status=np.zeros(9, np.int64),
                        residuals=np.zeros((9, 2)), predictions=None, failed=np.zeros(0, np.int64), mode="loop",
                        chunk=1, n_devices=1, wall_s=0.0, compile_s=0.0)
    marks = {"true": (0.2, 0.4), "start": (0.15, 0.38), "fit": (0.21, 0.41)}
    landscape = plots.twin_landscape_figure(tmp_path, TwinLandscape(keys, swept, marks))
    assert landscape.name == "twin_landscape.png" and landscape.stat().st_size > 5_000

    cases = [{"a": a, "law": 2.0 * a ** 0.5, "used_in_fit": a != 2.0, "model_start": 1.5 * a ** 0.5,
              "model_fit": 2.1 * a ** 0.5} for a in (0.5, 1.0, 2.0, 4.0)]
    history = {"loss": np.array([1.0, 0.5, 0.6]), "theta": np.array([[0.4, 0.6], [0.38, 0.62], [0.37, 0.6]]),
               "accepted": np.array([True, True, False])}
    result = SimpleNamespace(to_json=lambda: {"cases": cases}, law="a law", side_walls=SideWalls(0.1, 0.3),
                             fit=SimpleNamespace(history=history, keys=("mu1", "mu2")))
    figures = plots.law_figures(tmp_path / "law", result, law=lambda a: 2.0 * np.sqrt(a))
    assert [pathlib.Path(f).name for f in figures] == ["law_runout.png", "law_history.png"]
    assert all(pathlib.Path(f).stat().st_size > 5_000 for f in figures)


def test_a_search_keeps_its_best_start_and_its_interval_for_posterior(tmp_path):
    """``save_start`` writes a search's best start as a finished fit's file and ``read_record``
    gives back what the posterior checks read: the point, the residuals there and the interval
    (noise, covariance, standard errors, 95 % intervals, grid term); the file resumes as one LM
    start from that point."""
    from calibration import Bounds, FitOptions, JudgeOptions
    from calibration.inference.gauss_newton import gauss_newton_uncertainty
    from calibration.inference.gridcheck import GridCheck
    from calibration.optim.fit import FitResult, save_start
    from calibration.optim.history import read_history
    from calibration.optim.record import read_record

    keys, bounds = ("beta", "mu1"), Bounds(("beta", "mu1"), (0.0, 0.05), (1.0, 2.0))
    objective = SimpleNamespace(keys=keys, bounds=bounds, fingerprint=lambda: {"toy": 1}, describe=lambda: {})
    rng = np.random.default_rng(0)
    J, r = rng.standard_normal((20, 2)), 0.01 * rng.standard_normal(20)
    grid = GridCheck(0.01, 0.015, 2, np.array([0.01, -0.02]), np.array([0.06, 0.12]), 1.0)
    unc = gauss_newton_uncertainty(J, r, keys, np.array([0.3, 0.4]), blocks={"profile": slice(0, 20)},
                                   row_scale=np.ones(20), bounds=bounds, grid=grid)
    history = {"theta": np.array([[0.2, 0.5], [0.3, 0.4]]), "z": np.zeros((2, 2)), "loss": np.array([1.0, 0.5]),
               "grad_norm": np.ones(2), "status": np.zeros(2, int), "accepted": np.array([True, True]),
               "lam": np.array([1e-3, 3e-4]), "wall_s": np.array([1.0, 2.0])}
    result = FitResult(keys, {"beta": 0.3, "mu1": 0.4}, 0.5, 2, 2.0, "lm", True, "converged: toy", history, r, J, {},
                       uncertainty=unc)
    path = tmp_path / "search.h5"
    save_start(path, objective, result, FitOptions(), JudgeOptions(), {"setup": {"toy": True}})
    record = read_record(path)
    assert record.keys == keys and record.theta == {"beta": 0.3, "mu1": 0.4}
    np.testing.assert_array_equal(record.residuals, r)
    for name in ("cov", "stderr", "ci95"):
        np.testing.assert_allclose(getattr(record.uncertainty, name), getattr(unc, name), rtol=1e-15)
    assert record.uncertainty.noise == unc.noise and not record.uncertainty.withheld
    np.testing.assert_array_equal(record.uncertainty.grid.halfwidth, grid.halfwidth)
    assert record.header["meta"]["setup"] == {"toy": True} and record.report["params"] == result.theta
    saved = read_history(path)
    assert bool(saved["resume"]["done"]) and saved["resume"]["lam"] == pytest.approx(3e-4)
    np.testing.assert_allclose(bounds.to_physical(saved["resume"]["z"]), [0.3, 0.4], rtol=1e-12)


class _Box:
    keys = ("beta", "mu1")

    def __init__(self):
        from calibration.problem.bounds import Bounds

        self.bounds = Bounds(self.keys, (0.0, 0.1), (1.0, 1.5))

    def check_thetas(self, thetas, name="thetas"):
        pass


@pytest.mark.parametrize("first_is_fit, second_loss", [(True, 0.5), (False, 0.5), (False, 2.0)])
def test_coarse_to_fine_refines_the_next_coarse_minima_where_the_best_is_no_fit(monkeypatch, first_is_fit,
                                                                                 second_loss):
    """Six coarse minima, refine = 2: the fine stage refines the best two; only where its best
    point is not a fit of the data are the next two refined, and the lower loss kept."""
    import importlib

    search_module = importlib.import_module("calibration.optim.search")
    fine, coarse = _Box(), _Box()
    minima = [SimpleNamespace(theta={"beta": 0.1 * i, "mu1": 0.3 + 0.05 * i}, within_noise=False, starts=(i,))
              for i in range(1, 7)]
    refined = []

    def fake_search(objective, starts, **kw):
        if objective is coarse:
            return SimpleNamespace(minima=minima, starts=np.zeros((6, 2)), wall_s=1.0)
        refined.append(np.round(np.asarray(starts)[:, 0], 6).tolist())
        second = len(refined) == 2
        best = SimpleNamespace(loss=second_loss if second else 1.0,
                               verdict=SimpleNamespace(is_fit=first_is_fit or second))
        return SimpleNamespace(best=best, wall_s=1.0, start_note="")

    monkeypatch.setattr(search_module, "search", fake_search)
    result = search_module.coarse_to_fine(fine, coarse, 6, refine=2)
    assert refined == ([[0.1, 0.2]] if first_is_fit else [[0.1, 0.2], [0.3, 0.4]])
    assert result.best.loss == (1.0 if first_is_fit else min(1.0, second_loss))
    kept_second = not first_is_fit and second_loss < 1.0
    assert ("the next 2 were refined too and gave the best point" in result.start_note) == kept_second
    assert ("without a lower loss" in result.start_note) == (not first_is_fit and not kept_second)
    assert result.wall_s == (2.0 if first_is_fit else 3.0)  # the coarse stage and every refinement
