"""The shipped data (``experiments_data/``): where the folder is, and its files by manifest name.

The one finder of the shipped data for the engine (the avalanche's terrain, the experiment files)
and for ``calibration`` (which re-exports it from ``calibration.data``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib

__all__ = ["DatasetInfo", "data_dir", "dataset_path", "list_datasets", "ENV"]

#: The environment variable that points at another ``experiments_data`` folder.
ENV = "JAXMPM_EXPERIMENTS_DATA"


@dataclasses.dataclass(frozen=True)
class DatasetInfo:
    """One file of ``experiments_data/`` as its manifest describes it."""

    name: str
    path: pathlib.Path
    kind: str  # the manifest's "kinds": setup, scaling_law, flow_rule, h_stop, incline, experiment, ...
    description: str
    synthetic: bool
    secondary: bool
    source: str = ""  # where a third-party file comes from (manifest "source"; empty for the project's own)
    licence: str = ""  # its licence where it is not the project's (manifest "licence")


def data_dir() -> pathlib.Path:
    """The ``experiments_data`` folder: ``$JAXMPM_EXPERIMENTS_DATA`` if set, else the one next to the
    ``jaxmpm`` package (a source checkout), else the installed ``jaxmpm.experiments_data``.
    Raises ``FileNotFoundError`` if none holds a ``manifest.json``."""
    env = os.environ.get(ENV)
    if env:
        folder = pathlib.Path(env)
        if not (folder / "manifest.json").is_file():
            raise FileNotFoundError(f"${ENV} = {env!r} has no manifest.json")
        return folder
    checkout = pathlib.Path(__file__).resolve().parent.parent / "experiments_data"
    if (checkout / "manifest.json").is_file():
        return checkout
    installed = _installed_data_dir()
    if installed is not None and (installed / "manifest.json").is_file():
        return installed
    raise FileNotFoundError(
        f"experiments_data/ not found: neither at {str(checkout)!r} (a source checkout) nor as the installed "
        f"package jaxmpm.experiments_data ({'not installed' if installed is None else str(installed)!r}). "
        f"Reinstall jaxmpm (pip install .) or set {ENV} to the folder's path")


def _installed_data_dir() -> pathlib.Path | None:
    """Where ``pip install .`` put the shipped data, or None if it is not installed."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("jaxmpm.experiments_data")
    except ImportError:
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return pathlib.Path(next(iter(spec.submodule_search_locations)))


def list_datasets() -> dict[str, DatasetInfo]:
    """The shipped files by manifest name (e.g. ``'synthetic/S4_beta0.25'``)."""
    folder = data_dir()
    manifest = json.loads((folder / "manifest.json").read_text())
    out = {}
    for entry in manifest["files"]:
        out[entry["name"]] = DatasetInfo(
            name=entry["name"], path=folder / entry["path"], kind=entry["kind"], description=entry["description"],
            synthetic=bool(entry["synthetic"]), secondary=bool(entry["secondary"]),
            source=str(entry.get("source", "")), licence=str(entry.get("licence", "")),
        )
    return out


def dataset_path(name: str) -> pathlib.Path:
    """Path of a shipped file from its manifest name or its path inside ``experiments_data/``."""
    datasets = list_datasets()
    info = datasets.get(name) or next((d for d in datasets.values() if d.path == data_dir() / name), None)
    if info is None:
        raise FileNotFoundError(f"no shipped dataset {name!r}; known: {sorted(datasets)}")
    if not info.path.is_file():
        raise FileNotFoundError(f"dataset {name!r} is in the manifest but {str(info.path)!r} is missing")
    return info.path
