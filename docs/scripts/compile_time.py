"""What a run costs to compile: the S4 rollout and its forward-mode derivative, as calibration
compiles them (``jax.jit(make_rollout(config))`` and a ``jax.jvp`` through it), on one core.

    python docs/scripts/compile_time.py [--dx 0.0148] [--t-end 0.1] [--dtype float64]

Prints one JSON object: the step budget and its blocks, the seconds spent tracing and lowering,
compiling the run, and compiling its derivative, and the run's steps and status. Compile times
move with the machine (2 to 3 times between days here); compare two builds in the same hour."""

from __future__ import annotations

import argparse
import json
import time

from jaxmpm.threads import use_one_thread


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dx", type=float, default=0.089 / 6, help="grid cell [m] (default: L/6, the tests' tiny S4)")
    parser.add_argument("--t-end", type=float, default=0.1, help="end time [s]")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    args = parser.parse_args(argv)
    use_one_thread()
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", args.dtype == "float64")
    from jaxmpm import scenes
    from jaxmpm.rollout import make_rollout

    scene = scenes.cohesive_collapse(dx=args.dx, t_end=args.t_end, dtype=args.dtype)
    config, state, params = scene.config, scene.state, scene.params
    rollout = make_rollout(config)

    clock = time.perf_counter()
    lowered = jax.jit(rollout).lower(state, params)
    lower_s = time.perf_counter() - clock
    clock = time.perf_counter()
    run = lowered.compile()
    compile_s = time.perf_counter() - clock
    final, _ = jax.block_until_ready(run(state, params))

    def front(beta):
        final, _ = rollout(state, params.replace(beta=beta))
        return jnp.max(final.x[:, 0])

    clock = time.perf_counter()
    jax.jit(lambda b: jax.jvp(front, (b,), (jnp.ones_like(b),))).lower(params.beta).compile()
    jvp_s = time.perf_counter() - clock
    out = {"scene": "cohesive-collapse", "dx": args.dx, "t_end": args.t_end, "dtype": args.dtype,
           "n_particles": int(state.x.shape[0]), "max_steps": config.max_steps, "blocks": list(config.blocks),
           "lower_s": round(lower_s, 2), "compile_s": round(compile_s, 2), "jvp_compile_s": round(jvp_s, 2),
           "steps": int(final.steps), "status": int(final.status), "jax": jax.__version__}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
