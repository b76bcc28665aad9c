"""The S4 step's cost and kernel count (docs/performance.md): S4 at dx = 4 mm (p_c0 = 500 Pa,
ξ = 50) run for 0.1 s, then 200 steps in one compiled scan, timed 7 times (the median), with the
number of fusions, scatters and gathers in the compiled step.

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \\
        taskset -c 0 python docs/scripts/step_time.py [--tag now]      # one thread
    python docs/scripts/step_time.py --tag two-threads                  # XLA's default threads

To compare with another version, run it with that version first on PYTHONPATH. Prints one JSON line.
"""

import argparse
import dataclasses
import json
import re
import time

import jax

from jaxmpm.rollout import make_rollout
from jaxmpm.scenes import cohesive_collapse
from jaxmpm.step import make_step


def kernel_count(hlo: str) -> tuple[int, int]:
    """Fusions, scatters, gathers and sorts called from the program's non-fused computations, and its while loops."""
    kernels = loops = 0
    for computation in re.split(r"\n(?=\S)", hlo):
        name = computation.split("\n")[0].split(" ")[0]
        if "fused" in name or "wrapped" in name:
            continue
        kernels += len(re.findall(r"[\]}] (fusion|scatter|gather|sort)\(", computation))
        loops += len(re.findall(r"[\]})] while\(", computation))
    return kernels, loops


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dx", type=float, default=0.004)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--tag", default="")
    args = parser.parse_args()
    config, state, params = cohesive_collapse(dx=args.dx, pc0=500.0, xi=50.0)
    warm = make_rollout(dataclasses.replace(config, t_end=0.1, frame_times=()), observer=None)
    state = jax.jit(warm)(state, params)[0]
    step = make_step(config)
    n = args.steps
    scan = jax.jit(lambda s, p: jax.lax.scan(lambda c, _: (step(c, p), None), s, None, length=n)[0])
    t0 = time.perf_counter()
    compiled = scan.lower(state, params).compile()
    compile_s = time.perf_counter() - t0
    kernels, loops = kernel_count(compiled.as_text())
    jax.block_until_ready(compiled(state, params))
    times = []
    for _ in range(7):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(state, params))
        times.append(time.perf_counter() - t0)
    median = sorted(times)[3]
    print(json.dumps({"tag": args.tag, "particles": state.n_particles, "ms_per_step": round(median / n * 1e3, 4),
                      "us_per_particle_step": round(median / n / state.n_particles * 1e6, 4),
                      "kernels_per_step": kernels, "while_loops": loops, "compile_s": round(compile_s, 2)}))


if __name__ == "__main__":
    main()
