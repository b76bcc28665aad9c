"""The command line: `run` writes a complete HDF5 file and a JSON summary; `bench` prints the
documented JSON fields (timings are reported, never asserted)."""

import json
import pathlib

import numpy as np
import pytest
from helpers import cli, main_exit

import jaxmpm as jm


def _cli(*args, cwd=None):
    return cli("jaxmpm", *args, cwd=cwd)


def test_run_writes_h5_csv_and_json(tmp_path):
    path, csv = tmp_path / "run.h5", tmp_path / "deposit.csv"
    out = _cli("run", "cohesive-collapse", "--dx", "0.0111", "--t-end", "0.05", "--frames", "2", "--out", str(path),
               "--profile-csv", str(csv), "--json", "--no-progress", "--set", "beta=0.1",
               "--ply", str(tmp_path / "ply"))
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert [pathlib.Path(f).name for f in summary["ply"]] == ["initial.ply", "frame_00000.ply", "frame_00001.ply",
                                                              "final.ply"]
    assert (tmp_path / "ply" / "final.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    for key in ("scene", "n_particles", "n_steps", "dx", "t_end", "x_min", "x_max", "y_max", "runout", "status",
                "compile_s", "run_s"):
        assert key in summary
    assert summary["scene"] == "cohesive-collapse" and summary["status"] == 0 and summary["t_end"] == 0.05
    assert abs(summary["runout"] - (summary["x_max"] - 0.089)) < 1e-6
    data = jm.io.read_h5(path)
    assert len(data["frames"]) == 2 and abs(data["attrs"]["param/beta"] - 0.1) < 1e-7
    attrs = data["attrs"]  # the scene's description, SceneInfo.to_dict()
    assert (attrs["length"], attrs["height"], attrs["front0"]) == (0.089, 0.089, 0.089) and "L" not in attrs
    lines = csv.read_text().splitlines()
    assert lines[0].startswith("# experiment: cohesive-collapse (synthetic") and "x_m,h_m" in lines
    scene = json.loads(next(line for line in lines if line.startswith("# scene: "))[len("# scene: "):])
    assert scene["length"] == 0.089 and scene["sampling"] == "jitter" and "L" not in scene
    rows = np.loadtxt(csv, delimiter=",", comments="#", skiprows=lines.index("x_m,h_m") + 1)
    assert rows.shape[1] == 2 and np.all(rows[:, 1] >= 0) and np.all(np.diff(rows[:, 0]) > 0)


@pytest.mark.parametrize("scene", ["gates-collapse", "slope-collapse", "aspect-ratio", "elastic-block"])
def test_run_every_scene_on_tiny_settings(scene):
    args = ["run", scene, "--t-end", "0.01", "--json", "--no-progress"]
    if scene != "elastic-block":
        args += ["--dx", "0.02"]
    out = _cli(*args)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["status"] == 0


@pytest.mark.parametrize("argv, message", [
    (["run", "cohesive-collapse", "--set", "nu=0.7"], "nu must be in (-1, 0.5)"),
    (["run", "cohesive-collapse", "--dx", "-1"], "dx must be > 0"),
    (["run", "cohesive-collapse", "--slope", "10"], "--slope applies to slope-collapse"),
    # A grid cell larger than the column ran one particle outside the body and exited 0.
    (["run", "cohesive-collapse", "--dx", "10"], "dx must be at most the column's thinnest side (0.089 m)"),
    # A zero option was taken as "not given" (the run went to the scene's 0.39 s).
    (["run", "elastic-block", "--t-end", "0"], "t_end must be > 0"),
    (["bench", "--grad", "--steps", "0"], "steps must be a positive int, got 0"),
])
def test_run_rejects_bad_input(argv, message, capsys):
    """In this process (a subprocess would spend its time importing JAX); the refusal of a real
    process, its exit status and its stderr, is the experiment file's below."""
    code, err = main_exit("jaxmpm", argv, capsys)
    assert code == 2 and message in err, err



def test_run_refuses_an_experiment_file_naming_a_missing_measurement(tmp_path):
    """`run FILE.toml` with a [[profile]] whose file is not there ran and exited 0; now it is
    refused before anything compiles, at the key's line, as every command refuses it."""
    path = tmp_path / "column.toml"
    path.write_text('[geometry]\nlength = "60 mm"\nheight = "90 mm"\n[numerics]\ndx = "15 mm"\nt_end = "0.01 s"\n'
                    '\n[[profile]]\nfile = "missing.csv"\n')
    out = _cli("run", str(path), "--json", "--no-progress", cwd=tmp_path)
    assert out.returncode == 2 and out.stdout == "", out.stderr
    assert out.stderr.strip().endswith(f"{path}:9: [[profile]] #1 file: no such file: {tmp_path / 'missing.csv'}")

def test_bench_prints_the_documented_fields():
    out = _cli("bench", "--quick", "--json", "--particles", "256", "--repeat", "1")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    for key in ("scene", "dim", "dtype", "n_particles", "n_steps", "compile_s", "run_s",
                "particle_steps_per_s", "step_compile_s", "step_run_s", "step_particle_steps_per_s",
                "run_over_step", "peak_rss_mb", "device", "cores"):
        assert key in result
    assert result["dtype"] == "float32" and result["n_steps"] > 0 and result["status"] == 0
    # The ratio is of the two throughputs (the times are rounded to 0.1 ms, too coarse for this tiny
    # run); the command line ran on one core.
    ratio = result["particle_steps_per_s"] / result["step_particle_steps_per_s"]
    assert result["run_over_step"] == pytest.approx(ratio, abs=1e-3)
    assert result["cores"] == 1


@pytest.mark.parametrize("module", ["jaxmpm", "calibration"])
def test_every_help_page_formats(module, capsys):
    """argparse formats help strings with %: a stray '95 % i...' broke ``python -m calibration --help``."""
    import argparse
    import importlib

    parser = importlib.import_module(f"{module}.__main__").build_parser()
    parser.format_help()
    subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert subparsers, "no subcommands found"
    for name, sub in subparsers[0].choices.items():
        assert sub.format_help(), name
