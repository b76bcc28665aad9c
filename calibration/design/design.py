"""What to measure before measuring it: the expected intervals of candidate experiments.

``design`` runs each candidate experiment (the scene and its ``variants``) once at θ with every
observation of ``KINDS`` recorded, takes one forward-mode Jacobian of it, and gives every *set* of
observations, by choosing its rows, the expected 95 % half-widths of the fit the library would
make from such data (the sandwich covariance of ``gauss_newton_uncertainty``), optionally with the
particle draw's and the grid's shares. The sets are ranked by what they cost the experimenter and
the cheapest that constrains every key within ``tolerance`` of |θ| is recommended. Incline
experiments (flow-rule tables, ``inclines``) join the candidates with their one observation,
"flow_rule" (``calibration.design.inclines``), so that sets may mix kinds of experiment. The
half-widths are linear-Gaussian: they hold where the misfit is close to quadratic over the
interval. The method, its costs and its validation: docs/what_collapses_tell.md.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..inference.gauss_newton import _inverse, _sandwich_fisher
from ..inference.gridcheck import GCI_SAFETY, GRID_ORDER, check_grid_options
from ..inference.noise import Z95
from ..inference.scatter import coarse_residuals, redrawn_residuals
from ..problem.objective import Objective
from ..problem.targets import FrontTarget, ProfileTarget
from .inclines import INCLINE_KINDS, incline_experiment, incline_plans, incline_sigma

__all__ = ["KINDS", "INCLINE_KINDS", "Experiment", "DesignResult", "expected_halfwidths", "design"]


#: The observations an experiment can give: the deposit profile at the end (a photograph), the
#: profiles at ``times`` during the flow (a side view), the front's position and the height of the
#: column's top near the back wall at ``front_times`` (a video). An incline gives ``INCLINE_KINDS``.
KINDS = ("final", "profiles", "front", "top")


VIDEO = ("profiles", "front", "top")


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One experiment's runs at θ: its objective with every observation, the rows of each kind,
    the weighted Jacobian and, when measured, the residual draws and the coarse grid's mean.
    ``closed_form``: a model with no particles and no grid (an incline's flow rule), whose draws'
    and grid's shares are zero rather than unmeasured."""

    label: str
    objective: Objective
    rows: dict[str, np.ndarray]  # kind -> row indices
    noise_rows: np.ndarray  # σ of every row (relative units)
    J: np.ndarray  # relative units (J / row_scale)
    weights: np.ndarray  # each row's weight in the fit's loss (row_scale²)
    draws: np.ndarray | None  # (K, m) relative residual deviations of other particle draws
    coarse: np.ndarray | None  # (m,) relative mean residual at ρ dx
    ratio: float | None
    closed_form: bool = False


@dataclasses.dataclass(frozen=True)
class Candidate:
    name: str
    parts: tuple[tuple[str, str], ...]  # (experiment, kind)
    cost: float
    halfwidth: np.ndarray  # 95 %, every term
    relative: np.ndarray  # halfwidth / |θ|
    cov: np.ndarray
    meets: bool  # every relative half-width within the tolerance
    halfwidth_data: np.ndarray  # 95 %, the data's noise alone (the library's fit)
    halfwidth_weighted: np.ndarray  # 95 %, the data's noise alone, every row weighed by 1/σ² (the bound)
    cov_data: np.ndarray  # the data's share of ``cov``


