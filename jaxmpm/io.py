"""HDF5 output: one file per run, written atomically.

Layout of a file written by ``write_h5``::

    /frames/frame_00000 ...   one group per frame time, attribute ``t``; a dataset per key of
                              ``Result.frames`` (x, v, p, q and the internal variables)
    /initial                  the state the run started from (when ``write_h5`` is given it,
                              as ``python -m jaxmpm run`` does): the same datasets as /final
    /final                    the final state: x, v, p, q, vol (current particle volumes,
                              V0 det F_e exp(eps_v^p)), the internal variables, and impulse
                              (n_walls, dim): the momentum each wall and terrain of the
                              config took from the material since t = 0 (State.impulse)
    root attributes           ``param/<key>`` per parameter, ``params_json``, ``config_json``,
                              ``jaxmpm_version``, ``status``, ``status_text`` (JSON list),
                              ``t_end``, ``steps``, ``frame_times`` and any extra attributes

The file is written under a temporary name in the target directory and moved onto ``path``
with ``os.replace`` only once it is complete and closed, so a file at ``path`` is never a
partial run. Batched results (leading batch axes, from ``jax.vmap``) are stored as they are:
each frame dataset keeps the batch axes in front.

Particles keep their order: row k of /initial/x and of /final/x is the same particle, so
``final["x"] - initial["x"]`` is its displacement (the region that moved).

``write_ply`` writes particles as a binary PLY point cloud (ParaView, MeshLab, CloudCompare open
it; the reference code writes the same format) and ``write_ply_frames`` one file per frame.
docs/output.md documents both formats for readers without jaxmpm.

The CSV format (deposit profiles and other tables) lives in ``jaxmpm.tables``; its
``write_profile_csv`` and ``PROFILE_COLUMNS`` are importable from here as well.
"""

from __future__ import annotations

import json
import os
import pathlib
import uuid
from collections.abc import Mapping
from typing import Any

import h5py
import jax
import numpy as np

from .config import Config
from .materials.base import invariants
from .observables import particle_volumes
from .params import Params
from .simulate import Result
from .state import State, describe_status
from .tables import PROFILE_COLUMNS, write_profile_csv  # the CSV format's home is tables

__all__ = ["write_h5", "read_h5", "write_ply", "write_ply_frames", "atomic_write", "atomic_h5", "write_profile_csv",
           "PROFILE_COLUMNS"]

#: Root attributes stored as JSON strings (decoded by ``read_h5``).
_JSON_KEY_LIST = "json_keys"
_RESERVED = (
    "params_json", "config_json", "jaxmpm_version", "status", "status_text", "t_end", "steps",
    "frame_times", _JSON_KEY_LIST,
)


def _json_default(obj):
    if isinstance(obj, (np.ndarray, np.generic, jax.Array)):
        return np.asarray(obj).tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _dumps(obj) -> str:
    return json.dumps(obj, default=_json_default)


def _leaves(tree) -> dict[str, np.ndarray]:
    """A pytree's leaves as numpy arrays named by their key paths ("x", "internal/pc", ...)."""
    if tree is None:
        return {}
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        parts = []
        for key in path:
            for attr in ("key", "name", "idx"):
                if hasattr(key, attr):
                    parts.append(str(getattr(key, attr)))
                    break
            else:
                parts.append(str(key))
        out["/".join(parts) or "value"] = np.asarray(leaf)
    return out


def _version() -> str:
    from ._version import __version__

    return str(__version__)


def _state_values(state: State) -> dict[str, Any]:
    """The datasets of /initial and /final: x, v, p, q, vol and the internal variables."""
    p, q = invariants(state.tau)
    return {"x": state.x, "v": state.v, "p": p, "q": q, "vol": particle_volumes(state), **_leaves(state.internal)}


