"""Cost of one calibration evaluation: the run alone, forward mode (residuals and the whole
Jacobian, by the objective's column passes and, for comparison, by jax.jacfwd's vmapped batch)
and reverse mode (the loss gradient), with compile time apart from run time and the
memory XLA plans for each. ``python -m calibration bench --json`` prints one JSON object.

This is the measurement behind ``Objective``'s choice of forward mode for Levenberg–Marquardt
(it needs the m × n Jacobian; reverse mode would need m passes) and the ``grad_mode`` option of
Adam (one reverse pass against one batched forward pass with n tangents).
"""

from __future__ import annotations

import platform
import resource
import time

import jax
import numpy as np

from jaxmpm.scenes import build_scene

from .objective import FrontTarget, Objective, ProfileTarget

__all__ = ["bench"]


def _timed(fn, repeat: int):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    run = float(np.median(runs))
    return max(first - run, 0.0), run


def _temp_bytes(jitted, *args) -> int | None:
    try:
        stats = jitted.lower(*args).compile().memory_analysis()
        return int(stats.temp_size_in_bytes + stats.output_size_in_bytes)
    except Exception:  # memory analysis is not available on every backend
        return None


def bench(keys=("beta", "mu1", "mu2", "I0", "xi"), dx: float = 0.089 / 16, t_end: float = 0.5, repeat: int = 2,
          dtype=None, values=None) -> dict:
    """``values``: scene parameters by key over the bench's own (β = 0.25)."""
    scene = build_scene("cohesive-collapse", dx=dx, t_end=t_end, dtype=dtype, values={"beta": 0.25, **dict(values or {})})
    xs = np.linspace(0.0, 0.2, 50)
    times = np.linspace(0.05, t_end, 10)
    obj = Objective(scene, keys, profile=ProfileTarget(xs, np.ones_like(xs)),
                    front=FrontTarget(times, np.ones_like(times)), check_data=False)  # placeholder data: cost only
    theta = np.array([float(getattr(scene.params, k)) for k in keys])
    th = obj._theta(theta)
    out = {"scene": scene.name, "keys": list(keys), "n_params": len(keys), "n_residuals": obj.n_residuals,
           "n_particles": int(scene.state.x.shape[0]), "max_steps": obj.config.max_steps, "dx": dx,
           "dtype": str(obj.dtype), "machine": platform.machine(), "backend": jax.default_backend(),
           "devices": len(jax.devices()), "values": {k: float(getattr(scene.params, k)) for k in ("beta", "mu1", "pc0", "xi")}}
    # The vmapped batch of all tangents, for comparison with the column passes the objective uses.
    batch = jax.jit(jax.jacfwd(lambda t, s, b: obj._residual_fn(t, s, b), has_aux=True))
    for name, fn, jitted in (("forward", lambda: obj.residuals(theta), obj._residuals),
                             ("jacobian", lambda: obj.residuals_and_jacobian(theta), obj._jacobian),
                             ("jacfwd_batch", lambda: batch(th, obj._state, obj._base), batch),
                             ("grad_rev", lambda: obj.value_and_grad(theta), obj._value_and_grad)):
        compile_s, run_s = _timed(fn, repeat)
        out[name] = {"compile_s": round(compile_s, 3), "run_s": round(run_s, 3),
                     "xla_temp_bytes": _temp_bytes(jitted, th, obj._state, obj._base)}
    f = out["forward"]["run_s"]
    out["jacobian_over_forward"] = round(out["jacobian"]["run_s"] / f, 2)
    out["jacfwd_batch_over_forward"] = round(out["jacfwd_batch"]["run_s"] / f, 2)
    out["grad_rev_over_forward"] = round(out["grad_rev"]["run_s"] / f, 2)
    steps = obj.config.max_steps
    out["particle_steps_per_s_forward"] = round(out["n_particles"] * steps / f)
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    return out
