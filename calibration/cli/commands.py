"""The commands of ``python -m calibration`` (docs/cli.md): each parses its flags into the library's
objects (``calibration.cli.args``), refuses bad input before anything compiles (``calibration.cli.checks``),
makes its library call and prints the result.
"""

from __future__ import annotations

import json
import pathlib

from jaxmpm.cli import print_json, scene_dtype, scene_from_args
from jaxmpm.precision import use_dtype
from jaxmpm.scenes.collapse import S4_SIDE
from jaxmpm.threads import apply_threads

from ..batch.workers import Workers
from ..plots.fits import (
    fit_figures,
    law_figures,
    plot_coverage,
    plot_design,
    plot_ladder,
    sweep_figures,
    twin_landscape_figure,
)
from ..plots.posteriors import likelihood_figures
from .args import (
    coarse_setup,
    design_inclines,
    design_noise,
    experiments_of,
    finish,
    fit_fields,
    fit_meta,
    fit_options,
    fit_request,
    guard,
    h_stop_fields,
    h_stop_tables,
    parse_floats,
    parse_keys,
    parse_over,
    parse_pairs,
    parse_variants,
    posterior_options,
    setup_of,
    start_count,
    worker_count,
)
from .checks import check_args
from .parser import build_parser

__all__ = ["main"]


def _print_with_figures(out: dict, args, figures=None) -> int:
    """Print ``out`` with the paths ``figures()`` draws under --plot, if asked for (a failure is
    kept under "output_errors" and the JSON still prints); ``finish``'s exit status."""
    errors: dict[str, str] = {}
    if args.plot and figures is not None:
        out["figures"] = guard(errors, "--plot", figures)
    return finish(out, args, errors)


def _fit(args) -> int:
    from ..optim.report import fit_report
    from ..optim.search import fit_from_starts

    experiments = experiments_of(args)
    request = fit_request(args, experiments)
    starts = start_count(args, request.init)
    setup = setup_of(args, request.keys)
    h_stops = h_stop_tables(setup)  # reported beside the fit, never fitted: read before anything runs
    objective = setup.objective()
    init = objective.expand(request.init)  # a plain key's start for each experiment's own value
    # No --noise and none in the collapse files: the tables' stated noise for their blocks, the others estimated.
    options, judge = fit_options(args, request.noise if request.noise is not None else setup.stated_noise() or None)
    if args.grid_ladder is not None:
        return _fit_ladder(args, setup, objective, init, starts, options, judge, h_stops)
    coarse = coarse_setup(setup, args.coarse).objective() if starts > 1 and args.coarse is not None else None
    with Workers(worker_count(args)) as workers:
        result, found = fit_from_starts(objective, init, starts=starts, options=options, judge=judge, coarse=coarse,
                                        refine=args.refine, seed=args.search_seed, out=args.out, resume=args.resume,
                                        overwrite=args.overwrite, progress=not args.no_progress,
                                        meta=fit_meta(setup), workers=workers)
    out = {**fit_report(objective, result, found), **fit_fields(args, setup, init, found)}
    out.update(h_stop_fields(h_stops, out["params"]))
    return _print_with_figures(out, args, lambda: fit_figures(args.plot, objective, result))


def _fit_ladder(args, setup, objective, init, starts, options, judge, h_stops) -> int:
    """``fit --grid-ladder N``: the fits on N grids (``calibration.optim.ladder.grid_ladder``);
    the report is the finest fit's, with the ladder's point, interval and rungs under "ladder"."""
    from ..optim.ladder import grid_ladder
    from ..optim.report import fit_report

    with Workers(worker_count(args)) as workers:
        ladder = grid_ladder(objective, init, rungs=args.grid_ladder, ratio=args.grid_check, starts=starts,
                             seed=args.search_seed, options=options, judge=judge, out=args.out,
                             overwrite=args.overwrite, progress=not args.no_progress, workers=workers)
    out = {**fit_report(objective, ladder.fit, None), "ladder": ladder.to_json(),
           **fit_fields(args, setup, init, ladder.search if starts > 1 else None)}
    out.update(h_stop_fields(h_stops, out["params"]))
    if starts > 1:
        out["search"] = {"starts": starts, "rung": "coarsest", "why": "the global search runs on the ladder's "
                                                                      "coarsest grid"}
    return _print_with_figures(out, args, lambda: fit_figures(args.plot, objective, ladder.fit) + [
        str(plot_ladder(out["ladder"], pathlib.Path(args.plot) / "fit_ladder.png"))])


