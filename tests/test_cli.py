"""The command line: `run` writes a complete HDF5 file and a JSON summary; `bench` prints the
documented JSON fields (timings are reported, never asserted)."""

import json
import subprocess
import sys

import jaxmpm as jm


def _cli(*args, cwd=None):
    out = subprocess.run([sys.executable, "-m", "jaxmpm", *args], capture_output=True, text=True, cwd=cwd, timeout=600)
    return out


def test_run_writes_h5_and_json(tmp_path):
    path = tmp_path / "block.h5"
    out = _cli("run", "--particles", "64", "--t-end", "0.02", "--frames", "2", "--out", str(path), "--json",
               "--set", "E=2e6")
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["n_particles"] == 64 and summary["status"] == 0 and summary["t_end"] == 0.02
    data = jm.io.read_h5(path)
    assert len(data["frames"]) == 2 and data["attrs"]["param/E"] == 2e6
    assert data["attrs"]["config_json"]["t_end"] == 0.02


def test_run_rejects_bad_parameter(tmp_path):
    out = _cli("run", "--particles", "64", "--t-end", "0.01", "--set", "nu=0.7", "--out", "", cwd=tmp_path)
    assert out.returncode != 0 and "nu must be in (-1, 0.5)" in out.stderr


def test_bench_prints_the_documented_fields():
    out = _cli("bench", "--quick", "--json", "--particles", "256", "--repeat", "1")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    for key in ("scene", "dim", "dtype", "n_particles", "n_steps", "compile_s", "run_s",
                "particle_steps_per_s", "peak_rss_mb", "device"):
        assert key in result
    assert result["dtype"] == "float32" and result["n_steps"] > 0 and result["status"] == 0
