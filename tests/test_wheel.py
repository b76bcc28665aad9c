"""The wheel that ``pip install .`` builds holds every module and every shipped data file, and an
installed copy (not editable, not next to a checkout) finds its data with no environment variable."""

import json
import os
import pathlib
import shutil
import subprocess
import sys
import zipfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _tracked(*folders: str) -> list[str]:
    """The files git tracks (under ``folders``), deleted ones left out."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout (an unpacked source archive): the tracked files are unknown")
    # A checkout (CI's clean clone) must answer: a failing git is an error, not a skip.
    out = subprocess.run(["git", "ls-files", *folders], cwd=ROOT, capture_output=True, text=True, check=True)
    return [line for line in out.stdout.splitlines() if line and (ROOT / line).is_file()]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> pathlib.Path:
    # Built from a copy of the tracked files: setuptools reuses a checkout's build/ folder, which
    # could hold files that are no longer in the repository.
    source = tmp_path_factory.mktemp("source")
    for name in _tracked():
        target = source / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, target)
    out = tmp_path_factory.mktemp("wheel")
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--quiet", "-w", str(out)],
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr[-3000:]
    (path,) = out.glob("jaxmpm-*.whl")
    return path


def test_the_wheel_holds_every_module_and_every_shipped_file(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = [f for f in _tracked("jaxmpm", "calibration") if f.endswith(".py")]
    assert modules and not [f for f in modules if f not in names]
    data = _tracked("experiments_data")
    expected = {"jaxmpm/" + f for f in data}
    missing = sorted(expected - names)
    assert not missing, f"shipped files not in the wheel: {missing}"
    # And the manifest names only files that are there.
    manifest = json.loads(zipfile.ZipFile(wheel).read("jaxmpm/experiments_data/manifest.json"))
    assert {"jaxmpm/experiments_data/" + e["path"] for e in manifest["files"]} <= names
    # No test, docs or CI file leaks into the wheel.
    assert not [n for n in names if n.startswith(("tests/", "docs/", ".ci/"))]


def test_an_installed_copy_finds_its_data_without_the_environment_variable(wheel, tmp_path):
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as zf:  # a pure-Python wheel installs by unpacking
        zf.extractall(site)
    env = {k: v for k, v in os.environ.items() if k != "JAXMPM_EXPERIMENTS_DATA"}
    env["PYTHONPATH"] = str(site)  # ahead of any editable install's finder
    script = (
        "import json, pathlib, calibration, calibration.data as d\n"
        "from jaxmpm.scenes.avalanche import default_terrain_path\n"
        "found = {n: str(d.dataset_path(n)) for n in d.list_datasets()}\n"
        "print(json.dumps({'module': calibration.__file__, 'data': str(d.data_dir()), 'found': found,\n"
        "                  'terrain': str(default_terrain_path()),"
        " 'setup': d.load_setup('setups/S1_incline') is not None,\n"
        "                  'experiment': d.read_measurements(__import__('jaxmpm.experiment').experiment"
        ".shipped_experiment('aluminium-bars')).profiles[0].file.is_file(),\n"
        "                  'profile_points':"
        " len(d.load_profile(d.dataset_path('bui2008/bui2008_final_surface')).x)}))\n"
    )
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert pathlib.Path(out["module"]).is_relative_to(site), "imported the checkout, not the installed copy"
    assert pathlib.Path(out["data"]) == site / "jaxmpm" / "experiments_data"
    assert out["found"] and all(pathlib.Path(p).is_relative_to(site) for p in out["found"].values())
    assert pathlib.Path(out["terrain"]).is_relative_to(site)
    assert out["profile_points"] == 23 and out["setup"] and out["experiment"]
