"""optax Adam in the unconstrained variables z, for a batch of starts, as an ``(init, update)`` pair.

``adam(learning_rate, steps, clip)`` clips each start's gradient dloss/dz to a global norm of
``clip`` and scales it by Adam with a cosine learning-rate schedule over ``steps`` iterations
(optax's transformations, vmapped over the starts so that no start's gradient clips another's).
Each evaluation is at the current point; a start whose run fails (status bits, a non-finite loss
or gradient) stops there with a message that begins "stopped", and takes no step.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .evaluate import Evaluation
from .loop import Optimiser, status_text, where_rows

__all__ = ["AdamState", "adam"]


class AdamState(NamedTuple):
    z_next: np.ndarray  # (k, n) the current points, where the next evaluation is
    inner: Any  # optax's state, every leaf with a leading axis k
    count: np.ndarray  # (k,) evaluations so far
    accepted: np.ndarray  # (k,) whether the last evaluation was usable (a step was taken)
    done: np.ndarray  # (k,)
    message: np.ndarray  # (k,) object: "" while a start goes on


def adam(learning_rate: float, steps: int, clip: float) -> Optimiser:
    schedule = optax.cosine_decay_schedule(learning_rate, decay_steps=steps, alpha=0.05)
    transform = optax.chain(optax.clip_by_global_norm(clip), optax.adam(schedule))

    def init(z):
        z = np.asarray(z, float)
        k = z.shape[0]
        return AdamState(z_next=z, inner=jax.vmap(transform.init)(jnp.asarray(z)), count=np.zeros(k, int),
                         accepted=np.zeros(k, bool), done=np.zeros(k, bool), message=np.full(k, "", object))

    def update(evaluation: Evaluation, state: AdamState) -> AdamState:
        ok = (evaluation.status == 0) & np.isfinite(evaluation.loss) & np.all(np.isfinite(evaluation.grad), axis=1)
        z = jnp.asarray(state.z_next)
        with jax.numpy_dtype_promotion("standard"):  # optax's schedules mix int counts and floats
            updates, inner = jax.vmap(transform.update)(jnp.asarray(evaluation.grad_z), state.inner, z)
            z_next = np.asarray(optax.apply_updates(z, updates), float)
        messages = np.array([f"stopped: the run at iteration {i} failed ({status_text(int(s))})"
                             for i, s in zip(state.count, evaluation.status)], object)
        return AdamState(z_next=np.where(ok[:, None], z_next, state.z_next),
                         inner=where_rows(ok, inner, state.inner), count=state.count + 1, accepted=ok,
                         done=state.done | ~ok, message=np.where(ok, state.message, messages))

    return Optimiser(init, update)