def _write(f: h5py.File, result: Result, config: Config, params: Params, extra: Mapping[str, Any],
           initial: State | None = None):
    state = result.state
    batch = np.ndim(state.x) - 2  # number of leading batch axes
    frame_times = tuple(float(t) for t in result.frame_times)

    frames = f.create_group("frames")
    arrays = _leaves(result.frames)
    for k, t in enumerate(frame_times if arrays else ()):
        group = frames.create_group(f"frame_{k:05d}")
        group.attrs["t"] = t
        for name, arr in arrays.items():
            group.create_dataset(name, data=arr[(slice(None),) * batch + (k,)])

    groups = {"final": state} if initial is None else {"initial": initial, "final": state}
    for group_name, group_state in groups.items():
        group = f.create_group(group_name)
        for name, arr in _state_values(group_state).items():
            group.create_dataset(name, data=np.asarray(arr))
        group.create_dataset("impulse", data=np.asarray(group_state.impulse))  # per wall, not per particle

    attrs = f.attrs
    param_values = params.to_dict()
    for key, value in param_values.items():
        attrs[f"param/{key}"] = value
    attrs["params_json"] = _dumps(param_values)
    attrs["config_json"] = _dumps(config.to_dict())
    attrs["jaxmpm_version"] = _version()
    attrs["status"] = int(result.status)
    attrs["status_text"] = _dumps(describe_status(result.status))
    attrs["t_end"] = float(config.t_end)
    attrs["steps"] = np.asarray(state.steps)
    attrs["frame_times"] = np.asarray(frame_times, dtype=float)
    json_keys = ["params_json", "config_json", "status_text"]
    for key, value in extra.items():
        if isinstance(value, (str, bool, int, float, np.generic)):
            attrs[key] = value
        else:
            attrs[key] = _dumps(value)
            json_keys.append(key)
    attrs[_JSON_KEY_LIST] = _dumps(json_keys)


def atomic_write(path: str | os.PathLike, write, hidden: bool = False) -> pathlib.Path:
    """Call ``write(tmp)`` on a temporary path next to ``path`` (``.name.XXXX.tmp`` if
    ``hidden``), then rename it onto ``path``: a file at ``path`` is never a partial one, and on
    any error the temporary file is removed and the error re-raised."""
    path = pathlib.Path(path)
    tag = uuid.uuid4().hex[:8]
    tmp = path.with_name(f".{path.name}.{tag}.tmp" if hidden else f"{path.name}.{tag}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_h5(path: str | os.PathLike, write) -> pathlib.Path:
    """``write(f)`` an open HDF5 file at a hidden temporary path next to ``path``, then rename it
    onto ``path`` (``atomic_write``)."""

    def write_file(tmp):
        with h5py.File(tmp, "w") as f:
            write(f)

    return atomic_write(path, write_file, hidden=True)


def write_h5(
    path: str | os.PathLike,
    result: Result,
    config: Config,
    params: Params,
    attrs: Mapping[str, Any] | None = None,
    initial: State | None = None,
) -> pathlib.Path:
    """Write one run to the HDF5 file ``path`` (layout in the module docstring); return its path.

    ``attrs`` adds root attributes: strings and scalars as they are, anything else as JSON.
    ``initial``: the state the run started from, stored as /initial (same particles, same order
    as /final; unbatched, or batched as the result is). An existing file at ``path`` is replaced,
    but only once the new one is completely written; on any error the temporary file is removed
    and the error re-raised.
    """
    if not isinstance(result, Result):
        raise ValueError(f"result must be a Result, got {type(result).__name__}")
    if not isinstance(config, Config):
        raise ValueError(f"config must be a Config, got {type(config).__name__}")
    if not isinstance(params, Params):
        raise ValueError(f"params must be a Params, got {type(params).__name__}")
    if initial is not None:
        if not isinstance(initial, State):
            raise ValueError(f"initial must be a State (the run's initial state), got {type(initial).__name__}")
        shape, want = np.shape(initial.x), np.shape(result.state.x)
        if shape[-2:] != want[-2:] or len(shape) > len(want):
            raise ValueError(f"initial holds particles of shape {shape}, the result {want}: not the same run's "
                             "initial state")
    extra = dict(attrs or {})
    for key in extra:
        if not isinstance(key, str) or not key:
            raise ValueError(f"attrs keys must be non-empty strings, got {key!r}")
        if key in _RESERVED or key.startswith("param/"):
            raise ValueError(f"attrs key {key!r} is reserved by write_h5")
    path = pathlib.Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"path's parent directory does not exist: {str(path.parent)!r}")
    if path.is_dir():
        raise ValueError(f"path is a directory: {str(path)!r}")

    def write(tmp):
        with h5py.File(tmp, "x") as f:
            _write(f, result, config, params, extra, initial)

    return atomic_write(path, write)


