"""Sweeps: grid and Latin-hypercube points, and the same numbers looped, vmapped, chunked and
sharded over 4 CPU devices, with failed members reported and the others untouched.

Equality: XLA's CPU backend may order a batched reduction differently from the unbatched one
(its YNNPACK reduce fusion), so results compiled for different batch shapes agree to the last
few bits only (measured: residuals 4e-16 apart, losses 2e-15 relative); those comparisons
use rtol 1e-12. Results from one compiled shape are compared bitwise.
"""

import json
import os
import pathlib
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import tiny_s4

import jaxmpm
from calibration.batch.sweep import SweepResult, grid_points, latin_hypercube, sweep
from calibration.problem.objective import Objective
from calibration.problem.targets import FrontTarget, ProfileTarget

RTOL = 1e-12
#: (beta, E): member 1 runs out of its step budget (E = 1e8 needs 10x more steps than the
#: scene's budget, set for E = 1e6: BUDGET) and member 3 blows up (E < 0: NONFINITE). E < 0 is
#: not a valid parameter set, which ``sweep`` refuses by default; these sweeps pass
#: ``validate=False`` to exercise how a member that fails inside the run is reported.
THETAS = np.array([[0.10, 1.0e6], [0.25, 1.0e8], [0.40, 1.0e6], [0.30, -1.0e6], [0.20, 1.2e6]])
FAILED = [1, 3]


def make_objective():
    """A tiny cohesive collapse (144 particles, 0.05 s, about 230 steps) against made-up data."""
    scene = tiny_s4(t_end=0.05)
    x = np.linspace(0.01, 0.15, 8)
    h = np.maximum(0.089 * (1.0 - x / 0.15), 0.0) + 1e-3
    return Objective(scene, ["beta", "E"], profile=ProfileTarget(x, h, None),
                     front=FrontTarget(np.array([0.025, 0.05]), np.array([0.10, 0.11])))


class ToyObjective:
    """A closed-form stand-in for an ``Objective`` (compiles in milliseconds): member fails
    with a status bit when a > 10, and with a non-finite residual but no bit when b < 0."""

    keys = ("a", "b")
    dtype = jnp.float64

    def residual_fn(self, theta):
        a, b = theta[0], theta[1]
        k = jnp.arange(6, dtype=theta.dtype)
        r = jnp.sin(a * k) + jnp.sqrt(b) * jnp.cos(k) - 0.5
        status = jnp.where(a > 10.0, jaxmpm.NONFINITE, 0)
        return r, {"status": status, "mean": jnp.mean(r)}

    def check_thetas(self, thetas, name="thetas"):
        """Every row is a parameter set of the toy."""

    def fingerprint(self):
        return {"toy": "sin(a k) + sqrt(b) cos(k) - 1/2"}

    def describe(self):
        return {"toy": "sin"}


@pytest.fixture(scope="module")
def objective():
    return make_objective()


@pytest.fixture(scope="module")
def looped(objective):
    return sweep(objective, THETAS, mode="loop", validate=False)


@pytest.fixture(scope="module")
def vmapped(objective):
    return sweep(objective, THETAS, mode="vmap", chunk=len(THETAS), validate=False)


def assert_same_members(result: SweepResult, reference: SweepResult, exact: bool = False):
    """Same failures and statuses; successful members' loss and residuals equal (bitwise if
    ``exact``, else to RTOL)."""
    np.testing.assert_array_equal(result.failed, reference.failed)
    np.testing.assert_array_equal(result.status, reference.status)
    ok = reference.ok
    assert np.all(np.isnan(result.loss[~ok]))
    check = np.testing.assert_array_equal if exact else (
        lambda a, b: np.testing.assert_allclose(a, b, rtol=RTOL, atol=RTOL * np.max(np.abs(b))))
    check(result.loss[ok], reference.loss[ok])
    check(result.residuals[ok], reference.residuals[ok])


