"""``python -m calibration fit|posterior|sweep|twin`` end to end on tiny settings."""

import json
import pathlib

import numpy as np
import pytest
from helpers import ROOT, S4_DATA, TINY_DX, TINY_FLAGS

from calibration.cli.commands import main

S4 = str(S4_DATA)
WPD = str(ROOT / "experiments_data" / "examples" / "wpd_example.csv")
TINY = list(TINY_FLAGS)


def run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr().out
    return code, json.loads(out)


@pytest.fixture(scope="module")
def documented_fit(tmp_path_factory):
    """The documented fit of (β, μ1), two iterations, with its file and figures: (code, JSON, folder)."""
    import contextlib
    import io

    folder = tmp_path_factory.mktemp("documented")
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["fit", "--scene", "cohesive-collapse", "--data", S4, "--fit", "beta,mu1", "--init", "beta=0.2",
                     "--steps", "2", "--out", str(folder / "fit.h5"), "--plot", str(folder / "figs"), *TINY])
    return code, json.loads(stdout.getvalue()), folder


def test_fit_prints_the_documented_json_and_writes_history_and_figures(documented_fit):
    code, out, tmp_path = documented_fit
    assert code == 0
    for key in ("params", "loss", "iterations", "wall_s", "start", "verdict", "search"):
        assert key in out, key
    assert set(out["params"]) == {"beta", "mu1"} and out["start"]["beta"] == 0.2
    assert out["iterations"] == 2 and np.isfinite(out["loss"])
    # Two iterations are no verified minimum: no Gauss–Newton interval, and the verdict says why.
    assert out["verdict"]["verdict"] == "not a fit of the data" and not out["verdict"]["verified_minimum"]
    assert "stderr" not in out and "ci95" not in out and "No Gauss–Newton interval" in out["statement"]
    assert out["search"]["starts"] == 1
    assert out["roundoff"]["samples"] == 8  # the default: the run's own scatter, measured at the end point
    # The default grid check: the objective rebuilt at 1.5 dx, two draws there (no interval to add it to).
    assert out["grid"]["ratio"] == 1.5 and out["grid"]["draws"] == 2 and set(out["grid"]["shift"]) == {"beta", "mu1"}
    # One profile: the loss is the mean squared misfit relative to the data's peak, so the RMS in metres
    # is its root times that peak.
    from calibration import load_profile

    peak = float(np.max(load_profile(S4).h))
    assert out["residual_rms_m"] == pytest.approx(np.sqrt(out["loss"]) * peak, rel=1e-5)
    assert out["residual_rms_m_by_block"] == {"profile": pytest.approx(out["residual_rms_m"])}
    assert (tmp_path / "fit.h5").exists()
    for fig in out["figures"]:
        assert pathlib.Path(fig).stat().st_size > 5_000


@pytest.mark.slow  # 19 s; the WebPlotDigitizer reader and its units are tested by default in tests/test_data.py
def test_fit_reads_a_webplotdigitizer_export_with_units(capsys, tmp_path):
    code, out = run(capsys, "fit", "--scene", "cohesive-collapse", "--data", WPD, "--units", "mm", "--t-end",
                    "0.5", "--fit", "mu1", "--steps", "1", "--starts", "2", "--roundoff-samples", "0",
                    "--out", str(tmp_path / "fit.h5"), *TINY)
    assert code == 0 and set(out["params"]) == {"mu1"}
    # Without --init the fit is a global search (here of two starts, one iteration each).
    assert out["method"] == "lm-search" and out["search"]["starts"] == 2 and out["search"]["minima"]
    # One iteration is no verified minimum: no interval, and no profile likelihood around it either.
    code, out = run(capsys, "posterior", str(tmp_path / "fit.h5"), "--profiles", "5", "--json")
    assert "profile_likelihood" not in out and "not a fit of the data" in out["profile_likelihood_skipped"]


