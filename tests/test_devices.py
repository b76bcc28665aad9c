"""A run split over devices by its particles (``simulate(..., devices=K)``, ``jaxmpm.devices``):
the undivided run's state and frames to float64 round-off, whatever the path (one compiled
rollout, or block by block), with padding, side walls and XPIC; what cannot be split is refused
before anything compiles."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import jaxmpm
from jaxmpm import simulate
from jaxmpm.scenes import falling_block

# Two CPU devices must be asked for before JAX starts, so the comparison runs in a fresh Python.
SPLIT_RUNS = r"""
import json
import sys
import dataclasses
import jax
jax.config.update("jax_num_cpu_devices", 2)
jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxmpm import SideWalls, simulate
from jaxmpm.scenes import cohesive_collapse, falling_block

def gap(a, b):
    # The largest difference of any leaf, relative to the leaf's largest finite magnitude
    # (equal values, infinities included, differ by 0).
    worst = 0.0
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        x, y = np.asarray(x, float), np.asarray(y, float)
        if x.shape != y.shape:
            return float("inf")
        d = np.abs(np.where(x == y, 0.0, x - y))
        worst = max(worst, float(np.max(d, initial=0.0)) / (np.max(np.abs(x[np.isfinite(x)]), initial=0.0) or 1.0))
    return worst

def compare(one, two):
    plastic = [np.asarray(r.state.internal["plastic"]) for r in (one, two)]
    states = [r.state.replace(internal={k: v for k, v in r.state.internal.items() if k != "plastic"})
              for r in (one, two)]
    frames = [{k: v for k, v in r.frames.items() if k != "plastic"} for r in (one, two)]
    return {"steps": [int(one.state.steps), int(two.state.steps)], "status": [one.status, two.status],
            "n": [one.state.n_particles, two.state.n_particles], "state": gap(*states), "frames": gap(*frames),
            "plastic_differs": float(np.mean(plastic[0] != plastic[1]))}

out = {}
config, state, params = cohesive_collapse(dx=0.0089, t_end=0.12, frames=3, dtype="float64",
                                          side_walls=SideWalls(0.02, 0.3), pc0=500.0, xi=50.0, beta=0.25)
n = state.n_particles - 1  # an odd count: padded to an even one for two devices
state = state.replace(**{k: jax.tree.map(lambda a: a[:n], getattr(state, k))
                         for k in ("x", "v", "C", "F", "tau", "vol0", "internal")})
one = simulate(config, state, params, throw=False)
out["collapse"] = compare(one, simulate(config, state, params, throw=False, devices=2))
if sys.argv[1] == "quick":
    print(json.dumps(out))
    raise SystemExit
out["blocks"] = compare(one, simulate(config, state, params, throw=False, devices=2, timed=True))
config, state, params = falling_block(n_particles=300, t_end=0.05, frames=2, dtype="float64")
config = dataclasses.replace(config, xpic=2)
one = simulate(config, state, params, throw=False)
two = simulate(config, state, params, throw=False, devices=2)
out["xpic"] = {"steps": [int(one.state.steps), int(two.state.steps)], "state": gap(one.state, two.state),
               "frames": gap(one.frames, two.frames)}
print(json.dumps(out))
"""


def _split_runs(which: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    done = subprocess.run([sys.executable, "-c", SPLIT_RUNS, which], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def split_runs():
    return _split_runs("quick")


@pytest.fixture(scope="module")
def all_split_runs():
    return _split_runs("all")


def test_a_collapse_split_over_two_devices_is_the_undivided_run(split_runs):
    _check_collapse(split_runs["collapse"])


@pytest.mark.slow
def test_block_by_block_the_split_run_is_the_undivided_run_too(all_split_runs):
    _check_collapse(all_split_runs["blocks"])


def _check_collapse(case):
    """S4 with side walls (their pressure summed over the devices too), frames and an odd
    particle count: the same steps and status, every field and frame to float64 round-off.
    The plastic flag (1 where the trial state was inadmissible) is a threshold: at a particle
    on the yield surface round-off decides it, while its stress agrees to round-off."""
    assert case["steps"][0] == case["steps"][1] > 100
    assert case["status"] == [0, 0]
    assert case["n"][0] == case["n"][1] and case["n"][0] % 2 == 1
    assert case["state"] < 1e-9
    assert case["frames"] < 1e-9
    assert case["plastic_differs"] < 0.02


@pytest.mark.slow
def test_xpic_is_summed_over_the_devices(all_split_runs):
    case = all_split_runs["xpic"]
    assert case["steps"][0] == case["steps"][1] > 10
    assert case["state"] < 1e-10
    assert case["frames"] < 1e-10


@pytest.fixture(scope="module")
def block():
    return falling_block(n_particles=50, t_end=0.01)


@pytest.mark.parametrize("devices", [0, -1, 1.5, True, "2"])
def test_devices_must_be_a_positive_integer(block, devices):
    with pytest.raises(ValueError, match="devices must be a positive integer"):
        simulate(*block, devices=devices)


def test_what_cannot_be_split_is_refused_before_anything_compiles(block):
    import dataclasses

    config, state, params = block
    with pytest.raises(ValueError, match="sparse grid"):
        simulate(dataclasses.replace(config, active_nodes=400), state, params, devices=2)
    with pytest.raises(ValueError, match="observer: a run split over devices"):
        simulate(config, state, params, observer=lambda s, p: s.x.mean(), devices=2)
    batch = jaxmpm.State(**{k: (np.stack([v, v]) if k in ("x", "v", "C", "F", "tau", "vol0") else v)
                            for k, v in vars(state).items()})
    with pytest.raises(ValueError, match="a batch of states"):
        simulate(config, batch, params, devices=2)
    many = len(__import__("jax").devices()) + 1
    with pytest.raises(ValueError, match=f"devices={many}: JAX sees"):
        simulate(config, state, params, devices=many)


@pytest.mark.parametrize("argv, message", [
    (["--devices", "2", "--threads", "all"], "--threads all with --devices 2: a split run uses one core per device"),
    (["--devices", "0"], "--devices must be an integer >= 1, got 0"),
])
def test_the_command_line_refuses_devices_it_cannot_use(capsys, argv, message):
    from jaxmpm.__main__ import main

    with pytest.raises(SystemExit) as exc:
        main(["run", "cohesive-collapse", "--no-progress", *argv])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
