"""Cost against size: forward throughput and peak memory from 10^3 to 10^6 particles, 2D and
3D, on the machine this runs on, with XLA on all cores or on one pinned thread.

Each case runs ``python -m jaxmpm bench --json --particles N --steps S`` in its own process, so
that the peak resident memory (``peak_rss_mb``) belongs to that size alone. The step count is
capped so that every size costs about the same wall time (``S = clip(1.5e7 / N, 10, 1000)``); the
``BUDGET`` status bit that a capped run sets is expected. ``xla_temp_mb`` is the scratch memory
XLA plans for the compiled rollout, the part of the memory that belongs to the algorithm rather
than to the Python process and the loaded libraries.

    python docs/scripts/cost_vs_size.py                   # about 10 minutes on 2 cores
    python docs/scripts/cost_vs_size.py --threads 1       # XLA on one thread, pinned to core 0
    python docs/scripts/cost_vs_size.py --quick           # 10^3 to 10^4 only, a minute

writes docs/results/cost_vs_size[_1thread].json; ``--plot-only`` draws
docs/figures/cost_vs_size.png from the results present, the step before its
redesign (docs/results/cost_vs_size_issue12.json) beside today's.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys

from jaxmpm.threads import SINGLE_THREAD_FLAGS

ROOT = pathlib.Path(__file__).resolve().parents[2]
CASES = {  # name: (label, bench arguments)
    "block2d": ("2D Hencky block", ["--scene", "block", "--dim", "2"]),
    "block3d": ("3D Hencky block", ["--scene", "block", "--dim", "3"]),
    "column": ("2D column, full model (S2)", ["--scene", "column"]),
}
SIZES = (1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000)


RESULTS = {  # file: line style in the figure
    "cost_vs_size_issue12.json": ("the step before its redesign, all cores", ":"),
    "cost_vs_size.json": ("now, all cores", "-"),
    "cost_vs_size_1thread.json": ("now, one thread", "--"),
}


def run_case(args: list[str], n: int, repeat: int, threads: int | None) -> dict:
    steps = int(min(1000, max(10, round(1.5e7 / n))))
    cmd = [sys.executable, "-m", "jaxmpm", "bench", "--json", "--particles", str(n), "--steps", str(steps),
           "--repeat", str(repeat), *args]
    env = dict(os.environ)
    if threads == 1:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {SINGLE_THREAD_FLAGS}".strip()
        cmd = ["taskset", "-c", "0", *cmd]
    else:
        cmd.extend(["--threads", "all"])
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def plot(directory: pathlib.Path, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    colors = dict(zip((label for label, _ in CASES.values()), ("C0", "C1", "C2")))
    device = ""
    for name, (variant, style) in RESULTS.items():
        if not (directory / name).exists():
            continue
        results = json.loads((directory / name).read_text())
        device = results["device"]
        for label, rows in results["cases"].items():
            n = [r["n_particles"] for r in rows]
            ax1.loglog(n, [r["particle_steps_per_s"] for r in rows], "o" + style, color=colors[label],
                       label=f"{label}: {variant}", ms=3)
            if name == "cost_vs_size_1thread.json":
                ax2.loglog(n, [r["peak_rss_mb"] for r in rows], "o-", color=colors[label],
                           label=f"{label}: process peak")
                ax2.loglog(n, [max(r["xla_temp_mb"], 0.05) for r in rows], "s--", color=colors[label],
                           label=f"{label}: XLA scratch")
    ax1.set_xlabel("particles")
    ax1.set_ylabel("particle-steps per second")
    ax1.set_title(f"forward throughput, float32, {device}", fontsize=9)
    ax1.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=6, loc="lower left", ncol=1, framealpha=0.6)
    ax2.set_xlabel("particles")
    ax2.set_ylabel("memory (MB)")
    ax2.set_title("peak resident memory and XLA's planned scratch", fontsize=9)
    ax2.grid(True, which="both", alpha=0.3)
    ax2.legend(fontsize=7)
    fig.savefig(path, dpi=130)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--threads", type=int, choices=(1,), default=None,
                        help="1: XLA on one thread pinned to core 0 (default: XLA's own, every core)")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated cases, from {','.join(CASES)}")
    parser.add_argument("--plot-only", action="store_true", help="draw the figure from the stored results")
    parser.add_argument("--figure", type=pathlib.Path, default=ROOT / "docs/figures/cost_vs_size.png")
    args = parser.parse_args()
    directory = ROOT / "docs/results"
    if args.plot_only:
        plot(directory, args.figure)
        print(f"wrote {args.figure}")
        return
    out = directory / ("cost_vs_size_1thread.json" if args.threads == 1 else "cost_vs_size.json")
    sizes = SIZES[:3] if args.quick else SIZES
    results = {"sizes": list(sizes), "threads": args.threads or "all", "cases": {}}
    for name in args.cases.split(","):
        if name not in CASES:
            parser.error(f"--cases: unknown case {name!r}; choose from {','.join(CASES)}")
        label, case = CASES[name]
        rows = []
        for n in sizes:
            row = run_case(case, n, args.repeat, args.threads)
            rows.append(row)
            print(f"{label:28s} n={row['n_particles']:>8d} nodes={row['grid_nodes']:>8d} steps={row['n_steps']:>5d} "
                  f"{row['particle_steps_per_s'] / 1e6:6.2f} M/s  rss {row['peak_rss_mb']:7.1f} MB  "
                  f"xla {row['xla_temp_mb']} MB  compile {row['compile_s']} s", flush=True)
        results["cases"][label] = rows
        if out.exists():  # keep the cases of an earlier run that this one did not measure
            results["cases"] = {**json.loads(out.read_text())["cases"], **results["cases"]}
        results["device"] = rows[-1]["device"]
        out.write_text(json.dumps(results, indent=1) + "\n")  # after every case
    plot(directory, args.figure)
    print(f"wrote {out} and {args.figure}")


if __name__ == "__main__":
    main()