# 23 s: a fit and the posterior's model-error runs; the posterior command's round trip and its
# input errors stay in the default suite.
@pytest.mark.slow
def test_the_posterior_checks_measure_the_model_error(capsys, tmp_path):
    """posterior builds the fit's objective again from its file and measures the model's own error
    at its point (--model-error draws, coarse runs on a grid 1.5 times coarser, also with the
    fit's own grid check off) and adds it to the data's noise; the check itself is skipped here
    (one iteration is no fit), the likelihood it would use is reported."""
    fit = str(tmp_path / "fit.h5")
    code, out = run(capsys, "fit", "--scene", "cohesive-collapse", "--data", S4, "--t-end", "0.5", "--fit", "mu1",
                    "--init", "mu1=0.4", "--steps", "1", "--roundoff-samples", "0", "--noise", "0.02",
                    "--grid-check", "0", "--out", fit, *TINY)
    assert code == 0 and out["out"] == fit
    code, out = run(capsys, "posterior", fit, "--noise", "0.02", "--profiles", "3", "--model-error", "2", "--json")
    assert code == 0 and "profile_likelihood_skipped" in out and out["params"] == {"mu1": pytest.approx(0.4)}
    error = out["model_error"]
    assert error["draws"] == 3 and error["coarse_draws"] == 2 and error["ratio"] == 1.5
    assert error["draw"]["profile"] > 0 and error["grid"]["profile"] >= 0
    assert out["posterior_noise"]["profile"] == pytest.approx(np.hypot(0.02, error["total"]["profile"]))


@pytest.mark.parametrize("argv, message", [
    (["--fit", "beta,friction"], "keys: unknown parameter"),
    (["--fit", "beta", "--init", "beta=2"], "init: beta = 2.0 must lie strictly inside"),
    (["--fit", "beta", "--resume"], "--resume needs --out"),
    (["--fit", "beta", "--steps", "0"], "--steps must be >= 1"),
    (["--fit", "beta", "--init", "beta"], "--init expects key=value"),
])
def test_fit_input_errors_name_the_argument(capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--scene", "cohesive-collapse", "--data", S4, *argv, *TINY])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--nuts", "2"], "--nuts must be 0 (off) or >= 4"),
    (["--nuts", "8", "--chains", "0"], "--chains must be >= 1"),
    (["--emulated", "5"], "--emulated must be 0 (off) or >= 30"),
    (["--emulated", "40", "--chains", "1"], "--chains must be >= 2 with emulated"),
    (["--profiles", "5", "--model-error", "1"], "--model-error must be 0 (off) or >= 2"),
    (["--profiles", "5", "--model-error", "-3"], "--model-error must be 0 (off) or >= 2"),
    (["--emulated", "40", "--prior", "beta=0.2"], "--prior expects KEY=MEAN:SD"),
    (["--emulated", "40", "--prior", "beta=0.2:0"], "--prior expects KEY=MEAN:SD"),
    (["--emulated", "40", "--prior", "beta=0.2:0.1", "--prior", "beta=0.3:0.1"], "--prior beta is given twice"),
    (["--profiles", "5", "--prior", "beta=0.2:0.1"], "--prior enters the posteriors of nuts and emulated"),
    (["--emulated", "40", "--prior", "I0=0.3:0.1"], "--prior: ['I0'] not among the fitted keys"),
    ([], "ask for a check: --profiles, --posterior, --nuts or --emulated"),
])
def test_posterior_input_errors_name_the_argument(capsys, documented_fit, argv, message):
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["posterior", str(documented_fit[2] / "fit.h5"), *argv])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_posterior_refuses_a_file_that_is_no_fit(capsys, tmp_path):
    for name, text in (("missing.h5", None), ("empty.h5", "")):
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(SystemExit) as exc:
            main(["posterior", str(tmp_path / name), "--profiles", "3"])
        assert exc.value.code == 2 and "FIT.h5:" in capsys.readouterr().err


