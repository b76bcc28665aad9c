"""Cost against size (issue 12, goal 3): forward throughput and peak memory from 10^3 to 10^6
particles, 2D and 3D, on the machine this runs on.

Each case runs ``python -m jaxmpm bench --json --particles N --steps S`` in its own process, so
that the peak resident memory (``peak_rss_mb``) belongs to that size alone. The step count is
capped so that every size costs about the same wall time (``S = clip(1.5e7 / N, 10, 1000)``); the
``BUDGET`` status bit that a capped run sets is expected. ``xla_temp_mb`` is the scratch memory
XLA plans for the compiled rollout, the part of the memory that belongs to the algorithm rather
than to the Python process and the loaded libraries.

    python docs/scripts/cost_vs_size.py            # about 12 minutes on 2 cores
    python docs/scripts/cost_vs_size.py --quick    # 10^3 to 10^4 only, a minute

writes docs/results/cost_vs_size.json and docs/figures/cost_vs_size.png.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]
CASES = {  # label: bench arguments
    "2D Hencky block": ["--scene", "block", "--dim", "2"],
    "3D Hencky block": ["--scene", "block", "--dim", "3"],
    "2D column, full model (S2)": ["--scene", "column"],
}
SIZES = (1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000)


def run_case(args: list[str], n: int, repeat: int) -> dict:
    steps = int(min(1000, max(10, round(1.5e7 / n))))
    cmd = [sys.executable, "-m", "jaxmpm", "bench", "--json", "--particles", str(n), "--steps", str(steps),
           "--repeat", str(repeat), *args]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def plot(results: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for label, rows in results["cases"].items():
        n = [r["n_particles"] for r in rows]
        ax1.loglog(n, [r["particle_steps_per_s"] for r in rows], "o-", label=label)
        (line,) = ax2.loglog(n, [r["peak_rss_mb"] for r in rows], "o-", label=f"{label}: process peak")
        ax2.loglog(n, [max(r["xla_temp_mb"], 0.05) for r in rows], "s--", color=line.get_color(),
                   label=f"{label}: XLA scratch")
    ax1.set_xlabel("particles")
    ax1.set_ylabel("particle-steps per second")
    ax1.set_title(f"forward throughput, float32, {results['device']}", fontsize=9)
    ax1.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=8)
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
    parser.add_argument("--out", type=pathlib.Path, default=ROOT / "docs/results/cost_vs_size.json")
    parser.add_argument("--figure", type=pathlib.Path, default=ROOT / "docs/figures/cost_vs_size.png")
    args = parser.parse_args()
    sizes = SIZES[:3] if args.quick else SIZES
    results = {"sizes": list(sizes), "cases": {}}
    for label, case in CASES.items():
        rows = []
        for n in sizes:
            row = run_case(case, n, args.repeat)
            rows.append(row)
            print(f"{label:28s} n={row['n_particles']:>8d} nodes={row['grid_nodes']:>8d} steps={row['n_steps']:>5d} "
                  f"{row['particle_steps_per_s'] / 1e6:6.2f} M/s  rss {row['peak_rss_mb']:7.1f} MB  "
                  f"xla {row['xla_temp_mb']} MB  compile {row['compile_s']} s", flush=True)
        results["cases"][label] = rows
    results["device"] = rows[-1]["device"]
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    plot(results, args.figure)
    print(f"wrote {args.out} and {args.figure}")


if __name__ == "__main__":
    main()