@dataclasses.dataclass(frozen=True)
class DesignResult:
    keys: tuple[str, ...]
    theta: np.ndarray
    noise: dict[str, float]
    tolerance: float
    candidates: tuple[Candidate, ...]  # by cost, then by the largest relative half-width
    recommended: Candidate | None
    experiments: tuple[str, ...]
    wall_s: float
    notes: tuple[str, ...] = ()  # a share that was asked for and could not be measured, and why

    def to_json(self) -> dict[str, Any]:
        def one(c):
            return {"name": c.name, "cost": c.cost, "meets_tolerance": c.meets,
                    "halfwidth95": dict(zip(self.keys, map(float, c.halfwidth))),
                    "relative_halfwidth95": dict(zip(self.keys, map(float, c.relative))),
                    "halfwidth95_data_only": dict(zip(self.keys, map(float, c.halfwidth_data))),
                    "halfwidth95_noise_weighted": dict(zip(self.keys, map(float, c.halfwidth_weighted)))}

        return {"keys": list(self.keys), "theta": dict(zip(self.keys, map(float, self.theta))), "noise": self.noise,
                "tolerance": self.tolerance, "experiments": list(self.experiments),
                "candidates": [one(c) for c in self.candidates],
                "recommended": None if self.recommended is None else one(self.recommended),
                "statement": self.statement, "notes": list(self.notes), "wall_s": round(self.wall_s, 2)}

    def lines(self) -> list[str]:
        """The ranking as text: one line per candidate, by cost (the recommended one starred),
        with every key's relative 95 % half-width and its data-only and noise-weighted parts,
        then the statement and the notes."""
        out = []
        for c in self.candidates:
            widths = ", ".join(f"{k} ±{100 * r:.3g} % (data alone ±{100 * d / max(abs(t), 1e-12):.3g} %, "
                               f"noise-weighted ±{100 * b / max(abs(t), 1e-12):.3g} %)"
                               for k, r, d, b, t in zip(self.keys, c.relative, c.halfwidth_data,
                                                        c.halfwidth_weighted, self.theta))
            out.append(f"{'*' if c is self.recommended else ' '} cost {c.cost:g}  {c.name}: {widths}")
        return [*out, self.statement, *(f"note: {note}" for note in self.notes)]

    @property
    def statement(self) -> str:
        first = self.candidates[0]
        loose = [f"{k} (±{100 * r:.3g} %)" for k, r in zip(self.keys, first.relative) if r > self.tolerance]
        text = (f"The cheapest set, {first.name}, constrains every key to {100 * self.tolerance:.3g} %." if not loose
                else f"{first.name} leaves {', '.join(loose)} beyond {100 * self.tolerance:.3g} %.")
        if self.recommended is None:
            return text + " No candidate constrains every key to the tolerance: add experiments or lower the noise."
        if self.recommended is not first:
            text += (f" The cheapest set that constrains every key is {self.recommended.name} (cost "
                     f"{self.recommended.cost:g}).")
        return text


def _check(noise, tolerance, times, front_times, scene):
    t_end = float(scene.config.t_end)
    if not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive fraction, got {tolerance!r}")
    for name, values in (("times", times), ("front_times", front_times)):
        values = np.asarray(values, float)
        if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
            raise ValueError(f"{name} must be a non-empty list of times (s), got {values!r}")
        if np.any(values <= 0) or np.any(values > t_end) or np.any(np.diff(values) <= 0):
            raise ValueError(f"{name} must increase strictly within (0, t_end = {t_end}], got {values.tolist()}")
    for kind, sigma in noise.items():
        if kind not in ("profile", "front", "top", "velocity"):
            raise ValueError(f"noise: unknown kind {kind!r} (profile, front, top, velocity)")
        if not (math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"noise[{kind!r}] must be a positive fraction, got {sigma!r}")


