"""Measure the package's hand-written PSIS, R-hat/ESS and Levenberg–Marquardt against the libraries.

Prints one JSON object (``python library_check.py > out.json``) with three parts, each on the
same seeded inputs for both sides:

- ``psis``: ``calibration.inference.surrogates.psis`` against ArviZ's
  ``arviz_stats.base.array_stats.psislw`` (its numpy layer: the top-level ``arviz_stats`` API
  needs xarray) and, for information, ``blackjax.diagnostics.psis_weights``: k-hat and the
  normalised smoothed log weights, max abs differences, wall time per call, and what each does
  with failed runs (−inf), equal weights and too few weights.
- ``diagnostics``: blackjax's ``rhat``, ``ess_bulk`` and ``ess_tail`` (what
  ``calibration.inference.mcmc`` used before it took arviz-stats' on this measurement), run as
  the package ran them (JAX's default float32) and in float64, against
  ``array_stats.rhat(method="rank")``, ``array_stats.ess(method="bulk")`` and
  ``array_stats.ess(method="tail", prob=(0.05, 0.95))``: relative differences and time per key.
- ``lm``: the package's LM (``calibration.optim.lm.levenberg_marquardt`` run by
  ``calibration.optim.loop.run``) against
  ``optimistix.least_squares`` with ``optimistix.LevenbergMarquardt`` on classic problems:
  model evaluations (residuals + Jacobian, the cost when one is a simulation), final loss,
  distance to a MINPACK reference; and concrete tests of what the fit needs from optimistix
  driven step by step (``solver.init``/``step``/``terminate``) with the model evaluated outside
  JAX: an external evaluation per step, a failed run, a failed start, save and exact resume, a
  batch of starts, the statistical stopping rule.

Needs: numpy, scipy, jax, blackjax (>= 1.7 for ``psis_weights``), arviz-stats, optimistix and
the ``calibration`` package. Runs on the CPU in about a minute.
"""

from __future__ import annotations

import importlib
import importlib.util
import io
import json
import math
import platform
import sys
import time
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)  # the libraries' side in float64; ``_summary`` is also run in float32

# Where today's code lives (first) and where it may move to.
PSIS_MODULES = ("calibration.inference.surrogates",)
LM_MODULES = ("calibration.optim.lm",)
LOOP_MODULES = ("calibration.optim.loop", "calibration.optim.evaluate")


def _find(attr, names):
    """``attr`` from the first module of ``names`` that has it, and that module's name. When the
    package's ``__init__`` cannot be imported (a restructuring half done), the submodules are
    imported under a bare package object instead."""
    errors = []
    for bare in (False, True):
        if bare:
            spec = importlib.util.find_spec("calibration")
            if spec is None or spec.submodule_search_locations is None:
                break
            pkg = types.ModuleType("calibration")
            pkg.__path__ = list(spec.submodule_search_locations)
            sys.modules["calibration"] = pkg
        for name in names:
            try:
                module = importlib.import_module(name)
            except Exception as err:  # noqa: BLE001 - report why each candidate failed
                errors.append(f"{name}: {type(err).__name__}: {err}")
                continue
            if hasattr(module, attr):
                return getattr(module, attr), name + (" (package __init__ bypassed)" if bare else "")
    raise ImportError(f"{attr} not found: " + "; ".join(errors))


def _version(dist):
    try:
        from importlib.metadata import version

        return version(dist)
    except Exception:  # noqa: BLE001
        return None


def _per_call(fn, min_time=0.2, max_calls=200):
    """Median wall time of one call of ``fn()`` after a warm-up call (seconds)."""
    fn()
    times, start = [], time.perf_counter()
    while len(times) < 3 or (time.perf_counter() - start < min_time and len(times) < max_calls):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _outcome(fn):
    """What ``fn()`` gives: its k-hat, or the error it raises."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = fn()
        k = float(out[1])
        lw = np.asarray(out[0], float)
        total = float(np.sum(np.exp(lw[np.isfinite(lw)]))) if np.isfinite(lw).any() else float("nan")
        return f"k_hat={k:.4g}, sum of weights={total:.6g}, non-finite log weights={int(np.sum(~np.isfinite(lw)))}"
    except Exception as err:  # noqa: BLE001
        return f"raises {type(err).__name__}: {err}"


def _clean(x):
    """JSON-safe: NaN and ±inf as strings, numpy scalars as floats."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else str(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


# ---------------------------------------------------------------------------------------------
# 1. PSIS


