"""What an objective is: the members the calibration's functions call on one.

``ResidualModel`` is a pure θ -> residuals map with its keys (what sweeps and the NUTS log density
need; a closed-form stand-in implements this much); ``ObjectiveLike`` adds what a fit, a search
and their uncertainty call. ``calibration.Objective`` and ``calibration.CompositeObjective``
implement ``ObjectiveLike``; the consumers rely on it and probe for nothing. Both protocols are
``runtime_checkable`` (``isinstance`` checks that every member is there, not their signatures).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .bounds import Bounds

__all__ = ["ObjectiveLike", "ResidualModel", "as_theta", "is_valid"]


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
      depend on (equal fingerprints: equal residuals); None where there is none (nothing is then
      cached or checked).
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

    - ``bounds``: the box of θ and its map to z; ``bound_notes``: why a bound was narrowed;
      ``initial()``: the scene's values of the keys (a fit's default start); ``expand(values)``:
      values by plain key as values of the objective's keys (a composite spreads them).
    - ``blocks``: each residual block's name and rows; ``row_scale``: every row's weight factor
      (``r / row_scale`` is the unweighted residual); ``in_metres(r)``: the residuals in metres
      by block (model − data).
    - Evaluations, compiled once (θ physical, z unconstrained; J = dr/dθ, J_z = dr/dz):
      ``residuals(theta) -> (r, prediction)``; ``residuals_and_jacobian(theta) -> (r, J,
      prediction)`` by ``jacobian`` ("ad" or "fd"); ``residuals_and_jacobian_z(z) -> (r, J_z, J,
      prediction)`` from one trace; ``batched_jacobian_z() -> fn``, the same at every row of
      ``Z`` (k, n); ``value_and_grad(theta) -> ((Σ r², prediction), dΣr²/dθ)``, reverse mode.
    - ``parts``: each single objective it concatenates, with where its keys sit among these (an
      index array) and the bounds its z is mapped with; a part makes its own worker tasks
      (``column_task(z, tangent, bounds)``, ``residual_task(theta, seed)``: ``(fn, args)``
      pairs); ``join(outs)``: the parts' outputs (``(r, ..., prediction)``) as this objective's.
    - For the verdict's extra runs: ``dx`` (m) and ``coarsened(ratio)``, the objective on a grid
      ``ratio`` times coarser; ``seeded``, whether the particles can be drawn again,
      ``sampling_seed`` (None where they are not one draw of one scene: a lattice, a composite)
      and ``residuals_resampled(theta, seed)``."""

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


def is_valid(objective: ResidualModel, theta) -> bool:
    """Whether ``theta`` (n,) is a parameter set of ``objective``'s model (``check_thetas`` passes)."""
    try:
        objective.check_thetas(np.asarray(theta)[None, :])
    except ValueError:
        return False
    return True


def as_theta(theta, keys: Sequence[str], dtype, name: str = "theta"):
    """``theta`` as a JAX array of ``dtype``, its shape checked against ``keys`` (one value each)."""
    import jax.numpy as jnp

    theta = jnp.asarray(theta, dtype)
    if theta.shape != (len(keys),):
        raise ValueError(f"{name} must have shape ({len(keys)},) for keys {tuple(keys)}, got {theta.shape}")
    return theta