def _experiment(label, scene, keys, theta, xs, times, front_times, top_x, noise, sampling_seeds, grid_ratio,
                grid_draws, workers) -> Experiment:
    t_end = float(scene.config.t_end)
    theta = np.asarray([theta[k] for k in keys], float)
    profile_times = [float(t) for t in times if t < t_end] + [t_end]
    ones = np.ones_like(xs)
    placeholders = ([ProfileTarget(xs, ones, t) for t in profile_times]
                    + [ProfileTarget(np.array([top_x]), np.ones(1), float(t)) for t in front_times])
    front_placeholder = FrontTarget(np.asarray(front_times), np.ones(len(front_times)))
    gen = Objective(scene, keys, profile=placeholders, front=front_placeholder, check_data=False)
    pred = gen.predict(theta)
    if int(np.asarray(pred["status"])) != 0:
        raise ValueError(f"experiment {label!r}: the run at theta has status bits {int(pred['status'])} "
                         "(it left the grid or failed): no design from it")
    h = np.asarray(pred["h"], float)
    targets, at = [], 0
    for t in profile_times:
        targets.append(ProfileTarget(xs, h[at:at + xs.size], t, f"{label} profile at t = {t:g} s"))
        at += xs.size
    for t in front_times:
        top = max(float(h[at]), 1e-6)
        targets.append(ProfileTarget(np.array([top_x]), np.array([top]), float(t), f"{label} top at t = {t:g} s"))
        at += 1
    front = FrontTarget(np.asarray(front_times, float), np.asarray(pred["front"], float), source=f"{label} front")
    objective = Objective(scene, keys, profile=targets, front=front, check_data=False)
    r, J, _ = objective.residuals_and_jacobian(theta)
    scale = objective.row_scale
    J = np.asarray(J, float) / scale[:, None]
    names = list(objective.blocks)
    n_prof = len(profile_times)

    def block_rows(name):
        return np.arange(objective.blocks[name].start, objective.blocks[name].stop)

    rows = {"final": block_rows(names[n_prof - 1]),
            "profiles": np.concatenate([block_rows(b) for b in names[:n_prof]]),
            "top": np.array([objective.blocks[b].start for b in names[n_prof:n_prof + len(front_times)]]),
            "front": block_rows("front")}
    sigma = np.empty(np.size(objective.row_scale))
    sigma[rows["profiles"]] = noise["profile"]
    sigma[rows["top"]] = noise["top"]
    sigma[rows["front"]] = noise["front"]
    draws = None
    if sampling_seeds and getattr(scene, "sampler", None) is not None:
        runs = redrawn_residuals(objective, theta, sampling_seeds, workers)
        if len(runs) >= 2:
            draws = np.stack(runs + [np.asarray(r, float)]) / scale
            draws = draws - draws.mean(axis=0)
    coarse_mean = None
    if grid_ratio is not None:
        _, kept = coarse_residuals(objective, theta, grid_ratio, grid_draws, workers)
        if kept:
            coarse_mean = np.mean(kept, axis=0) / scale
    return Experiment(label, objective, rows, sigma, J, scale ** 2, draws, coarse_mean, grid_ratio)


def _cost(parts, slopes: Mapping[str, int] | None = None) -> float:
    """A convention, not a price: 1 per collapse for running it and photographing the deposit, 2
    more if anything of it is filmed (``VIDEO``); 1 per slope of an incline's table (tilting the
    chute and measuring the velocities of its layers at that slope; ``slopes``: {incline label:
    its number of slopes}); 1 more for each experiment beyond the first (another set-up). A set
    given with its own cost (``design``'s ``sets``) replaces this."""
    slopes = dict(slopes or {})
    by_experiment: dict[str, set] = {}
    for label, kind in parts:
        by_experiment.setdefault(label, set()).add(kind)
    return sum((float(slopes[label]) if label in slopes else 1.0 + (2.0 if kinds & set(VIDEO) else 0.0))
               + (1.0 if i > 0 else 0.0) for i, (label, kinds) in enumerate(by_experiment.items()))


