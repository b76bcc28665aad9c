"""What a fit's JSON says to run next (``calibration.optim.report.next_steps``): one line per
reason the verdict or the interval gives, none for a usable answer."""

from types import SimpleNamespace

from calibration.optim.report import next_steps


def _result(message="converged", verified=True, misfit=False, at_bound=(), theta=None, grid_converged=None,
            iterations=25, probe=None):
    verdict = SimpleNamespace(verified=verified, at_bound=tuple(at_bound), chi2={"profile": 600.0 if misfit else 9.0},
                              chi2_limit={"profile": 467.0}, probe=probe)
    theta = theta or {"mu1": 0.38, "mu2": 0.64}
    return SimpleNamespace(verdict=verdict, uncertainty=SimpleNamespace(grid_converged=grid_converged),
                           iterations=iterations, message=message, keys=tuple(theta), theta=theta)


def test_a_fit_of_the_data_converged_in_the_grid_needs_nothing_next():
    assert next_steps(_result(grid_converged=True)) == []
    assert next_steps(_result(grid_converged=None)) == []
    assert next_steps(SimpleNamespace(verdict=None, uncertainty=None, iterations=3, message="")) == []


def test_each_reason_has_its_next_step():
    advice = next_steps(_result("stopped after 25 iterations (steps = 25)", verified=False, misfit=True))
    assert len(advice) == 2
    assert "--resume --steps 50" in advice[0] and "side walls" in advice[1]
    rough = "stopped: 6 rejected steps in a row (no decrease within the runs' round-off and scatter)"
    assert "--profiles 9" in next_steps(_result(rough, verified=False))[0]
    bound = next_steps(_result(at_bound=["beta"], theta={"beta": 0.0, "mu1": 0.4}))
    assert bound[0].startswith("beta ended at a bound")
    assert "mu2 below mu1" in next_steps(_result(theta={"mu1": 0.61, "mu2": 0.16}))[0]
    assert "--dx" in next_steps(_result(grid_converged=False))[0]
    lower = SimpleNamespace(passed=False, lowest=[0.3246, 0.64])
    assert "--init mu1=0.3246 --init mu2=0.64" in next_steps(_result(probe=lower))[0]
    assert next_steps(_result(probe=SimpleNamespace(passed=True, lowest=[0.38, 0.64]))) == []
