"""Global search: multi-start Levenberg–Marquardt with every start in one vmapped batch.

``search(objective, starts=8)`` draws k starts from a space-filling design over the bounded box
and runs ``calibration.optim.lm`` from all of them at once through ``calibration.optim.loop.run``
(the same steps and stops as ``fit``); a start that has stopped leaves the batch, which shrinks to
the next power of two that holds the active starts. The end points are clustered into distinct
minima, each with its Δχ² against the best and whether it lies within the noise; the best point
is judged as a fit's is. ``coarse_to_fine`` places the starts on a coarser grid first. How and
why: docs/fitting.md ("The global search"). scipy (the ``sampling`` extra) provides the designs.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Mapping
from typing import Any

import jax
import numpy as np

from ..batch.workers import using
from ..inference.gridcheck import GRID_DRAWS
from ..inference.noise import block_noise, chi2_of, chi2_quantile
from ..inference.options import JudgeOptions
from ..inference.scatter import ROUNDOFF_SAMPLES
from ..inference.verdict import judge_point
from ..problem.options import check_int
from ..problem.protocol import ObjectiveLike, is_valid
from .evaluate import BatchEvaluator
from .fit import FitResult, measured_at, roundoff_stop, save_start, start_theta
from .history import History, check_out
from .lm import DEFAULT_JACOBIAN, DEFAULT_MODEL, LMOptions, levenberg_marquardt, with_exact_jacobians
from .loop import run
from .options import FitOptions

__all__ = [
    "DESIGNS", "DEFAULT_STARTS", "WITHIN_NOISE_P", "COARSE_OPTIONS", "design_starts", "Minimum", "SearchResult",
    "search", "coarse_to_fine", "fit_from_starts",
]


DESIGNS = ("sobol", "lhs")


#: Starts of a search when none are asked for (the command line's default without --init).
DEFAULT_STARTS = 8


#: A minimum is within the noise of the best when its Δχ² is below this quantile of χ²_n.
WITHIN_NOISE_P = 0.95


#: The coarse stage of ``coarse_to_fine``: a few iterations, stopped at 0.1 % steps or 0.01 % gains.
COARSE_OPTIONS = {"steps": 12, "xtol": 1e-3, "ftol": 1e-4}


#: ``dominated_stop``'s allowance for a loss falling further than its linearised model promises.
DOMINATED_MARGIN = 10.0


#: Starts are drawn this fraction of the range inside the bounds (the sigmoid's flat tails).
DESIGN_MARGIN = 0.02


def _qmc():
    try:
        from scipy.stats import qmc
    except ImportError as err:  # pragma: no cover (jax depends on scipy)
        raise ImportError("calibration.optim.search draws its starts with scipy.stats.qmc: "
                          "pip install 'jaxmpm[sampling]'") from err
    return qmc


def design_starts(objective: ObjectiveLike, k: int, *, seed: int = 0, design: str = "sobol") -> np.ndarray:
    """``k`` physical starts (k, n) in the objective's bounds, ``DESIGN_MARGIN`` inside them,
    space-filling (scrambled Sobol or Latin hypercube, seeded), every one a valid parameter set
    of the engine (``objective.check_thetas``): invalid rows are skipped and more are drawn."""
    k = check_int("starts", k, 1)
    seed = check_int("seed", seed, 0)
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {DESIGNS}, got {design!r}")
    qmc = _qmc()
    bounds = objective.bounds
    lo, hi = np.asarray(bounds.lower), np.asarray(bounds.upper)
    draw = max(2, 1 << (4 * k - 1).bit_length())  # a power of two, >= 4k: room for invalid rows
    for _ in range(4):
        if design == "sobol":
            u = qmc.Sobol(bounds.n, scramble=True, seed=seed).random_base2(int(math.log2(draw)))
        else:
            u = qmc.LatinHypercube(bounds.n, seed=seed).random(draw)
        thetas = lo + (hi - lo) * (DESIGN_MARGIN + (1 - 2 * DESIGN_MARGIN) * u)
        valid = [theta for theta in thetas if is_valid(objective, theta)]
        if len(valid) >= k:
            return np.asarray(valid[:k])
        draw *= 4
    raise ValueError(f"starts: fewer than {k} of {draw // 4} design points in the bounds are valid parameter sets "
                     "(the fixed parameters leave little room: narrow the bounds or fit fewer keys)")


@dataclasses.dataclass(frozen=True)
class Minimum:
    """One distinct endpoint of the search (a cluster of starts)."""

    theta: dict[str, float]
    loss: float
    delta_chi2: float  # against the best minimum
    within_noise: bool  # Δχ² below the χ²_n quantile WITHIN_NOISE_P
    starts: tuple[int, ...]  # the starts that ended here, best first
    verified: bool  # the best of them met an LM convergence test
    at_bound: tuple[str, ...]
    message: str

    def to_dict(self) -> dict[str, Any]:
        return {"params": self.theta, "loss": self.loss, "delta_chi2": self.delta_chi2,
                "within_noise_of_best": self.within_noise, "starts": list(self.starts),
                "verified_minimum": self.verified, "at_bound": list(self.at_bound), "message": self.message}


@dataclasses.dataclass
class SearchResult:
    keys: tuple[str, ...]
    starts: np.ndarray  # (k, n) physical starts
    design: str
    seed: int
    minima: list[Minimum]  # by loss, best first
    best: FitResult  # the best start's fit (history, residuals, Jacobian, verdict, uncertainty)
    best_start: int
    finals: np.ndarray  # (k, n) every start's endpoint
    losses: np.ndarray  # (k,) their losses (NaN: the start failed)
    residuals: np.ndarray  # (k, m) their residuals
    histories: list[dict[str, np.ndarray]]  # every start's, in the fields of FitResult.history
    messages: list[str]
    delta_chi2_limit: float
    iterations: int  # batched iterations (model evaluations per active start)
    evaluations: int  # single-run evaluations (batch members, padding included)
    wall_s: float
    compile_s: float
    start_note: str = ""
    coarse: SearchResult | None = None  # the coarse stage of coarse_to_fine, if there was one

    @property
    def within_noise(self) -> list[Minimum]:
        return [m for m in self.minima if m.within_noise]

    def to_json(self) -> dict[str, Any]:
        out = self.best.to_json()
        out["method"] = "lm-search"
        out["search"] = {
            "starts": len(self.starts), "design": self.design, "seed": self.seed, "best_start": self.best_start,
            "start_used": dict(zip(self.keys, self.starts[self.best_start].tolist())),
            "iterations": self.iterations, "evaluations": self.evaluations, "wall_s": round(self.wall_s, 3),
            "compile_s": round(self.compile_s, 3), "delta_chi2_limit": self.delta_chi2_limit,
            "minima": [m.to_dict() for m in self.minima],
            "n_within_noise": len(self.within_noise),
            "failed_starts": [i for i, v in enumerate(self.losses) if not np.isfinite(v)],
        }
        if self.start_note:
            out["search"]["start_note"] = self.start_note
        if self.coarse is not None:
            c = self.coarse
            out["search"]["coarse"] = {
                "starts": len(c.starts), "iterations": c.iterations, "evaluations": c.evaluations,
                "wall_s": round(c.wall_s, 3), "compile_s": round(c.compile_s, 3),
                "minima": [m.to_dict() for m in c.minima],
                "refined_from": [dict(zip(self.keys, t.tolist())) for t in self.starts]}
        if len(self.within_noise) > 1:
            out["search"]["statement"] = (
                f"{len(self.within_noise)} distinct minima lie within the noise of the best (Δχ² < "
                f"{self.delta_chi2_limit:.3g}): the data do not tell them apart; the answer is the set, and an "
                "interval at the best alone understates what is unknown.")
        return out


def _starts(objective: ObjectiveLike, starts, init, seed: int, design: str) -> tuple[np.ndarray, str]:
    """The search's physical starts (k, n): ``starts`` design points (an int) or the given rows,
    checked; ``init`` (one more start, first) and its note."""
    keys, bounds = objective.keys, objective.bounds
    if isinstance(starts, (int, np.integer)) and not isinstance(starts, (bool, np.bool_)):
        k_design = check_int("starts", starts, 1) - (1 if init else 0)
        thetas = design_starts(objective, k_design, seed=seed, design=design) if k_design else np.zeros((0, len(keys)))
    else:
        thetas = np.asarray(starts, float)
        if thetas.ndim != 2 or thetas.shape[1] != len(keys) or thetas.shape[0] < 1:
            raise ValueError(f"starts must be an integer or an array (k, {len(keys)}), got shape {thetas.shape}")
        for i, theta in enumerate(thetas):
            bounds.check(theta, f"starts[{i}]")
        objective.check_thetas(thetas, "starts")
    if not init:
        return thetas, ""
    theta0, start_note = start_theta(objective, init)
    return np.concatenate([theta0[None], thetas]), start_note


def _minima(objective: ObjectiveLike, cur, messages, order, i_best: int, noise, cluster_tol: float):
    """The distinct minima among the starts' end points ``cur`` (closer than ``cluster_tol`` of
    every bound range: one minimum), best first, each with its Δχ² against the best and whether it
    lies within the noise; and that limit."""
    bounds, keys = objective.bounds, objective.keys
    sigma, _, _ = block_noise(cur.residuals[i_best], objective.row_scale, objective.blocks, noise)
    chi2 = {int(i): chi2_of(cur.residuals[i], objective.row_scale, objective.blocks, sigma) for i in order}
    limit = chi2_quantile(WITHIN_NOISE_P, len(keys))
    span = np.asarray(bounds.upper) - np.asarray(bounds.lower)
    clusters: list[list[int]] = []
    for i in order:
        for members in clusters:
            if np.max(np.abs(cur.theta[i] - cur.theta[members[0]]) / span) <= cluster_tol:
                members.append(int(i))
                break
        else:
            clusters.append([int(i)])
    minima = []
    for members in clusters:
        i = members[0]
        delta_chi2 = chi2[i] - chi2[i_best]
        minima.append(Minimum(theta=dict(zip(keys, map(float, cur.theta[i]))), loss=float(cur.loss[i]),
                              delta_chi2=float(delta_chi2), within_noise=bool(delta_chi2 <= limit),
                              starts=tuple(members), verified=messages[i].startswith("converged"),
                              at_bound=tuple(bounds.near_bound(cur.theta[i])), message=messages[i]))
    return minima, limit


def dominated_stop(n: int):
    """The loop's ``stop`` for a search: a start is dropped ("stopped: dominated") once its loss,
    less ``DOMINATED_MARGIN`` times the decrease its linearised model still promises, stays above
    the best start's loss by more than the noise allows (Δχ² at ``WITHIN_NOISE_P`` of χ²_n, σ² the
    best loss over m − n for m residuals, as LM's statistical stop estimates it): it cannot become
    the best."""
    limit = chi2_quantile(WITHIN_NOISE_P, n)

    def stop(state):
        loss = state.current.loss
        if not np.isfinite(loss).any():
            return state
        best, m = int(np.nanargmin(loss)), state.current.residuals.shape[1]
        bar = loss[best] * (1.0 + limit / max(m - n, 1))
        with np.errstate(invalid="ignore"):
            drop = ~state.done & (np.arange(loss.size) != best) & (loss - DOMINATED_MARGIN * state.promised > bar)
        if getattr(state, "fresh", None) is not None:  # LM with Broyden's updates: judged on exact Jacobians only
            drop &= state.fresh
        message = state.message.copy()
        for i in np.flatnonzero(drop):
            message[i] = (f"stopped: dominated by start {best}: its loss {loss[i]:.3g}, less {DOMINATED_MARGIN:g} "
                          f"times the decrease its linearised model promises, stays above {loss[best]:.3g} by more "
                          f"than the noise allows")
        return state._replace(done=state.done | drop, message=message)

    return stop


def _run_starts(objective: ObjectiveLike, thetas, evaluate, steps: int, lm_options: LMOptions, progress: bool,
                clock0: float, stop=None):
    """LM from every row of ``thetas`` at once through ``calibration.optim.loop.run``: the final
    state and the history of k rows."""
    k = len(thetas)
    optimiser = levenberg_marquardt(lm_options)

    def check_start(evaluation):
        if not np.any((evaluation.status == 0) & np.isfinite(evaluation.loss)):
            raise ValueError(f"search: the runs at all {k} starts fail (statuses "
                             f"{sorted(set(evaluation.status.tolist()))})")

    def report(state, rows):
        if progress and history.iterations > 1:  # from the first step on (not the runs at the starts)
            print(f"search: iteration {history.iterations}/{steps}, {len(rows)} active of {k}, best loss "
                  f"{np.nanmin(state.current.loss):.3e}", file=sys.stderr, flush=True)

    history = History(k, t0=clock0)
    Z = np.stack([objective.bounds.to_unconstrained(t) for t in thetas])
    state = run(optimiser, optimiser.init(Z), evaluate, history, steps=steps, check_start=check_start, report=report,
                stop=stop)
    return state, history


def search(objective: ObjectiveLike, starts: int | np.ndarray = DEFAULT_STARTS, *, seed: int = 0, design: str = "sobol",
           init: Mapping[str, float] | None = None, steps: int = 30, xtol: float = 1e-6, ftol: float = 1e-7,
           stat_tol: float = 0.1, max_rejections: int = 6, lm_model: str = DEFAULT_MODEL,
           lm_jacobian: str = DEFAULT_JACOBIAN, cluster_tol: float = 0.01,
           noise: Mapping[str, float] | float | None = None, uncertainty: bool = True, shrink: bool = True,
           roundoff_samples: int = ROUNDOFF_SAMPLES, sampling_seeds: int = 0, reference_noise: float = 0.01,
           threshold: float = 0.1, grid_ratio: float | None = None, grid_draws: int = GRID_DRAWS,
           grid_levels: int = 1, probe: bool = True, drop_dominated: bool = False,
           progress: bool = False, workers=None) -> SearchResult:
    """Multi-start LM from ``starts`` design points (an int k) or from given physical starts
    ((k, n) array). ``init`` (physical values by key, as for ``fit``): one more start, placed
    first. ``steps``: the maximum number of model evaluations per start, as in ``fit``.
    ``cluster_tol``: endpoints closer than this fraction of every bound range are one minimum.
    ``shrink``: evaluate only the active starts (padded to a power of two). ``drop_dominated``:
    stop starts that cannot become the best (``dominated_stop``; for starts already in their basins,
    as ``coarse_to_fine``'s are, where the linearised model says what is left). ``noise`` and the
    options from ``roundoff_samples`` on: the best point's verdict and uncertainty, as in ``fit``
    (``JudgeOptions``). ``workers``: with more than one, every iteration's forward-mode passes run
    in that many single-threaded processes instead of one vmapped batch, and so do the verdict's."""
    judge = JudgeOptions(noise=noise, uncertainty=uncertainty, roundoff_samples=roundoff_samples,
                         sampling_seeds=sampling_seeds, reference_noise=reference_noise, threshold=threshold,
                         grid_ratio=grid_ratio, grid_draws=grid_draws, grid_levels=grid_levels, probe=probe)
    with using(workers) as workers:
        clock0 = time.perf_counter()
        steps = check_int("steps", steps, 1)
        lm_options = FitOptions(steps=int(steps), xtol=xtol, ftol=ftol, stat_tol=stat_tol,
                                max_rejections=max_rejections, lm_model=lm_model,
                                lm_jacobian=lm_jacobian).lm_options()
        if not (math.isfinite(cluster_tol) and 0 < cluster_tol < 1):
            raise ValueError(f"cluster_tol must be in (0, 1), got {cluster_tol!r}")
        if objective.jacobian != "ad":
            raise ValueError("search uses forward-mode Jacobians: the objective's jacobian='fd' is not supported "
                             "(a single-start fit is)")
        keys = objective.keys
        thetas, start_note = _starts(objective, starts, init, seed, design)
        evaluate = BatchEvaluator(objective, len(thetas), shrink, workers)
        scatters: dict = {}
        dominated = dominated_stop(len(keys)) if drop_dominated and len(thetas) > 1 else None
        at_roundoff = roundoff_stop(objective, roundoff_samples if uncertainty else 0, workers, scatters)
        state, history = _run_starts(objective, thetas, evaluate, steps, lm_options, progress, clock0,
                                     stop=lambda s: at_roundoff(dominated(s) if dominated else s))
        valid = np.flatnonzero(np.isfinite(state.current.loss))
        order = valid[np.argsort(state.current.loss[valid], kind="stable")]
        i_best = int(order[0])
        state = with_exact_jacobians(state, [i_best], evaluate)  # the verdict's Jacobian, not Broyden's estimate
        cur, messages = state.current, list(state.message)
        converged = messages[i_best].startswith("converged")
        theta_b, r_b, J_b = cur.theta[i_best], cur.residuals[i_best], cur.jacobian[i_best]
        judged = dataclasses.replace(judge, uncertainty=uncertainty and bool(np.all(np.isfinite(J_b))),
                                     roundoff_samples=roundoff_samples if uncertainty else 0,
                                     grid_ratio=grid_ratio if uncertainty else None)
        verdict, unc = judge_point(objective, r_b, J_b, theta_b, converged=converged, message=messages[i_best],
                                   scatter=measured_at(scatters, i_best, theta_b),
                                   workers=workers, **judged.kwargs())
        wall = time.perf_counter() - clock0
        histories = [history.arrays(i) for i in range(len(thetas))]
        best = FitResult(keys=keys, theta=dict(zip(keys, map(float, theta_b))), loss=float(cur.loss[i_best]),
                         iterations=len(histories[i_best]["loss"]), wall_s=wall, method="lm", converged=converged,
                         message=messages[i_best], history=histories[i_best], residuals=r_b, jacobian=J_b,
                         prediction=jax.tree.map(lambda a: a[i_best], cur.prediction), uncertainty=unc,
                         start=dict(zip(keys, map(float, thetas[i_best]))),
                         start_note=start_note if i_best == 0 and init else "", verdict=verdict)
        minima, limit = _minima(objective, cur, messages, order, i_best, noise, cluster_tol)
        return SearchResult(keys=keys, starts=thetas, design=design, seed=int(seed), minima=minima, best=best,
                            best_start=i_best, finals=cur.theta.copy(), losses=cur.loss.copy(),
                            residuals=cur.residuals.copy(), histories=histories, messages=messages,
                            delta_chi2_limit=limit, iterations=history.iterations, evaluations=evaluate.evaluations,
                            wall_s=wall, compile_s=evaluate.compile_s, start_note=start_note)


def coarse_to_fine(objective: ObjectiveLike, coarse: ObjectiveLike, starts: int | np.ndarray = DEFAULT_STARTS, *,
                   refine: int = 2, seed: int = 0,
                   design: str = "sobol", init: Mapping[str, float] | None = None,
                   coarse_options: Mapping[str, Any] | None = None, progress: bool = False, workers=None,
                   **options) -> SearchResult:
    """A global search in two stages: ``search`` on ``coarse`` (the same keys, bounds and data on
    a cheaper resolution, with ``COARSE_OPTIONS`` overridden by ``coarse_options``) finds the
    basins; the best ``refine`` distinct minima it reports (all within the noise of the best if
    there are more; one that breaks a rule of the engine, such as μ1 > μ2, replaced by the last
    valid point on the line from its start) start a batched ``search`` on ``objective`` with
    ``options`` (steps, noise, ``lm_jacobian``, ...; the coarse stage's LM takes exact Jacobians:
    its few steps a start rank the basins, fewer than Broyden's estimate needs). Where the best
    point of that is not a fit of the data, the
    next ``refine`` coarse minima are refined too and the lower of the two is kept (the coarse
    grid's own model error can rank the data's basin below another). The result is the fine
    stage's, with the coarse one as ``.coarse``: nothing the coarse stage gets wrong survives into
    it, except a basin it never found or ranked below the refined ones."""
    refine = check_int("refine", refine, 1)
    if tuple(coarse.keys) != tuple(objective.keys):
        raise ValueError(f"coarse: fits {tuple(coarse.keys)}, the objective {tuple(objective.keys)}; they must agree")
    b_c, b_f = coarse.bounds, objective.bounds
    if not (np.allclose(b_c.lower, b_f.lower) and np.allclose(b_c.upper, b_f.upper)):
        raise ValueError("coarse: its bounds differ from the objective's; the two stages must search the same box")
    opts = {**COARSE_OPTIONS, **dict(coarse_options or {})}
    with using(workers) as workers:  # one pool for both stages
        first = search(coarse, starts, seed=seed, design=design, init=init, uncertainty=False,
                       noise=options.get("noise"), lm_model=options.get("lm_model", DEFAULT_MODEL),
                       progress=progress, workers=workers, **opts)

        def placed(m):
            """The minimum, moved inside the bounds; if it breaks an engine rule, the last valid point
            on the straight line from its (valid) start to it (bisection)."""
            theta = b_f.move_inside([m.theta[k] for k in objective.keys])[0]
            if is_valid(objective, theta):  # an LM endpoint may break a rule of the engine's (μ1 > μ2)
                return theta, False
            start = first.starts[m.starts[0]]
            lo, hi = 0.0, 1.0
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if is_valid(objective, start + mid * (theta - start)) else (lo, mid)
            return start + lo * (theta - start), True

        usable = [(m.within_noise, *placed(m)) for m in first.minima]
        within = [(t, moved) for inside, t, moved in usable if inside]
        chosen = within if len(within) > refine else [(t, moved) for _, t, moved in usable[:refine]]
        rest = [(t, moved) for _, t, moved in usable[len(chosen):]]  # in loss order, those within the noise first

        def refined(chosen):
            if progress:
                print(f"coarse_to_fine: refining {len(chosen)} of {len(first.minima)} coarse minima", file=sys.stderr,
                      flush=True)
            return search(objective, np.stack([t for t, _ in chosen]), seed=seed, design=design, drop_dominated=True,
                          progress=progress, workers=workers, **options)

        result, notes = refined(chosen), []
        if rest and result.best.verdict is not None and not result.best.verdict.is_fit:
            # The best refined basin is no fit of the data: the coarse grid ranks basins by its own
            # model error, so the next ones get their turn before the search gives up.
            more = rest[:refine]
            second = refined(more)
            notes.append(f"the best of the first {len(chosen)} refined coarse minima was not a fit of the data "
                         f"(loss {result.best.loss:.4g}); the next {len(more)} were refined too"
                         + (f" and gave the best point (loss {second.best.loss:.4g})"
                            if second.best.loss < result.best.loss else ", without a lower loss"))
            wall_s = result.wall_s + second.wall_s  # both refinements' time, whichever is kept
            result, chosen = (second if second.best.loss < result.best.loss else result), chosen + more
            result.wall_s = wall_s
        result.coarse = first
        moved = sum(1 for _, mv in chosen if mv)
        if moved:
            notes.append(f"{moved} coarse minimum(s) broke a rule of the engine's (such as mu1 <= mu2) and were "
                         "refined from the last valid point on the line from their start")
        for note in notes:
            result.start_note = f"{result.start_note}; {note}" if result.start_note else note
        result.wall_s += first.wall_s
        return result


def fit_from_starts(objective, init: Mapping[str, float] | None = None, *, starts: int = 1,
                    options: FitOptions | None = None, judge: JudgeOptions | None = None, coarse=None, refine: int = 2,
                    seed: int = 0, out=None, resume: bool = False, overwrite: bool = False, progress: bool = False,
                    meta: Mapping[str, Any] | None = None, workers=None) -> tuple[FitResult, SearchResult | None]:
    """The judged fit of ``objective`` from ``starts`` starts: one start (``fit`` from ``init``,
    with its history ``out``, ``resume``, ``overwrite`` and ``meta``), else the global search
    (``init`` one more start, ``seed`` its design's), in two stages (``coarse_to_fine``) when
    ``coarse`` (the objective on a coarser grid) is given. ``options`` and ``judge`` as for
    ``fit`` (the search takes only ``steps`` and ``lm_model``). Returns the best point and the search (None for
    one start). A search's ``out`` is its best start's file (``save_start``), which a resume
    continues as one start."""
    options, judge = options or FitOptions(), judge or JudgeOptions()
    from .fit import fit  # looked up at the call: the fit that runs is the module's

    if check_int("starts", starts, 1) == 1:
        with using(workers) as workers:  # one pool for the fit and its restarts
            result = fit(objective, init, options=options, judge=judge, out=out, resume=resume, overwrite=overwrite,
                         progress=progress, meta=meta, workers=workers)
            return _restarted(objective, result, options, judge, out, meta, progress, workers), None
    if resume:
        raise ValueError("resume continues one start's history: a search (starts > 1) cannot resume")
    path = check_out(out, resume=False, overwrite=overwrite)
    with using(workers) as workers:
        common = dict(seed=seed, init=init or None, steps=options.steps, lm_model=options.lm_model,
                      lm_jacobian=options.lm_jacobian,
                      progress=progress, workers=workers, **judge.kwargs())
        found = (coarse_to_fine(objective, coarse, starts, refine=refine, **common) if coarse is not None
                 else search(objective, starts, **common))
        found.best = _restarted(objective, found.best, options, judge, None, meta, progress, workers)
    if path is not None:
        save_start(path, objective, found.best, options, judge, meta)
    return found.best, found


def _restarted(objective, result, options: FitOptions, judge: JudgeOptions, out, meta, progress: bool,
               workers):
    """``result`` or, where its verdict's probe found a lower loss near its point, the fit started
    again from the lowest point the probe ran, at most ``options.restarts`` times; each restart
    ends lower than the last (LM only accepts decreases from a start already lower). The result
    lists the restarts; its file ``out`` (if any) becomes the last fit's."""
    from .fit import fit

    tried = []
    while (len(tried) < options.restarts and result.verdict is not None and result.verdict.probe is not None
           and not result.verdict.probe.passed):
        start = dict(zip(result.keys, map(float, result.verdict.probe.lowest)))
        if progress:
            print(f"fit: the probe found a lower loss near the point; fitting again from {start}", file=sys.stderr,
                  flush=True)
        again = fit(objective, start, options=options, judge=judge, progress=progress, workers=workers)
        tried.append({"ended": result.theta, "loss": result.loss, "probe_lowest": start,
                      "probe_rise": result.verdict.probe.lowest_rise, "wall_s": round(result.wall_s, 3)})
        again.wall_s += result.wall_s
        result = again
    if tried:
        result.restarts = tried
        if out is not None:
            save_start(check_out(out, resume=False, overwrite=True), objective, result, options, judge, meta)
    return result
