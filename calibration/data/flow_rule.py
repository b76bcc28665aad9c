"""Steady flows down a rough incline, as experimentalists tabulate them: the velocity of a layer of
thickness h at slope θ (a flow rule, Pouliquen 1999; Forterre and Pouliquen 2003), or at a height
z in it (a velocity profile); and the thickness h_stop(θ) a layer stops at, which the local μ(I)
model does not predict (it is read and reported, never fitted). The formats, and what is refused,
are in docs/data_files.md ("A flow-rule table", "An h_stop table").
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from typing import Any

import numpy as np

from jaxmpm import tables

__all__ = ["FLOW_RULE_COLUMNS", "FLOW_RULE_KEYS", "H_STOP_COLUMNS", "PROFILE_COLUMNS", "QUANTITIES", "FlowRuleTable",
           "HStopTable", "flow_rule_keys", "flow_rule_keys_problem", "load_flow_rule", "load_h_stop"]

#: The columns of a flow-rule table: slope (degrees), layer thickness (m), velocity (m/s).
FLOW_RULE_COLUMNS = ("slope_deg", "h_m", "u_m_s")
#: The columns of a velocity profile's table: a flow-rule table's with the height above the bed (m).
PROFILE_COLUMNS = ("slope_deg", "h_m", "z_m", "u_m_s")
#: The columns of an h_stop table: slope (degrees), the thickness a layer stops at (m).
H_STOP_COLUMNS = ("slope_deg", "h_stop_m")
#: The parameters a flow rule fixes (the grain size and φ = ρ/ρ_s are measured, not fitted).
FLOW_RULE_KEYS = ("mu1", "mu2", "I0")
#: What the velocity column measures: the depth-averaged velocity (the flow rule), the free
#: surface's, or the velocity at the height z_m above the bed (a profile).
QUANTITIES = ("depth_averaged", "surface", "profile")


def flow_rule_keys(side_walls=None) -> tuple[str, ...]:
    """The keys a flow rule can fit: μ1, μ2 and I0, and μ_w between ``side_walls`` (a
    ``jaxmpm.SideWalls`` or None) whose friction is the parameter "mu_w"."""
    reads = side_walls is not None and side_walls.friction == "mu_w"
    return FLOW_RULE_KEYS + (("mu_w",) if reads else ())


def flow_rule_keys_problem(keys, side_walls=None) -> str | None:
    """Why ``keys`` are not a flow rule's keys between ``side_walls`` (None: they are)."""
    keys, allowed = tuple(keys), flow_rule_keys(side_walls)
    if keys and not set(keys) - set(allowed) and len(set(keys)) == len(keys):
        return None
    why = ""
    if "h_stop" in keys:
        why = (" (h_stop is not a parameter: the local mu(I) model does not predict it, so it is never fitted; "
               "an incline file's [h_stop] table is reported beside the fit)")
    if "mu_w" in keys and "mu_w" not in allowed:
        why = (" (mu_w is the side walls' friction: it is fitted only between walls whose friction is "
               "\"mu_w\", e.g. side_walls = { width = \"5 cm\", friction = \"mu_w\" } or --side-walls 0.05,mu_w; "
               + ("these walls' friction is a number)" if side_walls is not None else "this chute has no side walls)"))
    return f"a flow rule fits distinct keys among {list(allowed)}, got {list(keys)}{why}"


@dataclasses.dataclass(frozen=True, eq=False)
class FlowRuleTable:
    """Velocities ``u`` (m/s) of steady layers of thickness ``h`` (m) at slopes ``slope_deg``, one
    row each; ``quantity`` says which velocity (``QUANTITIES``): for "profile", the velocity at
    the height ``z`` (m) above the bed, 0 < z <= h (None for the other quantities). ``noise``: the
    relative standard deviation of one velocity where the file states it (None: estimated from a
    fit's residuals). ``secondary``: the values were quoted, or computed from a published law, not
    read from the measurements themselves."""

    slope_deg: np.ndarray
    h: np.ndarray
    u: np.ndarray
    quantity: str
    source: str
    secondary: bool
    experiment: str = ""
    noise: float | None = None
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    path: str | None = None
    z: np.ndarray | None = None

    def __post_init__(self):
        where = self.path or "FlowRuleTable"
        if self.quantity not in QUANTITIES:
            raise ValueError(f"{where}: quantity must be one of {QUANTITIES}, got {self.quantity!r}")
        if (self.z is None) == (self.quantity == "profile"):
            raise ValueError(f"{where}: " + ("a profile (quantity: profile) needs the heights z above the bed"
                                             if self.z is None else
                                             f"heights z above the bed belong to a profile (quantity: profile), "
                                             f"not to a {self.quantity} table"))
        names = ("slope_deg", "h", "u") + (("z",) if self.z is not None else ())
        arrays = [np.array(getattr(self, name), float).ravel() for name in names]
        if len({a.size for a in arrays}) != 1 or arrays[0].size == 0:
            raise ValueError(f"{where}: {', '.join(names[:-1])} and {names[-1]} must be non-empty and of equal length")
        slope, h, u = arrays[:3]
        checks = [("slope_deg", slope, (slope > 0) & (slope < 90), "in (0, 90) degrees"), ("h_m", h, h > 0, "> 0 m")]
        if self.z is not None:
            z = arrays[3]
            checks += [("z_m", z, (z >= 0) & (z <= h), "a height above the bed in [0, h_m]"),
                       ("z_m", z, z > 0, "> 0: at the bed (z_m = 0) the no-slip model's velocity is 0, which a "
                                         "relative residual cannot compare; leave that row out")]
        _check_rows(where, checks + [("u_m_s", u, u > 0, "> 0 m/s")])
        if self.noise is not None and not (math.isfinite(self.noise) and self.noise > 0):
            raise ValueError(f"{where}: noise must be a relative standard deviation > 0, got {self.noise!r}")
        for name, values in zip(names, arrays):
            values.setflags(write=False)
            object.__setattr__(self, name, values)

    @property
    def n(self) -> int:
        return int(self.u.size)

    @property
    def slopes(self) -> np.ndarray:
        """The distinct slopes, increasing."""
        return np.unique(self.slope_deg)


