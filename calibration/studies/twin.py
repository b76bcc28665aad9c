"""The twin experiment: fit data that the model itself made, with known parameters.

A synthetic S4 cohesive collapse is run with the true parameters (``TWIN_TRUTH`` over the scene's);
its deposit profiles at ``PROFILE_TIMES`` and its front at ``FRONT_TIMES`` become the data,
optionally with Gaussian noise, and the fit from a perturbed start (``TWIN_START_FACTORS``) must
find the truth again and say which parameters the data constrain. ``twin(...)`` returns a
``TwinResult``; ``twin_landscape(result, n)`` sweeps its loss over the first two keys. The set-up
and what it shows: docs/twin.md.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from jaxmpm.scenes import build_scene
from jaxmpm.scenes.collapse import S4_SIDE

from ..batch.sweep import SweepResult, grid_points, sweep
from ..inference.noise import chi2_of, chi2_quantile
from ..inference.options import JudgeOptions
from ..inference.scatter import ROUNDOFF_SAMPLES
from ..optim.fit import FitResult
from ..optim.options import FitOptions, cli_steps
from ..optim.search import fit_from_starts
from ..problem.objective import Objective
from ..problem.targets import FrontTarget, ProfileTarget

__all__ = [
    "TWIN_START_FACTORS", "TWIN_TRUTH", "PROFILE_TIMES", "FRONT_TIMES", "TwinResult", "twin", "TwinLandscape",
    "twin_landscape",
]


#: Perturbation of the start, by key (multiplies the true value).
TWIN_START_FACTORS = {"beta": 0.6, "mu1": 1.2, "mu2": 0.9, "I0": 1.5, "xi": 0.6}


#: True values that differ from the S4 scene defaults (β = 0.25: the cohesive case).
TWIN_TRUTH = {"beta": 0.25}


PROFILE_TIMES = (0.1, 0.2, 0.5)


FRONT_TIMES = tuple(np.round(np.linspace(0.05, 0.5, 10), 6))


def twin_data(scene, keys, truth: np.ndarray, noise: float = 0.0, seed: int = 0, n_points: int = 50):
    """Synthetic profiles and front history from ``scene`` at ``truth``, with noise."""
    times = np.asarray(FRONT_TIMES)
    # First pass: where is the final front? (The data cover the deposit plus a margin.)
    probe = Objective(scene, keys, front=FrontTarget(times, np.ones_like(times)), check_data=False)  # placeholder
    _, pred = probe.residuals(truth)
    if int(pred["status"]):
        raise ValueError(f"the twin's true run fails (status {int(pred['status'])})")
    x_end = 1.3 * float(np.asarray(pred["front"])[-1])
    xs = np.linspace(0.0, x_end, n_points)
    gen = Objective(scene, keys, profile=[ProfileTarget(xs, np.ones_like(xs), t) for t in PROFILE_TIMES],
                    front=FrontTarget(times, np.ones_like(times)), check_data=False)  # placeholder data
    _, pred = gen.residuals(truth)
    h = np.asarray(pred["h"], float).reshape(len(PROFILE_TIMES), n_points)
    front = np.asarray(pred["front"], float)
    rng = np.random.default_rng(seed)
    if noise > 0:
        h = h + noise * h.max(axis=1, keepdims=True) * rng.standard_normal(h.shape)
        front = front + noise * float(scene.info.length) * rng.standard_normal(front.shape)
    profiles = [ProfileTarget(xs, h[i], t) for i, t in enumerate(PROFILE_TIMES)]
    return profiles, FrontTarget(times, front)


@dataclasses.dataclass(frozen=True, eq=False)
class TwinResult:
    """A twin experiment: the fit (``FitResult``) and the objective it fitted, against the truth.

    ``rel_error`` is fit / truth − 1 by key; ``in_ci95`` whether each 95 % interval holds the truth
    (None: the verdict withheld the interval); ``delta_chi2_truth`` the likelihood-ratio distance
    of the truth from the fit (None without noise). ``wall_s`` covers the data and the fit."""

    fit: FitResult
    objective: Objective
    keys: tuple[str, ...]
    truth: dict[str, float]
    start: dict[str, float]
    rel_error: dict[str, float]
    in_ci95: dict[str, bool] | None
    delta_chi2_truth: float | None
    noise: float
    seed: int
    dx: float
    n_particles: int
    wall_s: float

    @property
    def truth_in_joint_95(self) -> bool | None:
        """Δχ² of the truth against χ²_n(0.95), n fitted parameters (None without noise)."""
        if self.delta_chi2_truth is None:
            return None
        return bool(self.delta_chi2_truth <= chi2_quantile(0.95, len(self.keys)))

    @property
    def ci95(self) -> dict[str, list[float]] | None:
        """The 95 % intervals by key (None: withheld, or no uncertainty analysis)."""
        unc = self.fit.uncertainty
        if unc is None or unc.withheld:
            return None
        return {k: [float(lo), float(hi)] for k, (lo, hi) in zip(self.keys, unc.ci95)}

    def to_json(self) -> dict[str, Any]:
        """The fit's JSON and the comparison with the truth: what ``python -m calibration twin --json`` prints."""
        out = self.fit.to_json()
        out.update({"wall_s": round(self.wall_s, 3), "true": dict(self.truth), "start": dict(self.start),
                    "rel_error": dict(self.rel_error),
                    "in_ci95": None if self.in_ci95 is None else dict(self.in_ci95)})
        if self.delta_chi2_truth is not None:
            out.update(delta_chi2_truth=self.delta_chi2_truth, truth_in_joint_95=self.truth_in_joint_95)
        out.update({"noise": self.noise, "seed": self.seed, "dx": self.dx, "n_particles": self.n_particles})
        return out


