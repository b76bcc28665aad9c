"""Command line: ``python -m jaxmpm {run,bench} ...``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from .scenes import add_scene_arguments, parse_set, scene_from_args


def _run(args) -> int:
    import jax

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from . import io
    from .observables import deposit_profile, particle_volumes
    from .simulate import simulate
    from .state import describe_status

    frames = args.frames if args.frames is not None else (40 if args.gif else 0)
    scene = scene_from_args(args, frames=frames)
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
                "units": "m", "synthetic": True, "source": "python -m jaxmpm run " + " ".join(sys.argv[2:]),
                # float32 leaves printed to the precision they hold (0.3, not 0.30000001192092896)
                "parameters": {k: float(f"{v:.7g}") if args.dtype == "float32" else v
                               for k, v in params.to_dict().items()},
                "scene": {k: v for k, v in scene.meta.items() if v is not None}, "status": result.status,
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

    params = Params.create(**dict(parse_set(item) for item in args.set))
    history = element_test(args.test, params, rate=args.rate, pressure=args.pressure, steps=args.steps,
                           strain=args.strain, dim=args.dim)
    final = history.final()
    print(json.dumps(final) if args.json else json.dumps(final, indent=2))
    if args.plot:
        from .plots import plot_stress_path

        plot_stress_path(history, params, args.plot, title=f"{args.test}, rate {args.rate:g} 1/s")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m jaxmpm", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a reference scene (SCENES.md)")
    add_scene_arguments(run)
    run.add_argument("--frames", type=int, default=None, help="output frames (default 0, or 40 with --gif)")
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
    validate.add_argument("study", choices=("bagnold", "bagnold-from-rest", "convergence", "aspect-ratio", "cohesion",
                                            "speed-accuracy", "stability", "resolution", "cross-code"))
    validate.add_argument("--quick", action="store_true", help="a reduced, faster version")
    validate.add_argument("--json", action="store_true", help="print one JSON object")
    validate.add_argument("--plot", default=None, metavar="DIR", help="write the study's figure into DIR")
    validate.add_argument("--alpha", type=float, default=None, help="AFLIP blend for the bagnold studies (default 0.95)")
    validate.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                          help="precision of the study's runs (default float32, the run command's default)")

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
            if args.dtype == "float64":
                import jax

                jax.config.update("jax_enable_x64", True)
            from .validate import run_study

            out = run_study(args.study, quick=args.quick, plot_dir=args.plot, alpha=args.alpha)
            print(json.dumps(out) if args.json else json.dumps(out, indent=2))
            return 0
        from . import bench

        bench.main(args)
        return 0
    except ValueError as err:  # invalid input: a clear message, not a traceback
        parser.exit(2, f"python -m jaxmpm {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
