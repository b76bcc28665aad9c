"""Command line: ``python -m jaxmpm {run,element,validate,bench} ...``: each command parses its
options, calls the library and prints."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from .cli import (
    add_scene_arguments,
    add_threads_argument,
    check_figure_file,
    check_repeated_keys,
    check_run_outputs,
    check_scene_args,
    output_writer,
    parse_set,
    print_json,
    scene_dtype,
    scene_from_args,
)
from .precision import DTYPES, use_dtype
from .scenes import SCENE_NAMES, is_experiment_file
from .studies.bench import SCENES
from .threads import apply_threads


def _source() -> str:
    """The command that made a file, for its header."""
    return "python -m jaxmpm run " + " ".join(sys.argv[2:])


def _write_run(args, output, summary: dict, scene, result) -> None:
    """--out and --ply of ``run``: written through ``output`` (an ``output_writer``), their
    paths added to ``summary``."""
    from . import io

    config, state, params = scene
    if args.out:
        path = output("--out", lambda: io.write_h5(args.out, result, config, params, attrs=scene.run_attrs(),
                                                   initial=state))
        if path is not None:
            summary["out"] = str(path)
    if args.ply:
        written = output("--ply", lambda: io.write_ply_frames(args.ply, result, initial=state))
        if written is not None:
            summary["ply"] = [str(w) for w in written]


def _run(args) -> int:
    check_scene_args(args)
    if args.scene == "avalanche":
        return _run_avalanche(args)
    for option, value in (("--terrain", args.terrain), ("--station", args.station), ("--obstacle", args.obstacle)):
        if value is not None:
            raise ValueError(f"{option} applies to the avalanche scene, not {args.scene}")
    if args.quick or args.snow != "dry":
        raise ValueError(f"--quick and --snow apply to the avalanche scene, not {args.scene}")
    if args.frames is not None and args.frames < 0:
        raise ValueError(f"--frames must be >= 0, got {args.frames}")
    # Without --frames an experiment file keeps its own [numerics] frames.
    frames = args.frames if args.frames is not None else (40 if args.gif else
                                                          (None if is_experiment_file(args.scene) else 0))
    check_run_outputs(args, frames or 0)
    use_dtype(scene_dtype(args))
    from . import tables
    from .simulate import simulate

    scene = scene_from_args(args, frames=frames)
    result = simulate(*scene, throw=False, progress=not args.no_progress, timed=True)
    summary = scene.summary(result)
    # The outputs were checked before the run; should one still fail (a full disk, a folder
    # removed meanwhile), the others are written and the summary is printed all the same.
    errors = {}
    output = output_writer(errors)
    _write_run(args, output, summary, scene, result)
    profile = None
    if (args.profile_csv or args.plot) and not np.all(np.isfinite(np.asarray(result.state.x))):
        for option in ("--profile-csv", "--plot"):
            if getattr(args, option[2:].replace("-", "_")):
                errors[option] = "not written: the final positions are not finite (see status_text)"
    elif args.profile_csv or args.plot:
        xs, h = profile = scene.final_profile(result.state)
        if args.profile_csv:
            output("--profile-csv", lambda: tables.write_profile_csv(args.profile_csv, xs, h,
                                                                     scene.profile_header(result, _source())))
    if args.plot and profile is not None:
        from .studies.plots import plot_run

        output("--plot", lambda: plot_run(scene, result, args.plot, profile=profile))
    if args.gif:
        from .studies.plots import animate_run

        output("--gif", lambda: animate_run(scene, result, args.gif))
    if errors:
        summary["output_errors"] = errors
    bad = print_json(summary, args.json)
    return 0 if result.ok and not bad and not errors else 1


def _avalanche_options(args) -> dict:
    """The avalanche builder's keyword arguments from ``run avalanche``'s options."""
    for option, value in (("--dim", args.dim not in (None, 2)), ("--width", args.width is not None),
                          ("--side-walls", args.side_walls is not None),
                          ("--slope", args.slope is not None), ("--aspect", args.aspect is not None),
                          ("--sampling", args.sampling not in (None, "lattice"))):
        if value:
            raise ValueError(f"{option} does not apply to the avalanche scene (a 2D section, lattice-sampled)")
    if args.ppc is not None and (int(args.ppc) != args.ppc or args.ppc < 1):
        raise ValueError(f"--ppc must be a positive integer for the avalanche, got {args.ppc}")
    if args.frames is not None and args.frames < 2:
        raise ValueError("--frames must be >= 2 for the avalanche (its fields are sampled on the frames), "
                         f"got {args.frames}")
    if args.terrain is not None:
        from .boundary import Terrain

        Terrain.from_csv(args.terrain)  # a bad file fails here, before anything compiles
    t_end = args.t_end if args.t_end is not None else (20.0 if args.quick else 100.0)
    frames = args.frames if args.frames is not None else max(2, int(round(t_end)))
    kw = {"dx": args.dx if args.dx is not None else (2.0 if args.quick else 1.0), "t_end": t_end, "frames": frames,
          "snow": args.snow, "dtype": args.dtype or "float32", **dict(parse_set(item) for item in args.set)}
    if args.ppc is not None:
        kw["ppc"] = int(args.ppc)
    if args.obstacle is not None:
        if args.station is None:
            raise ValueError("--obstacle needs --station X, the obstacle's place along the path")
        kw["obstacle"] = (args.station, args.obstacle)
    return kw


def _run_avalanche(args) -> int:
    """``run avalanche``: S6 on its terrain, the fields avalanche engineers use."""
    kw = _avalanche_options(args)
    check_run_outputs(args, args.frames or 1)
    use_dtype(args.dtype)
    from . import tables
    from .scenes.avalanche import avalanche
    from .studies.avalanche import avalanche_summary, fields_header, run_avalanche

    scene = avalanche(args.terrain, **kw)
    result, fields = run_avalanche(scene, station=args.station, progress=not args.no_progress)
    summary = avalanche_summary(scene, result, fields, args.snow)
    errors = {}
    output = output_writer(errors)
    _write_run(args, output, summary, scene, result)
    if args.profile_csv:
        output("--profile-csv", lambda: tables.write_table(args.profile_csv, fields.columns(),
                                                           fields_header(scene, result, fields, _source())))
    if args.plot or args.gif:
        from .studies.plots import animate_avalanche, plot_avalanche

        if args.plot:
            title = (f"S6 avalanche, {args.snow} snow, dx = {scene.config.grid.dx:g} m, "
                     f"mu_w = {float(scene.params.mu_w):g}")
            output("--plot", lambda: plot_avalanche(fields, args.plot, title=title))
        if args.gif:
            output("--gif", lambda: animate_avalanche(fields, args.gif))
    if errors:
        summary["output_errors"] = errors
    bad = print_json(summary, args.json)
    return 0 if result.ok and not bad and not errors else 1


def _run_scene(text: str) -> str:
    if text == "avalanche" or text in SCENE_NAMES or is_experiment_file(text):
        return text
    raise argparse.ArgumentTypeError(f"must be one of {', '.join(SCENE_NAMES + ('avalanche',))} or an experiment "
                                     f"file (.toml), got {text!r}")


def _element(args) -> int:
    use_dtype("float64")  # a single point: double precision costs nothing
    from .params import Params
    from .studies.element import element_test

    check_repeated_keys(args.set, "--set")
    if args.plot:
        check_figure_file(args.plot, "--plot")
    params = Params.create(**dict(parse_set(item) for item in args.set))
    history = element_test(args.test, params, rate=args.rate, pressure=args.pressure, steps=args.steps,
                           strain=args.strain, dim=args.dim)
    final = history.final()
    error = history.failure()
    if error:
        final["error"] = error
    bad = print_json(final, args.json)
    if args.plot and not error:
        from .studies.plots import plot_stress_path

        plot_stress_path(history, params, args.plot, title=f"{args.test}, rate {args.rate:g} 1/s")
    return 1 if (error or bad) else 0


def _validation_options(args) -> dict:
    """The bagnold studies' own options (--xpic, --slopes, --divisions) as ``run_study``'s."""
    options = {}
    for key in ("xpic", "slopes", "divisions"):
        value = getattr(args, key)
        if value is None:
            continue
        if args.study != "bagnold" and not (key == "xpic" and args.study == "bagnold-from-rest"):
            raise ValueError(f"--{key} applies to the bagnold study, not {args.study}")
        if key == "xpic":
            options[key] = value
        else:
            try:
                items = [float(v) if key == "slopes" else int(v) for v in value.split(",")]
            except ValueError:
                raise ValueError(f"--{key} must be comma-separated numbers, got {value!r}") from None
            options[key] = tuple(items)
    return options


def _validate(args) -> int:
    options = _validation_options(args)
    use_dtype(args.dtype)
    from .studies.validation import run_study

    out = run_study(args.study, quick=args.quick, plot_dir=args.plot, alpha=args.alpha, **options)
    print(json.dumps(out) if args.json else json.dumps(out, indent=2))
    return 0


def _bench(args) -> int:
    from .studies.bench import run_bench

    result = run_bench(args.grad, args.quick, args.dim, args.dtype, args.repeat, args.particles, args.scene,
                       steps=args.steps, active_nodes=args.active_nodes)
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m jaxmpm", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a reference scene (docs/scenes.md)")
    run.add_argument("scene", type=_run_scene, metavar="SCENE|EXPERIMENT.toml",
                     help=f"a scene ({', '.join(SCENE_NAMES + ('avalanche',))}) or an experiment file "
                          "(docs/experiments.md)")
    add_scene_arguments(run, scene_choices=False)
    avalanche = run.add_argument_group("avalanche (S6) only")
    avalanche.add_argument("--terrain", default=None, metavar="FILE.csv",
                           help="terrain polyline x_m,z_m (default: the shipped ISeeSnow CoulombOnly centre line)")
    avalanche.add_argument("--snow", choices=("dry", "wet"), default="dry", help="the snow's parameter set")
    avalanche.add_argument("--station", type=float, default=None, metavar="X",
                           help="obstacle station x, m, for the force history (default: half way along the reach)")
    avalanche.add_argument("--obstacle", type=float, default=None, metavar="HEIGHT",
                           help="simulate a rigid vertical wall this high (m) at --station and report the force on it")
    avalanche.add_argument("--quick", action="store_true", help="a coarse, short run (dx = 2 m, 20 s)")
    run.add_argument("--frames", type=int, default=None, help="output frames (default 0, or 40 with --gif)")
    run.add_argument("--out", default=None, help="HDF5 output file")
    run.add_argument("--profile-csv", default=None, help="write the final deposit profile h(x) as CSV")
    run.add_argument("--plot", default=None, metavar="FIG.png", help="final deposit and profile")
    run.add_argument("--gif", default=None, metavar="ANIM.gif", help="animation of the frames")
    run.add_argument("--ply", default=None, metavar="DIR",
                     help="the particles as binary PLY point clouds (ParaView): initial, every frame, final")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--json", action="store_true", help="print one JSON object")

    element = sub.add_parser("element", help="drive one material point (a lab element test)")
    element.add_argument("test", choices=("isotropic", "simple-shear", "triaxial"))
    element.add_argument("--rate", type=float, default=1.0, help="applied engineering strain rate, 1/s")
    element.add_argument("--pressure", type=float, default=None,
                         help="confining pressure p, Pa, at most p_c0 (default p_c0/2: 50 Pa at the defaults)")
    element.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    element.add_argument("--steps", type=int, default=2000)
    element.add_argument("--strain", type=float, default=None, help="total strain (default 0.5 shear, 0.1 else)")
    element.add_argument("--dim", type=int, default=2, choices=(2, 3))
    element.add_argument("--json", action="store_true", help="print one JSON object")
    element.add_argument("--plot", default=None, metavar="FILE.png", help="stress path against the yield surface")

    validate = sub.add_parser("validate", help="run a validation study (docs/validation.md)")
    validate.add_argument("study", choices=("bagnold", "bagnold-from-rest", "convergence", "aspect-ratio", "cohesion",
                                            "speed-accuracy", "stability", "resolution", "cross-code", "avalanche",
                                            "side-walls"))
    validate.add_argument("--quick", action="store_true", help="a reduced, faster version")
    validate.add_argument("--json", action="store_true", help="print one JSON object")
    validate.add_argument("--plot", default=None, metavar="DIR", help="write the study's figure into DIR")
    validate.add_argument("--alpha", type=float, default=None,
                          help="AFLIP blend for the bagnold studies (default 0.95)")
    validate.add_argument("--xpic", type=int, default=None,
                          help="XPIC order on the FLIP part, bagnold studies only (0: off)")
    validate.add_argument("--slopes", default=None, help="comma-separated slopes (deg), bagnold only")
    validate.add_argument("--divisions", default=None, help="comma-separated h/dx, bagnold only")
    validate.add_argument("--dtype", choices=DTYPES, default="float32",
                          help="precision of the study's runs (default float32, the run command's default)")

    bench = sub.add_parser("bench", help="time the engine and print JSON")
    bench.add_argument("--scene", choices=SCENES, default="block",
                       help="block: 2D Hencky block, 10k particles; column: S2 collapse, full model; s4: the "
                            "cohesive collapse S4 at dx = 4 mm (beta = 0), full model")
    bench.add_argument("--quick", action="store_true", help="a small, fast case")
    bench.add_argument("--json", action="store_true", help="print one line of JSON")
    bench.add_argument("--dim", type=int, default=2, choices=(2, 3))
    bench.add_argument("--dtype", choices=DTYPES, default="float32")
    bench.add_argument("--repeat", type=int, default=3, help="timed runs; the median is reported")
    bench.add_argument("--particles", type=int, default=None, help="override the particle count")
    bench.add_argument("--grad", action="store_true", help="benchmark reverse-mode gradients instead")
    bench.add_argument("--active-nodes", type=int, default=None, metavar="K",
                       help="the sparse grid with K node slots instead of the dense grid (forward run)")
    bench.add_argument("--steps", type=int, default=None,
                       help="steps: for --grad (default 5000); for the forward run, a cap (default: until t_end)")
    for command in sub.choices.values():
        add_threads_argument(command)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        apply_threads(args.threads)
        handler = {"run": _run, "element": _element, "validate": _validate, "bench": _bench}[args.command]
        return handler(args)
    except ValueError as err:  # invalid input: a clear message, not a traceback
        parser.exit(2, f"python -m jaxmpm {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