def expected_halfwidths(experiments: Sequence[Experiment], parts) -> tuple[np.ndarray, ...]:
    """(95 % half-widths, their covariance, the data's share of the half-widths, the same with
    every row weighed by 1/σ², the data's share of the covariance) of θ from the observations
    ``parts`` ((experiment label, kind) pairs): the data's noise plus, where the experiments
    measured them, the particle draw's and the grid's shares (zero for a ``closed_form``
    experiment's rows: such a share is measured when every other experiment in the set measured
    it). The fourth is the Cramér–Rao bound of the data: a fit that weighs each row by its noise
    reaches it, the library's (each block weighed as a whole) only when the blocks are alike."""
    by_label = {e.label: e for e in experiments}
    chosen: dict[str, list[np.ndarray]] = {}
    for label, kind in parts:
        chosen.setdefault(label, []).append(by_label[label].rows[kind])
    Js, sigmas, weights, draws, coarse, ratios = [], [], [], [], [], []
    for label, row_sets in chosen.items():
        e = by_label[label]
        rows = np.unique(np.concatenate(row_sets))
        Js.append(e.J[rows])
        sigmas.append(e.noise_rows[rows])
        weights.append(e.weights[rows])
        draws.append(rows.size if e.closed_form else None if e.draws is None else e.draws[:, rows])
        coarse.append(np.zeros(rows.size) if e.closed_form else None if e.coarse is None else e.coarse[rows])
        ratios += [] if e.closed_form else [e.ratio]
    J, sigma, w = np.concatenate(Js), np.concatenate(sigmas), np.concatenate(weights)
    measured = [d for d in draws if not isinstance(d, int)]
    draws = ([d if not isinstance(d, int) else np.zeros((min(x.shape[0] for x in measured), d)) for d in draws]
             if measured and all(d is not None for d in measured) else [None])
    coarse = coarse if ratios and all(c is not None for c in coarse) else [None]
    # The fit's estimator weighs row i by w_i (its objective's row_scale²), not by 1/σ_i²: its
    # covariance is the sandwich (uncertainty.gauss_newton_uncertainty), and its response to a
    # change r of the residuals is −(JᵀWJ)⁻¹JᵀW r, the least-squares solution of the weighted rows.
    A = J.T @ (w[:, None] * J)
    B = J.T @ ((w * w * sigma * sigma)[:, None] * J)
    cov = cov_data = _inverse(_sandwich_fisher(A, B))
    data_only = Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0))
    Js = J / sigma[:, None]
    weighted = Z95 * np.sqrt(np.maximum(np.diag(_inverse(Js.T @ Js)), 0.0))
    root = np.sqrt(w)
    J = J * root[:, None]
    if all(d is not None for d in draws):
        k = min(d.shape[0] for d in draws)
        S = np.concatenate([d[:k] for d in draws], axis=1) * root[None, :]
        P = np.linalg.lstsq(J, S.T, rcond=None)[0].T
        cov = cov + np.atleast_2d(np.cov(P, rowvar=False, ddof=1))
    if all(c is not None for c in coarse):
        ratio = ratios[0]
        shift = -np.linalg.lstsq(J, np.concatenate(coarse) * root, rcond=None)[0]
        halfwidth = GCI_SAFETY * np.abs(shift) / (ratio ** GRID_ORDER - 1.0)
        norm = np.linalg.norm(shift)
        if norm > 0:
            v = shift / norm * np.linalg.norm(halfwidth / Z95)
            cov = cov + np.outer(v, v)
    return Z95 * np.sqrt(np.maximum(np.diag(cov), 0.0)), cov, data_only, weighted, cov_data


def _default_sets(labels: Sequence[str], inclines: Sequence[str] = ()) -> list[tuple[str, tuple[tuple[str, str], ...]]]:
    """The curated candidates: of the main collapse, of it with its variants and, with ``inclines``,
    each incline alone and with the main collapse's final profile, its filmed profiles and front,
    and (with variants) the final profiles of every collapse; all inclines together where several."""
    main, others = labels[0], labels[1:]
    sets = [("final profile", ((main, "final"),)),
            ("final profile + top height", ((main, "final"), (main, "top"))),
            ("final profile + front", ((main, "final"), (main, "front"))),
            ("profiles in time", ((main, "profiles"),)),
            ("profiles in time + front", ((main, "profiles"), (main, "front"))),
            ("profiles in time + front + top", ((main, "profiles"), (main, "front"), (main, "top")))]
    for r in range(1, len(others) + 1):
        for group in itertools.combinations(others, r):
            names = " + ".join(group)
            sets.append((f"final profiles of main + {names}", ((main, "final"),) + tuple((g, "final") for g in group)))
            sets.append((f"final profile + front of main + {names}",
                         ((main, "final"), (main, "front"))
                         + tuple(p for g in group for p in ((g, "final"), (g, "front")))))
            sets.append((f"profiles in time + front of main + {names}",
                         ((main, "profiles"), (main, "front"))
                         + tuple(p for g in group for p in ((g, "profiles"), (g, "front")))))
    groups = [(f"incline {i}", ((i, "flow_rule"),)) for i in inclines]
    if len(inclines) > 1:
        groups.append(("inclines " + " + ".join(inclines), tuple((i, "flow_rule") for i in inclines)))
    for name, rule in groups:
        sets += [(name, rule), (f"final profile + {name}", ((main, "final"),) + rule),
                 (f"profiles in time + front + {name}", ((main, "profiles"), (main, "front")) + rule)]
        if others:
            sets.append((f"final profiles of main + {' + '.join(others)} + {name}",
                         tuple((g, "final") for g in labels) + rule))
    return sets


