"""Steady flows down a rough incline, as experimentalists tabulate them: the velocity of a layer of
thickness h at slope θ (a flow rule, Pouliquen 1999; Forterre and Pouliquen 2003). The format, and
what is refused, are in docs/data_files.md ("A flow-rule table").
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from typing import Any

import numpy as np

from jaxmpm import tables

__all__ = ["FLOW_RULE_COLUMNS", "FLOW_RULE_KEYS", "QUANTITIES", "FlowRuleTable", "flow_rule_keys", "load_flow_rule",
           "flow_rule_keys_problem"]

#: The columns of a flow-rule table: slope (degrees), layer thickness (m), velocity (m/s).
FLOW_RULE_COLUMNS = ("slope_deg", "h_m", "u_m_s")
#: The parameters a flow rule fixes (the grain size and φ = ρ/ρ_s are measured, not fitted).
FLOW_RULE_KEYS = ("mu1", "mu2", "I0")
#: What the velocity column measures: the depth-averaged velocity (the flow rule) or the free surface's.
QUANTITIES = ("depth_averaged", "surface")


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
    if "mu_w" in keys and "mu_w" not in allowed:
        why = (" (mu_w is the side walls' friction: it is fitted only between walls whose friction is "
               "\"mu_w\", e.g. side_walls = { width = \"5 cm\", friction = \"mu_w\" } or --side-walls 0.05,mu_w; "
               + ("these walls' friction is a number)" if side_walls is not None else "this chute has no side walls)"))
    return f"a flow rule fits distinct keys among {list(allowed)}, got {list(keys)}{why}"


@dataclasses.dataclass(frozen=True, eq=False)
class FlowRuleTable:
    """Velocities ``u`` (m/s) of steady layers of thickness ``h`` (m) at slopes ``slope_deg``, one
    row each; ``quantity`` says which velocity (``QUANTITIES``). ``noise``: the relative standard
    deviation of one velocity where the file states it (None: estimated from a fit's residuals).
    ``secondary``: the values were quoted, or computed from a published law, not read from the
    measurements themselves."""

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

    def __post_init__(self):
        where = self.path or "FlowRuleTable"
        arrays = [np.array(getattr(self, name), float).ravel() for name in ("slope_deg", "h", "u")]
        if len({a.size for a in arrays}) != 1 or arrays[0].size == 0:
            raise ValueError(f"{where}: slope_deg, h and u must be non-empty and of equal length")
        slope, h, u = arrays
        if self.quantity not in QUANTITIES:
            raise ValueError(f"{where}: quantity must be one of {QUANTITIES}, got {self.quantity!r}")
        for name, values, ok, what in (("slope_deg", slope, (slope > 0) & (slope < 90), "in (0, 90) degrees"),
                                       ("h_m", h, h > 0, "> 0 m"), ("u_m_s", u, u > 0, "> 0 m/s")):
            bad = np.flatnonzero(~(np.isfinite(values) & ok))
            if bad.size:
                raise ValueError(f"{where}: {name} must be {what}; row {int(bad[0]) + 1} has {values[bad[0]]!r}")
        if self.noise is not None and not (math.isfinite(self.noise) and self.noise > 0):
            raise ValueError(f"{where}: noise must be a relative standard deviation > 0, got {self.noise!r}")
        for name, values in (("slope_deg", slope), ("h", h), ("u", u)):
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
    """Read a flow-rule CSV: columns ``slope_deg,h_m,u_m_s`` and a header with ``source``,
    ``secondary`` (true/false) and ``quantity`` (``depth_averaged`` or ``surface``), optionally
    ``experiment`` and ``noise`` (the relative standard deviation of one velocity). Every error
    names the file."""
    path = pathlib.Path(path)
    file = str(path)
    header, columns = tables.read_columns(path)
    if set(columns) != set(FLOW_RULE_COLUMNS):
        raise ValueError(f"{file}: expected the columns {','.join(FLOW_RULE_COLUMNS)}, got {list(columns)}")
    secondary = header.get("secondary")
    if secondary is not True and secondary is not False:
        raise ValueError(f"{file}: the header must say 'secondary: true' or 'secondary: false', got {secondary!r}")
    for key in ("source", "quantity"):
        if key not in header:
            raise ValueError(f"{file}: the header has no '{key}'")
    noise = header.get("noise")
    if noise is not None and (isinstance(noise, bool) or not isinstance(noise, (int, float))):
        raise ValueError(f"{file}: noise must be a number (a relative standard deviation), got {noise!r}")
    known = ("source", "secondary", "quantity", "experiment", "noise")
    return FlowRuleTable(slope_deg=columns["slope_deg"], h=columns["h_m"], u=columns["u_m_s"],
                         quantity=str(header["quantity"]), source=str(header["source"]), secondary=secondary,
                         experiment=str(header.get("experiment", path.stem)),
                         noise=None if noise is None else float(noise),
                         meta={k: v for k, v in header.items() if k not in known}, path=file)