def load_flow_rule(path: str | os.PathLike) -> FlowRuleTable:
    """Read a flow-rule CSV: columns ``slope_deg,h_m,u_m_s`` (``slope_deg,h_m,z_m,u_m_s`` for a
    profile) and a header with ``source``, ``secondary`` (true/false) and ``quantity``
    (``depth_averaged``, ``surface`` or ``profile``), optionally ``experiment`` and ``noise`` (the
    relative standard deviation of one velocity). Every error names the file."""
    path = pathlib.Path(path)
    file = str(path)
    header, columns = tables.read_columns(path)
    profile = header.get("quantity") == "profile"
    expected = PROFILE_COLUMNS if profile else FLOW_RULE_COLUMNS
    if set(columns) != set(expected):
        why = (" (z_m: the height above the bed of a profile's velocity)" if profile else
               "; z_m (a height above the bed) belongs to a profile, 'quantity: profile'" if "z_m" in columns else "")
        raise ValueError(f"{file}: expected the columns {','.join(expected)}{why}, got {list(columns)}")
    secondary = _source_and_secondary(file, header)
    if "quantity" not in header:
        raise ValueError(f"{file}: the header has no 'quantity'")
    noise = header.get("noise")
    if noise is not None and (isinstance(noise, bool) or not isinstance(noise, (int, float))):
        raise ValueError(f"{file}: noise must be a number (a relative standard deviation), got {noise!r}")
    known = ("source", "secondary", "quantity", "experiment", "noise")
    return FlowRuleTable(slope_deg=columns["slope_deg"], h=columns["h_m"], u=columns["u_m_s"],
                         quantity=str(header["quantity"]), source=str(header["source"]), secondary=secondary,
                         experiment=str(header.get("experiment", path.stem)),
                         noise=None if noise is None else float(noise),
                         meta={k: v for k, v in header.items() if k not in known}, path=file,
                         z=columns["z_m"] if profile else None)


@dataclasses.dataclass(frozen=True, eq=False)
class HStopTable:
    """The thickness ``h_stop`` (m) at which a layer stops (or a deposit is left) at each slope
    ``slope_deg``, one row each. The local μ(I) model does not predict it, so it is never fitted:
    a flow-rule fit reports it beside its point (``calibration.studies.flow_rule.h_stop_report``).
    ``secondary``: as for a ``FlowRuleTable``."""

    slope_deg: np.ndarray
    h_stop: np.ndarray
    source: str
    secondary: bool
    experiment: str = ""
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    path: str | None = None

    def __post_init__(self):
        where = self.path or "HStopTable"
        slope, h_stop = (np.array(getattr(self, name), float).ravel() for name in ("slope_deg", "h_stop"))
        if slope.size != h_stop.size or slope.size == 0:
            raise ValueError(f"{where}: slope_deg and h_stop must be non-empty and of equal length")
        _check_rows(where, [("slope_deg", slope, (slope > 0) & (slope < 90), "in (0, 90) degrees"),
                           ("h_stop_m", h_stop, h_stop > 0, "> 0 m")])
        for name, values in (("slope_deg", slope), ("h_stop", h_stop)):
            values.setflags(write=False)
            object.__setattr__(self, name, values)

    @property
    def n(self) -> int:
        return int(self.h_stop.size)


def load_h_stop(path: str | os.PathLike) -> HStopTable:
    """Read an h_stop CSV: columns ``slope_deg,h_stop_m`` and a header with ``source`` and
    ``secondary`` (true/false), optionally ``experiment``; refused as ``load_flow_rule`` refuses
    a table, naming the file."""
    path = pathlib.Path(path)
    file = str(path)
    header, columns = tables.read_columns(path)
    if set(columns) != set(H_STOP_COLUMNS):
        raise ValueError(f"{file}: expected the columns {','.join(H_STOP_COLUMNS)}, got {list(columns)}")
    secondary = _source_and_secondary(file, header)
    return HStopTable(slope_deg=columns["slope_deg"], h_stop=columns["h_stop_m"], source=str(header["source"]),
                      secondary=secondary, experiment=str(header.get("experiment", path.stem)),
                      meta={k: v for k, v in header.items() if k not in ("source", "secondary", "experiment")},
                      path=file)


def _source_and_secondary(file: str, header) -> bool:
    """The header's ``secondary`` (true or false), once it also names its ``source``."""
    secondary = header.get("secondary")
    if secondary is not True and secondary is not False:
        raise ValueError(f"{file}: the header must say 'secondary: true' or 'secondary: false', got {secondary!r}")
    if "source" not in header:
        raise ValueError(f"{file}: the header has no 'source'")
    return secondary


def _check_rows(where: str, checks) -> None:
    """Refuse the first row that fails a check ``(column, values, ok, what it must be)``, naming
    ``where``, the column and the row (1-based, in the table's order)."""
    for name, values, ok, what in checks:
        bad = np.flatnonzero(~(np.isfinite(values) & ok))
        if bad.size:
            raise ValueError(f"{where}: {name} must be {what}; row {int(bad[0]) + 1} has {float(values[bad[0]])!r}")
