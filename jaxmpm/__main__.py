"""Command line: ``python -m jaxmpm {run,bench} ...``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


SCENES = ("cohesive-collapse", "gates-collapse", "slope-collapse", "aspect-ratio", "elastic-block")


def build_scene(name: str, dx=None, ppc=2, dim=2, width=None, t_end=None, frames=0, slope=None, aspect=None,
                dtype=None, values=None):
    """A scene by its command-line name, with the command line's options."""
    from . import scenes

    values = dict(values or {})
    common = dict(ppc=ppc, dim=dim, width=width, frames=frames, dtype=dtype, **values)
    if t_end is not None:
        common["t_end"] = t_end
    if dx is not None:
        common["dx"] = dx
    if name != "slope-collapse" and slope is not None:
        raise ValueError(f"--slope applies to slope-collapse, not {name}")
    if name != "aspect-ratio" and aspect is not None:
        raise ValueError(f"--aspect applies to aspect-ratio, not {name}")
    if name == "cohesive-collapse":
        return scenes.cohesive_collapse(**common)
    if name == "gates-collapse":
        return scenes.gates_collapse(**{"dx": 0.005, **common})
    if name == "slope-collapse":
        return scenes.slope_collapse(10.0 if slope is None else slope, **{"dx": 0.01, **common})
    if name == "aspect-ratio":
        return scenes.aspect_ratio_collapse(1.0 if aspect is None else aspect, **common)
    if name == "elastic-block":
        if dim != 2 or width is not None:
            raise ValueError("elastic-block is 2D")
        return scenes.falling_block(n_particles=2_500, t_end=t_end or 0.39, frames=frames, dtype=dtype, **values)
    raise ValueError(f"scene must be one of {SCENES}, got {name!r}")


def _run(args) -> int:
    import jax

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from . import io
    from .observables import deposit_profile, particle_volumes
    from .simulate import simulate
    from .state import describe_status

    values = dict(_parse_set(item) for item in args.set)
    frames = args.frames if args.frames is not None else (40 if args.gif else 0)
    scene = build_scene(args.scene, dx=args.dx, ppc=args.ppc, dim=args.dim, width=args.width, t_end=args.t_end,
                        frames=frames, slope=args.slope, aspect=args.aspect, dtype=args.dtype, values=values)
    config, state, params = scene
    result = simulate(config, state, params, throw=False, progress=not args.no_progress, timed=True)
    x = np.asarray(result.state.x)
    summary = {
        "scene": scene.name,
        "n_particles": int(state.n_particles),
        "n_steps": int(result.state.steps),
        "dx": config.grid.dx,
        "t_end": config.t_end,
        "x_min": float(x[:, 0].min()),
        "x_max": float(x[:, 0].max()),
        "y_max": float(x[:, 1].max()),
        "runout": float(x[:, 0].max() - scene.meta["front0"]),
        "status": result.status,
        "status_text": describe_status(result.status),
        "compile_s": round(result.compile_s, 3),
        "run_s": round(result.run_s, 3),
    }
    meta = {"scene": scene.name, **{k: v for k, v in scene.meta.items() if v is not None}}
    if args.out:
        summary["out"] = str(io.write_h5(args.out, result, config, params, attrs=meta))
    if args.profile_csv or args.plot:
        sigma = config.grid.dx / scene.meta.get("ppc", 2)
        xs = np.arange(x[:, 0].min() - 3 * sigma, x[:, 0].max() + 3 * sigma, sigma / 2)
        h = np.asarray(deposit_profile(result.state.x, particle_volumes(result.state), xs, sigma,
                                       width=scene.meta.get("width")))
        if args.profile_csv:
            io.write_profile_csv(args.profile_csv, xs, h, {
                "experiment": f"{scene.name} (synthetic, jaxmpm {_version()})", "time_s": config.t_end,
                "units": "m", "source": "python -m jaxmpm run " + " ".join(sys.argv[2:]),
                "parameters": params.to_dict(), "status": result.status,
            })
    if args.plot:
        from .plots import plot_run

        plot_run(scene, result, args.plot, profile=(xs, h))
    if args.gif:
        from .plots import animate_run

        animate_run(scene, result, args.gif)
    print(json.dumps(summary) if args.json else json.dumps(summary, indent=2))
    return 0 if result.ok else 1


def _version() -> str:
    from . import __version__

    return __version__


