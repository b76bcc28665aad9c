"""The calibration objective: a scene, the parameters to fit, and the data the run must match.

An ``Objective`` turns physical parameter values θ (ordered as ``keys``) into weighted residuals
of the deposit profile(s) and the front history, one rollout per evaluation (docs/fitting.md,
"The residuals"). What is observed (``objective.observations``) is kept apart from what was
measured (``objective.data``), so objectives that observe the same run the same way share one
compilation.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm import PARAM_KEYS, validate_params

from .bounds import Bounds
from .layout import _checked_weights, residual_layout
from .observe import Observations, unwhiten_front
from .protocol import as_theta
from .residuals import Problem, column_pass, run_pass
from .targets import FrontTarget, _targets

__all__ = ["Objective"]


def _digest(*arrays) -> str:
    """A short content hash of float arrays (as float64, so the dtype of the input does not matter)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a, np.float64))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _engine_bounds(bounds: Bounds, params) -> tuple[Bounds, tuple[str, ...]]:
    """``bounds`` narrowed so that every θ inside them keeps the engine's rule μ1 ≤ μ2 with the
    scene's value of the one not fitted (μ1's upper bound at most μ2; μ2's lower at least μ1),
    and a note for each bound that moved. With both fitted the rule is checked per point
    (``Objective.check_thetas``)."""
    lower, upper, notes = list(bounds.lower), list(bounds.upper), []
    keys = bounds.keys
    # (fitted key, the scene's key it is held against, the bound of the fitted key that moves)
    for key, other, side in (("mu1", "mu2", "upper"), ("mu2", "mu1", "lower")):
        if key not in keys or other in keys:
            continue
        i, value = keys.index(key), float(getattr(params, other))
        limits = upper if side == "upper" else lower
        if (limits[i] > value) if side == "upper" else (limits[i] < value):
            verb = "lowered" if side == "upper" else "raised"
            notes.append(f"{key}'s {side} bound {limits[i]:g} {verb} to the scene's {other} = {value:g} (the engine "
                         "needs mu1 <= mu2)")
            limits[i] = value
    for k, lo, hi in zip(keys, lower, upper):
        if not lo < hi:
            raise ValueError(f"bounds[{k!r}]: ({lo:g}, {hi:g}) is empty once mu1 <= mu2 is imposed with the "
                             "scene's other friction coefficient; widen the bound or change the scene's value")
    return Bounds(keys, tuple(lower), tuple(upper)), tuple(notes)


