"""``Scene``: a ready-to-run set-up (configuration, initial state, parameters) with its facts
(``SceneInfo``) and what a run of it reports and records; every scene builder returns one."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..config import Config
from ..observables import back_wall_x, deposit_profile, particle_volumes
from ..params import Params
from ..state import State
from .info import SceneInfo

__all__ = ["Scene"]


@dataclasses.dataclass(frozen=True)
class Scene:
    """A ready-to-run scene. Unpacks as ``config, state, params = scene``."""

    name: str
    config: Config
    state: State
    params: Params
    info: SceneInfo  # geometry and set-up facts (body extents, slope, initial front, sampling, ...)
    #: seed -> the same body sampled with another seed (None: the scene's sampling has no seed).
    sampler: Callable[[int], State] | None = dataclasses.field(default=None, compare=False, repr=False)
    #: builder arguments -> the set-up built again with those changed (None: the builder cannot
    #: remake it); see ``variant`` and ``at_dx``.
    remake: Callable[..., Scene] | None = dataclasses.field(default=None, compare=False, repr=False)
    #: The ``jaxmpm.Experiment`` this scene was built from (None: built in Python).
    experiment: Any = dataclasses.field(default=None, compare=False, repr=False)

    def __iter__(self):
        return iter((self.config, self.state, self.params))

    @property
    def back_face(self) -> float | None:
        """The x (m) of the body's back face where it rests against a fixed back wall: where an
        experiment's back wall is (x = 0 for the collapses; the model's wall plane sits
        ``info.side_gap`` behind it so that no particle starts on the edge of its stencil).
        Deposit profiles are mirrored here (``jaxmpm.observables.deposit_profile``). None
        without a fixed wall facing +x."""
        wall = back_wall_x(self.config.walls)
        return None if wall is None else wall + float(self.info.side_gap or 0.0)

    def summary(self, result) -> dict:
        """What a run of this scene ended with (``simulate``'s ``Result``): sizes, extents, the
        runout beyond the body's initial front, the status and its meaning, the timings, and the
        experiment file it was built from; what ``python -m jaxmpm run`` prints."""
        from ..state import describe_status

        x = np.asarray(result.state.x)
        return {
            "scene": self.name, "n_particles": int(self.state.n_particles), "n_steps": int(result.state.steps),
            "dx": self.config.grid.dx, "t_end": self.config.t_end,
            "x_min": float(x[:, 0].min()), "x_max": float(x[:, 0].max()), "y_max": float(x[:, 1].max()),
            "runout": float(x[:, 0].max() - self.info.front0),
            "status": result.status, "status_text": describe_status(result.status),
            "compile_s": None if result.compile_s is None else round(result.compile_s, 3),
            "run_s": None if result.run_s is None else round(result.run_s, 3),
            **({} if self.experiment is None else {
                "experiment": str(self.experiment.path) if self.experiment.path else self.experiment.name}),
        }

    def run_attrs(self) -> dict:
        """The root attributes that record a run of this scene in its HDF5 file (``write_h5``'s
        ``attrs``): the scene's name and facts and, for a scene built from an experiment file, the
        file's TOML (``Experiment.from_h5`` makes the run again from it) and its path."""
        attrs = {"scene": self.name, **self.info.to_dict()}
        if self.experiment is not None:
            attrs["experiment_toml"] = self.experiment.to_toml()
            if self.experiment.path is not None:
                attrs["experiment_path"] = str(self.experiment.path.resolve())
        return attrs

    def profile_header(self, result, source: str) -> dict:
        """The header of this scene's final deposit profile as CSV (``tables.write_profile_csv``):
        a synthetic profile made by ``source`` (the command that ran it), with the run's time,
        parameters, scene facts and status."""
        from .._version import __version__

        float32 = np.asarray(self.state.x).dtype == np.float32
        return {
            "experiment": f"{self.name} (synthetic, jaxmpm {__version__})", "time_s": self.config.t_end,
            "units": "m", "synthetic": True, "source": source,
            # float32 leaves printed to the precision they hold (0.3, not 0.30000001192092896)
            "parameters": {k: float(f"{v:.7g}") if float32 else v for k, v in self.params.to_dict().items()},
            "scene": self.info.to_dict(), "status": result.status,
        }

    def final_profile(self, state) -> tuple[np.ndarray, np.ndarray]:
        """(x, h): the deposit's height profile of ``state``, smoothed over one particle spacing,
        sampled every half spacing from three spacings behind its rearmost particle to three
        beyond its front, mirrored at the back wall (``jaxmpm.observables.deposit_profile``)."""
        x = np.asarray(state.x)
        sigma = self.config.grid.dx / self.info.ppc
        xs = np.arange(x[:, 0].min() - 3 * sigma, x[:, 0].max() + 3 * sigma, sigma / 2)
        h = np.asarray(deposit_profile(state.x, particle_volumes(state), xs, sigma, width=self.info.width,
                                       mirror=self.back_face))
        return xs, h

    def resampled(self, seed: int) -> State:
        """The initial state of this scene with its particles sampled with ``seed`` instead of its
        own (same body, grid, walls and parameters; same particle count for lattice samplings):
        for ensembles over the sampling and for the sampling's share of a fit's uncertainty."""
        if self.sampler is None:
            raise ValueError(f"scene {self.name!r} has no seeded sampling to redraw")
        if not (isinstance(seed, int) and seed >= 0):
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        return self.sampler(seed)

    def variant(self, **changes) -> Scene:
        """This set-up built again with some of its builder's arguments changed (``collapse``'s:
        ``dx``, ``height``, ``length``, ``slope_deg``, ``front_gate_speed``, ``runout``, ``t_end``,
        ``ppc``, ``seed``, ...), with this scene's material (its ``params`` as they are now, set
        after building or not): the same material in another experiment, or the same experiment
        on another grid. Material keys are not builder arguments: replace ``params`` instead."""
        if self.remake is None:
            raise ValueError(f"scene {self.name!r} cannot be rebuilt (its builder records no recipe)")
        from ..params import PARAM_KEYS

        material = sorted(set(changes) & set(PARAM_KEYS))
        if material:
            raise ValueError(f"variant: {material} are material parameters, not builder arguments; "
                             "use scene.params.replace(...)")
        return dataclasses.replace(self.remake(**changes), params=self.params, name=self.name)

    def at_dx(self, dx: float) -> Scene:
        """This scene built at grid spacing ``dx`` (m): the same body, walls, gates, end time,
        sampling and seed, with this scene's parameters (``variant``); grid, particles and step
        budget follow from ``dx``. For the grid (discretisation) term of a fit
        (``calibration.grid_shift``) and resolution studies."""
        if not (isinstance(dx, (int, float)) and math.isfinite(dx) and dx > 0):
            raise ValueError(f"dx must be a positive number of metres, got {dx!r}")
        return self.variant(dx=float(dx))
