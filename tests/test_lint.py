"""The lint configuration in pyproject.toml ([tool.ruff]) holds for the whole repository; CI runs
it through this test (ruff is in the test extra)."""

import pathlib
import shutil
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    ruff = shutil.which("ruff") or (pathlib.Path(sys.executable).parent / "ruff")
    # ruff is in the test extra: a suite installed as the README says has it, so its absence is
    # a broken install, not a reason to skip the check.
    assert pathlib.Path(ruff).exists(), "ruff is not installed: pip install '.[test]' installs it"
    run = subprocess.run([str(ruff), "check", "--no-cache", str(ROOT)], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


def _imports(path: pathlib.Path) -> list[str]:
    import ast

    tree = ast.parse(path.read_text(), filename=str(path))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def test_the_engine_never_imports_calibration():
    """The layers run one way: calibration builds on jaxmpm, never the reverse (also inside
    functions, where a lazy import would hide the cycle)."""
    upward = {str(p.relative_to(ROOT)): [n for n in _imports(p) if n.split(".")[0] == "calibration"]
              for p in sorted((ROOT / "jaxmpm").rglob("*.py"))}
    assert {p: names for p, names in upward.items() if names} == {}
