"""A rollout is a fixed-length ``lax.scan`` of the step plus an observer (MODEL.md §5).

Only what the observer returns is stored, at the configured frame times (which the step lands
on exactly). Steps run in blocks of ``config.blocks[1]``, each wrapped in ``jax.checkpoint``,
so reverse-mode memory holds one carry per block plus one block's residuals: with blocks of
about sqrt(n) steps it grows like sqrt(n) instead of n.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from . import state as st
from .config import Config
from .materials.base import invariants
from .step import make_step

__all__ = ["make_rollout", "frame_observer", "Observer"]

Observer = Callable[[Any, Any], Any]


def frame_observer(state, params):
    """The default frame: positions, velocities, p and q, and the internal variables."""
    p, q = invariants(state.tau)
    return {"x": state.x, "v": state.v, "p": p, "q": q, **state.internal}


def _scan_steps(fn, carry, n: int, checkpoint: bool):
    def block(c):
        return jax.lax.scan(lambda c, _: (fn(c), None), c, None, length=n)[0]

    return jax.checkpoint(block)(carry) if checkpoint else block(carry)


def make_rollout(config: Config, observer: Observer | None = frame_observer, checkpoint: bool = True):
    """Build ``rollout(state, params) -> (final_state, frames)``.

    ``frames`` is the observer's pytree with a leading axis over ``config.frame_times`` (None
    when there are no frame times or no observer). The function is pure and unjitted: wrap it
    in ``jax.jit``, ``jax.vmap`` or ``jax.grad`` as needed. The final state's ``status`` carries
    the ``BUDGET`` bit if ``t_end`` was not reached within ``config.max_steps``.
    """
    step = make_step(config)
    frame_times = config.frame_times if observer is not None else ()
    n_frames = len(frame_times)
    n_blocks, block = config.blocks
    n_full, remainder = divmod(config.max_steps, block)

    def rollout(state, params):
        times = jnp.asarray(frame_times, state.t.dtype)

        def record(frames, k, s):
            return jax.tree.map(lambda f, o: f.at[k].set(o), frames, observer(s, params))

        if n_frames:
            first = observer(state, params)
            frames = jax.tree.map(lambda o: jnp.zeros((n_frames,) + o.shape, o.dtype), first)
            at_start = state.t == times[0]
            frames = jax.lax.cond(at_start, lambda f: record(f, 0, state), lambda f: f, frames)
            k = at_start.astype(jnp.int32)
        else:
            frames, k = None, jnp.zeros((), jnp.int32)

        def one(carry):
            s, frames, k = carry
            s = step(s, params)
            if n_frames:
                hit = (k < n_frames) & (s.t == times[jnp.minimum(k, n_frames - 1)])
                frames = jax.lax.cond(hit, lambda f: record(f, k, s), lambda f: f, frames)
                k = k + hit.astype(jnp.int32)
            return s, frames, k

        carry = (state, frames, k)
        carry = jax.lax.scan(
            lambda c, _: (_scan_steps(one, c, block, checkpoint), None), carry, None, length=n_full
        )[0]
        if remainder:
            carry = _scan_steps(one, carry, remainder, checkpoint)
        final, frames, _ = carry
        budget = jnp.where(final.t < config.t_end, st.BUDGET, 0)
        return final.replace(status=final.status | budget), frames

    return rollout
