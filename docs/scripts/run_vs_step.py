"""A whole run against its step (docs/performance.md, "At a glance"), measured in one go, each
command alone on the machine:

- ``python -m jaxmpm run cohesive-collapse --dx 0.004 --set pc0=500 --set xi=50 --set beta=B``
  for β = 0 and 0.25, on one core (the default) and with ``--threads all`` (XLA's pool, what the
  command line ran before it pinned itself);
- ``python -m jaxmpm bench --scene s4`` and ``--scene column``: a user's run next to the steps
  alone, on one core and with ``--threads all``;
- ``python -m jaxmpm bench --grad``.

    python docs/scripts/run_vs_step.py [--out docs/results/run_vs_step.json]

Prints one JSON object and writes it to ``--out``.
"""

import argparse
import json
import subprocess
import sys
import time


def _json(argv):
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "jaxmpm", *argv], capture_output=True, text=True, timeout=1800)
    wall = time.perf_counter() - start
    if out.returncode not in (0, 1):
        raise RuntimeError(f"{argv}: {out.stderr[-2000:]}")
    result = json.loads([line for line in out.stdout.splitlines() if line.strip().startswith("{")][-1])
    return {"argv": " ".join(argv), "process_wall_s": round(wall, 2), **result}


RUN_KEYS = ("n_particles", "n_steps", "runout", "compile_s", "run_s", "status")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    runs = []
    for threads in ("1", "all"):
        for beta in ("0", "0.25"):
            r = _json(["run", "cohesive-collapse", "--dx", "0.004", "--set", "pc0=500", "--set", "xi=50", "--set",
                       f"beta={beta}", "--no-progress", "--json", "--threads", threads])
            runs.append({"argv": r["argv"], "process_wall_s": r["process_wall_s"],
                         **{k: r[k] for k in RUN_KEYS if k in r}})
    benches = [_json(["bench", "--scene", scene, "--json", "--threads", threads])
               for scene in ("s4", "column") for threads in ("1", "all")]
    grad = _json(["bench", "--grad", "--json"])
    result = {"runs": runs, "bench": benches, "grad": grad}
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