def _psis_inputs():
    """(name, asymptotic k or None, log weights) on seeded draws: importance ratios between
    normal and Student-t densities (light and heavy tails), a normal ratio with known k, and
    exact Pareto tails (w = exp(k E), E ~ Exp(1), is Pareto with shape k)."""
    from scipy import stats

    out = []
    for S in (200, 1000, 5000):
        rng = np.random.default_rng(S)
        x = stats.t.rvs(3, size=S, random_state=rng)  # proposal t3, target N(0, 1): bounded weights
        out.append((f"t3 proposal, normal target (light), S={S}", None,
                    stats.norm.logpdf(x) - stats.t.logpdf(x, 3)))
        x = rng.standard_normal(S)  # proposal N(0, 1), target t3: k -> 1
        out.append((f"normal proposal, t3 target (heavy), S={S}", 1.0, stats.t.logpdf(x, 3) - stats.norm.logpdf(x)))
        x = rng.standard_normal(S)  # proposal N(0, 1), target N(0, 1.5^2): k = 1 - 1/1.5^2
        out.append((f"normal proposal, normal target sd 1.5, S={S}", 1 - 1 / 1.5**2,
                    stats.norm.logpdf(x, scale=1.5) - stats.norm.logpdf(x)))
        for k in (0.1, 0.5, 0.7, 1.2):
            out.append((f"Pareto k={k}, S={S}", k, k * rng.standard_exponential(S)))
    return out


def _tail_length(S):
    """The tail length of ``psis``: ceil(min(S/5, 3 sqrt S))."""
    return int(math.ceil(min(0.2 * S, 3.0 * math.sqrt(S))))


def _arviz_tail_length(S, r_eff):
    """arviz-stats' ``_get_ps_tails``: floor(3 sqrt(S/r_eff)) when S r_eff > 225, else floor(S/5)."""
    return int(math.floor(3 * math.sqrt(S / r_eff))) if S * r_eff > 225 else int(math.floor(S / 5))


def check_psis():
    psis, where = _find("psis", PSIS_MODULES)
    from arviz_stats.base import array_stats

    try:
        from blackjax.diagnostics import psis_weights
    except ImportError:
        psis_weights = None
    rows = []
    for name, k_true, lw in _psis_inputs():
        S = lw.size
        ours, k = psis(lw)
        az, k_az = array_stats.psislw(-lw, r_eff=1.0)  # psislw takes log-likelihoods: log weights = -input
        # r_eff that makes arviz's floor(3 sqrt(S/r_eff)) our ceil(3 sqrt S): the same tail.
        M = _tail_length(S)
        r_same = 9.0 * S / M**2 * (1 - 1e-12) if S > 225 else 1.0
        same_tail = _arviz_tail_length(S, r_same) == M
        az_m, k_az_m = array_stats.psislw(-lw, r_eff=r_same)
        row = {"case": name, "S": S, "k_asymptotic": k_true, "k_ours": k, "k_arviz": float(k_az),
               "tail_ours": M, "tail_arviz": _arviz_tail_length(S, 1.0),
               "k_diff_arviz": abs(k - float(k_az)), "lw_diff_arviz": float(np.max(np.abs(ours - az))),
               "same_tail_possible": same_tail,
               "k_diff_arviz_same_tail": abs(k - float(k_az_m)) if same_tail else None,
               "lw_diff_arviz_same_tail": float(np.max(np.abs(ours - az_m))) if same_tail else None,
               "t_ours_s": _per_call(lambda lw=lw: psis(lw)),
               "t_arviz_s": _per_call(lambda lw=lw: array_stats.psislw(-lw, r_eff=1.0))}
        if psis_weights is not None:
            jl = jnp.asarray(lw)
            bj, k_bj = psis_weights(jl)
            row.update({"k_blackjax": float(k_bj), "k_diff_blackjax": abs(k - float(k_bj)),
                        "lw_diff_blackjax": float(np.max(np.abs(ours - np.asarray(bj)))),
                        "t_blackjax_s": _per_call(lambda jl=jl: jax.block_until_ready(psis_weights(jl)))})
        rows.append(row)

    def worst(key):
        values = [r[key] for r in rows if r.get(key) is not None]
        return max(values) if values else None

    summary = {key: worst(key) for key in ("k_diff_arviz", "lw_diff_arviz", "k_diff_arviz_same_tail",
                                           "lw_diff_arviz_same_tail", "k_diff_blackjax", "lw_diff_blackjax")}
    summary["k_range_ours"] = [min(r["k_ours"] for r in rows), max(r["k_ours"] for r in rows)]
    for key in ("t_ours_s", "t_arviz_s", "t_blackjax_s"):
        summary[key + "_by_S"] = {S: float(np.median([r[key] for r in rows if r["S"] == S and key in r]))
                                  for S in (200, 1000, 5000) if any(key in r for r in rows)}

    # What each does with the inputs ``psis`` is written for.
    base = -0.5 * np.random.default_rng(7).standard_normal(1000) ** 2
    edge = {"failed runs (-inf entries)": np.r_[base, [-np.inf] * 5], "equal weights (S=1000)": np.zeros(1000),
            "20 weights": np.arange(20.0)}
    conventions = {}
    for label, lw in edge.items():
        finite = lw[np.isfinite(lw)]
        conventions[label] = {
            "ours": _outcome(lambda lw=lw: psis(lw)),
            "arviz psislw(-lw)": _outcome(lambda lw=lw: array_stats.psislw(-lw, r_eff=1.0)),
            "arviz psislw(-lw[finite])": _outcome(lambda finite=finite: array_stats.psislw(-finite, r_eff=1.0)),
        }
        if psis_weights is not None:
            conventions[label]["blackjax psis_weights(lw)"] = _outcome(lambda lw=lw: psis_weights(jnp.asarray(lw)))
    return {"module": where, "rows": rows, "summary": summary, "edge_cases": conventions}