# ---- points -----------------------------------------------------------------------------------
def test_grid_points_is_the_cartesian_product():
    keys, th = grid_points({"mu1": (0.2, 0.6), "beta": (0.0, 0.5)}, {"mu1": 3, "beta": 4})
    assert keys == ("mu1", "beta") and th.shape == (12, 2)
    np.testing.assert_array_equal(np.unique(th[:, 0]), np.linspace(0.2, 0.6, 3))
    np.testing.assert_array_equal(np.unique(th[:, 1]), np.linspace(0.0, 0.5, 4))
    np.testing.assert_array_equal(th[:4, 1], np.linspace(0.0, 0.5, 4))  # last key fastest
    assert len({tuple(row) for row in th}) == 12
    keys, th2 = grid_points({"mu1": (0.2, 0.6), "beta": (0.0, 0.5)}, 3, keys=("beta", "mu1"))
    assert keys == ("beta", "mu1") and th2.shape == (9, 2)


def test_latin_hypercube_has_one_point_per_stratum():
    ranges = {"beta": (0.0, 1.0), "mu1": (0.1, 0.9), "xi": (10.0, 500.0)}
    n = 17
    keys, th = latin_hypercube(ranges, n, seed=3)
    assert keys == tuple(ranges) and th.shape == (n, 3)
    lo, hi = np.array([r[0] for r in ranges.values()]), np.array([r[1] for r in ranges.values()])
    assert np.all(th >= lo) and np.all(th < hi)
    strata = np.floor((th - lo) / (hi - lo) * n).astype(int)
    for axis in range(3):
        np.testing.assert_array_equal(np.sort(strata[:, axis]), np.arange(n))
    np.testing.assert_array_equal(latin_hypercube(ranges, n, seed=3)[1], th)
    assert not np.array_equal(latin_hypercube(ranges, n, seed=4)[1], th)
    assert latin_hypercube(ranges, 1)[1].shape == (1, 3)


@pytest.mark.parametrize("call, match", [
    (lambda: grid_points({"beta": (0.5, 0.1)}, 3), "ranges\\['beta'\\]"),
    (lambda: grid_points({"beta": (0.0, np.inf)}, 3), "ranges\\['beta'\\]"),
    (lambda: grid_points({}, 3), "ranges"),
    (lambda: grid_points({"beta": (0.0, 1.0)}, 0), "num"),
    (lambda: grid_points({"beta": (0.0, 1.0)}, {"mu1": 3}), "num"),
    (lambda: grid_points({"beta": (0.0, 1.0)}, 3, keys=("mu1",)), "keys"),
    (lambda: latin_hypercube({"beta": (0.0, 1.0)}, 0), "n must"),
    (lambda: latin_hypercube({"beta": (0.0, 1.0)}, 2.5), "n must"),
    (lambda: latin_hypercube({"beta": (0.0, 1.0)}, 4, seed=-1), "seed"),
    (lambda: sweep(ToyObjective(), np.ones((3, 3))), "thetas"),
    (lambda: sweep(ToyObjective(), np.array([[1.0, np.nan]])), "thetas"),
    (lambda: sweep(ToyObjective(), (("a", "c"), np.ones((2, 2)))), "thetas"),
    (lambda: sweep(ToyObjective(), np.ones((2, 2)), mode="pmap"), "mode"),
    (lambda: sweep(ToyObjective(), np.ones((2, 2)), chunk=0), "chunk"),
    (lambda: sweep(ToyObjective(), np.ones((2, 2)), memory_budget_bytes=-1), "memory_budget_bytes"),
])
def test_input_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ---- the collapse objective: loop, vmap, chunks, failures -------------------------------------
def test_vmap_matches_loop(vmapped, looped):
    assert vmapped.mode == "vmap" and vmapped.chunk == 5 and looped.chunk == 1
    assert_same_members(vmapped, looped)
    for name in ("h", "front"):
        np.testing.assert_allclose(vmapped.predictions[name][looped.ok], looped.predictions[name][looped.ok],
                                   rtol=RTOL, atol=1e-15)