class Objective:
    """Residuals of one scene against a profile and/or a front history (a
    ``calibration.problem.protocol.ObjectiveLike``).

    Parameters
    ----------
    scene: a ``jaxmpm.scenes.Scene`` (its params are the fixed values of the unfitted keys).
    keys: the parameters to fit, in order (any of ``jaxmpm.PARAM_KEYS`` that has bounds).
    profile: a ``ProfileTarget`` (or the loader's ``Profile``), or a list of them at several times.
    front: a ``FrontTarget`` (or the loader's ``FrontHistory``).
    weights: ``{"profile": w_h, "front": w_f}`` (default 1 each).
    weighting: "block" (the default) gives each block (a profile, a front history) its weight in
        total, whatever its length (row scale sqrt(w / n)); "row" gives every row the weight (row
        scale sqrt(w)), the efficient fit when every row's relative noise is the same.
    sigma: the width of the profile's smoothing kernel (m; default: the particle spacing).
    front_threshold: the height (m) below which the deposit counts as ended, for the front
        (default: half a particle spacing, below the height of one isolated particle).
    x_ref: where the front is measured from (default: the back wall, x = 0).
    mirror: the x where the profile's kernel is mirrored (``deposit_profile``): "back-wall"
        (the default) takes the scene's ``back_face`` (none for a scene without one); None turns
        the mirror off.
    bounds: overrides of ``calibration.problem.bounds.DEFAULT_BOUNDS`` by key.
    check_data: refuse data that cannot come from ``scene`` (``calibration.problem.targets``'
        plausibility limits), naming the target's ``source``; off only for placeholder targets.
    """

    def __init__(self, scene, keys: Sequence[str], *, profile=None, front=None,
                 weights: Mapping[str, float] | None = None, weighting: str = "block", sigma: float | None = None,
                 front_threshold: float | None = None, x_ref: float = 0.0,
                 bounds: Mapping[str, tuple[float, float]] | None = None, jacobian: str = "ad",
                 fd_step: float = 1e-2, check_data: bool = True, mirror: float | str | None = "back-wall"):
        keys = tuple(keys)
        # What the constructor was given beyond the scene: ``at_dx`` rebuilds from it.
        self._options = dict(profile=profile, front=front, weights=weights, weighting=weighting, sigma=sigma,
                             front_threshold=front_threshold, x_ref=x_ref, bounds=bounds, jacobian=jacobian,
                             fd_step=fd_step, check_data=check_data, mirror=mirror)
        if jacobian not in ("ad", "fd"):
            raise ValueError(f"jacobian must be 'ad' or 'fd', got {jacobian!r}")
        if not (math.isfinite(fd_step) and 0 < fd_step < 0.5):
            raise ValueError(f"fd_step must be in (0, 0.5), got {fd_step!r}")
        self.jacobian, self.fd_step = jacobian, float(fd_step)
        bad = [k for k in keys if k not in PARAM_KEYS]
        if bad:
            raise ValueError(f"keys: unknown parameter(s) {bad}; valid keys are {list(PARAM_KEYS)}")
        if "mu_w" in keys and not scene.config.reads_mu_w:
            raise ValueError("keys: mu_w is read by no boundary of the scene, so it cannot be fitted: declare the "
                             "floor's or the side walls' friction as \"mu_w\" (e.g. jaxmpm.SideWalls(width, \"mu_w\"), "
                             "--side-walls WIDTH,mu_w)")
        self.bounds = Bounds.create(keys, bounds)
        self.keys = keys
        self.profiles, self.front = _targets(profile, front)
        self.weights = _checked_weights(weights, weighting, bool(self.profiles), self.front is not None)
        self.weighting = weighting

        self.scene = scene
        self.bounds, self.bound_notes = _engine_bounds(self.bounds, scene.params)
        config = scene.config
        info = scene.info
        spacing = config.grid.dx / info.ppc
        self.sigma = float(sigma) if sigma is not None else spacing
        self.front_threshold = float(front_threshold) if front_threshold is not None else 0.5 * spacing
        for name, value in (("sigma", self.sigma), ("front_threshold", self.front_threshold)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        self.x_ref = float(x_ref)
        if isinstance(mirror, str):
            if mirror != "back-wall":
                raise ValueError(f"mirror must be 'back-wall', None or a wall's x (m), got {mirror!r}")
            mirror = getattr(scene, "back_face", None)
        elif mirror is not None and not math.isfinite(float(mirror)):
            raise ValueError(f"mirror must be finite, got {mirror!r}")
        self.mirror = None if mirror is None else float(mirror)
        self.length = float(info.length)
        width = info.width if info.dim == 3 else None

        self.dtype = jnp.result_type(scene.params.E)
        self.layout = residual_layout(scene, self.profiles, self.front, weights=self.weights, weighting=weighting,
                                      dtype=self.dtype, check_data=check_data)
        self.blocks, self.row_scale = dict(self.layout.blocks), self.layout.row_scale
        self.n_residuals = self.layout.n_residuals
        front = self.layout.front
        # Uniform points for the front integral: from x_ref to the far edge of the grid.
        upper = config.grid.origin[0] + config.grid.cells[0] * config.grid.dx
        self.observations = Observations(
            profile_x=tuple(p.x for p in self.layout.profiles),
            profile_times=tuple(p.time for p in self.layout.profiles),
            front_times=None if front is None else front.t,
            front_points=np.arange(self.x_ref, upper, 0.5 * spacing), sigma=self.sigma,
            front_threshold=self.front_threshold, x_ref=self.x_ref, mirror=self.mirror, width=width)
        self.data = self.layout.data(self.dtype)
        self.times = self.observations.times  # the run's frame times
        self.problem = Problem(config, scene.state, scene.params, self.observations, self.keys, self.bounds)
        self.functions = self.problem.functions
        self.config = self.functions.config  # the scene's, with the observation times as its frame times

    # ---- pure functions of (theta, state, base params) ------------------------------------
    def params_of(self, theta, base=None):
        """The full ``Params`` with the fitted keys set from θ (physical values)."""
        base = self.problem.base if base is None else base
        theta = jnp.asarray(theta, self.dtype)
        return base.replace(**{k: theta[i] for i, k in enumerate(self.keys)})

    def arguments(self, state=None) -> tuple:
        """``(state, base params, data)``: the arguments after θ (or z, lower, upper) of
        ``functions``' members for this objective (``state``: another initial state)."""
        return (self.problem.state if state is None else state), self.problem.base, self.data

    def lower_upper(self):
        """The bounds as arrays of the run's dtype, the ``lower, upper`` of ``functions.jacobian_z``."""
        return self.problem.lower_upper()

    @property
    def parts(self) -> tuple[tuple[Objective, np.ndarray, Bounds]]:
        """Each single objective this one concatenates, with where its keys sit among this one's
        and the bounds its z is mapped with: here ``((self, every key, self.bounds),)``."""
        return ((self, np.arange(len(self.keys)), self.bounds),)

    @staticmethod
    def join(outs) -> tuple:
        """The parts' outputs (``(r, ...)`` tuples, one per part) as this objective's: its one part's."""
        return outs[0]

    def column_task(self, z, tangent, bounds: Bounds) -> tuple:
        """One forward-mode pass at z (mapped with ``bounds``) along ``tangent``, as a task
        ``(fn, args)`` (``residuals.column_pass``)."""
        lower, upper = (np.asarray(b, self.dtype) for b in (bounds.lower, bounds.upper))
        args = jax.tree.map(np.asarray, self.arguments())
        return column_pass, (*self.problem.static, np.asarray(self.as_theta(z, "z")), tangent, lower, upper, *args)

    def residual_task(self, theta, seed: int | None = None) -> tuple:
        """One run at θ (with the particles drawn with ``seed``, if given) as a task: (r, prediction)."""
        state = None if seed is None else self.scene.resampled(int(seed))
        return run_pass, (*self.problem.static, np.asarray(self.as_theta(theta)),
                          *jax.tree.map(np.asarray, self.arguments(state)))

    @property
    def sampling_seed(self) -> int | None:
        """The seed of the scene's own particle draw; None where its sampling has no seed (a lattice)."""
        return int(self.scene.info.seed) if self.seeded else None

    def batched_jacobian_z(self) -> Callable:
        """``Z (k, n) -> (r, dr/dz, dr/dθ, prediction)`` stacked over the rows of Z: the model
        functions' ``batched_jacobian_z`` at this objective's bounds and data."""
        lower, upper = self.lower_upper()
        args = self.arguments()
        functions = self.functions

        def batched(Z):
            Jz, J, (r, pred) = functions.batched_jacobian_z(Z, lower, upper, *args)
            return r, Jz, J, pred

        return batched

    # ---- the public calls (jitted once per objective; new θ never recompiles) --------------
    def residual_fn(self, theta):
        """Pure, unjitted θ -> (r, prediction): for ``jax.vmap`` and sweeps."""
        return self.functions.residual(theta, *self.arguments())

    def predict(self, theta):
        """The model's observations at θ, no data involved: {"status", "h" (every profile's
        points, concatenated), "front" (at the front's times)}."""
        return self.functions.predictions(self.as_theta(theta), self.problem.state, self.problem.base)

    def residuals(self, theta):
        """(r, prediction) at θ. ``prediction`` holds ``status`` and the modelled ``h``/``front``."""
        return self.functions.residuals(self.as_theta(theta), *self.arguments())

    def residuals_resampled(self, theta, seed: int):
        """(r, prediction) at θ with the scene's particles sampled with ``seed`` instead
        (``Scene.resampled``): the same objective on another draw of the same body."""
        return self.functions.residuals(self.as_theta(theta), *self.arguments(self.scene.resampled(seed)))

    def at_dx(self, dx: float) -> Objective:
        """The same objective (keys, data, weights, bounds, options) on the scene rebuilt at grid
        spacing ``dx`` (``Scene.at_dx``). A smoothing width or front threshold that was not given
        follows the new particle spacing, as a fit at that ``dx`` would have it."""
        return Objective(self.scene.at_dx(dx), self.keys, **self._options)

    @classmethod
    def from_experiment(cls, experiment, keys: Sequence[str] | None = None, *,
                        front_correlation_time: float | None = None, **options) -> Objective:
        """The objective of a ``jaxmpm.Experiment``: its scene, its measurements (``profile=`` and
        ``front=`` replace them), the keys of its [fit] table (or ``keys``) and its blocks' weights
        (``weights=`` over them, block by block: a block given None keeps the file's); the front's
        correlation time is the file's unless ``front_correlation_time`` is given; ``options`` as
        for ``Objective``."""
        from ..data.collapse import read_measurements
        from ..data.measurements import load_measurements

        listed = read_measurements(experiment)
        spec = listed.fit
        if keys is None:
            if spec is None:
                raise ValueError(f"{experiment.path or experiment.name}: no [fit] keys; pass keys")
            keys = spec.keys
        if options.get("profile") is None and options.get("front") is None:
            profiles, front = load_measurements(experiment)
            options.update(profile=profiles or None, front=front)
            if not profiles and front is None:
                raise ValueError(f"{experiment.path or experiment.name}: lists no measurement ([[profile]] or "
                                 "[front])")
        given = dict(options.get("weights") or {})
        filed = {"profile": spec.weight_profile, "front": spec.weight_front} if spec is not None else {}
        if filed or given:
            options["weights"] = {k: given[k] if given.get(k) is not None else filed.get(k, 1.0)
                                  for k in ("profile", "front")}
        front, tau = options.get("front"), front_correlation_time
        if tau is None and listed.front is not None and not isinstance(front, FrontTarget):
            tau = listed.front.correlation_time  # the file's, unless the target carries its own
        if front is not None and tau is not None:
            target = front if isinstance(front, FrontTarget) else FrontTarget.of(front)
            options["front"] = dataclasses.replace(target, correlation_time=tau)
        return cls(experiment.scene(), keys, **options)

    @property
    def dx(self) -> float:
        """The scene's grid spacing, m."""
        return float(self.scene.config.grid.dx)

    @property
    def seeded(self) -> bool:
        """Whether the scene's particles can be drawn again with another seed."""
        return getattr(self.scene, "sampler", None) is not None

    def coarsened(self, ratio: float) -> Objective:
        """The same objective on a grid ``ratio`` times coarser (``at_dx``): the grid term's
        coarse run (``calibration.inference.gridcheck.grid_shift``)."""
        return self.at_dx(ratio * self.dx)

    def residuals_and_jacobian_z(self, z, bounds: Bounds | None = None):
        """(r, dr/dz, dr/dθ, prediction) at the unconstrained z of ``bounds`` (default: the
        objective's), θ = ``bounds.to_physical(z)`` inside the traced run (forward mode): both
        Jacobians from one trace (dr/dθ infinite where z saturates a bound, dθ/dz = 0)."""
        bounds = self.bounds if bounds is None else bounds
        lower, upper = (jnp.asarray(b, self.dtype) for b in (bounds.lower, bounds.upper))
        Jz, J, (r, pred) = self.functions.jacobian_z(self.as_theta(z, "z"), lower, upper, *self.arguments())
        return r, Jz, J, pred

    def residuals_and_jacobian(self, theta, jacobian: str | None = None):
        """(r, J, prediction) at θ, with J = dr/dθ (m × n) from forward-mode autodiff
        (``jacobian="ad"``, the default) or from central differences with relative steps
        ``fd_step`` (``"fd"``: 2n + 1 runs in one vmapped batch), for flows whose exact derivative
        no longer follows the trend over finite steps (docs/fitting.md, "Gradients")."""
        theta = self.as_theta(theta)
        if (jacobian or self.jacobian) == "ad":
            J, (r, pred) = self.functions.jacobian(theta, *self.arguments())
            return r, J, pred
        lower, upper = self.lower_upper()
        steps = self.fd_step * jnp.maximum(jnp.abs(theta), 0.01 * (upper - lower))
        n = len(self.keys)
        eye = jnp.eye(n, dtype=self.dtype) * steps[None, :]
        batch = jnp.concatenate([theta[None, :], theta[None, :] + eye, theta[None, :] - eye])
        rs, preds = self.functions.batched(batch, *self.arguments())
        J = ((rs[1:n + 1] - rs[n + 1:]) / (2.0 * steps[:, None])).T
        pred = jax.tree.map(lambda a: a[0], preds)
        pred["status"] = jnp.bitwise_or.reduce(preds["status"])
        return rs[0], J, pred

    def in_metres(self, r) -> dict[str, np.ndarray]:
        """The weighted residuals ``r`` back in metres (model − data), by block: profile heights
        and front positions."""
        e = np.asarray(r, float) / self.row_scale
        if self.layout.front is not None:  # the front's rows are whitened (FrontTarget.correlation_time): undo it
            e[self.blocks["front"]] = unwhiten_front(e[self.blocks["front"]], self.layout.front.phi)
        metres = e * self.layout.scales()
        return {name: metres[sl] for name, sl in self.blocks.items()}

    def check_jacobian(self, theta) -> dict[str, Any]:
        """Autodiff against central differences (relative step ``fd_step``) at θ: both Jacobians
        and, per key, the relative difference of their columns."""
        _, J_ad, _ = self.residuals_and_jacobian(theta, "ad")
        _, J_fd, _ = self.residuals_and_jacobian(theta, "fd")
        J_ad, J_fd = np.asarray(J_ad, float), np.asarray(J_fd, float)
        diff = np.linalg.norm(J_ad - J_fd, axis=0) / np.maximum(np.linalg.norm(J_fd, axis=0), 1e-300)
        return {"ad": J_ad, "fd": J_fd, "rel_diff": dict(zip(self.keys, diff.tolist()))}

    def value_and_grad(self, theta):
        """((loss, prediction), dloss/dθ) from reverse mode through the checkpointed rollout."""
        return self.functions.value_and_grad(self.as_theta(theta), *self.arguments())

    def loss(self, theta) -> float:
        r, _ = self.residuals(theta)
        return float(jnp.sum(r * r))

    def as_theta(self, theta, name: str = "theta"):
        """``theta`` as an array of the run's dtype, its shape checked against ``keys``."""
        return as_theta(theta, self.keys, self.dtype, name)

    def initial(self) -> dict[str, float]:
        """The scene's values of the fitted keys."""
        return {k: float(getattr(self.problem.base, k)) for k in self.keys}

    def expand(self, values: Mapping[str, float]) -> dict[str, float]:
        """Values by key as values of this objective's keys (``CompositeObjective.expand`` spreads
        a plain key over the experiments; here every key is its own)."""
        stray = [k for k in values if k not in self.keys]
        if stray:
            raise ValueError(f"{stray[0]!r} is not fitted (keys: {list(self.keys)})")
        return {k: float(v) for k, v in values.items()}

    def check_thetas(self, thetas, name: str = "thetas") -> None:
        """Raise ``ValueError`` unless every row of ``thetas`` (B, n), with the scene's values for
        the other keys, passes ``jaxmpm.validate_params`` (a member with β < 0 or μ2 < μ1 is not a
        parameter set of the model). Names up to three offending rows."""
        thetas = np.asarray(thetas, float)
        if thetas.ndim == 1:
            thetas = thetas[None, :]
        if thetas.ndim != 2 or thetas.shape[1] != len(self.keys):
            raise ValueError(f"{name} must have shape (B, {len(self.keys)}) for keys {self.keys}, got {thetas.shape}")
        base = {k: np.full(thetas.shape[0], float(v)) for k, v in self.problem.base.to_dict().items()}
        values = {**base, **{k: thetas[:, j] for j, k in enumerate(self.keys)}}
        try:
            validate_params(values)
            return
        except ValueError:
            pass
        bad = []
        for i in range(thetas.shape[0]):
            try:
                validate_params({k: v[i] for k, v in values.items()})
            except ValueError as err:
                bad.append((i, err))
        rows = "; ".join(f"member {i} ({', '.join(f'{k} = {thetas[i, j]:g}' for j, k in enumerate(self.keys))}): "
                         f"{err}" for i, err in bad[:3])
        what = "the member is" if thetas.shape[0] == 1 else f"{len(bad)} of {thetas.shape[0]} members are"
        raise ValueError(f"{name}: {what} not a valid parameter set: {rows}")

    def fingerprint(self) -> dict[str, Any]:
        """What this objective's loss and its optimiser steps depend on, as a JSON-able dict (the
        data and the run configuration by content hash, file names aside): equal fingerprints
        compute equal residuals; ``fit`` refuses to resume a history made for another one."""
        data = [a for p in self.layout.profiles for a in (p.x, p.h, [p.time])]
        if self.layout.front is not None:
            data += [self.layout.front.t, self.layout.front.x_front]
            if self.front.correlation_time is not None:  # (absent when None: older histories still match)
                data += [[float(self.front.correlation_time)]]
        info = self.scene.info
        config = json.dumps(self.config.to_dict(), sort_keys=True, default=str)
        return {
            "scene": self.scene.name, "data": _digest(*data), "keys": list(self.keys),
            "dx": float(self.config.grid.dx), "ppc": info.ppc, "sampling": info.sampling,
            "seed": info.seed, "dim": info.dim, "width": info.width,
            "slope_deg": info.slope_deg, "L": info.length, "H": info.height,
            "t_end": float(self.config.t_end),
            "fixed": {k: float(v) for k, v in self.problem.base.to_dict().items() if k not in self.keys},
            "weights": {k: float(v) for k, v in self.weights.items()}, "sigma": self.sigma,
            **({"weighting": self.weighting} if self.weighting != "block" else {}),  # older files: "block"
            "front_threshold": self.front_threshold, "x_ref": self.x_ref, "mirror": self.mirror,
            "bounds": {k: [lo, hi] for k, lo, hi in zip(self.keys, self.bounds.lower, self.bounds.upper)},
            "dtype": np.dtype(self.dtype).name, "jacobian": self.jacobian, "fd_step": self.fd_step,
            "n_particles": int(self.problem.state.x.shape[0]),
            "particles": _digest(self.problem.state.x, self.problem.state.vol0),
            "config": hashlib.sha256(config.encode()).hexdigest()[:16],
        }

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (scene, data sizes, weights), for history files."""
        return {"scene": self.scene.name, "keys": list(self.keys), "times": list(self.times),
                "n_profile": [int(p.x.size) for p in self.layout.profiles],
                "n_front": int(self.layout.front.t.size) if self.layout.front is not None else 0,
                "weights": self.weights, "weighting": self.weighting, "sigma": self.sigma,
                "front_threshold": self.front_threshold,
                "dx": self.config.grid.dx, "n_particles": int(self.problem.state.x.shape[0]),
                "bounds": {k: [lo, hi] for k, lo, hi in zip(self.keys, self.bounds.lower, self.bounds.upper)},
                "bound_notes": list(self.bound_notes),
                "fixed": {k: float(v) for k, v in self.problem.base.to_dict().items() if k not in self.keys}}
