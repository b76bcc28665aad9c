#!/usr/bin/env bash
# The standard GPU benchmark in one short go (issue 12): the device JAX sees, then one JSON line
# per case. The 3D case is the published JAX MPM figure's size (2.7 million particles, float32,
# about 1.2e8 particle-steps/s on one GPU); float64 and the 2D full-model column beside it.
# Nothing in CI runs this. Usage, from the repository root with the project installed:
#     bash docs/scripts/gpu_bench.sh > gpu_bench.jsonl
set -euo pipefail
python -c "import jax; print({'devices': [str(d) for d in jax.devices()]})" >&2
python -m jaxmpm bench --json --dim 3 --particles 2700000 --repeat 3
python -m jaxmpm bench --json --dim 3 --particles 2700000 --repeat 3 --dtype float64
python -m jaxmpm bench --json --scene column --repeat 3
python -m jaxmpm bench --json --scene column --repeat 3 --dtype float64
python -m jaxmpm bench --json --grad --repeat 3