def _posterior(args) -> int:
    from ..inference.nuts import gaussian_prior
    from ..optim.record import read_record
    from ..optim.report import posterior_checks
    from ..problem.build import FitSetup

    options = posterior_options(args)
    record = read_record(args.fit_file)
    setup = record.header.get("meta", {}).get("setup")
    if setup is None:
        raise ValueError(f"{args.fit_file}: records no setup to build its objective from (written by a library "
                         "call without one, or an older calibration): fit it with python -m calibration fit --out")
    setup = FitSetup.from_json(setup)
    try:
        gaussian_prior(record.keys, options.prior)
    except ValueError as err:
        raise ValueError(f"--{err}") from None
    use_dtype(setup.dtype)
    objective = setup.objective()
    if record.header.get("fingerprint") not in (None, json.loads(json.dumps(objective.fingerprint()))):
        raise ValueError(f"{args.fit_file}: its objective, built again from the files it names, differs from the "
                         "one it fitted (a data file or the scene changed since the fit)")
    with Workers(worker_count(args)) as workers:
        checks = posterior_checks(objective, record, options, noise=args.noise, workers=workers,
                                  progress=not args.json)
    out = {"fit": str(args.fit_file), "keys": list(record.keys), "params": record.theta, **checks.report}
    figures = lambda: likelihood_figures(args.plot, checks.profiles, posterior=checks.posterior,  # noqa: E731
                                         nuts=checks.nuts, emulated=checks.emulated)
    return _print_with_figures(out, args, figures)


def _sweep(args) -> int:
    from ..batch.sweep import sweep, sweep_points, write_sweep

    keys, thetas = sweep_points(parse_over(args.over, lhs=args.lhs is not None), args.lhs, seed=args.lhs_seed)
    setup = setup_of(args, keys)
    objective = setup.objective()
    objective.check_thetas(thetas, "--over")  # every member, before anything compiles
    if args.cluster is not None:
        from ..batch.cluster import cluster_sweep, write_cluster_sweep

        clustered = cluster_sweep(setup.objective, thetas, cluster=args.cluster, chunk=args.chunk,
                                  retries=args.retries, progress=not args.no_progress, objective=objective)
        result, out = clustered.sweep, clustered.to_json()
        lost = any(t["lost"] for t in clustered.tasks)
        write = lambda: write_cluster_sweep(args.out, clustered, objective) or True  # noqa: E731
    else:
        result = sweep(objective, thetas, chunk=args.chunk, mode=args.mode, progress=not args.no_progress)
        out, lost = {**result.to_json(), "n_members": result.n}, False
        write = lambda: write_sweep(args.out, result, objective) or True  # noqa: E731
    out.pop("residuals", None)  # per-member residual vectors go to --out, not to the terminal
    out["scene"] = setup.experiments[0].name
    errors: dict[str, str] = {}
    if args.out and guard(errors, "--out", write):
        out["out"] = str(args.out)
    if args.plot:
        out["figures"] = guard(errors, "--plot", lambda: sweep_figures(args.plot, result, keys))
    code = finish(out, args, errors)
    return 1 if lost else code  # a task lost after every attempt: the sweep did not run in full


def _twin(args) -> int:
    from ..studies.twin import twin, twin_landscape

    use_dtype(args.dtype)
    result = twin(quick=args.quick, noise=args.noise, keys=parse_keys(args.fit), method=args.method,
                  steps=args.steps, seed=args.noise_seed, dx=args.dx, ppc=args.ppc, t_end=args.t_end,
                  values=parse_pairs(args.set, "--set"), dtype=args.dtype or "float32", out=args.out,
                  resume=args.resume, overwrite=args.overwrite, progress=not args.no_progress,
                  reference_noise=args.reference_noise, threshold=args.threshold,
                  roundoff_samples=args.roundoff_samples, probe=args.probe,
                  restarts=args.restarts)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        out["figures"] = guard(errors, "--plot", lambda: fit_figures(args.plot, result.objective, result.fit,
                                                                         prefix="twin", truth=result.truth))
    if args.landscape:
        landscape = twin_landscape(result, args.landscape, progress=not args.no_progress)
        out["landscape"] = landscape.to_json()
        if args.plot:
            out["landscape"]["figure"] = str(twin_landscape_figure(args.plot, landscape))
    return finish(out, args, errors)


