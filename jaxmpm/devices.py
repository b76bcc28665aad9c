"""A run split over devices by its particles (``simulate(..., devices=K)``).

Each of K devices holds 1/K of the particles and a whole grid. A step scatters each device's
particles to its grid, sums the K grids (one all-reduce of the grid's mass, momentum, force and,
with side walls, pressure), updates the grid on every device alike and gathers back to the
device's own particles. The time step (the largest speed) and the status bits are reduced over
the devices, so every device holds the same clock. The result equals the undivided run's up to
the order of the grid's sums (round-off).

The devices are JAX's: GPUs, or CPU devices made with ``jax.config.update("jax_num_cpu_devices",
K)`` before JAX starts (``python -m jaxmpm run --devices K`` does it; the process then runs on K
cores). A particle count that K does not divide is padded with copies of the first particle
that carry no mass or volume: they add nothing to the grid, follow that particle exactly, and are
cut off the result. Only the per-particle frames of ``frame_observer`` (or none) are recorded:
another observer may reduce over particles, which one device alone cannot; a sparse grid's slots
are each device's own, so it is refused too. docs/performance.md measures what this gains.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from .config import Config
from .rollout import frame_observer
from .state import State

__all__ = ["PARTICLE_AXIS", "check_devices", "padded", "unpadded", "specs", "split"]

#: The name of the mesh axis over which the particles are shared.
PARTICLE_AXIS = "particles"

# State's per-particle fields; the others (clock, status, impulse) are the same on every device.
_PER_PARTICLE = ("x", "v", "C", "F", "tau", "vol0", "internal")


def check_devices(devices, config: Config, state: State, observer) -> int:
    """``devices`` as an int (None: 1), or a ``ValueError`` naming what cannot be split, before
    anything compiles."""
    if devices is None:
        return 1
    if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or devices < 1:
        raise ValueError(f"devices must be a positive integer, got {devices!r}")
    devices = int(devices)
    if devices == 1:
        return 1
    if config.active_nodes is not None:
        raise ValueError("devices: a sparse grid (Config.active_nodes) is not split over devices (each device's "
                         "slots would be its own); run it on one device")
    if observer is not None and observer is not frame_observer:
        raise ValueError("observer: a run split over devices records frame_observer's per-particle frames or none; "
                         "another observer may reduce over the particles, which a device holding a share cannot")
    if np.ndim(state.x) != 2:
        raise ValueError(f"state: a batch of states (x of shape {np.shape(state.x)}) is not split over devices; "
                         "run the members one by one, or the batch on one device")
    available = jax.devices()
    if devices > len(available):
        raise ValueError(f"devices={devices}: JAX sees {len(available)} {available[0].platform} device(s); on a CPU "
                         f"call jax.config.update('jax_num_cpu_devices', {devices}) before JAX starts (python -m "
                         f"jaxmpm run --devices {devices} does)")
    return devices


def padded(state: State, devices: int) -> State:
    """``state`` with its particles padded to a multiple of ``devices`` by copies of the first,
    with no volume (so no mass, momentum, force or pressure on the grid)."""
    extra = (-state.n_particles) % devices
    if not extra:
        return state

    def pad(a):
        return jnp.concatenate([a, jnp.repeat(a[:1], extra, axis=0)])

    fields = {name: jax.tree.map(pad, getattr(state, name)) for name in _PER_PARTICLE}
    fields["vol0"] = jnp.concatenate([state.vol0, jnp.zeros((extra,), state.vol0.dtype)])
    return state.replace(**fields)


def unpadded(state: State, frames, n: int) -> tuple[State, Any]:
    """The final state and the frames of the first ``n`` particles (``padded``'s copies cut off),
    gathered on the default device as a run on one device leaves them."""
    if len(state.x.sharding.device_set) > 1:
        state, frames = jax.device_put((state, frames), jax.devices()[0])
    if state.n_particles == n:
        return state, frames
    cut = {name: jax.tree.map(lambda a: a[:n], getattr(state, name)) for name in _PER_PARTICLE}
    if frames is not None:
        frames = {key: value if key == "impulse" else jax.tree.map(lambda a: a[:, :n], value)
                  for key, value in frames.items()}
    return state.replace(**cut), frames


def specs(config: Config, observer) -> dict[str, Any]:
    """The partition specs of a run's pieces: ``state``, ``params``, ``carry`` (a block's state,
    frames and frame counter) and ``result`` (the final state and the frames)."""
    shared, same = PartitionSpec(PARTICLE_AXIS), PartitionSpec()
    state = State(**{name: shared if name in _PER_PARTICLE else same for name in State.__dataclass_fields__})
    frames = None
    if observer is not None and config.frame_times:
        keys = ("x", "v", "p", "q", *config.material.init_internal(1, jnp.float32))
        frames = {**{key: PartitionSpec(None, PARTICLE_AXIS) for key in keys}, "impulse": same}
    return {"state": state, "params": same, "carry": (state, frames, same), "result": (state, frames)}


def split(fn, devices: int, in_specs, out_specs):
    """``fn`` (built with ``axis_name=PARTICLE_AXIS``) run on the first ``devices`` devices, each
    holding the share of the particles that ``specs`` gives it."""
    mesh = Mesh(np.asarray(jax.devices()[:devices]), (PARTICLE_AXIS,))
    # check_vma=False: the return map's while loop starts from a scalar flag that is the same on
    # every device and ends with one that is the device's own, which the check refuses. What is
    # returned as the same on every device (clock, status, impulse) is made so by the reductions
    # of ``make_step``; tests/test_devices.py compares every field with the undivided run.
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)