def test_invalid_members_are_refused_before_anything_compiles(objective):
    """By default every member is checked with the engine's rules (E > 0, beta >= 0, mu2 >= mu1, ...)
    and the sweep refuses, naming the member, before compiling: a member with beta < 0 would run and
    could be reported as the best."""
    with pytest.raises(ValueError, match=r"thetas: 1 of 5 members are not a valid parameter set: member 3 "
                                         r"\(beta = 0.3, E = -1e\+06\): E must be > 0"):
        sweep(objective, THETAS)
    with pytest.raises(ValueError, match=r"member 0 \(beta = -0.2, E = 1e\+06\): beta must be >= 0"):
        sweep(objective, np.array([[-0.2, 1e6], [0.2, 1e6]]))


# 12 s: another chunk shape compiled; padding and chunking are checked by default on the toy objective
@pytest.mark.slow  # (test_toy_sweep_all_modes_and_failures)
def test_chunks_with_a_padded_last_chunk_match_one_chunk(objective, vmapped):
    chunked = sweep(objective, THETAS, mode="vmap", chunk=2, validate=False)  # chunks of 2, 2, 1 (+1 padding)
    assert chunked.chunk == 2 and chunked.residuals.shape == vmapped.residuals.shape
    assert chunked.predictions["h"].shape[0] == len(THETAS)
    assert_same_members(chunked, vmapped)


def test_failed_members_are_reported_and_do_not_touch_the_others(objective, vmapped, looped):
    np.testing.assert_array_equal(vmapped.failed, FAILED)
    assert np.all(np.isnan(vmapped.loss[FAILED])) and np.all(np.isfinite(vmapped.loss[vmapped.ok]))
    by_index = {f["index"]: f for f in vmapped.failures}
    assert by_index[1]["status"] & jaxmpm.BUDGET and "max_steps" in by_index[1]["status_text"]
    assert by_index[3]["status"] & jaxmpm.NONFINITE and "non-finite" in by_index[3]["status_text"]
    assert by_index[3]["params"] == {"beta": 0.3, "E": -1.0e6}
    assert vmapped.best()["index"] in (0, 2, 4)
    # The same compiled chunk with the failing members replaced by good ones: the others do not
    # move by a single bit.
    clean = THETAS.copy()
    clean[FAILED] = [[0.15, 1.0e6], [0.35, 1.1e6]]
    healthy = sweep(objective, clean, mode="vmap", chunk=len(THETAS))
    assert healthy.compile_s == 0.0 and healthy.failed.size == 0  # the cached executable
    keep = vmapped.ok
    np.testing.assert_array_equal(healthy.loss[keep], vmapped.loss[keep])
    np.testing.assert_array_equal(healthy.residuals[keep], vmapped.residuals[keep])
    json.dumps(vmapped.to_json(predictions=True))  # NaN becomes null: valid JSON


