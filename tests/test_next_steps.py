"""What a fit's JSON says to run next (``calibration.optim.report.next_steps``): one line per
reason the verdict or the interval gives, none for a usable answer."""

from types import SimpleNamespace

from calibration.inference.verdict import broken_relations
from calibration.optim.report import next_steps


def _result(reasons=(), at_bound=(), grid_converged=None, iterations=25):
    verdict = SimpleNamespace(reasons=tuple(reasons), at_bound=tuple(at_bound))
    return SimpleNamespace(verdict=verdict, uncertainty=SimpleNamespace(grid_converged=grid_converged),
                           iterations=iterations)


def test_a_fit_of_the_data_converged_in_the_grid_needs_nothing_next():
    assert next_steps(_result(grid_converged=True)) == []
    assert next_steps(_result(grid_converged=None)) == []
    assert next_steps(SimpleNamespace(verdict=None, uncertainty=None, iterations=3)) == []


def test_each_reason_has_its_next_step():
    stopped = ("not a verified minimum (stopped after 25 iterations (steps = 25); the remaining Gauss–Newton "
               "step is 3.9e+03 standard deviations of the run's round-off scatter, beyond 3.4)")
    misfit = "profile misfit well above the noise (rms 0.0149 against σ 0.0041 estimated; χ² 2.39e+03 > 467)"
    advice = next_steps(_result([stopped, misfit]))
    assert len(advice) == 2
    assert "--resume --steps 50" in advice[0] and "side walls" in advice[1]
    rough = "not a verified minimum (stopped: 6 rejected steps in a row (no decrease within the runs' round-off))"
    assert "--profiles 9" in next_steps(_result([rough]))[0]
    bound = next_steps(_result(["beta at a bound (the misfit falls towards or beyond the physical range)"],
                               at_bound=["beta"]))
    assert bound[0].startswith("beta ended at a bound")
    rule = broken_relations(("mu1", "mu2"), [0.61, 0.16])  # the verdict's own words
    assert "mu2 below mu1" in next_steps(_result(rule))[0]
    assert "--dx" in next_steps(_result(grid_converged=False))[0]
