"""Several objectives fitted together: a concatenation of their residuals (``CompositeObjective``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .bounds import Bounds
from .cache import BATCHES, content_key
from .objective import Objective
from .residuals import jacobian_by_columns

__all__ = ["CompositeObjective"]


def _shared_layout(members, shared: tuple[str, ...], labels) -> tuple[tuple[str, ...], list[np.ndarray]]:
    """The composite's keys (the shared ones, then each member's own as ``key@label``) and where
    each member's keys sit among them."""
    labels = tuple(str(label) for label in (labels or ()))
    if len(labels) != len(members) or len(set(labels)) != len(labels) or not all(labels):
        raise ValueError(f"labels: one distinct, non-empty label per member is needed ({len(members)} members), "
                         f"got {list(labels)}")
    if len(set(shared)) != len(shared):
        raise ValueError(f"shared: a key is repeated in {list(shared)}")
    for i, m in enumerate(members):
        missing = [k for k in shared if k not in m.keys]
        if missing:
            raise ValueError(f"shared: {missing} are not fitted by members[{i}] ({labels[i]}: {list(m.keys)})")
    keys = list(shared) + [f"{k}@{label}" for m, label in zip(members, labels) for k in m.keys if k not in shared]
    index = [np.asarray([keys.index(k if k in shared else f"{k}@{label}") for k in m.keys], int)
             for m, label in zip(members, labels)]
    return tuple(keys), index


