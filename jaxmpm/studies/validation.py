"""Validation studies: ``python -m jaxmpm validate NAME [--quick] [--json] [--plot DIR]``.

- ``bagnold``: S1 at 22°, 24°, 26°, 28° against the steady Bagnold profile (docs/model.md §6);
- ``bagnold-from-rest``: S1 at 24° from rest, the velocity profile converging towards it;
- ``resolution``, ``cross-code``: convergence over dx × ppc × sampling on S2 and S4, and S2
  against the reference code (``fidelity.py``);
- ``convergence``: S3 at 10° over dx (and ppc), runout and deposit profile against the finest;
- ``aspect-ratio``: S5 runout and final height against the glass-bead scaling laws (secondary);
- ``cohesion``: S4 with β = 0 and β = 0.25 side by side;
- ``speed-accuracy``: S3 at 10°, error against wall time over dx, ppc, transfer, dtype, cfl;
- ``stability``: settings pushed until methods fail, and how each failure is reported;
- ``avalanche``: S6 against dx and against the snow's parameters, with an obstacle's force.

Every study returns a JSON-ready dict and, with a plot directory, draws its figure there through
``jaxmpm.studies.plots``.
``--quick`` runs a reduced version (coarser, shorter) that finishes in a minute or two.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time

import jax
import numpy as np

from .. import scenes
from ..materials.base import invariants
from ..observables import deposit_profile, front_from_profile, particle_volumes
from ..precision import x64, x64_enabled
from ..scenes import S1_DEPTH, S3_LENGTH, S4_SIDE, S5_LENGTH
from ..simulate import simulate
from . import channel, fidelity

__all__ = ["STUDIES", "run_study", "bagnold", "convergence", "aspect_ratio", "cohesion", "speed_accuracy",
           "stability", "avalanche"]


def _profile_observer(state, params):
    return {"vx": state.v[:, 0], "y": state.x[:, 1], "vol": particle_volumes(state)}


def _timed(scene, observer=None):
    clock = time.perf_counter()
    result = simulate(*scene, observer=observer, throw=False)
    jax.block_until_ready(result.state.x)
    return result, time.perf_counter() - clock


def bagnold(quick=False, plot_dir=None, alpha=0.95, slopes=(22.0, 24.0, 26.0, 28.0), divisions=None,
            t_end=None, xpic=0) -> dict:
    """S1: start from the analytic profile, at the critical state (p_c = 2p, the state the
    analytic solution assumes), and measure how well the scheme holds it.

    The surface velocity is the mean over the top row of particles (the highest
    ``length_cells · ppc``), averaged over the last quarter of the run. It is compared with the
    analytic surface velocity v_max for the initial depth h0 = 0.038 m (``rel_error``), and with
    the analytic profile at the particles' own heights for the depth measured from the particle
    volumes (``rel_error_local``); the profile error is the RMS difference over all particles
    divided by v_max. Heights are measured from the bed: z = y − wall_gap (the layer's lowest
    particles start half a cell above it). The precision is the session's (float32 unless
    jax_enable_x64 is on). ``xpic``: the order of an XPIC filter on the FLIP part (0: off)."""
    divisions = divisions or ((8, 16) if quick else (8, 16, 32))
    t_end = (0.5 if quick else 3.0) if t_end is None else t_end
    cases, profiles = [], {}
    for slope in slopes:
        for div in divisions:
            scene = scenes.incline(slope, dx=S1_DEPTH / div, t_end=t_end, frames=16, alpha=alpha, critical_start=True)
            if xpic:
                scene = dataclasses.replace(scene, config=dataclasses.replace(scene.config, xpic=xpic))
            gap = scene.info.wall_gap
            result, wall = _timed(scene, _profile_observer)
            frames = {k: np.asarray(v) for k, v in result.frames.items()}
            # The critical start sets ε_v^p at t = 0; the volume change is counted from there.
            frames["vol"] = frames["vol"] / np.exp(np.asarray(scene.state.internal["eps_v_p"]))
            late = range(12, 16)
            v_s, v_a, prof = [], [], []
            row = scene.config.grid.cells[0] * scene.info.ppc
            v_max = float(scenes.bagnold_velocity(S1_DEPTH, S1_DEPTH, slope, scene.params))
            for k in late:
                vx, z, vol = frames["vx"][k], frames["y"][k] - gap, frames["vol"][k]
                h = vol.sum() / scene.info.length
                analytic = scenes.bagnold_velocity(z, h, slope, scene.params)
                top = np.argsort(z)[-row:]
                v_s.append(vx[top].mean())
                v_a.append(analytic[top].mean())
                prof.append(np.sqrt(np.mean((vx - analytic) ** 2)) / v_max)
            case = {
                "slope_deg": slope, "dx": scene.info.dx, "n_particles": scene.state.n_particles,
                "v_surface": float(np.mean(v_s)), "v_surface_analytic": v_max,
                "rel_error": float(np.mean(v_s) / v_max - 1.0),
                "rel_error_local": float(np.mean(v_s) / np.mean(v_a) - 1.0), "profile_rel_error": float(np.mean(prof)),
                "depth_from_volumes": float(h), "depth_from_positions": float(np.sort(z)[-row:].mean()),
                "status": result.status, "wall_s": round(wall, 2),
            }
            cases.append(case)
            profiles[(slope, div)] = (frames["vx"][15], frames["y"][15] - gap, h)
    finest = [c for c in cases if c["dx"] == min(c2["dx"] for c2 in cases)]
    out = {"study": "bagnold", "t_end": t_end, "alpha": alpha, "xpic": xpic, "dtype": str(jax.numpy.zeros(()).dtype),
           "cases": finest, "all_cases": cases}
    if plot_dir:
        suffix = ("" if alpha == 0.95 else f"_alpha{alpha:g}") + (f"_xpic{xpic}" if xpic else "")
        suffix += "" if out["dtype"] == "float32" else "_" + out["dtype"]
        from .plots import plot_bagnold

        plot_bagnold(profiles, slopes, divisions, cases, scene.params, pathlib.Path(plot_dir) / f"bagnold{suffix}.png")
    return out


def bagnold_from_rest(quick=False, plot_dir=None, alpha=0.95, slope=24.0, division=16, t_end=None, xpic=0) -> dict:
    """S1 at 24° from rest: the layer starts at rest at the critical state and accelerates
    towards the steady Bagnold profile. The velocity profile (binned in height) is recorded at
    a series of times, with its RMS distance to the analytic profile over v_max, and the
    surface velocity against v_max. Near the steady state the flow relaxes on the time scale
    v/(g cos θ μ'(I) I) (about 4 s at 24°), so the run lasts several of them."""
    t_end = (2.0 if quick else 12.0) if t_end is None else t_end
    frames = 24 if not quick else 8
    scene = scenes.incline(slope, dx=S1_DEPTH / division, t_end=t_end, frames=frames, alpha=alpha,
                           critical_start=True, start_from_analytic=False)
    if xpic:
        scene = dataclasses.replace(scene, config=dataclasses.replace(scene.config, xpic=xpic))
    gap = scene.info.wall_gap
    result, wall = _timed(scene, _profile_observer)
    fr = {k: np.asarray(v) for k, v in result.frames.items()}
    v_max = float(scenes.bagnold_velocity(S1_DEPTH, S1_DEPTH, slope, scene.params))
    edges = np.linspace(0.0, S1_DEPTH, 20)
    mid = 0.5 * (edges[1:] + edges[:-1])
    analytic_mid = scenes.bagnold_velocity(mid, S1_DEPTH, slope, scene.params)
    row = scene.config.grid.cells[0] * scene.info.ppc
    snapshots = []
    for k, t in enumerate(result.frame_times):
        vx, z = fr["vx"][k], fr["y"][k] - gap
        which = np.digitize(z, edges) - 1
        prof = np.array([vx[which == b].mean() if np.any(which == b) else np.nan for b in range(len(mid))])
        analytic = scenes.bagnold_velocity(z, S1_DEPTH, slope, scene.params)
        top = np.argsort(z)[-row:]
        snapshots.append({"t": float(t), "v_surface": float(vx[top].mean()),
                          "surface_rel": float(vx[top].mean() / v_max),
                          "profile_rel_error": float(np.sqrt(np.mean((vx - analytic) ** 2)) / v_max),
                          "profile": [None if not np.isfinite(v) else float(v) for v in prof]})
    out = {"study": "bagnold-from-rest", "slope_deg": slope, "dx": scene.info.dx, "alpha": alpha, "xpic": xpic,
           "dtype": str(jax.numpy.zeros(()).dtype), "t_end": t_end, "v_max_analytic": v_max,
           "z_bins": mid.tolist(), "analytic": analytic_mid.tolist(), "snapshots": snapshots,
           "status": result.status, "wall_s": round(wall, 1)}
    if plot_dir:
        from .plots import plot_bagnold_from_rest

        suffix = ("" if alpha == 0.95 else f"_alpha{alpha:g}") + (f"_xpic{xpic}" if xpic else "")
        suffix += "" if out["dtype"] == "float32" else "_" + out["dtype"]
        plot_bagnold_from_rest(out, pathlib.Path(plot_dir) / f"bagnold_from_rest{suffix}.png")
    return out


def convergence(quick=False, plot_dir=None) -> dict:
    """S3 at 10° at the scene defaults (sampling, particles per cell) over dx: the front (where
    the deposit profile falls below 3 mm), the deposit profile and the maximum-particle runout
    against the finest run; the observed order of the front from successive differences."""
    dxs = (0.02, 0.01) if quick else (0.02, 0.01, 0.005, 0.0025)
    t_end = 0.3 if quick else 1.0
    runs = []
    for dx in dxs:
        scene = _s3(dx, t_end)
        runs.append((scene, simulate(*scene, throw=False, timed=True)))
    ref_scene, ref = runs[-1]
    xs = np.linspace(-0.05, float(np.asarray(ref.state.x)[:, 0].max()) + 0.05, 400)
    h_ref, front_ref, runout_ref = _s3_observe(ref_scene, ref.state, xs)
    rows, profiles = [], []
    for scene, result in runs:
        h, front, runout = _s3_observe(scene, result.state, xs)
        profiles.append(h)
        rows.append({
            "dx": scene.info.dx, "ppc": scene.info.ppc, "sampling": scene.info.sampling,
            "n_particles": scene.state.n_particles, "front": front, "runout": runout,
            "front_diff": abs(front - front_ref), "runout_diff": abs(runout - runout_ref),
            "profile_l2_rel": float(np.linalg.norm(h - h_ref) / np.linalg.norm(h_ref)),
            "status": result.status, "run_s": round(result.run_s, 2),
        })
    diffs = [abs(b["front"] - a["front"]) for a, b in zip(rows, rows[1:])]
    orders = [math.log2(d1 / d2) for d1, d2 in zip(diffs, diffs[1:]) if d1 > 0 and d2 > 0]
    out = {"study": "convergence", "scene": "slope-collapse 10°", "t_end": t_end, "sigma_m": S3_SIGMA,
           "front_threshold_m": S3_FRONT_THRESHOLD, "runs": rows,
           "successive_front_differences": diffs, "observed_order": orders}
    if plot_dir:
        from .plots import plot_convergence

        plot_convergence(xs, rows, profiles, S3_SIGMA, t_end, pathlib.Path(plot_dir) / "convergence.png")
    return out


def aspect_ratio(quick=False, plot_dir=None) -> dict:
    """S5: ΔL/L0 and H_f/L0 against the glass-bead laws of Lajeunesse et al. 2005 (as quoted
    in K. Kumar's thesis: secondary)."""
    ratios = (0.5, 1.0, 2.0) if quick else (0.5, 1.0, 2.0, 4.0, 8.0)
    rows = []
    for a in ratios:
        scene = scenes.aspect_ratio_collapse(a, L0=S5_LENGTH, dx=S5_LENGTH / (6 if quick else 10))
        result, wall = _timed(scene)
        x = np.asarray(result.state.x)
        rows.append({"a": a, "runout_over_L0": float((x[:, 0].max() - S5_LENGTH) / S5_LENGTH),
                     "law_runout_over_L0": float(scenes.runout_law(a)),
                     "height_over_L0": float(x[:, 1].max() / S5_LENGTH),
                     "law_height_over_L0": float(scenes.height_law(a)),
                     "status": result.status, "wall_s": round(wall, 2)})
    out = {"study": "aspect-ratio", "laws": "Lajeunesse et al. 2005 via Kumar (secondary)", "runs": rows}
    if plot_dir:
        from .plots import plot_aspect_ratio

        plot_aspect_ratio(rows, pathlib.Path(plot_dir) / "aspect_ratio.png")
    return out


def cohesion(quick=False, plot_dir=None) -> dict:
    """S4 with β = 0 and β = 0.25: runout and final height side by side."""
    rows, shown = [], []
    for beta in (0.0, 0.25):
        scene = scenes.cohesive_collapse(beta, dx=S4_SIDE / (12 if quick else 24))
        result, wall = _timed(scene)
        x = np.asarray(result.state.x)
        rows.append({"beta": beta, "runout": float(x[:, 0].max() - S4_SIDE), "final_height": float(x[:, 1].max()),
                     "status": result.status, "wall_s": round(wall, 2)})
        shown.append((beta, x, np.asarray(invariants(result.state.tau)[0])))
    out = {"study": "cohesion", "runs": rows}
    if plot_dir:
        from .plots import plot_cohesion

        plot_cohesion(shown, pathlib.Path(plot_dir) / "cohesion.png")
    return out


def _s3(dx, t_end, ppc=None, transfer="aflip", alpha=0.95, cfl=0.5, dtype=None, sampling=None, xpic=0, **kw):
    scene = scenes.slope_collapse(10.0, dx=dx, ppc=ppc, t_end=t_end, transfer=transfer, alpha=alpha, cfl=cfl,
                                  dtype=dtype, sampling=sampling, **kw)
    if xpic:
        scene = dataclasses.replace(scene, config=dataclasses.replace(scene.config, xpic=xpic))
    return scene


#: Kernel width (m) of the S3 deposit profile in the speed-accuracy study: one width for every run.
S3_SIGMA = 5e-3
#: Height (m) below which the S3 deposit has ended (its front).
S3_FRONT_THRESHOLD = 3e-3


def _s3_observe(scene, state, xs):
    h = np.asarray(deposit_profile(state.x, particle_volumes(state), xs, S3_SIGMA))
    front = float(front_from_profile(xs, h, S3_FRONT_THRESHOLD, x_ref=0.0)) - S3_LENGTH
    return h, front, float(np.asarray(state.x)[:, 0].max()) - S3_LENGTH


def speed_accuracy(quick=False, plot_dir=None) -> dict:
    """S3 at 10°: errors in the front (where the deposit profile falls below 3 mm), the deposit
    profile and the maximum-particle runout against a fine reference run (dx = 2.5 mm, the
    scene defaults), versus run time (compilation apart), over dx, particles per cell, sampling,
    transfer, XPIC, float32/float64 and cfl. One point per run; the Pareto front (no other run
    both faster and more accurate on the front) is marked."""
    t_end = 0.3 if quick else 1.0
    ref_dx = 0.005 if quick else 0.0025
    variants = [dict(dx=dx) for dx in ((0.02, 0.01) if quick else (0.02, 0.01, 0.005))]
    variants += [dict(dx=0.01, transfer="pic"), dict(dx=0.01, transfer="apic"),
                 dict(dx=0.01, sampling="lattice", ppc=2)]
    if not quick:
        variants += [dict(dx=0.01, sampling=smp, ppc=n) for smp in ("lattice", "jitter") for n in (3, 4)]
        variants += [dict(dx=0.01, sampling="jitter", ppc=2), dict(dx=0.01, sampling="poisson", ppc=2.45),
                     dict(dx=0.005, sampling="lattice", ppc=2), dict(dx=0.01, xpic=2), dict(dx=0.01, dtype="float64"),
                     dict(dx=0.01, cfl=0.9), dict(dx=0.005, transfer="apic"), dict(dx=0.005, transfer="pic"),
                     dict(dx=0.02, ppc=4)]
    ref_scene = _s3(ref_dx, t_end, dtype="float32")
    ref = simulate(*ref_scene, throw=False, timed=True)
    xs = np.linspace(-0.05, float(np.asarray(ref.state.x)[:, 0].max()) + 0.05, 400)
    h_ref, front_ref, runout_ref = _s3_observe(ref_scene, ref.state, xs)
    rows = []
    for v in variants:
        with x64(v.get("dtype") == "float64" or x64_enabled()):
            scene = _s3(t_end=t_end, **v)
            result = simulate(*scene, throw=False, timed=True)  # compiled before the clock starts
            h, front, runout = _s3_observe(scene, result.state, xs)
        rows.append({
            "dx": v["dx"], "ppc": scene.info.ppc, "sampling": scene.info.sampling,
            "transfer": v.get("transfer", "aflip"), "xpic": v.get("xpic", 0),
            "dtype": v.get("dtype", "float32"), "cfl": v.get("cfl", 0.5), "n_particles": scene.state.n_particles,
            "n_steps": int(result.state.steps), "wall_s": round(result.run_s, 3),
            "front_rel_error": abs(front - front_ref) / front_ref,
            "runout_rel_error": abs(runout - runout_ref) / runout_ref,
            "profile_rel_error": float(np.linalg.norm(h - h_ref) / np.linalg.norm(h_ref)), "status": result.status,
        })
    for r in rows:
        r["pareto"] = not any(o["wall_s"] <= r["wall_s"] and o["front_rel_error"] < r["front_rel_error"]
                              for o in rows if o is not r)
    out = {"study": "speed-accuracy", "scene": "slope-collapse 10°", "t_end": t_end,
           "sigma_m": S3_SIGMA, "front_threshold_m": S3_FRONT_THRESHOLD,
           "reference": {"dx": ref_dx, "ppc": ref_scene.info.ppc, "sampling": ref_scene.info.sampling,
                         "transfer": "aflip", "wall_s": round(ref.run_s, 2), "front": front_ref, "runout": runout_ref},
           "runs": rows}
    if plot_dir:
        from .plots import plot_speed_accuracy

        plot_speed_accuracy(rows, pathlib.Path(plot_dir) / "speed_accuracy.png")
    return out


def _stability_case(label, scene, baseline_runout):
    from ..state import describe_status

    clock = time.perf_counter()
    result = simulate(*scene, throw=False)
    v = np.asarray(result.state.v)
    finite = bool(np.isfinite(v).all() and np.isfinite(np.asarray(result.state.x)).all())
    vmax = float(np.abs(v).max()) if finite else float("nan")
    runout = float(np.asarray(result.state.x)[:, 0].max() - scene.info.front0) if finite else float("nan")
    deviation = None if baseline_runout is None or not finite else abs(runout - baseline_runout) / abs(baseline_runout)
    if result.status:
        outcome = "flagged"
    elif not finite or vmax > 10.0:
        outcome = "silent blow-up"
    elif deviation is not None and deviation > 0.1:
        outcome = f"runs, but runout off by {100 * deviation:.0f}%"
    else:
        outcome = "ok"
    return {"case": label, "outcome": outcome, "status": result.status, "status_text": describe_status(result.status),
            "max_speed": vmax, "runout": runout, "runout_deviation": deviation,
            "steps": int(result.state.steps), "wall_s": round(time.perf_counter() - clock, 2)}


def stability(quick=False, plot_dir=None) -> dict:
    """Where methods fail: each case runs S4 (β = 0.25 where cohesion matters, else 0) or S3 with
    one setting pushed, and records whether it blows up and how the code reports it."""
    t_end = 0.1 if quick else 0.3
    cases = [
        ("baseline (AFLIP 0.95, cfl 0.5)", dict()),
        ("cfl = 1.5 (elastic bound too)", dict(cfl=1.5, cfl_elastic=1.5)),
        ("cfl = 3", dict(cfl=3.0, cfl_elastic=3.0)),
        ("pure FLIP (alpha = 1)", dict(alpha=1.0)),
        ("PIC", dict(transfer="pic")),
        ("stiff E = 1e8 at the dt of E = 1e6", dict(E=1e8, cfl_elastic=5.0)),
        ("tiny p_c0 = 1e-3 Pa (another material)", dict(pc0=1e-3)),
        ("beta = 0.5, free surface p̄ -> 0 (another material)", dict(beta=0.5)),
        ("very coarse dx = L/4", dict(dx=S4_SIDE / 4)),
        ("fine dx = L/48", dict(dx=S4_SIDE / 48)),
    ]
    if quick:
        cases = cases[:6]
    rows, baseline = [], None
    for label, opts in cases:
        opts = dict(opts)
        dt_opts = {k: opts.pop(k) for k in ("cfl", "cfl_elastic", "alpha", "transfer") if k in opts}
        scene = scenes.cohesive_collapse(opts.pop("beta", 0.0), dx=opts.pop("dx", S4_SIDE / 16), t_end=t_end, **opts)
        if dt_opts:
            scene = dataclasses.replace(scene, config=dataclasses.replace(scene.config, **dt_opts))
        rows.append(_stability_case(label, scene, None if "material" in label else baseline))
        baseline = baseline if baseline is not None else rows[0]["runout"]
    # Without plasticity nothing caps the stress: the elastic block shows the explicit limit.
    for cfl_e in (0.5, 1.5, 3.0):
        scene = scenes.falling_block(n_particles=2_500, t_end=0.2)
        scene = dataclasses.replace(scene, config=dataclasses.replace(scene.config, cfl_elastic=cfl_e))
        rows.append(_stability_case(f"Hencky block, cfl_e = {cfl_e}", scene, None))
    return {"study": "stability", "scene": "cohesive-collapse", "t_end": t_end, "cases": rows}


AVALANCHE_STATION = 3800.0  # on the run-out plain, where the study's obstacle stands


def _avalanche_row(label, dx, snow="dry", obstacle=None, **values):
    from ..scenes.avalanche import avalanche as make
    from .avalanche import run_avalanche

    scene = make(dx=dx, snow=snow, t_end=100.0, frames=100, obstacle=obstacle, **values)
    clock = time.perf_counter()
    result, fields = run_avalanche(scene, station=AVALANCHE_STATION)
    wall = time.perf_counter() - clock
    state0, state = scene.state, result.state
    vol0 = np.asarray(state0.vol0)  # one density: volume weights are mass weights
    start, end = (np.average(np.asarray(s.x), axis=0, weights=vol0) for s in (state0, state))
    volume = np.asarray(particle_volumes(state)) / vol0  # J = V / V0 of each particle
    row = {"case": label, "dx": dx, "snow": snow, **{k: float(v) for k, v in values.items()},
           "mu1": float(scene.params.mu1), "beta": float(scene.params.beta), "xi": float(scene.params.xi),
           "obstacle": None if obstacle is None else list(obstacle), "n_particles": int(state0.n_particles),
           "n_steps": int(state.steps), "status": result.status, **fields.summary(),
           # the centre of mass's travel angle, against the basal energy line's atan(μ_w)
           "com_travel_angle_deg": float(np.degrees(np.arctan2(start[1] - end[1], end[0] - start[0]))),
           "energy_line_angle_deg": float(np.degrees(np.arctan(float(scene.params.mu_w)))),
           "volume_ratio_percentiles": dict(zip(("p1", "p50", "p99"), np.percentile(volume, [1, 50, 99]).tolist())),
           "compile_s": round(result.compile_s, 2), "run_s": round(result.run_s, 2), "wall_s": round(wall, 1)}
    return row, fields


def avalanche(quick=False, plot_dir=None) -> dict:
    """S6 (docs/avalanche.md): runout and peak fields against dx (2, 1, 0.5 m; quick: 2, 1),
    then at one dx (1 m; quick: 2 m) against the snow: wet, μ1 = tan 15° and tan 25°, the dry
    set without hardening (ξ = 0), and a 5 m obstacle at x = 3800 m with the force on it. Each row
    also gives the centre of mass's travel angle and the particles' volume ratio J = V/V0."""
    grids = (2.0, 1.0) if quick else (2.0, 1.0, 0.5)
    base = 2.0 if quick else 1.0
    rows, shown = [], {}
    for dx in grids:
        row, fields = _avalanche_row(f"dry, dx = {dx:g} m", dx)
        rows.append(row)
        if dx == base:
            shown["open"] = fields
    cases = [("wet snow", {"snow": "wet"}), ("dry, mu1 = tan 15 deg", {"mu1": math.tan(math.radians(15.0))}),
             ("dry, mu1 = tan 25 deg", {"mu1": math.tan(math.radians(25.0))}),
             ("dry, xi = 0 (no hardening)", {"xi": 0.0}),
             ("dry, 5 m obstacle at x = 3800 m", {"obstacle": (AVALANCHE_STATION, 5.0)})]
    for label, opts in cases:
        row, fields = _avalanche_row(label, base, **opts)
        rows.append(row)
    shown["obstacle"] = fields
    runouts = [r["runout_x"] for r in rows[:len(grids)]]
    out = {"study": "avalanche", "scene": "avalanche", "terrain": "ISeeSnow CoulombOnly centre line", "mu_w": 0.4,
           "runs": rows, "runout_change_finest_pair": abs(runouts[-1] - runouts[-2]) / (runouts[-1] - 1345.0)}
    if plot_dir:
        from .plots import animate_avalanche, plot_avalanche, plot_obstacle_force

        plot_avalanche(shown["open"], pathlib.Path(plot_dir) / "avalanche.png",
                       title=f"S6 avalanche (ISeeSnow CoulombOnly terrain), dry snow, dx = {base:g} m, mu_w = 0.4")
        animate_avalanche(shown["open"], pathlib.Path(plot_dir) / "avalanche.gif", fps=8)
        plot_obstacle_force(shown["open"], shown["obstacle"], base, pathlib.Path(plot_dir) / "avalanche_obstacle.png")
    return out


STUDIES = {"bagnold": bagnold, "bagnold-from-rest": bagnold_from_rest, "convergence": convergence,
           "aspect-ratio": aspect_ratio, "cohesion": cohesion, "speed-accuracy": speed_accuracy, "stability": stability,
           "resolution": fidelity.resolution, "cross-code": fidelity.cross_code, "avalanche": avalanche,
           "side-walls": channel.side_walls}


def run_study(name: str, quick: bool = False, plot_dir=None, alpha: float | None = None, **options) -> dict:
    """Run one study; ``alpha`` (the AFLIP blend) applies to the bagnold studies only; other
    keyword options go to the study function (``slopes``, ``divisions``, ``xpic`` for bagnold)."""
    if name not in STUDIES:
        raise ValueError(f"study must be one of {sorted(STUDIES)}, got {name!r}")
    if alpha is not None and not name.startswith("bagnold"):
        raise ValueError(f"--alpha applies to the bagnold studies, not {name}")
    if alpha is not None and not (0.0 <= alpha <= 1.0):
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    if plot_dir is not None:
        pathlib.Path(plot_dir).mkdir(parents=True, exist_ok=True)
    clock = time.perf_counter()
    out = STUDIES[name](quick=quick, plot_dir=plot_dir, **({} if alpha is None else {"alpha": alpha}), **options)
    out["quick"] = quick
    out["wall_s"] = round(time.perf_counter() - clock, 1)
    return out
