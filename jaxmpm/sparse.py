"""A grid only where the material is: the active nodes of a step, found from the
particles, in a fixed number of slots.

The dense grid holds every node of the bounding box; a kilometre-long avalanche path with a
metre-deep flow would need tens of millions of them. With ``Config(active_nodes=K)`` the grid is
the same virtual grid, but each step keeps only the nodes that some particle's stencil touches,
in K slots:

1. the stencil's flat node numbers (S, N) are sorted (one sort of S·N integers); the first of
   each run of equal numbers opens a slot, in increasing node order;
2. each stencil entry gets its node's slot number (a binary search per stencil row); P2G scatters
   into, and G2P gathers from, K-long arrays through these slots, and the walls and terrain see
   each slot's node position;
3. if more than K nodes are touched, the step sets the ``GRID_FULL`` status bit (the run must be
   repeated with a larger K): nothing is dropped silently.

The slots are integers computed from the positions, so the transfers are the dense grid's with a
renumbering: each node's sum is accumulated in the same order, and the results equal the dense
grid's to round-off (tested). Everything stays jit/vmap/grad-compatible; the cost grows with the
number of particles, not with the bounding box.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .kernels import node_strides

__all__ = ["activate", "slot_positions"]


def activate(index, capacity: int, n_nodes: int, consecutive_rows: bool = True):
    """Slots of the nodes a stencil touches.

    Args:
      index: (S, N) flat node numbers of the dense grid (``Stencil.index``), S = 3^dim in the
        stencil's order (the last axis fastest).
      capacity: the number of slots K.
      n_nodes: the dense grid's node count (the number an empty slot holds).
      consecutive_rows: the three nodes of each stencil row along the last axis have consecutive
        numbers (true unless the last axis is periodic). Then only the first of each row is
        looked up: the other two are touched too, so they hold the next two slots.

    Returns:
      ``(slots, keys, count)``: (S, N) slot of each stencil entry, (K,) node number held by each
      slot in increasing order (``n_nodes`` where empty), and the number of distinct nodes
      touched (> K: overflow, the slots are then wrong and the caller flags the run).

    The node numbers are sorted alone (a sort with a payload costs 5 times more on the CPU) and
    each stencil row finds its slot by binary search in the sorted distinct numbers.
    """
    flat = index.reshape(-1)
    keys = jnp.sort(flat)
    opens = jnp.concatenate([jnp.ones((1,), bool), keys[1:] != keys[:-1]])
    rank = jnp.cumsum(opens, dtype=jnp.int32) - 1
    held = jnp.full((capacity,), n_nodes, flat.dtype).at[rank].set(keys, mode="drop")
    if consecutive_rows:
        starts = jnp.searchsorted(held, index[::3]).astype(flat.dtype)  # (S/3, N)
        slots = (starts[:, None, :] + jnp.arange(3, dtype=flat.dtype)[None, :, None]).reshape(index.shape)
    else:
        slots = jnp.searchsorted(held, index).astype(flat.dtype)
    return slots, held, rank[-1] + 1


def slot_positions(keys, grid, dtype):
    """(dim, K) positions of the nodes held in the slots, the same numbers as
    ``grid.node_positions()`` (each axis's coordinates are tabulated as the dense grid's are)."""
    strides = node_strides(grid.nodes)
    rest = keys
    out = []
    for a, n in enumerate(grid.nodes):
        i = rest // strides[a]
        rest = rest - i * strides[a]
        table = jnp.asarray(grid.origin[a] + grid.dx * np.arange(n), dtype)
        out.append(table[jnp.clip(i, 0, n - 1)])
    return jnp.stack(out)