SHARD_SCRIPT = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
sys.path.insert(0, {tests!r})
from test_sweep import THETAS, make_objective
from calibration.batch.sweep import sweep
result = sweep(make_objective(), THETAS, validate=False)  # auto: shard over all devices, chunk from memory analysis
print(json.dumps({{"n_devices_seen": len(jax.devices()), **result.to_json()}}))
"""


@pytest.mark.slow  # 16 s; vmap against loop stays in the default suite
def test_sharded_over_four_cpu_devices_matches_loop(tmp_path, looped):
    script = tmp_path / "shard.py"
    script.write_text(textwrap.dedent(SHARD_SCRIPT.format(tests=str(pathlib.Path(__file__).parent))))
    root = pathlib.Path(__file__).resolve().parents[1]
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4", "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300,
                         check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["n_devices_seen"] == 4 and out["n_devices"] == 4 and out["mode"] == "shard"
    assert out["chunk"] % 4 == 0 and out["chunk"] >= len(THETAS)  # one chunk, padded to 8
    sharded = SweepResult(
        keys=tuple(out["keys"]), thetas=np.array(out["thetas"]),
        loss=np.array([np.nan if v is None else v for v in out["loss"]]), status=np.array(out["status"]),
        residuals=np.array([[np.nan if v is None else v for v in row] for row in out["residuals"]]),
        predictions=None, failed=np.array(out["failed"], int), mode=out["mode"], chunk=out["chunk"],
        n_devices=out["n_devices"], wall_s=out["wall_s"], compile_s=out["compile_s"])
    np.testing.assert_array_equal(sharded.thetas, THETAS)
    assert_same_members(sharded, looped)


# ---- machinery on a closed-form objective -----------------------------------------------------
def test_toy_sweep_all_modes_and_failures():
    toy = ToyObjective()
    thetas = np.array([[0.1, 1.0], [11.0, 1.0], [0.3, -1.0], [0.4, 2.0], [0.5, 0.5], [0.6, 0.1], [0.7, 0.2]])
    loop = sweep(toy, thetas, mode="loop")
    np.testing.assert_array_equal(loop.failed, [1, 2])
    assert loop.failures[0]["status"] == jaxmpm.NONFINITE
    assert loop.failures[1]["status"] == 0 and "non-finite loss" in loop.failures[1]["status_text"]
    for kw in ({"mode": "vmap"}, {"mode": "vmap", "chunk": 3}, {"mode": "auto", "chunk": 4}):
        assert_same_members(sweep(toy, thetas, **kw), loop)
    again = sweep(toy, thetas, mode="vmap", chunk=3)
    assert again.compile_s == 0.0  # no recompilation for a chunk shape already compiled
    # Points given as (keys, thetas) in another order are reordered to the objective's keys.
    swapped = sweep(toy, (("b", "a"), thetas[:, ::-1]), mode="loop")
    np.testing.assert_array_equal(swapped.thetas, thetas)


def test_memory_budget_sets_the_chunk():
    toy = ToyObjective()
    thetas = latin_hypercube({"a": (0.0, 1.0), "b": (0.1, 2.0)}, 9, keys=("a", "b"))[1]
    roomy = sweep(toy, thetas, mode="vmap")
    assert roomy.chunk == 9  # the whole batch fits
    tight = sweep(toy, thetas, mode="vmap", memory_budget_bytes=1)  # nothing fits: one at a time
    assert tight.chunk == 1
    assert_same_members(tight, roomy)


def test_landscape_best_and_json():
    toy = ToyObjective()
    points = grid_points({"a": (0.0, 1.0), "b": (0.5, 2.0)}, {"a": 4, "b": 3})
    result = sweep(toy, points, mode="vmap")
    xs, ys, grid = result.landscape("a", "b")
    np.testing.assert_array_equal(xs, np.linspace(0.0, 1.0, 4))
    np.testing.assert_array_equal(ys, np.linspace(0.5, 2.0, 3))
    assert grid.shape == (3, 4)
    for i, (a, b) in enumerate(result.thetas):
        assert grid[list(ys).index(b), list(xs).index(a)] == result.loss[i]
    best = result.best()
    assert best["loss"] == np.nanmin(result.loss) and set(best["params"]) == {"a", "b"}
    assert (best["a"], best["b"]) == tuple(result.thetas[best["index"]])
    out = json.loads(json.dumps(result.to_json()))
    assert out["loss"] == result.loss.tolist() and out["best"]["index"] == best["index"]
    with pytest.raises(ValueError, match="full"):
        result_lhs = sweep(toy, latin_hypercube({"a": (0.0, 1.0), "b": (0.5, 2.0)}, 5), mode="vmap")
        result_lhs.landscape("a", "b")
    with pytest.raises(ValueError, match="key_x"):
        result.landscape("c", "b")
