"""What an objective is: the attributes and methods the calibration's functions call on one.

Two protocols, one inside the other:

- ``ResidualModel``: a pure θ -> residuals map with its keys, what ``calibration.sweep``,
  ``calibration.cluster`` and the NUTS log density (``calibration.mcmc``) need. A closed-form
  stand-in (the tests' toys) implements this much.
- ``ObjectiveLike``: everything ``fit``, ``search``, ``uncertainty``, ``likelihood``, ``design``,
  ``mcmc``, ``plots`` and ``report`` call: bounds, the residual blocks and their weights, the
  residuals with their Jacobians in θ and in the unconstrained z of ``calibration.bounds``, the
  tasks that ``calibration.workers`` spreads over processes, and the hooks of the verdict's
  extra runs (particles drawn again, a coarser grid).

``calibration.Objective`` and ``calibration.CompositeObjective`` implement ``ObjectiveLike``;
the consumers rely on it and probe for nothing. Both protocols are ``runtime_checkable``, so
``isinstance(x, ObjectiveLike)`` checks that every member is there (not their signatures).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .bounds import Bounds

__all__ = ["ObjectiveLike", "ResidualModel"]


@runtime_checkable
class ResidualModel(Protocol):
    """A pure map from physical parameter values θ (ordered as ``keys``) to weighted residuals.

    - ``keys``: the fitted parameters' names; ``dtype``: the float type the runs compute in.
    - ``residual_fn(theta) -> (r, prediction)``: pure and unjitted (for ``jax.vmap``);
      ``prediction`` a dict that may hold ``status`` (the run's status bits, 0: a good run).
    - ``check_thetas(thetas, name)``: raise ``ValueError`` naming the rows of ``thetas`` (B, n)
      that are not parameter sets of the model (a member with μ2 < μ1, say); ``name`` is the
      argument named in the message.
    - ``fingerprint() -> dict | None``: a JSON-able description of everything the residuals
      depend on (equal fingerprints: equal residuals), the content key of compiled batches and
      of a resumed fit's check; None where there is none to give (nothing is then cached or
      checked).
    - ``describe() -> dict``: a JSON-able summary for the files a run writes."""

    keys: tuple[str, ...]
    dtype: Any

    def residual_fn(self, theta) -> tuple[Any, dict[str, Any]]: ...

    def check_thetas(self, thetas, name: str = "thetas") -> None: ...

    def fingerprint(self) -> dict[str, Any] | None: ...

    def describe(self) -> dict[str, Any]: ...


@runtime_checkable
class ObjectiveLike(ResidualModel, Protocol):
    """An objective a fit, a search and their uncertainty work with (beyond ``ResidualModel``).

    Data and weights:

    - ``bounds``: the box of θ and its map to z; ``bound_notes``: why a bound was narrowed.
    - ``blocks``: each residual block's name and rows; ``row_scale``: every row's weight factor
      (``r / row_scale`` is the unweighted residual); ``n_residuals``: the rows.
    - ``in_metres(r)``: the residuals ``r`` in metres by block (model − data).
    - ``initial()``: the scene's values of the keys (a fit's default start); ``expand(values)``:
      values by plain key as values of the objective's keys (a composite spreads them).
    - ``members``: the single objectives this one is made of (an ``Objective``: itself).

    Evaluations (θ physical, z unconstrained; J = dr/dθ, J_z = dr/dz):

    - ``residuals(theta) -> (r, prediction)``; ``loss(theta) -> Σ r²``.
    - ``residuals_and_jacobian(theta) -> (r, J, prediction)``, by ``jacobian``: "ad" (forward
      mode) or "fd" (central differences); a fit with "ad" uses the z-space call below instead.
    - ``residuals_and_jacobian_z(z) -> (r, J_z, J, prediction)``: both Jacobians from one trace.
    - ``batched_jacobian_z() -> fn``: ``fn(Z)`` is ``residuals_and_jacobian_z`` at every row of
      ``Z`` (k, n) in one compiled, vmapped call (stacked outputs), compiled once per content.
    - ``value_and_grad(theta) -> ((loss, prediction), dloss/dθ)``: reverse mode.

    Work for ``calibration.workers`` (each task ``(fn, args)`` picklable, run in any process):

    - ``column_tasks_z(z)`` and ``combine_columns_z(results) -> (r, J_z, J, prediction)``;
    - ``residual_tasks(thetas, seeds)`` and ``combine_residuals(results, rows) -> [(r, prediction)]``.

    The verdict's extra runs (``calibration.uncertainty``):

    - ``dx``: the grid spacing (m); ``coarsened(ratio)``: the same objective on a grid ``ratio``
      times coarser.
    - ``seeded``: whether the particles can be drawn again with another seed;
      ``sampling_seed``: the seed of the particles' own draw (None where they cannot be drawn
      again as one scene: a lattice, a composite); ``residuals_resampled(theta, seed)``."""

    bounds: Bounds
    bound_notes: tuple[str, ...]
    blocks: Mapping[str, slice]
    row_scale: np.ndarray
    n_residuals: int
    jacobian: str

    @property
    def members(self) -> Sequence[Any]: ...

    @property
    def dx(self) -> float: ...

    @property
    def seeded(self) -> bool: ...

    @property
    def sampling_seed(self) -> int | None: ...

    def initial(self) -> dict[str, float]: ...

    def expand(self, values: Mapping[str, float]) -> dict[str, float]: ...

    def in_metres(self, r) -> dict[str, np.ndarray]: ...

    def residuals(self, theta) -> tuple[Any, dict[str, Any]]: ...

    def loss(self, theta) -> float: ...

    def residuals_and_jacobian(self, theta) -> tuple[Any, Any, dict[str, Any]]: ...

    def residuals_and_jacobian_z(self, z) -> tuple[Any, Any, Any, dict[str, Any]]: ...

    def batched_jacobian_z(self) -> Callable: ...

    def value_and_grad(self, theta) -> tuple[tuple[Any, dict[str, Any]], Any]: ...

    def residuals_resampled(self, theta, seed: int) -> tuple[Any, dict[str, Any]]: ...

    def coarsened(self, ratio: float) -> ObjectiveLike: ...

    def column_tasks_z(self, z) -> list[tuple]: ...

    def combine_columns_z(self, results) -> tuple: ...

    def residual_tasks(self, thetas, seeds=None) -> list[tuple]: ...

    def combine_residuals(self, results, rows: int) -> list[tuple]: ...
