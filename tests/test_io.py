"""HDF5 output: round trip of a tiny 2D run and atomic writing."""

import json

import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm import io


@pytest.fixture(scope="module")
def run():
    dx = 0.05
    grid = jm.Grid((20, 20), dx)
    cfg = jm.Config(
        grid=grid, t_end=0.02, max_steps=200, walls=(jm.Wall((0, 0.1), (0, 1)),),
        frame_times=(0.0, 0.01, 0.02),
    )
    x, vol = jm.seed_box((0.3, 0.1), (0.6, 0.4), dx, 2)
    state0 = jm.init_state(cfg, x, vol)
    params = jm.Params.create()
    return cfg, params, jm.simulate(cfg, state0, params)


def test_round_trip(run, tmp_path):
    cfg, params, result = run
    extra = {"scene": "box", "seed": 3, "tags": [1, 2]}
    path = io.write_h5(tmp_path / "run.h5", result, cfg, params, attrs=extra)
    assert path == tmp_path / "run.h5"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]  # no .tmp left behind

    data = io.read_h5(path)
    frames = data["frames"]
    assert len(frames) == len(cfg.frame_times)
    for k, frame in enumerate(frames):
        assert frame["t"] == cfg.frame_times[k]
        for key in ("x", "v", "p", "q"):
            np.testing.assert_array_equal(frame[key], np.asarray(result.frames[key][k]))
    assert frames[0]["x"].dtype == np.float64

    final = data["final"]
    np.testing.assert_array_equal(final["x"], np.asarray(result.state.x))
    np.testing.assert_array_equal(final["v"], np.asarray(result.state.v))
    p, q = jm.invariants(result.state.tau)
    np.testing.assert_array_equal(final["p"], np.asarray(p))
    np.testing.assert_array_equal(final["q"], np.asarray(q))

    attrs = data["attrs"]
    np.testing.assert_array_equal(attrs["frame_times"], cfg.frame_times)
    assert attrs["params_json"] == params.to_dict()
    for key, value in params.to_dict().items():
        assert attrs[f"param/{key}"] == value
    assert attrs["config_json"] == json.loads(json.dumps(cfg.to_dict()))
    assert attrs["config_json"]["t_end"] == cfg.t_end
    assert attrs["jaxmpm_version"] == jm.__version__
    assert attrs["status"] == result.status == 0
    assert attrs["status_text"] == []
    assert attrs["t_end"] == cfg.t_end
    assert attrs["steps"] == int(result.steps)
    assert (attrs["scene"], attrs["seed"], attrs["tags"]) == ("box", 3, [1, 2])


def test_overwrites_existing_file(run, tmp_path):
    cfg, params, result = run
    path = tmp_path / "run.h5"
    path.write_text("old")
    io.write_h5(str(path), result, cfg, params)
    assert io.read_h5(path)["attrs"]["status"] == 0


def test_failure_leaves_no_file(run, tmp_path, monkeypatch):
    cfg, params, result = run

    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(io, "invariants", fail)  # called after the temporary file is opened
    with pytest.raises(RuntimeError, match="disk full"):
        io.write_h5(tmp_path / "run.h5", result, cfg, params)
    assert list(tmp_path.iterdir()) == []


def test_failure_keeps_previous_file(run, tmp_path, monkeypatch):
    cfg, params, result = run
    path = io.write_h5(tmp_path / "run.h5", result, cfg, params)
    monkeypatch.setattr(io, "_dumps", lambda obj: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        io.write_h5(path, result, cfg, params)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]
    assert len(io.read_h5(path)["frames"]) == 3


def test_bad_arguments(run, tmp_path):
    cfg, params, result = run
    with pytest.raises(ValueError, match="path's parent directory"):
        io.write_h5(tmp_path / "missing" / "run.h5", result, cfg, params)
    with pytest.raises(ValueError, match="path is a directory"):
        io.write_h5(tmp_path, result, cfg, params)
    with pytest.raises(ValueError, match="attrs key 'status'"):
        io.write_h5(tmp_path / "run.h5", result, cfg, params, attrs={"status": 1})
    with pytest.raises(ValueError, match="result must be a Result"):
        io.write_h5(tmp_path / "run.h5", None, cfg, params)
    assert list(tmp_path.iterdir()) == []


