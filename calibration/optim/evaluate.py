"""The model at a batch of points z, as the optimisers see it.

An ``Evaluation`` holds the runs at k points; the evaluators make one from the rows z that
``calibration.optim.loop.run`` asks for: ``evaluator`` for a single fit, ``BatchEvaluator`` for a
search's batch of starts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..batch.workers import jacobians_z
from ..problem.protocol import ObjectiveLike

__all__ = ["BatchEvaluator", "Evaluation", "evaluator"]


class Evaluation(NamedTuple):
    """Model runs at k points z: every field has a leading axis k (None: not computed, the
    same fields for every evaluation of one evaluator)."""

    theta: np.ndarray  # (k, n) the physical parameters
    loss: np.ndarray  # (k,) the sum of squared residuals
    status: np.ndarray  # (k,) the runs' status bits
    grad: np.ndarray  # (k, n) dloss/dθ (its norm is recorded)
    residuals: np.ndarray | None  # (k, m)
    jacobian: np.ndarray | None  # (k, m, n) dr/dθ, for the result
    jacobian_z: np.ndarray | None  # (k, m, n) dr/dz: LM's step
    grad_z: np.ndarray | None  # (k, n) dloss/dz: Adam's step
    prediction: Any  # a pytree of arrays (k, ...), with "status"


def evaluator(objective: ObjectiveLike, rev: bool, workers=None) -> Callable[[np.ndarray], Evaluation]:
    """The model at the rows of z (k, n), one run each: residuals and their Jacobian from the
    objective (forward mode, or its differences), or with ``rev`` the reverse-mode gradient alone;
    ``evaluate(z, jacobian=mask)``: the residuals alone in the rows outside ``mask`` (their
    Jacobians and gradients NaN).
    With parallel ``workers`` (``calibration.batch.workers``) the forward-mode passes, one per key and
    row, run in the worker processes."""
    bounds = objective.bounds
    z_space = objective.jacobian == "ad"  # else central differences in θ (``residuals_and_jacobian``)
    if z_space and not rev and workers is not None and workers.parallel:
        return lambda Z, jacobian=None: _of_jacobians(bounds, Z, *jacobians_z(objective, Z, workers, jacobian),
                                                      with_grad_z=True)

    def one(z, with_jacobian=True):
        theta = np.asarray(bounds.to_physical(jnp.asarray(z)))
        dtheta_dz = np.asarray(bounds.jacobian_diag(jnp.asarray(z)))
        if not (rev or with_jacobian):  # the residuals alone (LM's Broyden trials): the Jacobian NaN
            r, pred = objective.residuals(theta)
            r = np.asarray(r, float)
            nan = np.full((r.size, len(theta)), np.nan)
            return theta, float(np.sum(r * r)), int(np.asarray(pred["status"])), nan[0], r, nan, nan, nan[0], pred
        if rev:
            (loss, pred), g = objective.value_and_grad(theta)
            r = J = Jz = None
            g = np.asarray(g)
        else:
            if z_space:  # dr/dz and dr/dθ from one autodiff trace through the bounds transform
                r, Jz, J, pred = objective.residuals_and_jacobian_z(jnp.asarray(z))
                r, Jz, J = np.asarray(r, float), np.asarray(Jz, float), np.asarray(J, float)
            else:  # central differences in θ
                r, J, pred = objective.residuals_and_jacobian(theta)
                r, J = np.asarray(r, float), np.asarray(J, float)
                Jz = J * dtheta_dz[None, :]
            with np.errstate(invalid="ignore", over="ignore"):
                loss, g = np.sum(r * r), 2.0 * J.T @ r
            return theta, float(loss), int(np.asarray(pred["status"])), g, r, J, Jz, 2.0 * Jz.T @ r, pred
        return theta, float(loss), int(np.asarray(pred["status"])), g, r, J, Jz, g * dtheta_dz, pred

    def evaluate(z, jacobian=None):
        jacobian = np.ones(len(z), bool) if jacobian is None else jacobian
        theta, loss, status, g, r, J, Jz, g_z, pred = zip(*[one(row, w) for row, w in zip(z, jacobian)])
        r, J, Jz = (None if parts[0] is None else np.stack(parts) for parts in (r, J, Jz))
        return Evaluation(theta=np.stack(theta), loss=np.array(loss), status=np.array(status), grad=np.stack(g),
                          residuals=r, jacobian=J, jacobian_z=Jz, grad_z=np.stack(g_z),
                          prediction=jax.tree.map(lambda *leaves: np.stack([np.asarray(a) for a in leaves]), *pred))

    return evaluate


def _of_jacobians(bounds, Z, r, Jz, J, pred, *, with_grad_z: bool) -> Evaluation:
    """The ``Evaluation`` of forward-mode runs at the rows Z from their residuals r (k, m) and
    Jacobians Jz, J (k, m, n) in z and θ; ``grad_z`` only ``with_grad_z``."""
    r, Jz, J = np.asarray(r, float), np.asarray(Jz, float), np.asarray(J, float)
    with np.errstate(invalid="ignore", over="ignore"):  # dθ/dz = 0 at a bound: J, |g| inf
        g = np.einsum("kmn,km->kn", 2.0 * J, r)
    g_z = np.einsum("kmn,km->kn", 2.0 * Jz, r) if with_grad_z else None
    return Evaluation(theta=np.asarray(bounds.to_physical(jnp.asarray(Z)), float), loss=np.sum(r * r, axis=1),
                      status=np.asarray(pred["status"], int).reshape(-1), grad=g, residuals=r, jacobian=J,
                      jacobian_z=Jz, grad_z=g_z, prediction=pred)


class BatchEvaluator:
    """The model at the rows of z of a search's active starts in one batched, compiled call,
    padded to a power of two up to ``k`` (``shrink``; else always ``k``) so that a shrinking batch
    compiles at most log2 k + 1 times; with parallel ``workers`` the rows' forward-mode passes
    go to the workers instead, unpadded. Counts the runs (``evaluations``) and the seconds of the
    first call of each size (``compile_s``: compilation and one run)."""

    def __init__(self, objective, k: int, shrink: bool, workers):
        self.objective, self.k, self.shrink, self.workers = objective, k, shrink, workers
        self.parallel = workers is not None and workers.parallel
        self.batch = None if self.parallel else objective.batched_jacobian_z()
        self.compile_s, self.evaluations, self.sizes = 0.0, 0, set()

    def __call__(self, Z, jacobian=None) -> Evaluation:
        """The runs at the rows of Z; ``jacobian`` (mask): with workers, the residuals alone in the
        rows outside it (their Jacobians NaN); the vmapped batch gives every row's Jacobian."""
        objective, dtype = self.objective, self.objective.dtype
        b = Z.shape[0]
        size = b if self.parallel else (min(self.k, 1 << (b - 1).bit_length()) if self.shrink else self.k)
        padded = np.concatenate([Z, np.repeat(Z[:1], size - b, axis=0)]) if size > b else Z
        clock = time.perf_counter()
        if self.parallel:
            r, Jz, J, pred = jacobians_z(objective, np.asarray(padded, dtype), self.workers, jacobian)
        else:
            r, Jz, J, pred = jax.tree.map(np.asarray, self.batch(jnp.asarray(padded, dtype)))
        if size not in self.sizes:
            self.sizes.add(size)
            self.compile_s += time.perf_counter() - clock  # the first call of a shape: compile + one run
        self.evaluations += size
        r, Jz, J = (np.array(a[:b], float) for a in (r, Jz, J))
        return _of_jacobians(objective.bounds, Z, r, Jz, J, jax.tree.map(lambda a: a[:b], pred), with_grad_z=False)
