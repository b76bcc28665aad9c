"""Cost of one calibration evaluation: the run alone, forward mode (the residuals and the whole
Jacobian, by the objective's column passes and by jax.jacfwd's vmapped batch) and reverse mode
(the loss gradient), with compile time apart from run time and the memory XLA plans for each.
``bench(...)`` returns a ``BenchResult``, what ``python -m calibration bench --json`` prints
(docs/cost.md).
"""

from __future__ import annotations

import dataclasses
import platform
import resource
import time
from typing import Any

import jax
import numpy as np

from jaxmpm.scenes import build_scene
from jaxmpm.scenes.collapse import S4_SIDE

from ..problem.objective import Objective
from ..problem.targets import FrontTarget, ProfileTarget

__all__ = ["Timing", "MEASURES", "BenchResult", "bench"]


def _timed(fn, repeat: int):
    runs = []
    for _ in range(repeat + 1):  # the first call compiles
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    run = float(np.median(runs[1:]))
    return max(runs[0] - run, 0.0), run


def _temp_bytes(jitted, *args) -> int | None:
    try:
        stats = jitted.lower(*args).compile().memory_analysis()
        return int(stats.temp_size_in_bytes + stats.output_size_in_bytes)
    except Exception:  # memory analysis is not available on every backend
        return None


@dataclasses.dataclass(frozen=True)
class Timing:
    """One measured evaluation: compile time (the first call less a later one), the median run
    time of the later calls, and the bytes XLA plans for it (None where it does not say)."""

    compile_s: float
    run_s: float
    xla_temp_bytes: int | None

    def to_json(self) -> dict[str, Any]:
        return {"compile_s": round(self.compile_s, 3), "run_s": round(self.run_s, 3),
                "xla_temp_bytes": self.xla_temp_bytes}


#: The measured evaluations, in the order they run and print.
MEASURES = ("forward", "jacobian", "jacfwd_batch", "grad_rev")


@dataclasses.dataclass(frozen=True)
class BenchResult:
    """The problem measured (scene, keys, sizes, machine) and a ``Timing`` per ``MEASURES`` entry:
    ``forward`` (the run alone), ``jacobian`` (residuals and Jacobian by the objective's column
    passes), ``jacfwd_batch`` (jax.jacfwd's vmapped batch), ``grad_rev`` (the reverse-mode loss
    gradient). ``peak_rss_mb`` is the process's peak resident memory at the end."""

    scene: str
    keys: tuple[str, ...]
    n_residuals: int
    n_particles: int
    max_steps: int
    dx: float
    dtype: str
    machine: str
    backend: str
    devices: int
    values: dict[str, float]  # the scene's beta, mu1, pc0, xi
    timings: dict[str, Timing]
    peak_rss_mb: float

    def to_json(self) -> dict[str, Any]:
        """What ``python -m calibration bench --json`` prints: times to the millisecond, and the
        ratios to the forward run and the particle-steps per second from those printed times."""
        out = {"scene": self.scene, "keys": list(self.keys), "n_params": len(self.keys),
               "n_residuals": self.n_residuals, "n_particles": self.n_particles, "max_steps": self.max_steps,
               "dx": self.dx, "dtype": self.dtype, "machine": self.machine, "backend": self.backend,
               "devices": self.devices, "values": dict(self.values)}
        for name in MEASURES:
            out[name] = self.timings[name].to_json()
        f = out["forward"]["run_s"]
        for name in MEASURES[1:]:
            out[f"{name}_over_forward"] = round(out[name]["run_s"] / f, 2)
        out["particle_steps_per_s_forward"] = round(self.n_particles * self.max_steps / f)
        out["peak_rss_mb"] = round(self.peak_rss_mb, 1)
        return out


def bench(keys=("beta", "mu1", "mu2", "I0", "xi"), dx: float = S4_SIDE / 16, t_end: float = 0.5, repeat: int = 2,
          dtype=None, values=None) -> BenchResult:
    """Measure the S4 cohesive collapse at ``dx`` for ``t_end`` s, fitting ``keys``; ``repeat``
    timed calls after the first. ``values``: scene parameters by key over the bench's own (β = 0.25)."""
    scene = build_scene("cohesive-collapse", dx=dx, t_end=t_end, dtype=dtype,
                        values={"beta": 0.25, **dict(values or {})})
    xs = np.linspace(0.0, 0.2, 50)
    times = np.linspace(0.05, t_end, 10)
    obj = Objective(scene, keys, profile=ProfileTarget(xs, np.ones_like(xs)),
                    front=FrontTarget(times, np.ones_like(times)), check_data=False)  # placeholder data: cost only
    theta = np.array([float(getattr(scene.params, k)) for k in keys])
    th, fns, args = obj.as_theta(theta), obj.functions, obj.arguments()
    # The vmapped batch of all tangents, for comparison with the column passes the objective uses.
    batch = jax.jit(jax.jacfwd(fns.residual, has_aux=True))
    timings = {}
    for name, jitted in (("forward", fns.residuals), ("jacobian", fns.jacobian), ("jacfwd_batch", batch),
                         ("grad_rev", fns.value_and_grad)):
        compile_s, run_s = _timed(lambda jitted=jitted: jitted(th, *args), repeat)  # called in this iteration
        timings[name] = Timing(compile_s, run_s, _temp_bytes(jitted, th, *args))
    return BenchResult(scene=scene.name, keys=tuple(keys), n_residuals=obj.n_residuals,
                       n_particles=int(scene.state.x.shape[0]), max_steps=obj.config.max_steps, dx=dx,
                       dtype=str(obj.dtype), machine=platform.machine(), backend=jax.default_backend(),
                       devices=len(jax.devices()),
                       values={k: float(getattr(scene.params, k)) for k in ("beta", "mu1", "pc0", "xi")},
                       timings=timings, peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