def _candidate_sets(sets, scenes, plans) -> list[tuple[str, tuple[tuple[str, str], ...], float | None]]:
    """``design``'s ``sets`` (default: ``_default_sets``) as (name, parts, the cost given or None),
    every part checked against the experiments and the kinds each can give."""
    given = sets if sets is not None else _default_sets(list(scenes), list(plans))
    kinds = {**{label: KINDS for label in scenes}, **{label: INCLINE_KINDS for label in plans}}
    out = []
    for entry in given:
        if not isinstance(entry, Sequence) or len(entry) not in (2, 3):
            raise ValueError(f"sets: each entry is (name, [(experiment, kind), ...]) or (name, parts, cost), "
                             f"got {entry!r}")
        name, parts = entry[0], tuple((str(e), str(k)) for e, k in entry[1])
        cost = None if len(entry) == 2 else float(entry[2])
        if cost is not None and not (math.isfinite(cost) and cost >= 0):
            raise ValueError(f"sets: {name!r} has the cost {entry[2]!r}; a cost is a finite number >= 0")
        for label, kind in parts:
            if kind not in kinds.get(label, ()):
                raise ValueError(f"sets: {name!r} names ({label!r}, {kind!r}); experiments are {list(kinds)}, "
                                 f"their kinds {list(KINDS)} (a collapse) and {list(INCLINE_KINDS)} (an incline)")
        out.append((name, parts, cost))
    return out


def _notes(experiments, sampling_seeds, grid_ratio) -> list[str]:
    notes = []
    for e in experiments:
        if e.closed_form:
            continue  # no particles, no grid: its shares are zero, not unmeasured
        if sampling_seeds and e.draws is None:
            notes.append(f"experiment {e.label!r}: the particle draw's share was not measured (a sampling with no "
                         "seed to redraw, or fewer than two redrawn runs without status bits)")
        if grid_ratio is not None and e.coarse is None:
            notes.append(f"experiment {e.label!r}: the grid's share was not measured (no run at {grid_ratio:g} × dx "
                         "ran without status bits)")
    return notes