def _coverage(args) -> int:
    from ..studies.coverage import coverage

    result = coverage(args.seeds, noise=args.noise, keys=parse_keys(args.fit), quick=args.quick,
                      progress=not args.no_progress, dx=args.dx, values=parse_pairs(args.set, "--set"),
                      steps=args.steps)
    return _print_with_figures(result.to_json(), args,
                               lambda: [str(plot_coverage(result, pathlib.Path(args.plot) / "coverage.png"))])


def _design(args) -> int:
    from ..design.design import design

    use_dtype(scene_dtype(args))
    keys, variants = parse_keys(args.fit), parse_variants(args.variant)
    times = parse_floats(args.times, "--times") if args.times else None
    inclines = design_inclines(args.incline)
    scene = scene_from_args(args)
    with Workers(worker_count(args)) as workers:
        result = design(scene, keys, parse_pairs(args.at, "--at"), noise=design_noise(args),
                        tolerance=args.tolerance, times=times, variants=variants, inclines=inclines,
                        sampling_seeds=args.sampling_seeds, grid_ratio=args.grid_check or None, workers=workers)
    out = result.to_json()
    errors: dict[str, str] = {}
    if args.plot:
        out["figure"] = guard(errors, "--plot", lambda: str(plot_design(result, args.plot)))
    if not args.json:
        print("\n".join(result.lines()))
        return 1 if errors else 0
    return finish(out, args, errors)


def _law(args) -> int:
    from ..studies.scaling import fit_runout_law, named_law

    law, label = named_law(args.law, sand=args.sand)
    result = fit_runout_law(parse_floats(args.train, "--train"), parse_floats(args.test, "--test"),
                            parse_keys(args.fit), law=law, label=label, dx=args.dx, ppc=args.ppc,
                            values=parse_pairs(args.set, "--set"), steps=args.steps, out=args.out,
                            overwrite=args.overwrite, progress=not args.no_progress, jacobian=args.jacobian,
                            fd_step=args.fd_step, side_walls=args.side_walls)
    return _print_with_figures(result.to_json(), args, lambda: law_figures(args.plot, result, law))


def _flow_rule(args) -> int:
    from ..data.flow_rule import load_flow_rule, load_h_stop
    from ..data.incline import load_incline
    from ..plots.flow_rule import plot_flow_rule
    from ..studies.flow_rule import FLOW_RULE_KEYS, fit_flow_rule

    init, values = parse_pairs(args.init, "--init"), parse_pairs(args.set, "--set")
    keys, walls, h_stop = (parse_keys(args.fit) if args.fit else FLOW_RULE_KEYS), args.side_walls, None
    if str(args.table).endswith(".toml"):  # an incline experiment: its material, table, walls and [fit]; flags win
        experiment = load_incline(args.table)
        keys = parse_keys(args.fit) if args.fit else experiment.keys
        init = {**{k: v for k, v in experiment.init.items() if k in keys}, **init}
        values = {**experiment.material, **values}
        walls = walls if walls is not None else experiment.side_walls
        table = load_flow_rule(experiment.table_file)
        h_stop = None if experiment.h_stop_file is None else load_h_stop(experiment.h_stop_file)
    else:
        table = load_flow_rule(args.table)
    if walls is not None and walls.friction == "mu_w" and "mu_w" not in values and "mu_w" not in init:
        raise ValueError("--side-walls: the walls' friction is the parameter mu_w; give its value with --set mu_w=... "
                         "(or fit it: --fit ...,mu_w --init mu_w=...)")
    result = fit_flow_rule(table, keys, init=init, values=values, steps=args.steps, side_walls=walls, h_stop=h_stop)
    return _print_with_figures(result.to_json(), args, lambda: [str(plot_flow_rule(result, args.plot))])


def _bench(args) -> int:
    from ..studies.bench import bench

    use_dtype(args.dtype)
    kw = {"dx": S4_SIDE / 8, "t_end": 0.2} if args.quick else {"dx": args.dx}
    values = parse_pairs(args.set, "--set")
    result = bench(parse_keys(args.fit), repeat=args.repeat, dtype=args.dtype, values=values, **kw)
    return 1 if print_json(result.to_json(), args.json) else 0


COMMANDS = {"fit": _fit, "posterior": _posterior, "sweep": _sweep, "twin": _twin, "bench": _bench, "law": _law,
            "flow-rule": _flow_rule, "coverage": _coverage, "design": _design}


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        apply_threads(args.threads)
        check_args(args)
        return COMMANDS[args.command](args)
    except ValueError as err:
        parser.exit(2, f"python -m calibration {args.command}: error: {err}\n")
