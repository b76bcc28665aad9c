"""The public call: validate in Python, run the compiled rollout, check the status bits."""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import jax
import numpy as np

from .config import Config
from .params import Params, validate_params
from .rollout import Observer, frame_observer, make_rollout, make_rollout_parts
from .state import BUDGET, LEFT_GRID, NONFINITE, State, describe_status

__all__ = ["Result", "SimulationError", "simulate", "compiled_rollout", "check_state"]


class SimulationError(RuntimeError):
    """A run finished with status bits set. ``.result`` holds what it produced."""

    def __init__(self, status: int, result: Result):
        self.status = status
        self.result = result
        reasons = "; ".join(describe_status(status))
        super().__init__(f"simulation status {status}: {reasons}. Pass throw=False to inspect the result.")


@dataclasses.dataclass(frozen=True)
class Result:
    """What ``simulate`` returns: the final state, the observer's frames at ``frame_times``, the
    status bits, and the compile and run times when measured."""

    state: State  # final state
    frames: Any  # observer output stacked over config.frame_times (None if none)
    frame_times: tuple[float, ...]
    status: int  # OR of the status bits (over the batch, if batched)
    compile_s: float | None = None  # measured when run with progress=True
    run_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.status == 0

    @property
    def steps(self):
        return np.asarray(self.state.steps)


@functools.lru_cache(maxsize=64)
def compiled_rollout(config: Config, observer: Observer | None = frame_observer, checkpoint: bool = True):
    """``jax.jit`` of ``make_rollout``, cached per (config, observer): new parameter values or
    initial states of the same shapes never recompile."""
    return jax.jit(make_rollout(config, observer, checkpoint))


@functools.lru_cache(maxsize=16)
def compiled_parts(config: Config, observer: Observer | None = frame_observer):
    """Jitted start/block/finish of the rollout, for block-by-block runs with a progress bar."""
    parts = make_rollout_parts(config, observer, checkpoint=False,
                               steps_per_block=max(config.blocks[1], config.max_steps // 100))
    return jax.jit(parts.start), jax.jit(parts.block), jax.jit(parts.finish), parts.steps_per_block


def _run_blocks(config: Config, state: State, params: Params, observer, show_bar: bool = True):
    """Run block by block with a progress bar (tqdm, if installed), stopping at t_end.
    Returns (final, frames, compile_s, run_s)."""
    start, block, finish, per_block = compiled_parts(config, observer)
    try:
        from tqdm import tqdm
    except ImportError:  # the optional 'progress' extra
        tqdm = None
    tqdm = tqdm if show_bar else None
    clock = time.perf_counter()
    start = start.lower(state, params).compile()
    carry = start(state, params)
    block = block.lower(carry, params).compile()
    finish = finish.lower(carry).compile()
    compile_s = time.perf_counter() - clock
    clock = time.perf_counter()
    bar = tqdm(total=config.t_end, unit="s", unit_scale=False, desc="simulated time",
               bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s [{elapsed}<{remaining}{postfix}]") if tqdm else None
    steps, last_t = 0, 0.0
    stopped_early = False
    try:
        while steps < config.max_steps:
            carry = block(carry, params)
            steps += per_block
            t = float(carry[0].t)
            if bar is not None:
                bar.update(t - last_t)
                bar.set_postfix_str(f"{steps / max(time.perf_counter() - clock, 1e-9):.0f} steps/s")
            last_t = t
            if t >= config.t_end:
                break
            if int(carry[0].status) & (NONFINITE | LEFT_GRID):
                stopped_early = int(carry[0].steps) < config.max_steps
                break
    finally:
        if bar is not None:
            bar.close()
    final, frames = jax.block_until_ready(finish(carry))
    if stopped_early:
        # ``finish`` sets BUDGET whenever t < t_end; here t_end was not reached because the run
        # was stopped on a fatal bit with steps to spare, not because the budget ran out (the
        # plain path, which runs on, never sets it for the same run).
        final = final.replace(status=final.status & ~BUDGET)
    return final, frames, compile_s, time.perf_counter() - clock


def check_state(config: Config, state: State) -> None:
    """Raise ``ValueError`` if a concrete state does not fit the configuration."""
    x = np.asarray(state.x)
    if x.ndim < 2 or x.shape[-1] != config.dim:
        raise ValueError(f"state.x must have shape (..., n_particles, {config.dim}), got {x.shape}")
    if x.shape[-2] == 0:
        raise ValueError("state.x is empty: the scene has no particles")
    if not np.all(np.isfinite(x)):
        raise ValueError("state.x must be finite")
    want = (len(config.walls), config.dim)
    if np.shape(state.impulse)[-2:] != want:
        raise ValueError(f"state.impulse must end in shape {want} (one row per wall and terrain of the config), got "
                         f"{np.shape(state.impulse)}: build the state with init_state(config, ...) for this config")
    lower, upper = config.grid.lower, config.grid.upper
    outside = config.grid.outside(x)
    if np.any(outside):
        raise ValueError(
            f"state.x: {int(outside.sum())} particle(s) lie outside the grid interior "
            f"[{lower.tolist()}, {upper.tolist()})"
        )


def simulate(
    config: Config,
    state: State,
    params: Params,
    observer: Observer | None = frame_observer,
    throw: bool = True,
    progress: bool = False,
    timed: bool = False,
) -> Result:
    """Run ``config`` from ``state`` with ``params`` and return the final state and frames.

    Inputs are validated before any tracing. If the run sets status bits (particle left the
    grid, non-finite state, det F_e <= 0, step budget exhausted), a ``SimulationError`` is
    raised unless ``throw=False``; the bits are always in ``Result.status``. With
    ``progress=True`` the run goes block by block with a progress bar (and stops early at
    t_end or on a fatal status bit); the result is the same. ``timed=True`` runs block by block
    without the bar; both fill ``Result.compile_s`` and ``Result.run_s``.
    """
    if not isinstance(config, Config):
        raise ValueError(f"config must be a Config, got {type(config).__name__}")
    if not isinstance(params, Params):
        raise ValueError(f"params must be a Params, got {type(params).__name__}")
    validate_params(params)
    check_state(config, state)
    timings = (None, None)
    if progress or timed:
        final, frames, *timings = _run_blocks(config, state, params, observer, show_bar=progress)
    else:
        final, frames = compiled_rollout(config, observer)(state, params)
    status = int(np.bitwise_or.reduce(np.asarray(final.status).reshape(-1)))
    result = Result(state=final, frames=frames, frame_times=config.frame_times, status=status,
                    compile_s=timings[0], run_s=timings[1])
    if throw and status:
        raise SimulationError(status, result)
    return result
