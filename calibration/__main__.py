"""Command line: ``python -m calibration {fit,sweep,twin} ...``.

    python -m calibration fit --scene cohesive-collapse --data deposit.csv --fit beta,mu1 --json
    python -m calibration sweep --scene cohesive-collapse --data deposit.csv --over beta=0.05:0.5:8 \\
        --over mu1=0.3:0.5:8 --plot figs
    python -m calibration twin --quick --noise 0.02 --json
    python -m calibration bench --json

``fit``, ``sweep`` and ``twin`` take the scene options of ``python -m jaxmpm run`` (--dx, --ppc,
--t-end, --set key=value, ...). Invalid input exits with status 2 and a message naming the
argument and what was wrong.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

__all__ = ["main", "build_parser"]


def _keys(text: str) -> tuple[str, ...]:
    keys = tuple(k.strip() for k in text.split(",") if k.strip())
    if not keys:
        raise ValueError(f"--fit: expected comma-separated parameter names, got {text!r}")
    return keys


def _pairs(items, option: str) -> dict[str, float]:
    from jaxmpm.scenes import parse_set

    out = {}
    for item in items:
        try:
            key, value = parse_set(item)
        except ValueError as err:
            raise ValueError(str(err).replace("--set", option)) from None
        out[key] = value
    return out


def _load_data(args):
    from .data import load_front_history, load_profile

    profiles = [load_profile(p, units=args.units) for p in args.data]
    front = load_front_history(args.front, units=args.units, time_units=args.time_units) if args.front else None
    if not profiles and front is None:
        raise ValueError("--data (a profile CSV) and/or --front (a front-history CSV) is required")
    return profiles, front


def _scene_and_objective(args, keys):
    import jax

    from jaxmpm.scenes import scene_from_args

    from .objective import Objective

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    profiles, front = _load_data(args)
    if args.t_end is None:  # run until the latest data time, if the data say when they were taken
        times = [p.time_s for p in profiles if p.time_s is not None]
        if front is not None:
            times.append(float(front.t[-1]))
        if times:
            args.t_end = max(times)
    scene = scene_from_args(args)
    objective = Objective(scene, keys, profile=profiles or None, front=front,
                          weights={"profile": args.weight_profile, "front": args.weight_front},
                          front_threshold=args.front_threshold, jacobian=getattr(args, "jacobian", "ad"))
    return scene, objective


def _write_json(obj) -> str:
    return json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


def _fit(args) -> int:
    from .fit import fit
    from .uncertainty import gauss_newton_uncertainty

    keys = _keys(args.fit)
    init = _pairs(args.init, "--init")
    scene, objective = _scene_and_objective(args, keys)
    noise = args.noise
    steps = args.steps or (25 if args.method == "lm" else 150)
    result = fit(objective, init, method=args.method, steps=steps, out=args.out, resume=args.resume,
                 learning_rate=args.lr, progress=not args.no_progress, noise=noise,
                 meta={"command": "python -m calibration " + " ".join(sys.argv[1:]), "data": args.data,
                       "front": args.front})
    result.uncertainty = gauss_newton_uncertainty(
        result.jacobian, result.residuals, keys, [result.theta[k] for k in keys], objective.blocks,
        objective.row_scale, noise=noise, reference_noise=args.reference_noise, threshold=args.threshold,
        bounds=objective.bounds)
    out = result.to_json()
    out["scene"] = scene.name
    if args.out:
        out["out"] = str(args.out)
    near = objective.bounds.near_bound([result.theta[k] for k in keys])
    if near:
        out["warning"] = f"{near} ended at a bound: the data push them outside the physical range"
    if args.plot:
        out["figures"] = _plots(args.plot, objective, result, prefix="fit")
    print(_write_json(out) if args.json else json.dumps(json.loads(_write_json(out)), indent=2))
    return 0


def _plots(directory, objective, result, prefix: str, truth=None, initial=None):
    from .plots import plot_fit, plot_history

    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    figs = [plot_fit(objective, result, d / f"{prefix}_profiles.png", initial_prediction=initial),
            plot_history(result.history, result.keys, d / f"{prefix}_history.png", truth=truth)]
    return [str(f) for f in figs]


def _parse_over(items) -> dict[str, tuple[float, float, int]]:
    out = {}
    for item in items:
        key, sep, rng = item.partition("=")
        parts = rng.split(":")
        if not sep or len(parts) not in (2, 3):
            raise ValueError(f"--over expects key=lo:hi[:n], got {item!r}")
        try:
            lo, hi = float(parts[0]), float(parts[1])
            n = int(parts[2]) if len(parts) == 3 else 5
        except ValueError:
            raise ValueError(f"--over {key}: lo, hi must be numbers and n an integer, got {rng!r}") from None
        out[key.strip()] = (lo, hi, n)
    if not out:
        raise ValueError("--over key=lo:hi[:n] is required (once per swept parameter)")
    return out


def _sweep(args) -> int:
    import numpy as np

    from .sweep import grid_points, latin_hypercube, sweep

    over = _parse_over(args.over)
    keys = tuple(over)
    ranges = {k: (lo, hi) for k, (lo, hi, _) in over.items()}
    if args.lhs:
        keys, thetas = latin_hypercube(ranges, args.lhs, seed=args.seed)
    else:
        keys, thetas = grid_points(ranges, {k: n for k, (_, _, n) in over.items()})
    scene, objective = _scene_and_objective(args, keys)
    result = sweep(objective, thetas, chunk=args.chunk, mode=args.mode, progress=not args.no_progress)
    out = result.to_json()
    out.pop("residuals", None)  # per-member residual vectors go to --out, not to the terminal
    out["scene"] = scene.name
    if args.out:
        import h5py

        with h5py.File(args.out, "w") as f:
            f.attrs["keys_json"] = json.dumps(list(keys))
            f.attrs["objective_json"] = json.dumps(objective.describe())
            f.create_dataset("thetas", data=np.asarray(result.thetas))
            f.create_dataset("loss", data=np.asarray(result.loss))
            f.create_dataset("status", data=np.asarray(result.status))
            f.create_dataset("residuals", data=np.asarray(result.residuals))
        out["out"] = str(args.out)
    if args.plot and len(keys) >= 2 and not args.lhs:
        from .plots import plot_landscape

        d = pathlib.Path(args.plot)
        d.mkdir(parents=True, exist_ok=True)
        xs, ys, loss = result.landscape(keys[0], keys[1])
        best = result.best()
        failed = [i for i in result.failed]
        fx = np.asarray(result.thetas)[failed, 0] if failed else np.zeros(0)
        fy = np.asarray(result.thetas)[failed, 1] if failed else np.zeros(0)
        out["figures"] = [str(plot_landscape(xs, ys, loss, keys[0], keys[1], d / "landscape.png",
                                             marks={"lowest": (best[keys[0]], best[keys[1]])}, failed=(fx, fy)))]
    print(_write_json(out) if args.json else json.dumps(json.loads(_write_json(out)), indent=2))
    return 0


def _twin(args) -> int:
    import jax

    from .twin import twin

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    if args.slope is not None or args.aspect is not None or args.dim != 2 or args.width is not None:
        raise ValueError("twin is the 2D S4 cohesive collapse: --slope, --aspect, --dim and --width do not apply")
    keys = _keys(args.fit)
    out = twin(quick=args.quick, noise=args.noise, keys=keys, method=args.method, steps=args.steps, seed=args.seed,
               dx=args.dx, ppc=args.ppc, t_end=args.t_end, values=_pairs(args.set, "--set"), dtype=args.dtype,
               out=args.out, resume=args.resume, progress=not args.no_progress,
               reference_noise=args.reference_noise, threshold=args.threshold)
    result, objective = out.pop("_fit"), out.pop("_objective")
    if args.plot:
        out["figures"] = _plots(args.plot, objective, result, prefix="twin", truth=out["true"])
    if args.landscape:
        out["landscape"] = _twin_landscape(args, objective, out)
    print(_write_json(out) if args.json else json.dumps(json.loads(_write_json(out)), indent=2))
    return 0


def _twin_landscape(args, objective, out) -> dict:
    """Sweep the twin's loss over its first two keys (±40 % around the truth, the others at
    their true values) and draw it with the truth, the start and the fit marked."""
    import numpy as np

    from .sweep import grid_points, sweep

    if len(objective.keys) < 2:
        raise ValueError("--landscape needs at least two fitted keys")
    kx, ky = objective.keys[:2]
    ranges = {k: (0.6 * out["true"][k], 1.4 * out["true"][k]) for k in (kx, ky)}
    _, grid = grid_points(ranges, args.landscape, keys=(kx, ky))
    thetas = np.tile([out["true"][k] for k in objective.keys], (grid.shape[0], 1))
    thetas[:, :2] = grid
    result = sweep(objective, thetas, progress=not args.no_progress)
    xs, ys, loss = result.landscape(kx, ky)
    summary = {"keys": [kx, ky], "n": int(grid.shape[0]), "failed": len(result.failed), "wall_s": result.wall_s,
               "mode": result.mode}
    if args.plot:
        from .plots import plot_landscape

        marks = {"true": (out["true"][kx], out["true"][ky]), "start": (out["start"][kx], out["start"][ky]),
                 "fit": (out["params"][kx], out["params"][ky])}
        summary["figure"] = str(plot_landscape(xs, ys, loss, kx, ky, pathlib.Path(args.plot) / "twin_landscape.png",
                                               marks=marks, title=f"twin loss over ({kx}, {ky}), others at truth"))
    return summary


def _floats(text: str, option: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{option} expects comma-separated numbers, got {text!r}") from None


def _law(args) -> int:
    import functools

    from jaxmpm.scenes import runout_law

    from .scaling import fit_runout_law

    if args.law:
        from .data import load_scaling_law
        from .scaling import law_from_table

        table = load_scaling_law(args.law)
        law = law_from_table(table)
        label = f"{table.experiment} ({'secondary' if table.secondary else 'primary'}: {table.source})"
    else:
        law = functools.partial(runout_law, sand=True) if args.sand else runout_law
        label = ("sand (Lube et al. 2005" if args.sand else "glass beads (Lajeunesse et al. 2005") + ", secondary)"
    for a in _floats(args.train, "--train") + _floats(args.test, "--test"):
        law(a)  # an aspect ratio the law file does not tabulate fails here, before any run
    out = fit_runout_law(_floats(args.train, "--train"), _floats(args.test, "--test"), _keys(args.fit), law=law,
                         dx=args.dx, ppc=args.ppc, values=_pairs(args.set, "--set"), steps=args.steps, out=args.out,
                         progress=not args.no_progress, jacobian=args.jacobian, fd_step=args.fd_step)
    result = out.pop("_fit")
    out["law"] = label
    if args.plot:
        from .plots import plot_history, plot_runout_law

        d = pathlib.Path(args.plot)
        d.mkdir(parents=True, exist_ok=True)
        out["figures"] = [str(plot_runout_law(out["cases"], d / "law_runout.png", law=law, title=out["law"])),
                          str(plot_history(result.history, result.keys, d / "law_history.png"))]
    print(_write_json(out) if args.json else json.dumps(json.loads(_write_json(out)), indent=2))
    return 0


def _bench(args) -> int:
    import jax

    from .bench import bench

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    kw = {"dx": 0.089 / 8, "t_end": 0.2} if args.quick else {"dx": args.dx}
    out = bench(_keys(args.fit), repeat=args.repeat, dtype=args.dtype, **kw)
    print(json.dumps(out) if args.json else json.dumps(out, indent=2))
    return 0


def _common(p, data: bool = True) -> None:
    from jaxmpm.scenes import SCENE_NAMES, add_scene_arguments

    if data:
        p.add_argument("--scene", required=True, choices=SCENE_NAMES, help="the scene the data come from")
        p.add_argument("--data", action="append", default=[], metavar="FILE.csv",
                       help="a deposit profile (project CSV or WebPlotDigitizer export); repeat for several times")
        p.add_argument("--front", default=None, metavar="FILE.csv", help="a front history (t_s,xf_m)")
        p.add_argument("--units", default=None, choices=("m", "cm", "mm"),
                       help="length units of files that do not state them (WebPlotDigitizer exports)")
        p.add_argument("--time-units", default=None, choices=("s", "ms"), help="time units of a front file")
        p.add_argument("--weight-profile", type=float, default=1.0, help="weight of the profile misfit")
        p.add_argument("--weight-front", type=float, default=1.0, help="weight of the front misfit")
        p.add_argument("--front-threshold", type=float, default=None,
                       help="height (m) below which the deposit has ended, for the front (default dx/ppc/2)")
    add_scene_arguments(p, scene_choices=False)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _fit_options(p, default_keys: str | None) -> None:
    p.add_argument("--fit", required=default_keys is None, default=default_keys, metavar="KEYS",
                   help="comma-separated parameters to fit, from beta,mu1,mu2,I0,xi")
    p.add_argument("--method", choices=("lm", "adam"), default="lm")
    p.add_argument("--steps", type=int, default=None, help="maximum iterations (default 25 for lm, 150 for adam)")
    p.add_argument("--out", default=None, metavar="FILE.h5", help="history file, written after every iteration")
    p.add_argument("--resume", action="store_true", help="continue the fit stored in --out")
    p.add_argument("--plot", default=None, metavar="DIR", help="write the figures into DIR")
    p.add_argument("--reference-noise", type=float, default=0.01,
                   help="noise (fraction of the data scale) at which identifiability is judged (default 0.01)")
    p.add_argument("--threshold", type=float, default=0.1,
                   help="a parameter is constrained if its 95%% half-width is below this fraction (default 0.1)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m calibration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    fit = sub.add_parser("fit", help="fit parameters to a measured deposit profile and/or front history")
    _common(fit)
    _fit_options(fit, None)
    fit.add_argument("--init", action="append", default=[], metavar="KEY=VALUE", help="starting value")
    fit.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (in the unconstrained variables)")
    fit.add_argument("--jacobian", choices=("ad", "fd"), default="ad",
                     help="LM Jacobian: forward-mode autodiff, or central differences for long violent runs")
    fit.add_argument("--noise", type=float, default=None,
                     help="known noise of the data (fraction of the peak height); default: estimated")

    sweep = sub.add_parser("sweep", help="the loss over a grid or a Latin hypercube of parameters")
    _common(sweep)
    sweep.add_argument("--over", action="append", default=[], metavar="KEY=LO:HI[:N]", help="swept parameter")
    sweep.add_argument("--lhs", type=int, default=None, metavar="N", help="N Latin-hypercube samples instead of a grid")
    sweep.add_argument("--seed", type=int, default=0)
    sweep.add_argument("--chunk", type=int, default=None, help="members per vmapped chunk (default: by memory)")
    sweep.add_argument("--mode", choices=("auto", "vmap", "shard", "loop"), default="auto")
    sweep.add_argument("--out", default=None, metavar="FILE.h5")
    sweep.add_argument("--plot", default=None, metavar="DIR", help="the loss landscape of the first two keys")

    be = sub.add_parser("bench", help="time a forward run, the forward-mode Jacobian and the reverse-mode gradient")
    be.add_argument("--fit", default="beta,mu1,mu2,I0,xi", metavar="KEYS", help="parameters (default all five)")
    be.add_argument("--dx", type=float, default=0.089 / 16, help="grid spacing of the S4 scene, m")
    be.add_argument("--quick", action="store_true", help="dx = L/8 and 0.2 s")
    be.add_argument("--repeat", type=int, default=2)
    be.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    be.add_argument("--json", action="store_true", help="print one line of JSON")

    law = sub.add_parser("law", help="fit the S5 runout-against-aspect-ratio law and predict unused aspect ratios")
    law.add_argument("--fit", default="mu1,mu2", metavar="KEYS", help="parameters to fit (default mu1,mu2)")
    law.add_argument("--train", default="0.5,1,4", help="aspect ratios used in the fit")
    law.add_argument("--test", default="2,8", help="aspect ratios only predicted")
    law.add_argument("--sand", action="store_true", help="the sand law of Lube et al. 2005 instead of glass beads")
    law.add_argument("--law", default=None, metavar="FILE.csv",
                     help="a scaling-law table (a,dL_over_L0), e.g. experiments_data/scaling_laws/runout_glass_beads.csv")
    law.add_argument("--dx", type=float, default=None, help="grid spacing, m (default L0/10)")
    law.add_argument("--ppc", type=int, default=2)
    law.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    law.add_argument("--steps", type=int, default=15)
    law.add_argument("--jacobian", choices=("ad", "fd"), default="fd")
    law.add_argument("--fd-step", type=float, default=0.05, help="relative step of the central differences")
    law.add_argument("--out", default=None, metavar="FILE.h5")
    law.add_argument("--plot", default=None, metavar="DIR")
    law.add_argument("--no-progress", action="store_true")
    law.add_argument("--json", action="store_true")

    tw = sub.add_parser("twin", help="fit synthetic S4 data made with known parameters")
    _common(tw, data=False)
    _fit_options(tw, "beta,mu1,xi")
    tw.add_argument("--quick", action="store_true", help="a coarse grid (dx = L/8): about a minute")
    tw.add_argument("--noise", type=float, default=0.0, help="Gaussian noise, fraction of the peak height")
    tw.add_argument("--seed", type=int, default=0, help="seed of the noise")
    tw.add_argument("--landscape", type=int, default=None, metavar="N",
                    help="also sweep the loss on an N × N grid over the first two keys (figure with --plot)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        for name in ("steps", "chunk", "lhs"):
            value = getattr(args, name, None)
            if value is not None and value < 1:
                raise ValueError(f"--{name} must be >= 1, got {value}")
        for name in ("noise", "reference_noise", "threshold"):
            value = getattr(args, name, None)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        if getattr(args, "resume", False) and not args.out:
            raise ValueError("--resume needs --out (the history file to continue)")
        commands = {"fit": _fit, "sweep": _sweep, "twin": _twin, "bench": _bench, "law": _law}
        return commands[args.command](args)
    except ValueError as err:
        parser.exit(2, f"python -m calibration {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