class CompositeObjective:
    """Several objectives fitted together (e.g. one scene per aspect ratio), their residuals
    concatenated, so the loss is the sum of theirs (a ``calibration.problem.protocol.ObjectiveLike``).

    By default the members fit the same keys. With ``shared`` (and ``labels``, one per member) a
    key in ``shared`` is one value for every member, and any other key a member fits is its own,
    named ``key@label`` (its column zero for the other members); the residual blocks are named
    ``label/block`` (else ``i/block``)."""

    def __init__(self, members: Sequence[Objective], shared: Sequence[str] | None = None,
                 labels: Sequence[str] | None = None):
        members = tuple(members)
        if not members:
            raise ValueError("members: at least one objective is needed")
        if shared is None:
            keys = members[0].keys
            for i, m in enumerate(members):
                if m.keys != keys:
                    raise ValueError(f"members[{i}] fits {m.keys}, members[0] fits {keys}; say which keys are "
                                     "shared (shared=, --shared) to fit the others per experiment")
            index = [np.arange(len(keys))] * len(members)
            labels = None
        else:
            keys, index = _shared_layout(members, tuple(shared), labels)
        self.members, self.keys, self.shared, self.labels = members, tuple(keys), shared, labels
        self._index = tuple(np.asarray(i, int) for i in index)  # member i's keys at these composite positions
        # The box every member accepts (their bounds differ only where a scene's μ1 or μ2 narrowed them).
        lower = np.full(len(self.keys), -np.inf)
        upper = np.full(len(self.keys), np.inf)
        for m, idx in zip(members, self._index):
            lower[idx] = np.maximum(lower[idx], m.bounds.lower)
            upper[idx] = np.minimum(upper[idx], m.bounds.upper)
        if np.any(lower >= upper):
            raise ValueError("members: their bounds do not overlap (each member's scene narrows mu1 or mu2 to keep "
                             "mu1 <= mu2); fit scenes with compatible friction coefficients")
        self.bounds = Bounds(self.keys, tuple(float(v) for v in lower), tuple(float(v) for v in upper))
        self.bound_notes = tuple(note for m in members for note in m.bound_notes)
        self.dtype = members[0].dtype
        self._offsets = offsets = np.cumsum([0] + [m.n_residuals for m in members])
        self.n_residuals = int(offsets[-1])
        self._prefix = tuple(labels) if labels is not None else tuple(str(i) for i in range(len(members)))
        self.blocks = {f"{self._prefix[i]}/{name}": slice(offsets[i] + s.start, offsets[i] + s.stop)
                       for i, m in enumerate(members) for name, s in m.blocks.items()}
        self.row_scale = np.concatenate([m.row_scale for m in members])
        #: The composite's Jacobians are forward-mode autodiff through the members' runs.
        self.jacobian = "ad"

    @classmethod
    def sharing(cls, members: Sequence[Objective], shared: Sequence[str], labels: Sequence[str]):
        """Members that share the keys in ``shared`` and fit the rest of their keys each for
        itself (named ``key@label``)."""
        return cls(members, shared=shared, labels=labels)

    def expand(self, values: Mapping[str, float]) -> dict[str, float]:
        """Values by plain key (``beta``) as values of the composite's keys: a shared key as it
        is, a member's own key (``beta@label``) from the plain one; a composite key passes."""
        out = {}
        for k, v in values.items():
            if k in self.keys:
                out[k] = float(v)
                continue
            own = [c for c in self.keys if c.split("@")[0] == k]
            if not own:
                raise ValueError(f"{k!r} is not fitted (keys: {list(self.keys)})")
            out.update({c: float(v) for c in own})
        return out

    @property
    def parts(self) -> tuple[tuple[Objective, np.ndarray, Bounds], ...]:
        """Each member, with where its keys sit among the composite's and the bounds its z is
        mapped with (the composite's, on its keys)."""
        return tuple((m, idx, self._member_bounds(i)) for i, (m, idx) in enumerate(zip(self.members, self._index)))

    def join(self, outs) -> tuple:
        """The members' outputs (``(r, ...)`` tuples) as the composite's (``_joined``)."""
        return self._joined([tuple(np.asarray(a) for a in o[:-1]) + (o[-1],) for o in outs])

    def _member_theta(self, theta, i: int):
        """Member ``i``'s θ (or z) from the composite's: θ itself when every member fits the same
        keys, else its keys' entries (numpy stays numpy, a traced array stays traced)."""
        if self.shared is None:
            return theta
        idx = self._index[i]
        return theta[..., idx] if isinstance(theta, jax.Array) else np.asarray(theta)[..., idx]

    def _member_bounds(self, i: int) -> Bounds:
        if self.shared is None:
            return self.bounds
        idx = self._index[i]
        return Bounds(self.members[i].keys, tuple(self.bounds.lower[j] for j in idx),
                      tuple(self.bounds.upper[j] for j in idx))

    def _joined(self, outs) -> tuple:
        """The members' outputs, each ``(r, prediction)``, ``(r, J, prediction)`` or ``(r, J_z, J,
        prediction)``, as the composite's: the residuals concatenated, the Jacobians scattered into
        the composite's columns (``_scatter``), the predictions as ``{"status": every member's bits OR-ed,
        "members": [each member's]}``. numpy in, numpy out; anything else (traced) in jnp."""
        xp = np if all(isinstance(o[0], np.ndarray) for o in outs) else jnp
        preds = [o[-1] for o in outs]
        status = xp.bitwise_or.reduce(xp.stack([xp.asarray(p["status"]) for p in preds]))
        r = xp.concatenate([xp.asarray(o[0]) for o in outs])
        pred = {"status": status, "members": preds}
        return (r, *(self._scatter([o[j] for o in outs]) for j in range(1, len(outs[0]) - 1)), pred)

    def _scatter(self, jacobians):
        """The members' Jacobians (rows × their own keys) stacked as the composite's (rows ×
        keys), numpy in, numpy out."""
        xp = np if all(isinstance(J, np.ndarray) for J in jacobians) else jnp
        if self.shared is None:
            return xp.concatenate(jacobians)
        blocks = []
        for J, idx in zip(jacobians, self._index):
            full = np.zeros(J.shape[:-1] + (len(self.keys),), J.dtype)
            if xp is np:
                full[..., idx] = J
            else:
                full = jnp.zeros(J.shape[:-1] + (len(self.keys),), J.dtype).at[..., idx].set(J)
            blocks.append(full)
        return xp.concatenate(blocks)

    @property
    def dx(self) -> float:
        """The first gridded member's grid spacing, m (the grid term coarsens every member by one
        ratio); NaN where no member has a grid (closed forms)."""
        return next((m.dx for m in self.members if np.isfinite(m.dx)), float("nan"))

    @property
    def seeded(self) -> bool:
        return all(m.seeded for m in self.members)

    def coarsened(self, ratio: float) -> CompositeObjective:
        """Every member on a grid ``ratio`` times coarser (``Objective.coarsened``); a member with
        no grid (a closed form, whose ``coarsened`` raises ``NotImplementedError``) as it is."""
        members = []
        for m in self.members:
            try:
                members.append(m.coarsened(ratio))
            except NotImplementedError:
                members.append(m)
        if all(a is b for a, b in zip(members, self.members)):
            raise NotImplementedError("no member has a grid to coarsen")
        return CompositeObjective(members, self.shared, self.labels)

    def residuals_resampled(self, theta, seed: int):
        """The members' residuals at θ with every scene's particles drawn with ``seed``."""
        return self._joined([m.residuals_resampled(self._member_theta(theta, i), seed)
                             for i, m in enumerate(self.members)])

    @property
    def sampling_seed(self) -> None:
        """None: the members' particles are not one draw of one scene (``calibration.problem.protocol``)."""
        return None

    def batched_jacobian_z(self) -> Callable:
        """``Z (k, n) -> (r, dr/dz, dr/dθ, prediction)`` stacked over the rows of Z (the
        composite's bounds): one jit(vmap(...)) of the members' concatenated runs, kept in
        ``calibration.problem.cache.BATCHES`` by the composite's content (``content_key``)."""
        bounds = self.bounds

        def member(z):
            Jz, (r, pred) = jacobian_by_columns(lambda z_: self.residual_fn(bounds.to_physical(z_)), z)
            return r, Jz, Jz / bounds.jacobian_diag(z)[None, :], pred

        content = content_key(self)
        return BATCHES.get(None if content is None else ("search", content), lambda: jax.jit(jax.vmap(member)))

    def residual_fn(self, theta):
        """Pure, unjitted θ -> (r, prediction), the members' concatenated: for ``jax.vmap``."""
        return self._joined([m.residual_fn(self._member_theta(theta, i)) for i, m in enumerate(self.members)])

    def in_metres(self, r) -> dict[str, np.ndarray]:
        """The residuals in metres by block (``Objective.in_metres`` of each member)."""
        r, offsets = np.asarray(r, float), self._offsets
        return {f"{self._prefix[i]}/{name}": v for i, m in enumerate(self.members)
                for name, v in m.in_metres(r[offsets[i]:offsets[i + 1]]).items()}

    def residuals(self, theta):
        return self._joined([m.residuals(self._member_theta(theta, i)) for i, m in enumerate(self.members)])

    def residuals_and_jacobian_z(self, z):
        """(r, dr/dz, dr/dθ, prediction) at the unconstrained z of the composite's bounds (every
        member maps z with the composite's bounds, not its own)."""
        return self._joined([m.residuals_and_jacobian_z(self._member_theta(z, i), self._member_bounds(i))
                             for i, m in enumerate(self.members)])

    def residuals_and_jacobian(self, theta):
        return self._joined([m.residuals_and_jacobian(self._member_theta(theta, i))
                             for i, m in enumerate(self.members)])

    def value_and_grad(self, theta):
        outs = [m.value_and_grad(self._member_theta(theta, i)) for i, m in enumerate(self.members)]
        loss = sum(o[0][0] for o in outs)
        status = jnp.bitwise_or.reduce(jnp.stack([o[0][1]["status"] for o in outs]))
        grad = jnp.zeros(len(self.keys), jnp.result_type(outs[0][1]))
        for (_, g), idx in zip(outs, self._index):
            grad = grad.at[idx].add(g)
        return (loss, {"status": status}), grad

    def loss(self, theta) -> float:
        return sum(m.loss(self._member_theta(theta, i)) for i, m in enumerate(self.members))

    def initial(self) -> dict[str, float]:
        """Each composite key's scene value (a shared key's from the first member fitting it)."""
        out = {}
        for m, idx in zip(self.members, self._index):
            values = m.initial()
            for k, j in zip(m.keys, idx):
                out.setdefault(self.keys[j], values[k])
        return {k: out[k] for k in self.keys}

    def check_thetas(self, thetas, name: str = "thetas") -> None:
        for i, member in enumerate(self.members):
            member.check_thetas(self._member_theta(thetas, i), name)

    def fingerprint(self) -> dict[str, Any]:
        out = {"members": [m.fingerprint() for m in self.members]}
        if self.shared is not None:
            out.update(shared=list(self.shared), labels=list(self.labels), keys=list(self.keys))
        return out

    def describe(self) -> dict[str, Any]:
        out = {"members": [m.describe() for m in self.members], "keys": list(self.keys)}
        if self.shared is not None:
            out.update(shared=list(self.shared), labels=list(self.labels))
        return out
