"""Command line: ``python -m jaxmpm {run,bench} ...``."""

from __future__ import annotations

import argparse
import json
import sys
import time


def _run(args) -> int:
    import jax
    import numpy as np

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from . import io, simulate
    from .scenes import falling_block
    from .state import describe_status

    values = dict(_parse_set(item) for item in args.set)
    config, state, params = falling_block(
        n_particles=args.particles, dim=args.dim, t_end=args.t_end, frames=args.frames, dtype=args.dtype, **values
    )
    start = time.perf_counter()
    result = simulate(config, state, params, throw=False)
    jax.block_until_ready(result.state.x)
    wall = time.perf_counter() - start
    path = io.write_h5(args.out, result, config, params, attrs={"scene": "elastic-block"}) if args.out else None
    x = np.asarray(result.state.x)
    summary = {
        "scene": "elastic-block",
        "n_particles": int(state.n_particles),
        "n_steps": int(result.state.steps),
        "dx": config.grid.dx,
        "t_end": config.t_end,
        "x_min": float(x[:, 0].min()),
        "x_max": float(x[:, 0].max()),
        "y_max": float(x[:, -1].max()),
        "status": result.status,
        "status_text": describe_status(result.status),
        "wall_s": round(wall, 3),
        "out": str(path) if path else None,
    }
    print(json.dumps(summary) if args.json else json.dumps(summary, indent=2))
    return 0 if result.ok else 1


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

    run = sub.add_parser("run", help="run the default scene (an elastic block bouncing on a floor)")
    run.add_argument("--particles", type=int, default=2_500, help="number of particles (default 2500)")
    run.add_argument("--dim", type=int, default=2, choices=(2, 3))
    run.add_argument("--t-end", type=float, default=0.39, help="end time in s (default 0.39)")
    run.add_argument("--frames", type=int, default=20, help="number of output frames (default 20)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="material parameter")
    run.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    run.add_argument("--out", default="run.h5", help="HDF5 output file ('' for none; default run.h5)")
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
        from . import bench

        bench.main(args)
        return 0
    except ValueError as err:  # invalid input: a clear message, not a traceback
        parser.exit(2, f"python -m jaxmpm {args.command}: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
