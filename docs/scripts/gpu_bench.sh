#!/usr/bin/env bash
# The standard GPU benchmark in one short go: the device JAX sees, then one JSON line per case.
# The 3D block is the published JAX MPM figure's size (2.7 million particles, float32, about
# 1.2e8 particle-steps/s on one GPU), capped at a few hundred steps so that it stays short;
# float64 and the 2D full-model column beside it; the reverse-mode gradient; one S4 forward run
# at dx = 4 mm (issue 28's goal of 5 s) and a vmap sweep of S4 over β (what a GPU buys a
# calibration: many runs at once). Every case has its own time limit; a case that fails or runs
# out prints a JSON line saying so and the rest go on. Nothing in CI runs this.
# Usage, from the repository root with the project importable:
#     bash docs/scripts/gpu_bench.sh > gpu_bench.jsonl
# Sizes can be made smaller for a dry run on a CPU: P3D, STEPS3D, SWEEP_N, CASE_LIMIT_S.
set -uo pipefail
P3D=${P3D:-2700000}
STEPS3D=${STEPS3D:-300}
SWEEP_N=${SWEEP_N:-64}
LIMIT=${CASE_LIMIT_S:-120}
DATA=experiments_data/synthetic/S4_beta0.25.csv
SWEEP_OUT=${TMPDIR:-/tmp}/gpu_bench_sweep.h5

case_() {  # case_ NAME COMMAND...: the command's last line (its JSON), or a line saying why not
    local name=$1; shift
    local start out rc
    start=$(date +%s.%N)
    out=$(timeout "$LIMIT" "$@" 2>"${TMPDIR:-/tmp}/gpu_bench_$name.err")
    rc=$?
    local wall
    wall=$(python3 -c "import time; print(round(time.time() - $start, 1))")
    if [ $rc -eq 0 ]; then
        python3 -c "import json, sys; d = json.loads(sys.argv[1]); d.update(case=sys.argv[2], wall_s_command=float(sys.argv[3])); print(json.dumps(d))" \
            "$(printf '%s\n' "$out" | tail -n 1)" "$name" "$wall"
    else
        python3 -c "import json, sys; print(json.dumps({'case': sys.argv[1], 'rc': int(sys.argv[2]), 'wall_s_command': float(sys.argv[3]), 'error': sys.argv[4][-600:]}))" \
            "$name" "$rc" "$wall" "$(tail -c 600 "${TMPDIR:-/tmp}/gpu_bench_$name.err")"
    fi
}

python3 -c "import jax; print({'devices': [str(d) for d in jax.devices()], 'jax': jax.__version__})" >&2
case_ block3d_f32 python3 -m jaxmpm bench --json --threads all --dim 3 --particles "$P3D" --steps "$STEPS3D" --repeat 2
case_ block3d_f64 python3 -m jaxmpm bench --json --threads all --dim 3 --particles "$P3D" --steps "$STEPS3D" --repeat 2 --dtype float64
case_ column_f32 python3 -m jaxmpm bench --json --threads all --scene column --repeat 3
case_ column_f64 python3 -m jaxmpm bench --json --threads all --scene column --repeat 3 --dtype float64
case_ grad python3 -m jaxmpm bench --json --threads all --grad --repeat 2
case_ s4_dx4mm python3 -m jaxmpm run cohesive-collapse --json --threads all --no-progress --dx 0.004 --set pc0=500 --set xi=50
case_ s4_sweep python3 -m calibration sweep --json --threads all --no-progress --scene cohesive-collapse --data "$DATA" \
    --dx 0.004 --set pc0=500 --set xi=50 --over "beta=0:0.5:$SWEEP_N" --mode vmap --chunk "$SWEEP_N" --out "$SWEEP_OUT" --overwrite
