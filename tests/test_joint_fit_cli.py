"""``python -m calibration fit COLLAPSE.toml INCLINE.toml --shared mu1,mu2,I0``: an incline
experiment file is one of fit's experiment files (docs/incline_fits.md). Its setup is read,
merged and recorded without a run; the options and key sets it cannot take are refused naming
them; and the joint fit runs from the command line, with posterior building it again."""

import json
import re
import shutil

import numpy as np
import pytest
from helpers import ROOT, TINY_DX, call_main, main_exit, strict_json

from calibration.cli.commands import main
from calibration.data.incline import InclineExperiment, incline_from_text, load_incline
from calibration.problem.build import FitSetup
from calibration.problem.composite import CompositeObjective
from calibration.problem.flow_rule import FlowRuleObjective

TWIN = ROOT / "experiments_data" / "synthetic" / "flow_rule_twin"
KEYS = "beta,mu1,mu2,I0"
INIT = ("--init", "beta=0.2", "--init", "mu1=0.36", "--init", "mu2=0.75", "--init", "I0=0.5")
QUICK = ("--steps", "1", "--roundoff-samples", "0", "--grid-check", "0", "--workers", "1", "--no-progress", "--json")


@pytest.fixture
def files(tmp_path):
    """A tiny S4 collapse (dx = L/6, 0.05 s, one profile) and the flow-rule twin's incline file,
    side by side: (collapse.toml, incline.toml)."""
    text = (ROOT / "experiments_data" / "experiments" / "S4_cohesive_collapse.toml").read_text()
    for key, value in (("dx", TINY_DX), ("t_end", 0.05), ("beta", 0.25)):
        text = re.sub(rf"\n{key} = .*", f"\n{key} = {value}", text)
    collapse = tmp_path / "collapse.toml"
    collapse.write_text(text + '\n[[profile]]\nfile = "deposit.csv"\n')
    (tmp_path / "deposit.csv").write_text("# units: m\n# time_s: 0.05\nx_m,h_m\n0,0.085\n0.05,0.07\n0.1,0.03\n"
                                          "0.14,0\n")
    shutil.copy(TWIN.with_suffix(".csv"), tmp_path)
    shutil.copy(TWIN.with_suffix(".toml"), tmp_path / "incline.toml")
    return collapse, tmp_path / "incline.toml"


def parsed(*argv):
    from calibration.cli.parser import build_parser

    return build_parser().parse_args(["fit", *map(str, argv)])


def test_an_incline_file_is_read_merged_and_recorded_among_the_experiments(files, tmp_path):
    from calibration.cli.args import experiments_of, fit_request, setup_of

    collapse, incline = files
    args = parsed(collapse, incline, "--fit", KEYS, "--shared", "mu1,mu2,I0", "--dx", 0.02)
    experiments = experiments_of(args)
    assert isinstance(experiments[1], InclineExperiment) and experiments[1] == load_incline(incline)
    assert experiments[0].builder_arguments()["dx"] == 0.02  # the scene options apply to the collapse
    # Without --init, the incline's [fit] init starts the keys it fits (the collapse has no [fit]).
    request = fit_request(args, experiments)
    assert request.keys == tuple(KEYS.split(",")) and request.init == {"mu1": 0.3, "mu2": 0.9, "I0": 0.8}
    setup = setup_of(parsed(collapse, incline, "--fit", KEYS, "--shared", "mu1,mu2,I0"), request.keys)
    objective = setup.objective()
    assert isinstance(objective, CompositeObjective) and objective.keys == ("mu1", "mu2", "I0", "beta@collapse")
    member = objective.members[1]
    assert isinstance(member, FlowRuleObjective) and member.keys == ("mu1", "mu2", "I0")
    assert member.material["d"] == pytest.approx(0.7e-3) and np.dtype(member.dtype) == np.float32
    # The record: the incline's file text and path; the objective built again is the same.
    record = json.loads(json.dumps(setup.to_json()))
    assert record["experiments"][1] == {"kind": "incline", "toml": incline.read_text(), "path": str(incline)}
    again = FitSetup.from_json(record)
    assert again == setup and again.experiments[1].table_file == tmp_path / "flow_rule_twin.csv"
    assert again.objective().fingerprint() == objective.fingerprint()
    assert incline_from_text(incline.read_text(), check_files=False).path is None


