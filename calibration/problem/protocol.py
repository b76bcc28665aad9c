"""What an objective is: the members the calibration's functions call on one.

Two protocols, one inside the other:

- ``ResidualModel``: a pure θ -> residuals map with its keys, what ``calibration.batch.sweep``,
  ``calibration.batch.cluster`` and the NUTS log density (``calibration.inference.nuts``) need. A
  closed-form stand-in (the tests' toys) implements this much.
- ``ObjectiveLike``: what ``fit``, ``search``, the verdict, the likelihoods, the posteriors, the
  designer, the plots and the report call besides.

``calibration.Objective`` (one ``Problem`` with its data) and ``calibration.CompositeObjective``
(a concatenation of them) implement ``ObjectiveLike``; the consumers rely on it and probe for
nothing. Both protocols are ``runtime_checkable``: ``isinstance(x, ObjectiveLike)`` checks that
every member is there (not their signatures).
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

    The fitted box and the residuals' layout:

    - ``bounds``: the box of θ and its map to z; ``bound_notes``: why a bound was narrowed;
      ``initial()``: the scene's values of the keys (a fit's default start); ``expand(values)``:
      values by plain key as values of the objective's keys (a composite spreads them).
    - ``blocks``: each residual block's name and rows; ``row_scale``: every row's weight factor
      (``r / row_scale`` is the unweighted residual); ``in_metres(r)``: the residuals in metres
      by block (model − data).

    Evaluations (θ physical, z unconstrained; J = dr/dθ, J_z = dr/dz), compiled once:

    - ``residuals(theta) -> (r, prediction)``;
    - ``residuals_and_jacobian(theta) -> (r, J, prediction)``, by ``jacobian``: "ad" (forward
      mode) or "fd" (central differences); ``residuals_and_jacobian_z(z) -> (r, J_z, J,
      prediction)``, both Jacobians from one trace; ``batched_jacobian_z() -> fn``: the same at
      every row of ``Z`` (k, n) in one vmapped call; ``value_and_grad(theta) -> ((Σ r²,
      prediction), dΣr²/dθ)``, reverse mode.

    What it is made of, for the work ``calibration.batch.workers`` spreads over processes:

    - ``parts``: each single objective it concatenates, with where that one's keys sit among
      these (an index array) and the bounds its z is mapped with; a part makes its own tasks
      (``column_task(z, tangent, bounds)``, ``residual_task(theta, seed)``: ``(fn, args)``
      pairs, e.g. ``calibration.problem.residuals.column_pass``); ``join(outs)``: the parts'
      outputs (``(r, ..., prediction)`` tuples) as this objective's.

    The verdict's extra runs (``calibration.inference.scatter`` and ``.gridcheck``):

    - ``dx``: the grid spacing (m); ``coarsened(ratio)``: the same objective on a grid ``ratio``
      times coarser.
    - ``seeded``: whether the particles can be drawn again; ``sampling_seed``: the seed of their
      own draw (None where they are not one draw of one scene: a lattice, a composite);
      ``residuals_resampled(theta, seed)``."""

    bounds: Bounds
    bound_notes: tuple[str, ...]
    blocks: Mapping[str, slice]
    row_scale: np.ndarray
    jacobian: str

    @property
    def parts(self) -> Sequence[tuple[Any, np.ndarray, Bounds]]: ...

    @property
    def dx(self) -> float: ...

    @property
    def seeded(self) -> bool: ...

    @property
    def sampling_seed(self) -> int | None: ...

    def initial(self) -> dict[str, float]: ...

    def expand(self, values: Mapping[str, float]) -> dict[str, float]: ...

    def in_metres(self, r) -> dict[str, np.ndarray]: ...

    def join(self, outs) -> tuple: ...

    def residuals(self, theta) -> tuple[Any, dict[str, Any]]: ...

    def residuals_and_jacobian(self, theta) -> tuple[Any, Any, dict[str, Any]]: ...

    def residuals_and_jacobian_z(self, z) -> tuple[Any, Any, Any, dict[str, Any]]: ...

    def batched_jacobian_z(self) -> Callable: ...

    def value_and_grad(self, theta) -> tuple[tuple[Any, dict[str, Any]], Any]: ...

    def residuals_resampled(self, theta, seed: int) -> tuple[Any, dict[str, Any]]: ...

    def coarsened(self, ratio: float) -> ObjectiveLike: ...
