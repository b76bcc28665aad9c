"""A rollout is a fixed-length ``lax.scan`` of the step plus an observer (docs/model.md §5).

Only what the observer returns is stored, at the configured frame times (which the step lands
on exactly). Steps run in blocks of ``config.blocks[1]``, each wrapped in ``jax.checkpoint``,
and so is each step inside a block, so reverse-mode memory holds one carry per block, one carry
per step of the block being transposed and one step's residuals: with blocks of about sqrt(n)
steps it grows like sqrt(n) instead of n.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import state as st
from .config import Config
from .materials.base import invariants
from .step import make_step

__all__ = ["make_rollout", "make_rollout_parts", "RolloutParts", "frame_observer", "Observer"]

Observer = Callable[[Any, Any], Any]


def frame_observer(state, params):
    """The default frame: positions, velocities, p and q, the internal variables, and the walls'
    impulse (``State.impulse``: one row per wall, not per particle)."""
    p, q = invariants(state.tau)
    return {"x": state.x, "v": state.v, "p": p, "q": q, **state.internal, "impulse": state.impulse}


def _scan_steps(fn, carry, n: int, checkpoint: bool):
    # With checkpointing each step is rematerialised too: the backward pass of a block re-runs
    # the block storing one carry per step, then recomputes each step's residuals just before
    # its transpose, instead of storing every step's residuals (stencils, return-map state) for
    # the whole block. Same time within noise (5.4 against 5.7 forward runs for bench --grad),
    # 11 times less memory (31 MB against 350 MB of temporaries).
    step = jax.checkpoint(fn) if checkpoint else fn

    def block(c):
        return jax.lax.scan(lambda c, _: (step(c), None), c, None, length=n)[0]

    return jax.checkpoint(block)(carry) if checkpoint else block(carry)


class RolloutParts(NamedTuple):
    """The rollout in three pure pieces, for callers that drive the blocks themselves (a
    progress bar, early exit): ``start(state, params) -> carry``, ``block(carry, params) ->
    carry`` (``steps_per_block`` steps) and ``finish(carry) -> (final_state, frames)``."""

    start: Callable
    block: Callable
    finish: Callable
    steps_per_block: int


def make_rollout_parts(config: Config, observer: Observer | None = frame_observer, checkpoint: bool = True,
                       steps_per_block: int | None = None) -> RolloutParts:
    step = make_step(config)
    frame_times = config.frame_times if observer is not None else ()
    n_frames = len(frame_times)
    block = steps_per_block or config.blocks[1]

    def record(frames, k, s, params):
        return jax.tree.map(lambda f, o: f.at[k].set(o), frames, observer(s, params))

    def start(state, params):
        if not n_frames:
            return state, None, jnp.zeros((), jnp.int32)
        if np.any(np.diff(np.asarray(frame_times, state.t.dtype)) <= 0):  # at trace time, before compiling
            raise ValueError(f"frame_times: two of them coincide at the run's precision ({state.t.dtype}); a frame "
                             f"would never be recorded: {frame_times!r}")
        times = jnp.asarray(frame_times, state.t.dtype)
        first = observer(state, params)
        frames = jax.tree.map(lambda o: jnp.zeros((n_frames,) + o.shape, o.dtype), first)
        at_start = state.t == times[0]
        frames = jax.lax.cond(at_start, lambda f: record(f, 0, state, params), lambda f: f, frames)
        return state, frames, at_start.astype(jnp.int32)

    def one(carry, params):
        s, frames, k = carry
        s = step(s, params)
        if n_frames:
            times = jnp.asarray(frame_times, s.t.dtype)
            hit = (k < n_frames) & (s.t == times[jnp.minimum(k, n_frames - 1)])
            frames = jax.lax.cond(hit, lambda f: record(f, k, s, params), lambda f: f, frames)
            k = k + hit.astype(jnp.int32)
        return s, frames, k

    def run_block(carry, params, n=block):
        return _scan_steps(lambda c: one(c, params), carry, n, checkpoint)

    def finish(carry):
        final, frames, _ = carry
        budget = jnp.where(final.t < config.t_end, st.BUDGET, 0)
        return final.replace(status=final.status | budget), frames

    return RolloutParts(start, run_block, finish, block)


def make_rollout(config: Config, observer: Observer | None = frame_observer, checkpoint: bool = True):
    """Build ``rollout(state, params) -> (final_state, frames)``.

    ``frames`` is the observer's pytree with a leading axis over ``config.frame_times`` (None
    when there are no frame times or no observer). The function is pure and unjitted: wrap it
    in ``jax.jit``, ``jax.vmap`` or ``jax.grad`` as needed. The final state's ``status`` carries
    the ``BUDGET`` bit if ``t_end`` was not reached within ``config.max_steps``.
    """
    parts = make_rollout_parts(config, observer, checkpoint)
    # Whole blocks only: the last one's steps beyond max_steps do nothing (the step's budget
    # guard). A shorter last block was a second copy of the step in the program, which XLA
    # compiled too (S4 at L/6 in float64, paired on one core: the run compiles in 8.2-9.2 s
    # against 10.8-11.4 s, its forward-mode derivative in 17.2-17.9 s against 22.9-23.1 s;
    # docs/scripts/compile_time.py).
    n_blocks = -(-config.max_steps // parts.steps_per_block)

    def rollout(state, params):
        carry = parts.start(state, params)
        carry = jax.lax.scan(lambda c, _: (parts.block(c, params), None), carry, None, length=n_blocks)[0]
        return parts.finish(carry)

    return rollout
