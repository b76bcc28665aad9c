"""The measurements of an experiment, of the command line's files, and the shipped set-ups: what a
fit reads before it builds its objective. ``data_dir``, ``dataset_path`` and ``list_datasets`` are
``jaxmpm.datasets``' (the one finder of the shipped files).
"""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any

from jaxmpm.datasets import dataset_path  # the one finder, re-exported

from .collapse import read_measurements
from .loaders import load_front_history, load_profile

__all__ = ["data_end_time", "load_measurements", "check_run_status", "load_data", "load_setup"]


def data_end_time(profiles, front=None) -> float | None:
    """The latest time (s) at which the data were taken (profiles that state their time, the
    front history's last), or None where nothing says: the end time a run needs to be compared
    with them, when none is given."""
    times = [float(p.time_s) for p in profiles if getattr(p, "time_s", None) is not None]
    if front is not None:
        times.append(float(front.t[-1]))
    return max(times) if times else None


def load_measurements(experiment, *, sort: bool = False, clip_noise: bool = False) -> tuple[list, Any]:
    """(profiles, front history or None) that a ``jaxmpm.Experiment`` lists ([[profile]],
    [front]), read with the units and times it states; ``sort`` and ``clip_noise`` as for
    ``load_profile``."""
    listed = read_measurements(experiment)
    profiles = [load_profile(p.file, units=p.units, time_s=p.time, dataset=p.dataset, sort=sort, clip_noise=clip_noise)
                for p in listed.profiles]
    front = None
    if listed.front is not None:
        front = load_front_history(listed.front.file, units=listed.front.units, time_units=listed.front.time_units,
                                   sort=sort)
    return profiles, front


def check_run_status(datasets) -> None:
    """Refuse any of ``datasets`` (profiles, front histories; None is skipped) whose header
    records a run that failed (a nonzero ``status``, as ``python -m jaxmpm run --profile-csv``
    writes it): such a file is not a result of its scene."""
    from jaxmpm import describe_status

    for data in datasets:
        status = data.meta.get("status") if data is not None else None
        if status not in (None, 0):
            raise ValueError(f"{data.path}: written by a run that failed (status {status}: "
                             f"{'; '.join(describe_status(int(status)))}); it is not a result of its scene")


def load_data(profiles=(), front=None, *, units: str | None = None, time_units: str | None = None,
              dataset: str | None = None, sort: bool = False, clip_noise: bool = False) -> tuple[list, Any]:
    """(profiles, front history or None) read from the profile CSVs ``profiles`` and the
    front-history CSV ``front`` (None: none) as ``load_profile`` and ``load_front_history`` read
    them (``units``, ``time_units``, ``dataset``, ``sort``, ``clip_noise``); a file written by a
    run that failed is refused (``check_run_status``)."""
    loaded = [load_profile(p, units=units, dataset=dataset, sort=sort, clip_noise=clip_noise) for p in profiles]
    history = (load_front_history(front, units=units, time_units=time_units, dataset=dataset, sort=sort)
               if front else None)
    check_run_status([*loaded, history])
    return loaded, history


def load_setup(name: str | os.PathLike) -> dict[str, Any]:
    """A scene set-up (``setups/*.json``: S1's) by manifest name (``'setups/S1_incline'``) or path.
    The collapses' set-ups are experiment files: ``jaxmpm.experiment.shipped_experiment``."""
    path = pathlib.Path(name)
    if not path.is_file():
        path = dataset_path(str(name))
    return json.loads(path.read_text())
