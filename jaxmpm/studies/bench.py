"""Benchmarks that print JSON: compile time apart from run time, throughput, memory, device.

``python -m jaxmpm bench --json`` times a forward run of the default scene (a 2D elastic block of
10,000 particles, float32, about 2,000 steps) twice: as a user's run goes (``simulate`` block by
block with its observer and rest check, as ``python -m jaxmpm run`` calls it: ``run_s``,
``particle_steps_per_s``) and as the steps alone (every step in one compiled scan, no observer:
``step_run_s``, ``step_particle_steps_per_s``), so that the two cannot drift apart unseen
(``run_over_step``). ``--scene s4`` is the cohesive collapse S4 at dx = 4 mm (β = 0, p_c0 = 500 Pa,
ξ = 50: 4,489 particles, 6,438 steps). ``--grad`` measures reverse mode: the cost of a gradient as
a multiple of the forward run, and the memory XLA plans for it with and without the checkpointed
blocks. Timings are medians over ``--repeat`` runs; ``cores`` is the number of cores the process
ran on (one unless ``--threads all``: ``jaxmpm.threads``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import resource
import statistics
import time

import jax
import jax.numpy as jnp

from ..precision import use_dtype
from ..rollout import make_rollout
from ..scenes import S2_HEIGHT, S2_LENGTH, cohesive_collapse, falling_block, gates_collapse
from ..simulate import simulate
from ..threads import cores_in_use

__all__ = ["bench_forward", "bench_gradient", "bench_scene", "device_name", "median_time", "run_bench", "temp_mb"]


def device_name() -> str:
    dev = jax.devices()[0]
    kind = getattr(dev, "device_kind", dev.platform)
    return f"{dev.platform}:{kind} ({os.cpu_count()} cores, {platform.machine()})"


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(fn, *args, repeat=3):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def median_time(fn, *args, repeat=20):
    """Median seconds of ``fn(*args)`` over ``repeat`` calls after one warm-up call (for the
    profiling scripts in docs/scripts, which time already-compiled pieces)."""
    jax.block_until_ready(fn(*args))
    return _timed(fn, *args, repeat=repeat)[0]


SCENES = ("block", "column", "s4")


def bench_scene(scene: str, quick: bool, dim: int, dtype, n_particles=None):
    if scene == "s4":
        if dim != 2 or n_particles:
            raise ValueError("--scene s4 is the 2D S4 collapse at dx = 4 mm (--quick: L/10); it takes no --dim 3 "
                             "or --particles")
        return cohesive_collapse(dx=0.0089 if quick else 0.004, pc0=500.0, xi=50.0, beta=0.0, dtype=dtype)
    if scene == "column":
        if dim != 2:
            raise ValueError(f"--scene column is 2D (a quasi-2D channel), got dim={dim}")
        # ~10,240 particles at dx = 1.25 mm (2x2 per cell); the first 0.05 s (~2,000 steps).
        dx = 0.0025 if quick else 0.00125
        if n_particles:
            dx = math.sqrt(S2_LENGTH * S2_HEIGHT / n_particles * 4)
        # A fixed 2 x 2 lattice, whatever the scenes' default sampling: the benchmark's particle
        # count (and so its throughput) stays comparable over time and with the Taichi reference.
        return gates_collapse(dx=dx, t_end=0.01 if quick else 0.05, dtype=dtype, ppc=2, sampling="lattice")
    n = n_particles or ((2_500 if dim == 2 else 4_000) if quick else (10_000 if dim == 2 else 32_000))
    return falling_block(n_particles=n, dim=dim, t_end=0.05 if quick else 0.39, dtype=dtype)


def bench_forward(quick=False, dim=2, dtype="float32", repeat=3, n_particles=None, scene="block", steps=None,
                  active_nodes=None) -> dict:
    """Forward-run throughput, as a user's run and as the steps alone (module docstring).
    ``steps`` caps the run at that many steps (the ``BUDGET`` status bit is then expected), so
    that large cases stay affordable. ``active_nodes`` runs the sparse grid with that many slots
    instead of the dense grid."""
    config, state, params = bench_scene(scene, quick, dim, dtype, n_particles)
    if active_nodes is not None:
        config = dataclasses.replace(config, active_nodes=active_nodes)
    if steps is not None:
        if not (isinstance(steps, int) and steps >= 1):
            raise ValueError(f"steps must be a positive int, got {steps!r}")
        config = dataclasses.replace(config, max_steps=min(steps, config.max_steps), block_size=None)
    runs = [simulate(config, state, params, throw=False, timed=True) for _ in range(repeat)]
    run_s = statistics.median(r.run_s for r in runs)
    rollout = jax.jit(make_rollout(config, observer=None, checkpoint=False))
    start = time.perf_counter()
    compiled = rollout.lower(state, params).compile()
    step_compile_s = time.perf_counter() - start
    step_run_s, (final, _) = _timed(compiled, state, params, repeat=repeat)
    n, steps = state.n_particles, int(runs[0].state.steps)
    return {
        "scene": {"block": "elastic-block", "column": "column-S2", "s4": "cohesive-collapse-S4"}[scene],
        "dim": dim,
        "dtype": str(jnp.dtype(state.x.dtype)),
        "n_particles": n,
        "n_steps": steps,
        "grid_nodes": config.grid.n_nodes,
        "active_nodes": config.active_nodes,
        "compile_s": round(runs[0].compile_s, 3),
        "run_s": round(run_s, 4),
        "particle_steps_per_s": round(n * steps / run_s),
        "step_compile_s": round(step_compile_s, 3),
        "xla_temp_mb": temp_mb(compiled),
        "step_run_s": round(step_run_s, 4),
        "step_particle_steps_per_s": round(n * int(final.steps) / step_run_s),
        "run_over_step": round(n * steps / run_s / (n * int(final.steps) / step_run_s), 3),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "device": device_name(),
        "cores": cores_in_use(),
        "status": runs[0].status,
        "repeat": repeat,
    }


def temp_mb(compiled) -> float | None:
    analysis = compiled.memory_analysis()
    if analysis is None:
        return None
    return round(analysis.temp_size_in_bytes / 2**20, 1)


def bench_gradient(quick=False, dim=2, dtype="float32", repeat=3, n_particles=None, steps=None) -> dict:
    """Gradient of the final mean height with respect to all parameters, for ``steps`` steps."""
    n_particles = n_particles or (1_000 if quick else 2_500)
    if steps is None:
        steps = 500 if quick else 5_000
    elif not (isinstance(steps, int) and steps >= 1):
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    config, state, params = falling_block(n_particles=n_particles, dim=dim, t_end=10.0, max_steps=steps, dtype=dtype)
    out = {"scene": "elastic-block", "dim": dim, "dtype": str(jnp.dtype(state.x.dtype)),
           "n_particles": state.n_particles, "n_steps": steps, "device": device_name(), "cores": cores_in_use()}

    def loss_fn(checkpoint):
        rollout = make_rollout(config, observer=None, checkpoint=checkpoint)
        return lambda p: jnp.mean(rollout(state, p)[0].x[:, -1])

    forward = jax.jit(loss_fn(True)).lower(params).compile()
    out["forward_run_s"], _ = _timed(forward, params, repeat=repeat)
    for checkpoint in (True, False):
        start = time.perf_counter()
        grad = jax.jit(jax.grad(loss_fn(checkpoint))).lower(params).compile()
        tag = "checkpointed" if checkpoint else "plain"
        out[f"grad_{tag}_compile_s"] = round(time.perf_counter() - start, 3)
        out[f"grad_{tag}_temp_mb"] = temp_mb(grad)
        if checkpoint:
            run_s, g = _timed(grad, params, repeat=repeat)
            out["grad_run_s"] = round(run_s, 4)
            out["grad_over_forward"] = round(run_s / out["forward_run_s"], 2)
            out["grad_finite"] = bool(all(jnp.all(jnp.isfinite(v)) for v in jax.tree.leaves(g)))
    out["forward_run_s"] = round(out["forward_run_s"], 4)
    out["block_size"] = config.blocks[1]
    out["peak_rss_mb"] = round(_peak_rss_mb(), 1)
    return out


def run_bench(grad=False, quick=False, dim=2, dtype="float32", repeat=3, n_particles=None, scene="block",
              steps=None, active_nodes=None) -> dict:
    """The benchmark ``python -m jaxmpm bench`` runs: ``bench_gradient`` with ``grad`` (which
    takes neither ``scene`` nor ``active_nodes``), else ``bench_forward``; float64 turns JAX's
    64-bit mode on first (``precision.use_dtype``)."""
    use_dtype(dtype)
    if grad:
        return bench_gradient(quick, dim, dtype, repeat, n_particles, steps)
    return bench_forward(quick, dim, dtype, repeat, n_particles, scene, steps=steps, active_nodes=active_nodes)
