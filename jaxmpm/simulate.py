"""The public call: validate in Python, run the compiled rollout, check the status bits."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import numpy as np

from .config import Config
from .params import Params, validate_params
from .rollout import Observer, frame_observer, make_rollout
from .state import State, describe_status

__all__ = ["Result", "SimulationError", "simulate", "compiled_rollout", "check_state"]


class SimulationError(RuntimeError):
    """A run finished with status bits set. ``.result`` holds what it produced."""

    def __init__(self, status: int, result: "Result"):
        self.status = status
        self.result = result
        reasons = "; ".join(describe_status(status))
        super().__init__(f"simulation status {status}: {reasons}. Pass throw=False to inspect the result.")


@dataclasses.dataclass(frozen=True)
class Result:
    state: State  # final state
    frames: Any  # observer output stacked over config.frame_times (None if none)
    frame_times: tuple[float, ...]
    status: int  # OR of the status bits (over the batch, if batched)

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


def check_state(config: Config, state: State) -> None:
    """Raise ``ValueError`` if a concrete state does not fit the configuration."""
    x = np.asarray(state.x)
    if x.ndim < 2 or x.shape[-1] != config.dim:
        raise ValueError(f"state.x must have shape (..., n_particles, {config.dim}), got {x.shape}")
    if x.shape[-2] == 0:
        raise ValueError("state.x is empty: the scene has no particles")
    if not np.all(np.isfinite(x)):
        raise ValueError("state.x must be finite")
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
) -> Result:
    """Run ``config`` from ``state`` with ``params`` and return the final state and frames.

    Inputs are validated before any tracing. If the run sets status bits (particle left the
    grid, non-finite state, det F_e <= 0, step budget exhausted), a ``SimulationError`` is
    raised unless ``throw=False``; the bits are always in ``Result.status``.
    """
    if not isinstance(config, Config):
        raise ValueError(f"config must be a Config, got {type(config).__name__}")
    if not isinstance(params, Params):
        raise ValueError(f"params must be a Params, got {type(params).__name__}")
    validate_params(params)
    check_state(config, state)
    final, frames = compiled_rollout(config, observer)(state, params)
    status = int(np.bitwise_or.reduce(np.asarray(final.status).reshape(-1)))
    result = Result(state=final, frames=frames, frame_times=config.frame_times, status=status)
    if throw and status:
        raise SimulationError(status, result)
    return result
