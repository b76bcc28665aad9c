"""Cluster sweeps (calibration.batch.cluster) on a local Dask cluster of two workers, one of them
killed in the middle of a task: every member comes back, the lost task is retried and reported,
a task that always fails is reported with its error, never dropped."""

import functools
import os
import pathlib
import signal
import threading
import time

import h5py
import numpy as np
import pytest
from cluster_toy import make_toy
from helpers import S4_DATA, TINY_FLAGS

from calibration.batch.cluster import cluster_sweep, parse_cluster, write_cluster_sweep
from calibration.batch.sweep import sweep


def test_cluster_specs_are_checked_before_anything_starts():
    assert parse_cluster("local:2") == ("local", 2)
    assert parse_cluster("tcp://10.0.0.1:8786") == ("address", "tcp://10.0.0.1:8786")
    for bad in ("local:0", "local:x", "cluster", "", 3, None):
        with pytest.raises(ValueError, match="cluster"):
            parse_cluster(bad)
    with pytest.raises(ValueError, match="retries"):
        cluster_sweep(lambda: None, np.zeros((1, 2)), cluster="local:1", retries=-1)
    with pytest.raises(ValueError, match="make_objective"):
        cluster_sweep("not callable", np.zeros((1, 2)))


def _kill_first_busy_worker(marker_dir: pathlib.Path, killed: list, timeout: float = 120.0):
    clock = time.time()
    while time.time() - clock < timeout:
        markers = sorted(marker_dir.glob("started-*"))
        if markers:
            pid = int(markers[0].name.split("-")[1])
            time.sleep(0.2)  # well inside the task's second
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.05)


@pytest.mark.slow  # 15 s; a lost task's exit status stays in the default suite
def test_a_worker_killed_mid_sweep_loses_no_member(tmp_path):
    thetas = np.stack([np.linspace(0.0, 1.0, 14), np.linspace(0.2, 1.5, 14)], axis=-1)
    thetas[5, 1] = 20.0  # an engine-like failure (status bit 1)
    thetas[13, 0] = -1.0  # the last task (members 12, 13) raises on every attempt
    markers = tmp_path / "markers"
    markers.mkdir()
    recipe = functools.partial(make_toy, str(markers), 1.0)
    killed: list = []
    killer = threading.Thread(target=_kill_first_busy_worker, args=(markers, killed), daemon=True)
    killer.start()
    result = cluster_sweep(recipe, thetas, cluster="local:2", chunk=2, retries=1, x64=True)
    killer.join(timeout=1)
    assert killed, "no worker was killed"

    assert result.n_members == 14 and result.sweep.thetas.shape == (14, 2)
    np.testing.assert_array_equal(result.task, np.repeat(np.arange(7), 2))
    # The killed worker's task was retried and succeeded; its error says the worker was lost.
    retried = [t for t in result.retried if not t["lost"]]
    assert retried and any("KilledWorker" in e for t in retried for e in t["errors"]), result.tasks
    # The always-failing task is reported, with its error, after 1 + retries attempts.
    lost = [t for t in result.tasks if t["lost"]]
    assert [t["index"] for t in lost] == [6] and lost[0]["attempts"] == 2
    failed = {f["index"]: f for f in result.failed}
    assert set(failed) == {5, 12, 13}
    assert "a < 0 always fails" in failed[13]["why"] and failed[12]["task"] == 6
    assert failed[5]["status"] == 1 and "no status bit" not in failed[5]["why"]

    # Every other member equals the in-process sweep's to the bit.
    local = sweep(make_toy(str(markers), 0.0), thetas[:12], mode="vmap", chunk=2)
    ok = [i for i in range(12) if i != 5]
    np.testing.assert_array_equal(result.sweep.residuals[ok], local.residuals[ok])
    np.testing.assert_array_equal(result.sweep.loss[ok], local.loss[ok])
    np.testing.assert_array_equal(result.sweep.predictions["double"][ok], 2 * thetas[ok])
    assert np.all(np.isnan(result.sweep.loss[[5, 12, 13]]))

    # One HDF5 file with every member and the task that made it.
    path = tmp_path / "sweep.h5"
    write_cluster_sweep(path, result)
    with h5py.File(path) as f:
        np.testing.assert_array_equal(f["thetas"][...], thetas)
        np.testing.assert_array_equal(f["task"][...], result.task)
        assert f.attrs["cluster"] == "local:2" and "KilledWorker" in f.attrs["tasks_json"]
    json_out = result.to_json()
    assert json_out["n_members"] == 14 and len(json_out["failed"]) == 3


@pytest.mark.slow
def test_the_sweep_command_runs_on_a_local_cluster_with_the_in_process_numbers(tmp_path, capsys):
    import json

    from calibration.cli.commands import main

    common = ["sweep", "--scene", "cohesive-collapse", "--data", str(S4_DATA), "--over", "beta=0.1:0.4:4",
              *TINY_FLAGS, "--chunk", "2"]
    assert main([*common, "--cluster", "local:2", "--out", str(tmp_path / "c.h5")]) == 0
    clustered = json.loads(capsys.readouterr().out)
    assert main(common) == 0
    plain = json.loads(capsys.readouterr().out)
    assert clustered["n_members"] == plain["n_members"] == 4 and clustered["failed"] == []
    assert clustered["n_tasks"] == 2 and clustered["cluster"] == "local:2"
    np.testing.assert_array_equal(clustered["loss"], plain["loss"])
    with h5py.File(tmp_path / "c.h5") as f:
        assert f["loss"].shape == (4,) and list(f["task"][...]) == [0, 0, 1, 1]


def test_the_sweep_command_does_not_exit_0_when_a_task_was_lost(monkeypatch, capsys):
    """Members left without a result by a task that failed every attempt: reported in "failed"
    with the error, and the command exits 1 (the cluster itself is replaced by a stand-in)."""
    import json

    import calibration.batch.cluster as cluster
    from calibration.batch.sweep import SweepResult
    from calibration.cli.commands import main

    def lost_sweep(make_objective, thetas, **kw):
        n = len(thetas)
        result = SweepResult(keys=("beta",), thetas=thetas, loss=np.full(n, np.nan), status=np.zeros(n, np.int64),
                             residuals=np.full((n, 3), np.nan), predictions=None, failed=np.arange(n),
                             mode="cluster", chunk=n, n_devices=2, wall_s=0.0, compile_s=0.0)
        task = {"index": 0, "members": [0, n], "attempts": 3, "worker": None, "pid": None, "wall_s": None,
                "errors": ["KilledWorker: lost"] * 3, "lost": True}
        return cluster.ClusterSweepResult(sweep=result, task=np.zeros(n, int), tasks=(task,), cluster="local:2")

    monkeypatch.setattr(cluster, "cluster_sweep", lost_sweep)
    code = main(["sweep", "--scene", "cohesive-collapse", "--data", str(S4_DATA), "--over", "beta=0.1:0.3:2",
                 "--cluster", "local:2", *TINY_FLAGS])
    out = json.loads(capsys.readouterr().out)
    assert code == 1
    assert out["n_members"] == 2 and [f["index"] for f in out["failed"]] == [0, 1]
    assert "KilledWorker" in out["failed"][0]["why"]