def _element(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)  # a single point: double precision costs nothing
    from .element import element_test
    from .params import Params

    params = Params.create(**dict(_parse_set(item) for item in args.set))
    history = element_test(args.test, params, rate=args.rate, pressure=args.pressure, steps=args.steps,
                           strain=args.strain, dim=args.dim)
    final = history.final()
    print(json.dumps(final) if args.json else json.dumps(final, indent=2))
    if args.plot:
        from .plots import plot_stress_path

        plot_stress_path(history, params, args.plot, title=f"{args.test}, rate {args.rate:g} 1/s")
    return 0


def _parse_set(item: str):
    key, sep, value = item.partition("=")
    if not sep:
        raise SystemExit(f"--set expects key=value, got {item!r}")
    try:
        return key.strip(), float(value)
    except ValueError:
        raise SystemExit(f"--set {key}: value must be a number, got {value!r}") from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m jaxmpm", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a reference scene (SCENES.md)")
    run.add_argument("scene", choices=SCENES)
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    run.add_argument("--dx", type=float, default=None, help="grid spacing, m (default: a coarse, fast value)")
    run.add_argument("--ppc", type=int, default=2, help="particles per cell and axis (default 2)")
    run.add_argument("--dim", type=int, default=2, choices=(2, 3))
    run.add_argument("--width", type=float, default=None, help="channel width for --dim 3, m")
    run.add_argument("--slope", type=float, default=None, help="bed angle for slope-collapse, degrees")
    run.add_argument("--aspect", type=float, default=None, help="aspect ratio H0/L0 for aspect-ratio")
    run.add_argument("--t-end", type=float, default=None, help="end time, s (default: the scene's)")
    run.add_argument("--frames", type=int, default=None, help="output frames (default 0, or 40 with --gif)")
    run.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    run.add_argument("--out", default=None, help="HDF5 output file")
    run.add_argument("--profile-csv", default=None, help="write the final deposit profile h(x) as CSV")
    run.add_argument("--plot", default=None, metavar="FIG.png", help="final deposit and profile")
    run.add_argument("--gif", default=None, metavar="ANIM.gif", help="animation of the frames")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--json", action="store_true", help="print one JSON object")

    element = sub.add_parser("element", help="drive one material point (a lab element test)")
    element.add_argument("test", choices=("isotropic", "simple-shear", "triaxial"))
    element.add_argument("--rate", type=float, default=1.0, help="applied engineering strain rate, 1/s")
    element.add_argument("--pressure", type=float, default=1000.0, help="confining pressure p, Pa")
    element.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    element.add_argument("--steps", type=int, default=2000)
    element.add_argument("--strain", type=float, default=None, help="total strain (default 0.5 shear, 0.1 else)")
    element.add_argument("--dim", type=int, default=2, choices=(2, 3))
    element.add_argument("--json", action="store_true", help="print one JSON object")
    element.add_argument("--plot", default=None, metavar="FILE.png", help="stress path against the yield surface")

    validate = sub.add_parser("validate", help="run a validation study (docs/validation.md)")
    validate.add_argument("study", choices=("bagnold", "convergence", "aspect-ratio", "cohesion", "speed-accuracy",
                                            "stability"))
    validate.add_argument("--quick", action="store_true", help="a reduced, faster version")
    validate.add_argument("--json", action="store_true", help="print one JSON object")
    validate.add_argument("--plot", default=None, metavar="DIR", help="write the study's figure into DIR")

    bench = sub.add_parser("bench", help="time the engine and print JSON")
    bench.add_argument("--scene", choices=("block", "column"), default="block",
                       help="block: 2D Hencky block, 10k particles; column: S2 collapse, full model")
    bench.add_argument("--quick", action="store_true", help="a small, fast case")
    bench.add_argument("--json", action="store_true", help="print one line of JSON")
    bench.add_argument("--dim", type=int, default=2, choices=(2, 3))
    bench.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    bench.add_argument("--repeat", type=int, default=3, help="timed runs; the median is reported")
    bench.add_argument("--particles", type=int, default=None, help="override the particle count")
    bench.add_argument("--grad", action="store_true", help="benchmark reverse-mode gradients instead")
    bench.add_argument("--steps", type=int, default=None, help="steps for --grad (default 5000)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "element":
            return _element(args)
        if args.command == "validate":
            from .validate import run_study

            out = run_study(args.study, quick=args.quick, plot_dir=args.plot)
            print(json.dumps(out) if args.json else json.dumps(out, indent=2))
            return 0
        from . import bench

        bench.main(args)
        return 0
    except ValueError as err:  # invalid input: a clear message, not a traceback
        parser.exit(2, f"python -m jaxmpm {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
