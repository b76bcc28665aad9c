"""How a fit's end point is judged (``JudgeOptions``), validated once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ..problem.options import _is_int, _is_number, _require
from .gridcheck import GRID_DRAWS, check_grid_options
from .scatter import ROUNDOFF_SAMPLES

__all__ = ["JudgeOptions"]


@dataclasses.dataclass(frozen=True)
class JudgeOptions:
    """How a fit's end point is judged (``calibration.inference.verdict.judge_point``). ``noise``:
    the known noise (a number, or by residual block: a block not named is estimated; None: every
    block estimated); ``uncertainty``:
    compute intervals at all; ``roundoff_samples`` perturbed runs for the run's own scatter and
    ``sampling_seeds`` other particle draws (0, or 2 and more: 0 is not measured);
    ``reference_noise`` and ``threshold`` decide which parameters count as constrained;
    ``grid_ratio`` (None: not measured, else > 1), ``grid_draws`` and ``grid_levels`` (1 or 2
    coarser grids): the grid term (``calibration.inference.gridcheck.grid_shift``); ``probe``: run the
    model at a fit's interval edges and 2, 4 and 8 times as far (``calibration.inference.probe``), 8 runs
    a key."""

    noise: Mapping[str, float] | float | None = None
    uncertainty: bool = True
    roundoff_samples: int = ROUNDOFF_SAMPLES
    sampling_seeds: int = 0
    reference_noise: float = 0.01
    threshold: float = 0.1
    grid_ratio: float | None = None
    grid_draws: int = GRID_DRAWS
    grid_levels: int = 1
    probe: bool = True

    def __post_init__(self):
        noise = self.noise
        values = list(noise.values()) if isinstance(noise, Mapping) else ([] if noise is None else [noise])
        for value in values:
            _require(_is_number(value) and value >= 0, "noise", "None, a finite number >= 0 or one per block",
                     noise)
        for name in ("uncertainty", "probe"):
            _require(isinstance(getattr(self, name), bool), name, "True or False", getattr(self, name))
        for name in ("roundoff_samples", "sampling_seeds"):
            value = getattr(self, name)
            _require(_is_int(value) and (value == 0 or value >= 2), name, "0 (not measured) or an integer >= 2",
                     value)
        for name in ("reference_noise", "threshold"):
            value = getattr(self, name)
            _require(_is_number(value) and value >= 0, name, "a finite number >= 0", value)
        check_grid_options(self.grid_ratio, self.grid_draws, self.grid_levels)

    def kwargs(self) -> dict[str, Any]:
        """The fields as keyword arguments (``judge_point``, ``search``)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def to_json(self) -> dict[str, Any]:
        out = self.kwargs()
        if isinstance(self.noise, Mapping):
            out["noise"] = dict(self.noise)
        return out