def design(scene, keys: Sequence[str], theta: Mapping[str, float] | None = None, *,
           noise: Mapping[str, float] | float = 0.02, tolerance: float = 0.1, times: Sequence[float] | None = None,
           front_times: Sequence[float] | None = None, variants: Mapping[str, Mapping[str, Any]] | None = None,
           inclines: Mapping[str, Any] | None = None, sampling_seeds: int = 0, grid_ratio: float | None = None,
           grid_draws: int = 2, sets: Sequence[tuple] | None = None, workers=None) -> DesignResult:
    """Expected 95 % half-widths of ``keys`` at ``theta`` (default: the scene's values) for
    candidate sets of observations (see the module docstring).

    ``noise``: relative noise by kind, as the fit's ("profile": of the profile's peak, "front": of
    the column's length, "top": of the top's height, "velocity": of an incline's velocity), or one
    number for all. An incline's velocity noise is "velocity" where given, else its table's stated
    ``noise``, else 0.02.
    ``times``: the profile times during the flow (default t_end × (0.1, 0.2, 0.4)); the final
    profile is always recorded. ``front_times``: the front's and the top's times (default 20 over
    (0, t_end]). ``variants``: {label: changes to the scene's builder} (``Scene.variant``), the
    same material in other experiments. ``inclines``: {label: a ``FlowRuleTable``, or a pair
    (table, {key: value}) of the incline's own material (ρ, ρ_s, d) over the scene's}: steady
    flows of the same material; the table's slopes, thicknesses and quantity are the plan, its
    velocities are not used (the model's at θ are). ``sets``: the candidates as (name,
    [(experiment, kind)]) or (name, parts, cost) (default: the curated list of ``_default_sets``;
    "main" is the scene's label; the kinds are ``KINDS`` for a collapse and "flow_rule" for an
    incline; a cost not given follows ``_cost``'s convention).
    ``sampling_seeds``, ``grid_ratio``, ``grid_draws``: the particle draw's and the grid's shares,
    as for ``fit`` (an incline's are zero: a closed form)."""
    clock = time.perf_counter()
    keys = tuple(keys)
    t_end = float(scene.config.t_end)
    times = tuple(t_end * f for f in (0.1, 0.2, 0.4)) if times is None else tuple(times)
    front_times = tuple(np.linspace(t_end / 20, t_end, 20)) if front_times is None else tuple(front_times)
    velocity_given = not isinstance(noise, Mapping) or "velocity" in noise
    noise = ({k: float(noise) for k in ("profile", "front", "top", "velocity")} if not isinstance(noise, Mapping)
             else {"profile": 0.02, "front": 0.02, "top": 0.02, "velocity": 0.02,
                   **{k: float(v) for k, v in noise.items()}})
    _check(noise, tolerance, times, front_times, scene)
    check_grid_options(grid_ratio, grid_draws)
    if sampling_seeds and sampling_seeds < 2:
        raise ValueError(f"sampling_seeds must be 0 or >= 2, got {sampling_seeds!r}")
    values = {k: float(np.asarray(getattr(scene.params, k))) for k in keys}
    values.update({k: float(v) for k, v in dict(theta or {}).items()})
    unknown = sorted(set(values) - set(keys))
    if unknown:
        raise ValueError(f"theta: {unknown} are not among the keys {list(keys)}")
    scenes = {"main": scene}
    for label, changes in dict(variants or {}).items():
        if label == "main":
            raise ValueError("variants: 'main' names the scene itself; choose another label")
        scenes[label] = scene.variant(**dict(changes))
    plans = incline_plans(inclines, list(scenes))
    sigmas = {label: incline_sigma(table, noise, velocity_given) for label, (table, _, _) in plans.items()}
    incline_runs = [incline_experiment(label, table, material, scene.params, keys, values, sigmas[label], Experiment,
                                       walls)
                    for label, (table, material, walls) in plans.items()]  # refused here, before any collapse runs
    candidate_sets = _candidate_sets(sets, scenes, plans)
    length = float(scene.info.length)
    grid = scene.config.grid
    xs = np.linspace(0.0, 0.9 * (grid.origin[0] + grid.cells[0] * grid.dx), 60)  # the profiles' points
    top_x = 0.1 * length
    experiments = [_experiment(label, s, keys, values, xs, times, front_times, top_x, noise, sampling_seeds,
                               grid_ratio, grid_draws, workers) for label, s in scenes.items()] + incline_runs
    theta_arr = np.array([values[k] for k in keys])
    slopes = {label: int(table.slopes.size) for label, (table, _, _) in plans.items()}
    candidates = []
    for name, parts, cost in candidate_sets:
        halfwidth, cov, data_only, weighted, cov_data = expected_halfwidths(experiments, parts)
        relative = halfwidth / np.maximum(np.abs(theta_arr), 1e-12)
        candidates.append(Candidate(name, parts, _cost(parts, slopes) if cost is None else cost, halfwidth, relative,
                                    cov, bool(np.all(relative <= tolerance)), data_only, weighted, cov_data))
    candidates.sort(key=lambda c: (c.cost, float(np.max(c.relative))))
    recommended = next((c for c in candidates if c.meets), None)
    noise_used = {**{k: v for k, v in noise.items() if k != "velocity" or (plans and velocity_given)},
                  **{f"velocity@{label}": sigma for label, sigma in sigmas.items()}}
    return DesignResult(keys, theta_arr, noise_used, float(tolerance), tuple(candidates), recommended,
                        tuple(scenes) + tuple(plans), time.perf_counter() - clock,
                        tuple(_notes(experiments, sampling_seeds, grid_ratio)))