def test_batched_result(run, tmp_path):
    """Arrays with a leading batch axis are stored as they are."""
    import jax

    cfg, params, result = run
    stack = lambda tree: jax.tree.map(lambda a: np.stack([a, a]), tree)  # noqa: E731
    frames = {k: np.stack([v, v], axis=0) for k, v in result.frames.items()}
    batched = jm.Result(stack(result.state), frames, result.frame_times, status=0)
    data = io.read_h5(io.write_h5(tmp_path / "b.h5", batched, cfg, stack(params)))
    assert data["frames"][1]["x"].shape == (2,) + result.frames["x"].shape[1:]
    np.testing.assert_array_equal(data["frames"][1]["x"][1], result.frames["x"][1])
    assert data["attrs"]["steps"].shape == (2,)
    assert data["attrs"]["params_json"]["E"] == [params.to_dict()["E"]] * 2


def test_initial_state_round_trip(run, tmp_path):
    """/initial holds the state the run started from, with the datasets of /final, particle for
    particle; a file written without it reads back with initial None."""
    cfg, params, result = run
    x, vol = jm.seed_box((0.3, 0.1), (0.6, 0.4), cfg.grid.dx, 2)
    state0 = jm.init_state(cfg, x, vol)
    data = io.read_h5(io.write_h5(tmp_path / "run.h5", result, cfg, params, initial=state0))
    initial, final = data["initial"], data["final"]
    assert set(initial) == set(final) >= {"x", "v", "p", "q", "vol"}
    np.testing.assert_array_equal(initial["x"], np.asarray(state0.x))
    np.testing.assert_array_equal(initial["vol"], np.asarray(state0.vol0))
    np.testing.assert_array_equal(initial["p"], 0.0)
    np.testing.assert_array_equal(final["x"], np.asarray(result.state.x))
    assert final["vol"].shape == final["p"].shape and np.all(final["vol"] > 0)
    assert io.read_h5(io.write_h5(tmp_path / "old.h5", result, cfg, params))["initial"] is None
    with pytest.raises(ValueError, match="initial must be a State"):
        io.write_h5(tmp_path / "bad.h5", result, cfg, params, initial=np.asarray(state0.x))
    fewer = state0.replace(x=state0.x[:-1])
    with pytest.raises(ValueError, match="not the same run's initial state"):
        io.write_h5(tmp_path / "bad.h5", result, cfg, params, initial=fewer)
    assert not (tmp_path / "bad.h5").exists()


def _read_ply(path):
    """A reader written from the PLY specification, independent of write_ply."""
    blob = path.read_bytes()
    end = blob.index(b"end_header\n") + len(b"end_header\n")
    lines = blob[:end].decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    n = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    kinds = {"double": "<f8", "float": "<f4"}
    props = [(line.split()[2], kinds[line.split()[1]]) for line in lines if line.startswith("property")]
    rows = np.frombuffer(blob[end:], dtype=np.dtype(props), count=n)
    assert len(blob) == end + n * rows.dtype.itemsize  # nothing after the vertices
    return rows


def test_ply_frames_hold_the_particles(run, tmp_path):
    cfg, params, result = run
    initial = jm.init_state(cfg, *jm.seed_box((0.3, 0.1), (0.6, 0.4), cfg.grid.dx, 2))
    written = io.write_ply_frames(tmp_path / "ply", result, initial=initial)
    assert [w.name for w in written] == ["initial.ply", "frame_00000.ply", "frame_00001.ply", "frame_00002.ply",
                                         "final.ply"]
    final = _read_ply(tmp_path / "ply" / "final.ply")
    x = np.asarray(result.state.x)
    np.testing.assert_array_equal(final["x"], x[:, 0])
    np.testing.assert_array_equal(final["y"], x[:, 1])
    assert np.all(final["z"] == 0)  # 2D: the plane z = 0
    np.testing.assert_allclose(final["v_1"], np.asarray(result.state.v)[:, 1], rtol=1e-6)
    frame = _read_ply(tmp_path / "ply" / "frame_00001.ply")
    np.testing.assert_allclose(frame["p"], np.asarray(result.frames["p"][1]), rtol=1e-6)
    assert sorted(p.name for p in (tmp_path / "ply").iterdir()) == sorted(w.name for w in written)  # no .tmp


def test_ply_refuses_bad_fields(tmp_path):
    with pytest.raises(ValueError, match="x must have shape"):
        io.write_ply(tmp_path / "a.ply", np.zeros((3, 4)))
    with pytest.raises(ValueError, match=r"fields\['p'\] has shape"):
        io.write_ply(tmp_path / "a.ply", np.zeros((3, 2)), {"p": np.zeros(4)})
    with pytest.raises(ValueError, match="alphanumeric"):
        io.write_ply(tmp_path / "a.ply", np.zeros((3, 2)), {"p q": np.zeros(3)})
