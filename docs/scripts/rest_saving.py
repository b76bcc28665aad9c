"""What stopping at rest saves: S4 (dx = 4 mm, p_c0 = 500 Pa, ξ = 50; β = 0.25 and β = 0) and S7 at
its defaults, each run to t_end with and without ``Config.rest_speed`` (docs/performance.md).

    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" \
        taskset -c 0 python docs/scripts/rest_saving.py        # about 3 minutes

prints one JSON line per case and writes docs/results/rest_saving.json.
"""

import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxmpm as jm
from jaxmpm.observables import deposit_profile
from jaxmpm.scenes import aluminium_bars, cohesive_collapse

ROOT = pathlib.Path(__file__).resolve().parents[2]
CASES = {
    "S4 beta=0.25 dx=4mm": lambda rest: cohesive_collapse(beta=0.25, dx=0.004, pc0=500.0, xi=50.0, rest=rest),
    "S4 beta=0 dx=4mm": lambda rest: cohesive_collapse(beta=0.0, dx=0.004, pc0=500.0, xi=50.0, rest=rest),
    "S7 default": lambda rest: aluminium_bars(rest=rest),
}


def _finite_or_none(value):
    """JSON has no infinity: a run that never came to rest records null."""
    return value if np.isfinite(value) else None


def run(scene, repeat=2):
    """The final state and the fastest of ``repeat`` timings of the compiled rollout."""
    compiled = jax.jit(jm.make_rollout(scene.config, observer=None)).lower(scene.state, scene.params).compile()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        final, _ = compiled(scene.state, scene.params)
        final.x.block_until_ready()
        times.append(time.perf_counter() - t0)
    return final, min(times)


def main():
    results = []
    for name, make in CASES.items():
        out, x, profile = {"case": name}, {}, {}
        for rest in (False, True):
            scene = make(rest)
            final, seconds = run(scene)
            key = "rest" if rest else "full"
            xs = jnp.linspace(0.0, float(scene.config.grid.upper[0]), 400)
            x[key] = np.asarray(final.x, float)
            profile[key] = np.asarray(deposit_profile(final.x, scene.state.vol0, xs, scene.config.grid.dx))
            quiet = _finite_or_none(float(final.quiet_since))
            out[key] = {"steps": int(final.steps), "run_s": round(seconds, 2), "quiet_since": quiet,
                        "status": int(final.status), "n": int(final.x.shape[0])}
        out["max_particle_diff_mm"] = float(np.abs(x["rest"] - x["full"]).max() * 1e3)
        out["max_profile_diff_mm"] = float(np.abs(profile["rest"] - profile["full"]).max() * 1e3)
        out["step_saving"] = 1 - out["rest"]["steps"] / out["full"]["steps"]
        out["time_saving"] = 1 - out["rest"]["run_s"] / out["full"]["run_s"]
        print(json.dumps(out), flush=True)
        results.append(out)
    (ROOT / "docs/results/rest_saving.json").write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