def test_the_collapse_and_incline_fit_tables_merge_as_two_collapses_do(files):
    from calibration.cli.args import experiments_of, fit_request

    collapse, incline = files
    collapse.write_text(collapse.read_text() + '\n[fit]\nkeys = ["beta", "mu1"]\n')
    with pytest.raises(ValueError, match=r"--fit differs between the experiment files' \[fit\] tables"):
        fit_request(parsed(collapse, incline), experiments_of(parsed(collapse, incline)))
    # Their starts differ too (the collapse states none): --init overrules them, as for two collapses.
    with pytest.raises(ValueError, match=r"--init differs between the experiment files' \[fit\] tables"):
        fit_request(parsed(collapse, incline, "--fit", "beta,mu1"), experiments_of(parsed(collapse, incline)))
    request = fit_request(parsed(collapse, incline, "--fit", "beta,mu1", "--init", "mu1=0.4"),
                          experiments_of(parsed(collapse, incline)))
    assert request.keys == ("beta", "mu1") and request.init == {"mu1": 0.4}


@pytest.mark.parametrize("argv, message", [
    # A key set the incline cannot fit: it fits among mu1, mu2, I0 only.
    (["--fit", "beta,xi"], "incline.toml: an incline's flow rule fits only mu1, mu2, I0; it cannot fit beta, xi"),
    # Alone, every fitted key must be one of its own.
    (["--fit", "beta,mu1", "ALONE"], "incline.toml: an incline's flow rule fits only mu1, mu2, I0; it cannot fit beta"),
    # Without --shared, the members must fit the same keys (the composite's check).
    (["--fit", KEYS], "say which keys are shared (shared=, --shared)"),
    # --shared keys every member fits (the composite's check).
    (["--fit", "beta,mu1", "--shared", "beta"], "shared: ['beta'] are not fitted by members[1] (incline"),
    (["--fit", "mu1", "--data", "DEPOSIT", "ALONE"], "--data applies to a collapse; ")
])
def test_what_an_incline_cannot_take_is_refused_naming_it(files, capsys, argv, message):
    collapse, incline = files
    argv = [str(collapse.with_name("deposit.csv")) if a == "DEPOSIT" else a for a in argv]
    paths = [incline] if "ALONE" in argv else [collapse, incline]
    code, err = main_exit("calibration", ["fit", *paths, *[a for a in argv if a != "ALONE"], *QUICK], capsys)
    assert code == 2 and message in err, err


@pytest.mark.slow  # ~25 s on two busy cores: a one-step joint fit (its compile) and posterior rebuilding it;
# the setup, its record and the refusals above run by default
def test_the_joint_fit_runs_from_the_command_line_and_posterior_builds_it_again(files, tmp_path):
    collapse, incline = files
    out = tmp_path / "fit.h5"
    code, stdout, stderr = call_main(main, ["fit", collapse, incline, "--fit", KEYS, "--shared", "mu1,mu2,I0",
                                            *INIT, "--out", out, *QUICK])
    assert code in (0, 1), stderr  # 1: a number in the report is not finite after one step
    report = strict_json(stdout) if code == 0 else json.loads(stdout)
    assert set(report["params"]) == {"mu1", "mu2", "I0", "beta@collapse"}
    assert report["start"] == pytest.approx({"beta@collapse": 0.2, "mu1": 0.36, "mu2": 0.75, "I0": 0.5})
    assert report["experiments"] == [str(collapse), str(incline)] and report["iterations"] == 1
    assert set(report["verdict"]["noise"]) == {"collapse/profile", "incline/velocity"}
    code, stdout, stderr = call_main(main, ["posterior", out, "--profiles", "3", "--noise", "0.02",
                                            "--model-error", "0", "--workers", "1", "--json"])
    assert code == 0, stderr
    posterior = json.loads(stdout)
    assert posterior["params"] == pytest.approx(report["params"]) and "profile_likelihood_skipped" in posterior
