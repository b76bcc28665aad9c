"""A fit's end point kept in its file, for the commands that come after it.

``write_record(path, result)`` adds to a fit's HDF5 history file what the checks beyond
Gauss–Newton need of the fit; ``read_record(path)`` gives it back as a ``FitRecord``, with the
file's header: what ``python -m calibration posterior`` reads.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any

import h5py
import numpy as np

from jaxmpm.io import atomic_h5

from ..inference.gridcheck import GridCheck
from .history import read_history

__all__ = ["FitRecord", "RecordedUncertainty", "read_record", "write_record"]


@dataclasses.dataclass(frozen=True)
class RecordedUncertainty:
    """The part of a fit's ``Uncertainty`` its record keeps: the ``noise`` by block, the
    covariance ``cov``, ``stderr`` and 95 % intervals ``ci95`` (n, 2) (None: withheld, the point is
    not a fit of the data) and the ``grid`` term (a ``GridCheck``, None where not measured)."""

    noise: dict[str, float]
    cov: np.ndarray | None
    stderr: np.ndarray | None
    ci95: np.ndarray | None = None
    grid: GridCheck | None = None

    @property
    def withheld(self) -> bool:
        return self.stderr is None


@dataclasses.dataclass(frozen=True)
class FitRecord:
    """A fit's end point as its file keeps it: ``keys``, ``theta`` (by key), ``residuals`` there,
    its ``uncertainty`` (None: the fit computed none), the fit's JSON ``report`` and the file's
    ``header`` (``meta`` with the ``setup`` the objective was built from, ``fingerprint``, ...)."""

    keys: tuple[str, ...]
    theta: dict[str, float]
    residuals: np.ndarray
    uncertainty: RecordedUncertainty | None
    report: dict[str, Any]
    header: dict[str, Any]


def _array(values) -> np.ndarray | None:
    return None if values is None else np.asarray(values, float)


def write_record(path, result) -> None:
    """Add the end point of ``result`` (a ``FitResult``) to the fit's file ``path`` (atomically:
    the file is copied with the record into a temporary file, then renamed)."""
    path = pathlib.Path(path)
    unc = result.uncertainty
    record = {"keys": list(result.keys), "theta": result.theta, "report": result.to_json(), "uncertainty": None}
    if unc is not None:
        record["uncertainty"] = {name: _jsonable(getattr(unc, name)) for name in ("noise", "cov", "stderr", "ci95")}
        if unc.grid is not None:
            record["uncertainty"]["grid"] = {f.name: _jsonable(getattr(unc.grid, f.name))
                                             for f in dataclasses.fields(unc.grid)}

    def write(f):
        with h5py.File(path, "r") as old:  # the fit's file as it is, less an earlier record
            for name, value in old.attrs.items():
                if name != "record_json":
                    f.attrs[name] = value
            for name in old:
                if name != "record_residuals":
                    old.copy(old[name], f, name=name)
        f.attrs["record_json"] = json.dumps(record, default=float)
        f.create_dataset("record_residuals", data=np.asarray(result.residuals, float))

    atomic_h5(path, write)


def _jsonable(value):
    return np.asarray(value).tolist() if isinstance(value, np.ndarray) else value


def read_record(path) -> FitRecord:
    """The ``FitRecord`` of the fit in ``path``; raises ``ValueError`` naming the file when it is
    not a fit's file or holds no end point (a fit killed before it ended: resume it first)."""
    history = read_history(path)
    attrs = history["attrs"]
    if "record_json" not in attrs:
        raise ValueError(f"{str(path)!r} holds no fit's end point: the fit did not end (resume it to the end) or "
                         "was written by an older calibration")
    record = attrs["record_json"]
    with h5py.File(path, "r") as f:
        residuals = np.asarray(f["record_residuals"])
    unc = record["uncertainty"]
    if unc is not None:
        grid = unc.get("grid")
        if grid is not None:
            grid = GridCheck(**{k: _array(v) if isinstance(v, list) else v for k, v in grid.items()})
        unc = RecordedUncertainty(dict(unc["noise"]), _array(unc["cov"]), _array(unc["stderr"]),
                                  _array(unc.get("ci95")), grid)
    header = {k.removesuffix("_json"): v for k, v in attrs.items() if k != "record_json"}
    return FitRecord(tuple(record["keys"]), {k: float(v) for k, v in record["theta"].items()}, residuals, unc,
                     record["report"], header)