def _plain(value):
    """An HDF5 attribute value as Python: str for strings, Python scalars for 0-d values."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _datasets(group: h5py.Group) -> dict[str, np.ndarray]:
    """Every dataset under ``group`` as a numpy array, by path relative to the group."""
    out = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = obj[()]

    group.visititems(visit)
    return out


def read_h5(path: str | os.PathLike) -> dict[str, Any]:
    """Read a file written by ``write_h5``.

    Returns ``{"attrs": {...}, "frames": [{"t": t, "x": ..., ...}, ...], "initial": {...} or None,
    "final": {...}}`` (``initial`` is None for a file written without it, such as one from before
    /initial existed). JSON attributes (``params_json``, ``config_json``, ``status_text`` and
    non-scalar extras) come back decoded.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"path does not exist or is not a file: {str(path)!r}")
    with h5py.File(path, "r") as f:
        attrs = {key: _plain(value) for key, value in f.attrs.items()}
        for key in json.loads(attrs.pop(_JSON_KEY_LIST, "[]")):
            attrs[key] = json.loads(attrs[key])
        frames = []
        for name in sorted(f["frames"]):
            group = f["frames"][name]
            frames.append({"t": float(group.attrs["t"]), **_datasets(group)})
        initial = _datasets(f["initial"]) if "initial" in f else None
        final = _datasets(f["final"])
    return {"attrs": attrs, "frames": frames, "initial": initial, "final": final}


def _ply_columns(x: np.ndarray, fields: Mapping[str, Any]) -> dict[str, np.ndarray]:
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"x must have shape (n, 2) or (n, 3), got {x.shape}")
    n = x.shape[0]
    columns = {"x": x[:, 0], "y": x[:, 1], "z": x[:, 2] if x.shape[1] == 3 else np.zeros(n)}
    for name, value in fields.items():
        if not isinstance(name, str) or not name.replace("_", "").isalnum():
            raise ValueError(f"fields: a PLY property name must be alphanumeric (with _), got {name!r}")
        value = np.asarray(value)
        if value.shape[:1] != (n,):
            raise ValueError(f"fields[{name!r}] has shape {value.shape}, not one row per particle ({n})")
        flat = value.reshape(n, -1)
        if flat.shape[1] == 1:
            columns[name] = flat[:, 0]
        else:  # vectors and tensors by component: v_0, v_1, ...
            columns.update({f"{name}_{k}": flat[:, k] for k in range(flat.shape[1])})
    return columns


def write_ply(path: str | os.PathLike, x, fields: Mapping[str, Any] | None = None) -> pathlib.Path:
    """Write particles at ``x`` (n, 2 or 3; z = 0 in 2D) with per-particle ``fields`` (scalars,
    or arrays split into components ``name_0, name_1, ...``) as a binary little-endian PLY point
    cloud: positions as float64, fields as float32. Written atomically, like ``write_h5``."""
    columns = _ply_columns(x, dict(fields or {}))
    n = len(columns["x"])
    dtype = np.dtype([(k, "<f8" if k in ("x", "y", "z") else "<f4") for k in columns])
    rows = np.empty(n, dtype)
    for k, v in columns.items():
        rows[k] = v
    kinds = {"<f8": "double", "<f4": "float"}
    header = ["ply", "format binary_little_endian 1.0", f"comment jaxmpm {_version()}", f"element vertex {n}"]
    header += [f"property {kinds[dtype[k].str]} {k}" for k in columns] + ["end_header"]
    path = pathlib.Path(path)
    if not path.parent.is_dir():
        raise ValueError(f"path's parent directory does not exist: {str(path.parent)!r}")
    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rows.tobytes())

    return atomic_write(path, write)


def write_ply_frames(folder: str | os.PathLike, result: Result, initial: State | None = None) -> list[pathlib.Path]:
    """One PLY per frame of ``result`` (``frame_00000.ply`` ...), plus ``initial.ply`` (if given)
    and ``final.ply``, in ``folder`` (created if missing). Unbatched results only. Frame fields
    that are not one row per particle (the walls' impulse) are not written: they are not point
    data, and ``write_h5`` keeps them."""
    folder = pathlib.Path(folder)
    if np.ndim(result.state.x) != 2:
        raise ValueError("write_ply_frames writes one run: the result is batched (vmapped)")
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    if initial is not None:
        values = _state_values(initial)
        written.append(write_ply(folder / "initial.ply", values.pop("x"), values))
    n = np.shape(result.state.x)[0]
    # a PLY holds particles: frame fields with another shape (a wall's impulse) stay in the HDF5
    arrays = {name: arr for name, arr in _leaves(result.frames).items() if np.shape(arr)[1:2] == (n,)}
    for k, _ in enumerate(result.frame_times if arrays and "x" in arrays else ()):
        values = {name: arr[k] for name, arr in arrays.items()}
        written.append(write_ply(folder / f"frame_{k:05d}.ply", values.pop("x"), values))
    values = _state_values(result.state)
    written.append(write_ply(folder / "final.ply", values.pop("x"), values))
    return written
