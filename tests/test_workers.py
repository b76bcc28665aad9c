"""Worker processes (calibration.batch.workers): the runs and the Jacobian columns (slow) they compute
are the calling process's, bit for bit, whatever the number of workers; a fit and a search that
spread their runs over two workers follow the single-process path to round-off (slow); bad input
and failing tasks are reported."""

import numpy as np
import pytest
from helpers import model_data, tiny_s4

from calibration.batch.workers import Workers, as_workers, jacobians_z, residuals_at
from calibration.optim.fit import fit
from calibration.optim.search import search
from calibration.problem.objective import Objective
from jaxmpm.scenes import S4_SIDE

KEYS = ("beta", "mu1")
TRUTH = np.array([0.2, 0.4])


@pytest.fixture(scope="module")
def objective():
    scene = tiny_s4(beta=0.0, dx=S4_SIDE / 4)
    profile, _ = model_data(scene, KEYS, TRUTH, xs=np.linspace(0.0, 0.2, 25))
    return Objective(scene, KEYS, profile=profile)


@pytest.fixture(scope="module")
def pool():
    with Workers(2) as workers:
        yield workers


def _rows(objective):
    return np.stack([objective.bounds.to_unconstrained(np.array(t)) for t in ([0.1, 0.3], [0.3, 0.45], [0.25, 0.35])])


def test_runs_in_workers_equal_the_calling_process_bit_for_bit(objective, pool):
    # Runs, with the scene's particles and with other draws of them.
    thetas = np.array([[0.1, 0.3], [0.2, 0.4]])
    a, b = residuals_at(objective, thetas, Workers(1), seeds=[3, 4]), residuals_at(objective, thetas, pool, [3, 4])
    for (ra, _), (rb, _) in zip(a, b):
        np.testing.assert_array_equal(ra, rb)
    np.testing.assert_array_equal(residuals_at(objective, thetas[:1], pool)[0][0],
                                  np.asarray(objective.residuals(thetas[0])[0]))


@pytest.mark.slow  # 60 s on two cores, compiling the forward-mode columns in every process
def test_jacobian_columns_in_workers_equal_the_calling_process_bit_for_bit(objective, pool):
    Z = _rows(objective)[:2]
    here = jacobians_z(objective, Z, Workers(1))
    there = jacobians_z(objective, Z, pool)
    np.testing.assert_array_equal(there[0], here[0])
    np.testing.assert_array_equal(there[1], here[1])
    np.testing.assert_array_equal(there[2], here[2])
    np.testing.assert_array_equal(there[3]["h"], here[3]["h"])


@pytest.mark.slow  # 60 s on two cores, compiling the forward-mode columns in every process
def test_rows_without_their_jacobian_are_one_run_each_in_the_same_spread(objective, pool):
    """LM's Broyden trials (``jacobian`` mask): the rows outside the mask are the plain runs in the
    workers, their Jacobians NaN; the rows inside it are the full columns."""
    Z = _rows(objective)[:2]
    mixed = jacobians_z(objective, Z, pool, jacobian=[False, True])
    full = jacobians_z(objective, Z, pool)
    np.testing.assert_array_equal(mixed[0][0], residuals_at(objective, objective.bounds.to_physical(Z[:1]), pool)[0][0])
    assert np.all(np.isnan(mixed[1][0])) and np.all(np.isnan(mixed[2][0]))
    for a, b in zip(mixed[:3], full[:3]):
        np.testing.assert_array_equal(a[1], b[1])


@pytest.mark.slow  # 45-90 s on two cores; the runs they are made of are checked bit for bit above
def test_a_fit_and_a_search_in_workers_follow_the_single_process(objective, pool):
    # The columns the workers compute are the objective's own Jacobian (all columns in one
    # compiled lax.map), to round-off.
    Z = _rows(objective)
    here = jacobians_z(objective, Z[1:2], pool)
    r, Jz, _, _ = objective.residuals_and_jacobian_z(Z[1])
    np.testing.assert_allclose(here[1][0], Jz, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(here[0][0], r, rtol=1e-12, atol=1e-15)
    one = fit(objective, {"beta": 0.1, "mu1": 0.3}, steps=4, roundoff_samples=2)
    two = fit(objective, {"beta": 0.1, "mu1": 0.3}, steps=4, roundoff_samples=2, workers=pool)
    assert one.iterations == two.iterations
    np.testing.assert_allclose(two.history["theta"], one.history["theta"], rtol=1e-9)
    assert one.verdict.scatter is not None and two.verdict.scatter is not None
    found = search(objective, 2, steps=3, roundoff_samples=0, uncertainty=False, workers=pool)
    alone = search(objective, 2, steps=3, roundoff_samples=0, uncertainty=False)
    np.testing.assert_allclose(found.best.history["theta"], alone.best.history["theta"], rtol=1e-9)
    assert found.iterations == alone.iterations


def test_bad_input_and_failing_tasks_are_reported(pool):
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="workers must be an integer >= 1"):
            Workers(bad)
    assert as_workers(None).n == 1 and as_workers(pool) is pool and as_workers(3).n == 3
    with pytest.raises(ZeroDivisionError):
        pool.map(divmod, [(1, 0), (4, 2)])
    assert pool.map(divmod, [(7, 2), (9, 4)]) == [(3, 1), (2, 1)]