# ---------------------------------------------------------------------------------------------
# 2. R-hat and ESS


def _chains(kind, n, rng, chains=4):
    if kind == "iid":
        return rng.standard_normal((chains, n))
    if kind.startswith("ar1"):
        phi = float(kind.split("=")[1])
        x = np.empty((chains, n))
        x[:, 0] = rng.standard_normal(chains)
        e = rng.standard_normal((chains, n)) * math.sqrt(1 - phi**2)
        for t in range(1, n):
            x[:, t] = phi * x[:, t - 1] + e[:, t]
        return x
    if kind == "one chain shifted by 1 sd":
        return rng.standard_normal((chains, n)) + np.r_[np.zeros(chains - 1), 1.0][:, None]
    raise ValueError(kind)


class _x64:
    """JAX's 64-bit mode set inside the block and restored after it."""

    def __init__(self, enabled):
        self.enabled = enabled

    def __enter__(self):
        self.old = bool(jax.config.jax_enable_x64)
        jax.config.update("jax_enable_x64", self.enabled)

    def __exit__(self, *exc):
        jax.config.update("jax_enable_x64", self.old)


def _geyer_stops_inside(array_stats, x):
    """Whether the bulk ESS's autocorrelation pair sums turn non-positive before lag n - 3 of the
    split, rank-normalised chains (where the reference's loop stops); when they do not, blackjax
    and the reference truncate Geyer's sequence differently."""
    z = array_stats._z_scale(array_stats._split_chains(x))
    m, n = z.shape
    acov = array_stats.autocov(z, axis=1)
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n + np.var(z.mean(axis=1), ddof=1)
    rho = 1.0 - (mean_var - acov.mean(axis=0)) / var_plus
    rho[0] = 1.0
    pairs = rho[0 : n - 3 : 2][: (n - 3) // 2] + rho[1 : n - 2 : 2][: (n - 3) // 2]
    return bool(np.any(pairs <= 0))


def check_diagnostics():
    import blackjax
    from arviz_stats.base import array_stats

    where = "blackjax.diagnostics (what calibration.inference.mcmc._summary called before it took arviz-stats')"

    def arviz(x):
        return (float(array_stats.rhat(x, method="rank")), float(array_stats.ess(x, method="bulk")),
                float(array_stats.ess(x, method="tail", prob=(0.05, 0.95))))

    def ours(x):
        diag, x = blackjax.diagnostics, jnp.asarray(x)
        with jax.numpy_dtype_promotion("standard"):  # blackjax's estimators mix int and float
            return float(diag.rhat(x)), float(diag.ess_bulk(x)), float(diag.ess_tail(x))

    rows = []
    rng = np.random.default_rng(2021)
    for n in (200, 201, 1000):
        for kind in ("iid", "ar1 phi=0.5", "ar1 phi=0.95", "one chain shifted by 1 sd"):
            x = _chains(kind, n, rng)
            ref = arviz(x)
            row = {"case": kind, "chains": 4, "draws": n, "arviz": dict(zip(("rhat", "ess_bulk", "ess_tail"), ref))}
            for label, x64 in (("ours_float32", False), ("ours_float64", True)):
                with _x64(x64):
                    got = ours(x)
                    row[label] = dict(zip(("rhat", "ess_bulk", "ess_tail"), got))
                    row[label + "_rel_diff"] = {k: (g - r) / r for k, g, r in zip(("rhat", "ess_bulk", "ess_tail"),
                                                                                  got, ref)}
                    if n == 1000:
                        row["t_" + label + "_s_per_key"] = _per_call(lambda x=x: ours(x), min_time=0.5)
            if n == 1000:
                row["t_arviz_s_per_key"] = _per_call(lambda x=x: arviz(x))
            row["geyer_pairs_turn_negative_before_lag_n-3"] = _geyer_stops_inside(array_stats, x)
            if n % 2:  # blackjax drops the last draw of an odd chain, the reference the middle one
                middle = np.delete(x, n // 2, axis=1)
                with _x64(True):
                    got = ours(middle)
                row["ours_float64_middle_draw_removed_rel_diff"] = {
                    k: (g - r) / r for k, g, r in zip(("rhat", "ess_bulk", "ess_tail"), got, ref)}
            rows.append(row)

    def worst(label, key, pred=lambda r: True):
        return max(abs(r[label + "_rel_diff"][key]) for r in rows if pred(r))

    summary = {f"{label}_max_rel_diff": {key: worst(label, key) for key in ("rhat", "ess_bulk", "ess_tail")}
               for label in ("ours_float32", "ours_float64")}
    summary["ours_float64_max_rel_diff_iid_and_phi0.5"] = {
        key: worst("ours_float64", key, lambda r: r["case"] in ("iid", "ar1 phi=0.5"))
        for key in ("rhat", "ess_bulk", "ess_tail")}
    even_inside = [r for r in rows if r["draws"] % 2 == 0 and r["geyer_pairs_turn_negative_before_lag_n-3"]]
    even_outside = [r for r in rows if r["draws"] % 2 == 0 and not r["geyer_pairs_turn_negative_before_lag_n-3"]]
    summary["ours_float64_max_rel_diff_even_n_geyer_stops_inside"] = {
        key: max((abs(r["ours_float64_rel_diff"][key]) for r in even_inside), default=None)
        for key in ("rhat", "ess_bulk", "ess_tail")}
    summary["ours_float64_max_rel_diff_even_n_geyer_runs_to_the_end"] = {
        key: max((abs(r["ours_float64_rel_diff"][key]) for r in even_outside), default=None)
        for key in ("rhat", "ess_bulk", "ess_tail")}
    odd = [r for r in rows if r["draws"] % 2]
    summary["ours_float64_max_rel_diff_odd_n_middle_draw_removed"] = {
        key: max(abs(r["ours_float64_middle_draw_removed_rel_diff"][key]) for r in odd)
        for key in ("rhat", "ess_bulk", "ess_tail")}
    timed = [r for r in rows if "t_arviz_s_per_key" in r]
    summary["t_s_per_key_median_4x1000"] = {
        label: float(np.median([r["t_" + label + "_s_per_key"] for r in timed]))
        for label in ("ours_float32", "ours_float64", "arviz")}
    return {"module": where, "rows": rows, "summary": summary}


# ---------------------------------------------------------------------------------------------
# 3. Levenberg–Marquardt

OSBORNE1_Y = np.array([0.844, 0.908, 0.932, 0.936, 0.925, 0.908, 0.881, 0.850, 0.818, 0.784, 0.751, 0.718, 0.685,
                       0.658, 0.628, 0.603, 0.580, 0.558, 0.538, 0.522, 0.506, 0.490, 0.478, 0.467, 0.457, 0.448,
                       0.438, 0.431, 0.424, 0.420, 0.414, 0.411, 0.406])


def _problems():
    """name -> (residuals of θ, θ of z, z of θ, start θ, noisy). Residuals are in units of the
    noise where there is noise (so that ``stat_tol``'s noise level means what it says)."""
    ident = (lambda z: z, lambda th: np.asarray(th, float))
    rng = np.random.default_rng(11)
    t = np.linspace(0.0, 4.0, 40)
    y_exp = 2.5 * np.exp(-1.3 * t) + 0.05 * rng.standard_normal(t.size)
    lo, hi = np.array([0.1, 0.01]), np.array([10.0, 5.0])
    t2 = np.linspace(0.0, 8.0, 60)
    y_two = 1.0 * np.exp(-0.6 * t2) + 0.8 * np.exp(-1.2 * t2) + 0.2 + 0.01 * rng.standard_normal(t2.size)
    t_osb = 10.0 * np.arange(33)

    def exp_decay(th):
        return (th[0] * jnp.exp(-th[1] * t) - y_exp) / 0.05

    return {
        "rosenbrock (2 residuals, zero residual)": (
            lambda th: jnp.stack([10.0 * (th[1] - th[0] ** 2), 1.0 - th[0]]), *ident, [-1.2, 1.0], False),
        "exponential decay a exp(-b t), 40 points, sigma 0.05": (exp_decay, *ident, [1.0, 0.3], True),
        "exponential decay, bounded through z (a in (0.1, 10), b in (0.01, 5))": (
            exp_decay, lambda z: lo + (hi - lo) * jax.nn.sigmoid(z),
            lambda th: np.log((np.asarray(th) - lo) / (hi - np.asarray(th))), [1.0, 0.3], True),
        "Osborne 1 (5 parameters, 33 residuals, flat valley; MGH 17)": (
            lambda th: th[0] + th[1] * jnp.exp(-t_osb * th[3]) + th[2] * jnp.exp(-t_osb * th[4]) - OSBORNE1_Y,
            *ident, [0.5, 1.5, -1.0, 0.01, 0.02], False),
        "two exponentials + offset (5 parameters, 60 points, sigma 0.01, flat valley)": (
            lambda th: (th[0] * jnp.exp(-th[1] * t2) + th[2] * jnp.exp(-th[3] * t2) + th[4] - y_two) / 0.01,
            *ident, [0.5, 0.3, 0.5, 2.0, 0.0], True),
    }


class _History:
    """The in-memory stand-in for ``calibration.history.History`` that ``run`` records into."""

    def __init__(self, starts=1):
        self.iterations = 0
        self.rows = [[] for _ in range(starts)]

    def record(self, rows, z, evaluation, state):
        for j, i in enumerate(rows):
            self.rows[i].append({"z": np.array(z[j]), "loss": float(evaluation.loss[j]),
                                 "status": int(evaluation.status[j]), "accepted": bool(state.accepted[i])})
        self.iterations += 1

    def length(self, i=0):
        return len(self.rows[i])


def _model(resid, theta_of):
    """``one(z) -> (r, J_z)`` compiled once, and the θ of z: the stand-in for a model run."""
    r_of_z = lambda z: resid(theta_of(z))  # noqa: E731
    one = jax.jit(lambda z: (r_of_z(z), jax.jacfwd(r_of_z)(z)))
    return one, jax.jit(theta_of)


def _ours(Evaluation, run, optimiser, one, theta_of, z0, *, fail_at=(), steps=300):
    """The package's LM on one start; ``fail_at``: evaluation numbers (from 0) whose run fails."""
    count = [0]
    clock = [0.0]

    def evaluate(Z):
        t = time.perf_counter()
        r, J, status = [], [], []
        for z in Z:
            ri, Ji = (np.asarray(a, float) for a in one(jnp.asarray(z)))
            bad = count[0] in fail_at
            status.append(1 if bad else 0)
            r.append(np.full_like(ri, np.nan) if bad else ri)
            J.append(np.zeros_like(Ji) if bad else Ji)
            count[0] += 1
        r, J, status = np.stack(r), np.stack(J), np.array(status)
        with np.errstate(invalid="ignore"):
            loss = np.sum(r * r, axis=1)
            g = 2 * np.einsum("kmn,km->kn", J, r)
        theta = np.stack([np.asarray(theta_of(jnp.asarray(z))) for z in Z])
        clock[0] += time.perf_counter() - t
        return Evaluation(theta=theta, loss=loss, status=status, grad=g, residuals=r, jacobian=J, jacobian_z=J,
                          grad_z=g, prediction={"status": status})

    history = _History()
    start = time.perf_counter()
    state = run(optimiser, optimiser.init(np.asarray(z0, float)[None]), evaluate, history, steps=steps)
    wall = time.perf_counter() - start
    return {"evaluations": count[0], "z": np.asarray(state.z[0]), "loss": float(state.current.loss[0]),
            "message": str(state.message[0]), "history": history.rows[0],
            "overhead_s_per_iteration": (wall - clock[0]) / max(count[0], 1)}


def _surrogate(y, args):
    """The residuals optimistix sees in one step: exact value and Jacobian at ``args[2]``, the
    point the model was run at (``state.y_eval``, the only point ``step`` evaluates)."""
    r0, J0, y0 = args
    return r0 + J0 @ (y - y0), None


class _Driver:
    """optimistix's LevenbergMarquardt driven step by step with the model run outside JAX."""

    def __init__(self, solver, m, n):
        import equinox as eqx

        self.solver, self.m, self.n, self.eqx = solver, m, n, eqx
        tags = frozenset()
        self.f_struct = jax.ShapeDtypeStruct((m,), jnp.float64)
        self.step = eqx.filter_jit(lambda y, args, state: solver.step(_surrogate, y, args, {}, state, tags))
        self.terminate = eqx.filter_jit(lambda y, args, state: solver.terminate(_surrogate, y, args, {}, state, tags))
        self.tags = tags

    def blank(self, z0):
        args = (jnp.zeros(self.m), jnp.zeros((self.m, self.n)), jnp.asarray(z0, float))
        return jnp.asarray(z0, float), args, self.solver.init(_surrogate, jnp.asarray(z0, float), args, {},
                                                                self.f_struct, None, self.tags)

    def save(self, y, args, state):
        buf = io.BytesIO()
        self.eqx.tree_serialise_leaves(buf, (y, args, state))
        return buf.getvalue()

    def load(self, blob, z0):
        return self.eqx.tree_deserialise_leaves(io.BytesIO(blob), self.blank(z0))

    def solve(self, one, z0, *, max_steps=300, fail_at=(), stat_tol=None, max_rejections=None, save_at=None,
              resume=None):
        """Returns a dict: evaluations, y, loss, stopped (why), and the saved blob when asked."""
        y, args, state = self.blank(z0) if resume is None else self.load(resume[0], z0)
        count = 0 if resume is None else resume[1]
        out, why = {}, "max_steps"
        step_times = []
        for i in range(count, max_steps):
            if i > 0:
                if bool(self.terminate(y, args, state)[0]):
                    why = "optimistix terminate (Cauchy: small change in y and in the residuals)"
                    break
                if max_rejections is not None and int(state.num_steps_since_acceptance) >= max_rejections:
                    why = f"{max_rejections} rejected steps in a row"
                    break
                if stat_tol is not None:  # our statistical rule, from the state: the next step's promise
                    r = np.asarray(state.f_info.residual)
                    J = np.asarray(state.f_info.jac.as_matrix())
                    delta = np.asarray(state.y_eval) - np.asarray(y)
                    promised = np.sum(r * r) - np.sum((r + J @ delta) ** 2)
                    if promised <= stat_tol * self.n * np.sum(r * r) / max(self.m - self.n, 1):
                        why = "promised decrease below stat_tol * n * sigma^2"
                        break
            z = state.y_eval
            r, J = one(z)
            if i in fail_at:  # the run failed: no residuals
                r, J = jnp.full_like(r, jnp.nan), jnp.zeros_like(J)
            args = (r, J, z)
            count += 1
            t = time.perf_counter()
            y, state, _ = self.step(y, args, state)
            jax.block_until_ready(y)
            step_times.append(time.perf_counter() - t)
            if save_at is not None and count == save_at:
                out["saved"] = (self.save(y, args, state), count)
        r_final = np.asarray(state.f_info.residual)
        out.update({"evaluations": count, "y": np.asarray(y), "loss": float(np.sum(r_final**2)), "stopped": why,
                    "accepted_steps": int(state.num_accepted_steps),
                    "step_s_median": float(np.median(step_times)) if step_times else None, "state": state})
        return out


def _residual_fn(resid, theta_of):
    """optimistix's ``fn(y, args)``: the residuals at z = y."""
    return lambda y, args: resid(theta_of(y))


def check_lm():
    import optimistix as optx
    from scipy.optimize import least_squares as scipy_lsq

    levenberg_marquardt, where_lm = _find("levenberg_marquardt", LM_MODULES)
    LMOptions, _ = _find("LMOptions", LM_MODULES)
    run, where_loop = _find("run", LOOP_MODULES)
    Evaluation, _ = _find("Evaluation", LOOP_MODULES)

    settings = {"tight (rtol 1e-6, atol 1e-8)": (1e-6, 1e-8), "loose (rtol 1e-3, atol 1e-6)": (1e-3, 1e-6)}
    rows = []
    drivers = {}
    for name, (resid, theta_of, z_of, theta0, noisy) in _problems().items():
        one, theta_jit = _model(resid, theta_of)
        z0 = z_of(theta0)
        m, n = int(one(jnp.asarray(z0))[0].size), len(z0)
        ref = scipy_lsq(lambda z, one=one: np.asarray(one(jnp.asarray(z))[0]), z0,
                        jac=lambda z, one=one: np.asarray(one(jnp.asarray(z))[1]), method="lm", xtol=1e-15,
                        ftol=1e-15, gtol=1e-15, max_nfev=20000)
        th_ref = np.asarray(theta_jit(jnp.asarray(ref.x)))
        loss_ref = float(np.sum(ref.fun**2))
        se, sigma2 = None, None
        if noisy or m > n:  # sigma^2 = 1 (residuals in units of the noise) or the residuals' own estimate
            sigma2 = 1.0 if noisy else loss_ref / (m - n)
            Jt = np.asarray(jax.jacfwd(resid)(jnp.asarray(th_ref)))
            se = np.sqrt(sigma2 * np.diag(np.linalg.inv(Jt.T @ Jt)))

        def judge(z, loss, theta_jit=theta_jit, th_ref=th_ref, loss_ref=loss_ref, se=se, sigma2=sigma2):
            th = np.asarray(theta_jit(jnp.asarray(z)))
            d = {"loss": loss, "loss_minus_reference_rel": (loss - loss_ref) / max(loss_ref, 1e-300),
                 "max_abs_theta_diff": float(np.max(np.abs(th - th_ref)))}
            if se is not None:
                d["max_theta_diff_in_standard_errors"] = float(np.max(np.abs(th - th_ref) / se))
                d["loss_excess_in_sigma2"] = (loss - loss_ref) / sigma2
            return d

        row = {"problem": name, "m": m, "n": n, "reference": {"theta": th_ref.tolist(), "loss": loss_ref,
                                                                "scipy_lm_nfev": int(ref.nfev),
                                                                "sigma2": sigma2, "noise": "known" if noisy else
                                                                ("estimated: loss / (m - n)" if sigma2 else None)}}
        for label, options in (("ours (defaults: xtol 1e-6, ftol 1e-7, stat_tol 0.1, max_rejections 6)", LMOptions()),
                               ("ours with stat_tol 0", LMOptions(stat_tol=0.0))):
            got = _ours(Evaluation, run, levenberg_marquardt(options), one, theta_jit, z0)
            row[label] = {"evaluations": got["evaluations"], **judge(got["z"], got["loss"]), "message": got["message"],
                          "optimiser_overhead_s_per_iteration": got["overhead_s_per_iteration"]}
        for label, (rtol, atol) in settings.items():
            solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
            fn = _residual_fn(resid, theta_of)

            @jax.jit
            def solve(y0, fn=fn, solver=solver):
                sol = optx.least_squares(fn, solver, y0, max_steps=300, throw=False)
                return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful

            value, steps, ok = solve(jnp.asarray(z0))
            wall = _per_call(lambda solve=solve, z0=z0: jax.block_until_ready(solve(jnp.asarray(z0))[0]))
            entry = {"evaluations": int(steps), **judge(value, float(np.sum(np.asarray(fn(value, None)) ** 2))),
                     "successful": bool(ok), "whole_solve_in_jax_s": wall}
            driver = drivers.setdefault((rtol, atol, m, n), _Driver(solver, m, n))
            ext = driver.solve(one, z0)
            entry["external_driver"] = {
                "evaluations": ext["evaluations"],
                "max_abs_y_diff_to_least_squares": float(np.max(np.abs(ext["y"] - np.asarray(value)))),
                "step_overhead_s_median": ext["step_s_median"]}
            stat = driver.solve(one, z0, stat_tol=0.1, max_rejections=6)
            entry["external_driver_with_our_stat_tol_and_max_rejections"] = {
                "evaluations": stat["evaluations"], **judge(stat["y"], stat["loss"]), "stopped": stat["stopped"]}
            row["optimistix " + label] = entry
        rows.append(row)

    features = _lm_features(Evaluation, run, levenberg_marquardt, LMOptions, optx)
    return {"modules": [where_lm, where_loop], "rows": rows, "features": features}


def _lm_features(Evaluation, run, levenberg_marquardt, LMOptions, optx):
    """Concrete tests, on the exponential decay, of what the fit needs."""
    name = "exponential decay a exp(-b t), 40 points, sigma 0.05"
    resid, theta_of, z_of, theta0, _ = _problems()[name]
    one, theta_jit = _model(resid, theta_of)
    z0 = z_of(theta0)
    m, n = int(one(jnp.asarray(z0))[0].size), len(z0)
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)
    driver = _Driver(solver, m, n)
    out = {"problem": name}

    # An external evaluation per step: the model outside JAX, one (r, J) per step.
    plain = driver.solve(one, z0)
    sol = optx.least_squares(lambda y, a: resid(theta_of(y)), solver, jnp.asarray(z0), max_steps=300, throw=False)
    out["external_evaluation_per_step"] = {
        "how": "solver.init/step/terminate with fn = r0 + J0 (y - y0), (r0, J0) the model's run at state.y_eval "
               "passed as args (step evaluates fn only there); jitted once",
        "evaluations_driver": plain["evaluations"], "evaluations_least_squares": int(sol.stats["num_steps"]),
        "max_abs_y_diff": float(np.max(np.abs(plain["y"] - np.asarray(sol.value))))}

    # The same inside optx.least_squares: the model behind jax.pure_callback with a custom_jvp.
    calls = [0]

    def model_np(z):
        calls[0] += 1
        r, J = one(jnp.asarray(z))
        return np.asarray(r), np.asarray(J)

    shapes = (jax.ShapeDtypeStruct((m,), jnp.float64), jax.ShapeDtypeStruct((m, n), jnp.float64))

    @jax.custom_jvp
    def external(z):
        return jax.pure_callback(model_np, shapes, z)[0]

    @external.defjvp
    def _external_jvp(primals, tangents):
        r, J = jax.pure_callback(model_np, shapes, primals[0])
        return r, J @ tangents[0]

    sol_cb = optx.least_squares(lambda y, a: external(y), solver, jnp.asarray(z0), max_steps=300, throw=False)
    out["pure_callback_inside_least_squares"] = {
        "steps": int(sol_cb.stats["num_steps"]), "model_calls": calls[0],
        "max_abs_y_diff": float(np.max(np.abs(np.asarray(sol_cb.value) - np.asarray(sol.value))))}

    # A failed run (status bits) at the 4th evaluation: NaN residuals.
    failed = driver.solve(one, z0, fail_at=(3,))
    ours_failed = _ours(Evaluation, run, levenberg_marquardt(LMOptions()), one, theta_jit, z0, fail_at=(3,))
    out["failed_run_rejected"] = {
        "optimistix": {"evaluations": failed["evaluations"], "accepted_steps": failed["accepted_steps"],
                       "final_y_diff_to_no_failure": float(np.max(np.abs(failed["y"] - plain["y"]))),
                       "note": "NaN residuals make the trust-region test false: the step is rejected and the "
                               "step size falls by 4, as for any bad step"},
        "ours": {"evaluations": ours_failed["evaluations"],
                 "4th_evaluation_accepted": ours_failed["history"][3]["accepted"],
                 "4th_evaluation_status": ours_failed["history"][3]["status"]}}

    # A failed run at the start.
    bad_start = driver.solve(one, z0, fail_at=(0,), max_steps=40)
    ours_bad = _ours(Evaluation, run, levenberg_marquardt(LMOptions()), one, theta_jit, z0, fail_at=(0,))
    out["failed_start"] = {
        "optimistix": {"evaluations": bad_start["evaluations"], "final_y": bad_start["y"].tolist(),
                       "stopped": bad_start["stopped"], "accepted_steps": bad_start["accepted_steps"]},
        "ours": {"evaluations": ours_bad["evaluations"], "message": ours_bad["message"]}}

    # Save after every step and resume exactly: the state is a pytree of arrays.
    saved = driver.solve(one, z0, save_at=5)
    resumed = driver.solve(one, z0, resume=saved["saved"])
    out["save_and_resume"] = {
        "how": "equinox.tree_serialise_leaves((y, args, state)) after a step; tree_deserialise_leaves into a "
               "fresh solver.init as the template",
        "bytes_per_save": len(saved["saved"][0]),
        "resumed_equals_uninterrupted_bitwise": bool(np.array_equal(resumed["y"], saved["y"]))
        and resumed["evaluations"] == saved["evaluations"]}

    # A batch of starts: vmap of least_squares stops each start but runs every lane to the last.
    lane_calls = [0]

    def model_batch(z):
        z = np.asarray(z)
        lane_calls[0] += z.shape[0] if z.ndim == 2 else 1
        pairs = [one(jnp.asarray(row)) for row in np.atleast_2d(z)]
        r = np.stack([np.asarray(p[0]) for p in pairs])
        J = np.stack([np.asarray(p[1]) for p in pairs])
        return (r, J) if z.ndim == 2 else (r[0], J[0])

    @jax.custom_jvp
    def external_b(z):
        return jax.pure_callback(model_batch, shapes, z, vmap_method="expand_dims")[0]

    @external_b.defjvp
    def _external_b_jvp(primals, tangents):
        r, J = jax.pure_callback(model_batch, shapes, primals[0], vmap_method="expand_dims")
        return r, J @ tangents[0]

    starts = jnp.asarray(np.stack([z_of(th) for th in ([1.0, 0.3], [2.5, 1.3], [8.0, 0.05])]))
    per_start = [int(optx.least_squares(lambda y, a: external_b(y), solver, s, max_steps=300, throw=False)
                     .stats["num_steps"]) for s in starts]
    lane_calls[0] = 0
    steps_b = jax.vmap(lambda s: optx.least_squares(lambda y, a: external_b(y), solver, s, max_steps=300,
                                                    throw=False).stats["num_steps"])(starts)
    ours_batch = _ours_batch(Evaluation, run, levenberg_marquardt(LMOptions()), one, theta_jit, np.asarray(starts))
    out["batch_of_starts"] = {
        "optimistix_vmap": {"steps_per_start": np.asarray(steps_b).tolist(), "model_runs": lane_calls[0],
                            "steps_per_start_alone": per_start},
        "ours_loop_run": ours_batch}

    out["what_optimistix_offers"] = {
        "residuals and Jacobian from one forward-mode trace outside JAX": (
            "not as an API: least_squares builds J itself with jax.linearize (jac='fwd') or jax.jacrev of a traceable "
            "fn; an external (r, J) goes in only through the step-by-step driver's linear surrogate or a "
            "custom_jvp + pure_callback (both measured above: one model call per step)"),
        "reject a step when the run fails": (
            "yes if the failure is reported as NaN/inf residuals (the trust-region test is false); status bits must "
            "be mapped to NaN by the caller; a failed run at the start is accepted (first step is always accepted)"),
        "batch of starts with per-start stopping": (
            "vmap stops each start's iterate but the batched while_loop evaluates every lane until the last start "
            "stops; evaluating only the active starts needs the caller's own loop over per-start states"),
        "save every iteration and resume exactly": (
            "possible only through the step-by-step API (least_squares takes no initial state): serialise "
            "(y, args, state) with equinox and deserialise into a fresh init"),
        "statistical stopping rule (promised decrease below stat_tol n sigma^2)": (
            "no; the caller can compute it from state.f_info and state.y_eval (done above). Its own test is "
            "Cauchy (small change in y and in the residual vector, on accepted steps), plus max_steps"),
        "max rejections in a row": "no; state.num_steps_since_acceptance lets the caller stop",
        "counting evaluations": "yes: stats['num_steps'] (one evaluation per step, the start included)",
        "Marquardt scaling diag(J^T J) and a step cap per z (MAX_STEP)": (
            "no: DampedNewtonDescent damps with lambda I (lambda = 1/step size, starting at 1) and has no cap"),
        "messages converged/stopped for the verdict": "no: RESULTS.successful or max_steps_reached",
    }
    return out


def _ours_batch(Evaluation, run, optimiser, one, theta_jit, Z0):
    """The package's LM on several starts in one ``run``: model runs only for the active starts."""
    runs = [0]

    def evaluate(Z):
        r, J = [], []
        for z in Z:
            ri, Ji = (np.asarray(a, float) for a in one(jnp.asarray(z)))
            r.append(ri)
            J.append(Ji)
            runs[0] += 1
        r, J = np.stack(r), np.stack(J)
        g = 2 * np.einsum("kmn,km->kn", J, r)
        status = np.zeros(len(Z), int)
        return Evaluation(theta=np.stack([np.asarray(theta_jit(jnp.asarray(z))) for z in Z]),
                          loss=np.sum(r * r, axis=1), status=status, grad=g, residuals=r, jacobian=J,
                          jacobian_z=J, grad_z=g, prediction={"status": status})

    history = _History(len(Z0))
    run(optimiser, optimiser.init(np.asarray(Z0, float)), evaluate, history, steps=300)
    return {"evaluations_per_start": [history.length(i) for i in range(len(Z0))], "model_runs": runs[0]}


# ---------------------------------------------------------------------------------------------


def main():
    versions = {"python": platform.python_version()}
    for dist in ("numpy", "scipy", "jax", "jaxlib", "blackjax", "arviz-stats", "optimistix", "equinox", "lineax"):
        versions[dist] = _version(dist)
    out = {"versions": versions}
    for key, check in (("psis", check_psis), ("diagnostics", check_diagnostics), ("lm", check_lm)):
        start = time.perf_counter()
        try:
            out[key] = check()
        except Exception as err:  # noqa: BLE001 - one part failing leaves the others
            out[key] = {"error": f"{type(err).__name__}: {err}"}
        out[key]["check_wall_s"] = time.perf_counter() - start
    json.dump(_clean(out), sys.stdout, indent=1, default=str)
    print()


if __name__ == "__main__":
    main()