def test_fit_without_data_is_an_error(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--scene", "cohesive-collapse", "--fit", "beta", *TINY])
    assert "--data" in capsys.readouterr().err


def test_fit_rejects_a_file_without_units(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--scene", "cohesive-collapse", "--data", WPD, "--fit", "beta", *TINY])
    assert "units" in capsys.readouterr().err


def test_sweep_grid_json_and_landscape(capsys, tmp_path):
    code, out = run(capsys, "sweep", "--scene", "cohesive-collapse", "--data", S4, "--over", "beta=0.1:0.3:2",
                    "--over", "mu1=0.35:0.45:2", "--plot", str(tmp_path), "--out", str(tmp_path / "s.h5"), *TINY)
    assert code == 0
    assert len(out["loss"]) == 4 and out["failed"] == []
    assert pathlib.Path(out["figures"][0]).stat().st_size > 5_000


@pytest.mark.slow  # 30 s on 2 cores; the CLI's fit runs are tested by default
def test_twin_recovers_the_constrained_parameters(capsys):
    """A tiny twin (dx = L/6): the parameters the analysis calls constrained come back within
    2 % (the issue's criterion; in fact all of them, to ~1e-3)."""
    # An interval needs a verified minimum. In float64 LM verifies this one after 8 iterations; in
    # float32 it can end on 6 rejected steps at the round-off floor (loss ~1e-12): no interval then.
    code, out = run(capsys, "twin", "--fit", "beta,mu1", "--steps", "12", "--dtype", "float64", "--roundoff-samples",
                    "0", *TINY)
    assert code == 0
    assert out["verdict"]["is_fit"] and out["converged"], out["verdict"]
    for key in ("params", "stderr", "loss", "iterations", "wall_s", "true", "rel_error", "constrained"):
        assert key in out, key
    for key in out["constrained"]:
        assert abs(out["rel_error"][key]) < 0.02, (key, out["rel_error"])
    assert max(abs(v) for v in out["rel_error"].values()) < 0.02


@pytest.mark.slow
def test_twin_quick_with_noise_intervals_contain_the_truth(capsys):
    code, out = run(capsys, "twin", "--quick", "--noise", "0.02", "--no-progress", "--json")
    assert code == 0
    assert all(out["in_ci95"].values()), out["ci95"]


@pytest.mark.slow  # 160 s; the library's emulated posterior is tested by default (test_emulator.py, test_likelihood.py)
def test_fit_emulated_posterior_where_the_verdict_refuses_an_interval(capsys, tmp_path):
    """One iteration is no verified minimum, so Gauss–Newton gives no interval; --emulated samples
    the posterior anyway, around the point with the estimated noise, and reports its diagnostics
    (whether it converged is the diagnostics' verdict, which the JSON states)."""
    fit = str(tmp_path / "fit.h5")
    code, out = run(capsys, "fit", "--scene", "cohesive-collapse", "--data", S4, "--t-end", "0.5", "--fit", "mu1",
                    "--init", "mu1=0.4", "--steps", "1", "--roundoff-samples", "0", "--grid-check", "0", "--out", fit,
                    *TINY)
    assert code == 0 and not out["verdict"]["is_fit"]
    code, out = run(capsys, "posterior", fit, "--grid-check", "0", "--emulated", "30", "--chains", "2", "--plot",
                    str(tmp_path / "figs"), "--json")
    assert code == 0
    assert [pathlib.Path(f).name for f in out["figures"]] == ["posterior_emulated.png"]  # --plot drew nothing before
    em = out["emulated_posterior"]
    assert em["keys"] == ["mu1"] and em["model_runs"] == 30 and em["model_jacobians"] == 4 + 3 * (len(em["rounds"]) - 1)
    assert em["failed_checks"] == 0 and np.isfinite(em["pareto_k"]) and em["ess_importance"] > 0
    # 30 checks leave fewer than 100 effective draws: reported, and never called converged.
    assert em["ess_importance"] <= 30 and not em["converged"]
    lo, hi = em["ci95"]["mu1"]
    assert lo < em["mean"]["mu1"] < hi and em["sd"]["mu1"] > 0
    assert em["converged"] == (em["emulated"]["converged"] and em["pareto_k"] < 0.7 and em["ess_importance"] >= 100)


@pytest.mark.slow  # 90 s; the library's checks beyond Gauss-Newton are tested by default (test_likelihood.py)
def test_fit_with_profiles_and_posterior_draws_them(capsys, tmp_path):
    """A tiny twin file (dx = L/6, 0.3 s, 1 % noise) fitted for mu1 with --profiles, --posterior
    and --nuts: the profile interval and the posteriors' sd agree with Gauss–Newton on this
    near-linear fit."""
    from jaxmpm.__main__ import main as run_main

    profile = tmp_path / "p.csv"
    assert run_main(["run", "cohesive-collapse", "--dx", str(TINY_DX), "--set", "beta=0.25", "--t-end", "0.3",
                     "--profile-csv", str(profile), "--no-progress", "--json"]) == 0
    capsys.readouterr()
    from calibration import load_profile

    data = load_profile(profile)
    noisy = np.maximum(data.h + 0.01 * data.h.max() * np.random.default_rng(1).standard_normal(data.h.shape), 0)
    lines = [line for line in profile.read_text().splitlines() if line.startswith("#")]
    profile.write_text("\n".join(lines + ["x_m,h_m"] + [f"{a:.6e},{b:.6e}" for a, b in zip(data.x, noisy)]) + "\n")
    fit = str(tmp_path / "fit.h5")
    code, fitted = run(capsys, "fit", "--scene", "cohesive-collapse", "--data", str(profile), "--fit", "mu1",
                       "--set", "beta=0.25", "--init", "mu1=0.4", "--steps", "8", "--roundoff-samples", "0",
                       "--grid-check", "0", "--out", fit, *TINY)
    assert code == 0 and fitted["verdict"]["is_fit"]
    code, out = run(capsys, "posterior", fit, "--grid-check", "0", "--model-error", "0", "--profiles", "5",
                    "--posterior", "7", "--nuts", "40", "--chains", "2", "--plot", str(tmp_path / "figs"), "--json")
    assert code == 0
    assert out["nuts"]["chains"] == 2 and out["nuts"]["draws_per_chain"] == 40 and "draws" not in out["nuts"]
    # The CLI's plumbing: 2 chains of 40 draws establish no convergence (R-hat 1.17 here, reported
    # as such); the sampler's mixing is tested on exact targets in tests/test_mcmc.py.
    assert 0.6 < out["nuts"]["sd_over_gauss_newton"]["mu1"] < 1.5
    assert np.isfinite(out["nuts"]["rhat"]["mu1"]) and out["nuts"]["ess_bulk"]["mu1"] > 0
    assert out["nuts"]["converged"] == (out["nuts"]["rhat"]["mu1"] < 1.01 and out["nuts"]["ess_bulk"]["mu1"] >= 100
                                        and sum(out["nuts"]["divergences"]) == 0)
    lo, hi = out["profile_likelihood"]["mu1"]["ci95_profile"]
    gn_lo, gn_hi = fitted["ci95"]["mu1"]
    assert 0.7 < (hi - lo) / (gn_hi - gn_lo) < 1.4
    assert 0.7 < out["posterior"]["sd_over_gauss_newton"]["mu1"] < 1.4
    assert [pathlib.Path(f).name for f in out["figures"]] == ["fit_likelihood.png", "posterior_nuts.png"]
    assert all(pathlib.Path(f).stat().st_size > 0 for f in out["figures"])


@pytest.mark.slow  # four compilations of a tiny run (30-60 s)
def test_bench_prints_compile_apart_from_run_for_every_measure(capsys):
    from calibration.studies.bench import MEASURES

    code, out = run(capsys, "bench", "--quick", "--fit", "mu1", "--repeat", "1", "--json")
    assert code == 0 and out["keys"] == ["mu1"] and out["n_params"] == 1
    for name in MEASURES:
        assert out[name]["run_s"] > 0 and out[name]["compile_s"] >= 0, name
    assert out["particle_steps_per_s_forward"] > 0 and out["peak_rss_mb"] > 0