def twin(*, quick: bool = False, noise: float = 0.0, keys: Sequence[str] = ("beta", "mu1", "xi"),
         method: str = "lm", steps: int | None = None, seed: int = 0, dx: float | None = None, ppc: float | None = None,
         t_end: float | None = None, values: Mapping[str, float] | None = None, dtype=None, out=None,
         resume: bool = False, overwrite: bool = False, progress: bool = False, reference_noise: float = 0.01,
         threshold: float = 0.1, roundoff_samples: int = ROUNDOFF_SAMPLES, probe: bool = True,
         restarts: int = 2) -> TwinResult:
    """Run the twin experiment: make the data at the truth, fit them from the perturbed start.
    ``values`` are true scene parameters over ``TWIN_TRUTH``; ``out``/``resume``/``overwrite``
    keep the fit's history (``calibration.optim.fit``); ``probe`` and ``restarts`` as for ``fit_from_starts``."""
    if not (np.isfinite(noise) and 0 <= noise < 1):
        raise ValueError(f"noise must be in [0, 1), got {noise!r}")
    keys = tuple(keys)
    values = {**TWIN_TRUTH, **dict(values or {})}
    if dx is None:
        dx = S4_SIDE / (8 if quick else 16)
    if t_end is not None and t_end < max(PROFILE_TIMES):
        raise ValueError(f"t_end must be >= {max(PROFILE_TIMES)} s (the last profile), got {t_end}")
    scene = build_scene("cohesive-collapse", dx=dx, ppc=ppc, t_end=t_end, dtype=dtype, values=values)
    truth = np.array([float(getattr(scene.params, k)) for k in keys])
    start = {k: float(v) * TWIN_START_FACTORS.get(k, 0.8) for k, v in zip(keys, truth)}
    t0 = time.perf_counter()
    profiles, front = twin_data(scene, keys, truth, noise=noise, seed=seed)
    objective = Objective(scene, keys, profile=profiles, front=front)
    # Identifiability at the stated reference noise (or the twin's own noise when larger).
    options = FitOptions(method=method, steps=cli_steps(method, steps), restarts=restarts)
    judge = JudgeOptions(noise=None, reference_noise=max(reference_noise, noise), threshold=threshold,
                         roundoff_samples=roundoff_samples, probe=probe)
    meta = {"twin": True, "noise": noise, "seed": seed, "true": dict(zip(keys, truth.tolist()))}
    result, _ = fit_from_starts(objective, start, options=options, judge=judge, out=out, resume=resume,
                                overwrite=overwrite, progress=progress, meta=meta)
    wall_s = time.perf_counter() - t0
    unc = result.uncertainty
    in_ci95 = (None if unc.withheld else
               {k: bool(lo <= v <= hi) for k, v, (lo, hi) in zip(keys, truth, unc.ci95)})
    delta = None
    if noise > 0:
        # The likelihood-ratio view, which does not linearise: Δχ² of the truth against the fit,
        # with each block's residuals divided by its estimated noise, against χ²_n(0.95).
        chi2 = [chi2_of(r, objective.row_scale, objective.blocks, unc.noise)
                for r in (objective.residuals(truth)[0], result.residuals)]
        delta = chi2[0] - chi2[1]
    return TwinResult(fit=result, objective=objective, keys=keys, truth=dict(zip(keys, truth.tolist())), start=start,
                      rel_error={k: result.theta[k] / v - 1.0 for k, v in zip(keys, truth)}, in_ci95=in_ci95,
                      delta_chi2_truth=delta, noise=noise, seed=seed, dx=dx, n_particles=int(scene.state.x.shape[0]),
                      wall_s=wall_s)


@dataclasses.dataclass(frozen=True, eq=False)
class TwinLandscape:
    """The twin's loss swept over its first two keys (±40 % around the truth, the others at their
    true values): the sweep itself, and the truth, start and fit to mark on a figure."""

    keys: tuple[str, str]
    sweep: SweepResult
    marks: dict[str, tuple[float, float]]  # "true", "start", "fit": (x, y)

    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x values, y values and the loss on the grid (``SweepResult.landscape``)."""
        return self.sweep.landscape(*self.keys)

    def to_json(self) -> dict[str, Any]:
        return {"keys": list(self.keys), "n": int(self.sweep.n), "failed": len(self.sweep.failed),
                "wall_s": self.sweep.wall_s, "mode": self.sweep.mode}


def twin_landscape(result: TwinResult, n: int, *, progress: bool = False) -> TwinLandscape:
    """Sweep ``result``'s loss on an ``n`` × ``n`` grid over its first two keys."""
    keys = result.keys
    if len(keys) < 2:
        raise ValueError(f"a twin landscape needs at least two fitted keys, got {list(keys)}")
    kx, ky = keys[:2]
    truth = result.truth
    ranges = {k: (0.6 * truth[k], 1.4 * truth[k]) for k in (kx, ky)}
    _, grid = grid_points(ranges, n, keys=(kx, ky))
    thetas = np.tile([truth[k] for k in keys], (grid.shape[0], 1))
    thetas[:, :2] = grid
    swept = sweep(result.objective, thetas, progress=progress)
    theta = result.fit.theta
    marks = {"true": (truth[kx], truth[ky]), "start": (result.start[kx], result.start[ky]),
             "fit": (theta[kx], theta[ky])}
    return TwinLandscape((kx, ky), swept, marks)
