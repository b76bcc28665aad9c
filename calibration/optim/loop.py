"""One driver loop for the optimisers of ``calibration.optim.lm`` and ``.adam``, on a batch of starts.

An optimiser is an ``(init, update)`` pair in the style of ``optax.GradientTransformation``, on
k starts at once in the unconstrained z: ``init(z) -> state`` from the starts z (k, n), and
``update(evaluation, state) -> state`` from the runs at ``state.z_next``. Every state carries, per
start, ``z_next``, ``accepted`` (the last evaluation was taken), ``done`` and ``message`` (empty
while a start goes on; a finished start's begins with "converged", a verified minimum, or
"stopped"). ``run`` owns the rest: evaluating the starts that are not done, recording every
iteration in a ``calibration.optim.history.History``, and stopping. Everything is numpy with a
leading batch axis (the model runs are the cost).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

from jaxmpm import describe_status

from .evaluate import Evaluation

__all__ = ["Optimiser", "status_text", "where_rows", "run"]


class Optimiser(NamedTuple):
    """``init(z) -> state`` and ``update(evaluation, state) -> state`` (see the module's text)."""

    init: Callable[[np.ndarray], Any]
    update: Callable[[Evaluation, Any], Any]


def status_text(status: int) -> str:
    return f"status {status}: {'; '.join(describe_status(status))}" if status else "status 0"


def where_rows(mask, new, old):
    """``new`` where ``mask`` (k,), else ``old``, row by row in every leaf of two like pytrees."""
    mask = np.asarray(mask, bool)
    return jax.tree.map(lambda a, b: np.where(mask.reshape((-1,) + (1,) * (np.ndim(a) - 1)), a, b), new, old)


def _take(state, rows):
    """The rows ``rows`` of ``state``."""
    return jax.tree.map(lambda a: a[rows], state)


def _put(state, rows, part):
    """``state`` with its rows ``rows`` replaced by ``part`` (a state of those rows). With every
    row, ``part`` is the new state (so an update may fill a field that was None: LM's first)."""
    if len(rows) == len(state.done):
        return part

    def put(full, sub):
        full = np.array(full, copy=True)
        full[rows] = sub
        return full

    return jax.tree.map(put, state, part)


def run(optimiser: Optimiser, state, evaluate: Callable[[np.ndarray], Evaluation], history, *, steps: int,
        check_start: Callable[[Evaluation], None] | None = None,
        report: Callable[[Any, np.ndarray], None] | None = None, stop: Callable[[Any], Any] | None = None):
    """Evaluate and update the starts of ``state`` until every one is done or ``history``
    holds ``steps`` iterations; returns the final state, in which a start that ran out of
    iterations has the message "stopped after N iterations (steps = ...)".

    ``evaluate(z)``: the model at the rows z (b, n) of the starts that are not done; where the
    state has ``want_jacobian`` (LM with Broyden's updates), ``evaluate(z, jacobian=mask)``, the
    Jacobian needed only in the rows of ``mask``.
    ``check_start(evaluation)``: called with the first evaluation of an empty history before
    it is recorded (it raises to refuse the starts). ``stop(state) -> state``: after each update,
    may end starts the optimiser would go on with (``done``, with their message). ``report(state,
    rows)``: called after each iteration is recorded and saved, with the rows that took part."""
    while history.iterations < steps and not state.done.all():
        rows = np.flatnonzero(~state.done)
        z = state.z_next[rows]
        want = getattr(state, "want_jacobian", None)  # LM with Broyden's updates: which rows need their Jacobian
        evaluation = evaluate(z) if want is None else evaluate(z, jacobian=want[rows])
        if check_start is not None and not history.iterations:
            check_start(evaluation)
        state = _put(state, rows, optimiser.update(evaluation, _take(state, rows)))
        if stop is not None:
            state = stop(state)
        history.record(rows, z, evaluation, state)
        if report is not None:
            report(state, rows)
    message = state.message.copy()
    for i in np.flatnonzero(~state.done):
        message[i] = f"stopped after {history.length(i)} iterations (steps = {steps})"
    return state._replace(message=message)
