"""Threads against processes (docs/performance.md): the Jacobians of 8 starts (16 forward-mode
columns) of the S4 objective at dx = L/8 (p_c0 = 500 Pa, ξ = 50, float32), timed on their first
call (spawn, compile, run) and warm.

    XLA_FLAGS= python docs/scripts/workers_scaling.py batched     # 0.2.0's path: one vmapped batch, XLA's threads
    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
        taskset -c 0 python docs/scripts/workers_scaling.py 1     # Workers(1): one single-threaded process
    python docs/scripts/workers_scaling.py 2                      # Workers(2)

Prints one JSON line.
"""

import json
import sys
import time

import numpy as np

from calibration.batch.workers import Workers, jacobians_z
from calibration.problem.objective import Objective
from calibration.problem.targets import ProfileTarget
from jaxmpm import scenes

KEYS = ("beta", "mu1")


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main(mode):
    scene = scenes.cohesive_collapse(dx=scenes.S4_SIDE / 8, pc0=500.0, xi=50.0)
    xs = np.linspace(0.0, 0.25, 40)
    gen = Objective(scene, KEYS, profile=ProfileTarget(xs, np.ones_like(xs)), check_data=False)
    _, pred = gen.residuals(np.array([0.2, 0.4]))
    obj = Objective(scene, KEYS, profile=ProfileTarget(xs, np.asarray(pred["h"])))
    rng = np.random.default_rng(0)
    thetas = np.column_stack([rng.uniform(0.05, 0.5, 8), rng.uniform(0.3, 0.55, 8)])
    Z = np.stack([obj.bounds.to_unconstrained(t) for t in thetas])
    out = {"mode": mode, "particles": int(scene.state.n_particles)}
    if mode == "batched":  # the previous search path: one compiled batch of all rows

        def jacobians():
            np.asarray(obj.functions.batched_jacobian_z(Z, *obj.lower_upper(), *obj.arguments())[0])

        out["first_s"], out["warm_s"] = _timed(jacobians), _timed(jacobians)
    else:
        with Workers(int(mode)) as workers:
            out["first_s"] = _timed(lambda: jacobians_z(obj, Z, workers))
            out["warm_s"] = _timed(lambda: jacobians_z(obj, Z, workers))
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in out.items()}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
