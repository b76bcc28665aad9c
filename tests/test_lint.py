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


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolved_imports(path: pathlib.Path) -> list[tuple[str, list[str], bool]]:
    """Every import in ``path`` (also inside functions) as ``(module, names, absolute)`` with
    relative imports resolved to absolute module names: ``from .. import scenes`` in
    jaxmpm/studies/x.py is ``("jaxmpm", ["scenes"], False)``, ``import jaxmpm.io`` is
    ``("jaxmpm.io", [], True)``."""
    import ast

    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, [], True) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join(base + (node.module.split(".") if node.module else []))
            out.append((module, [a.name for a in node.names], node.level == 0))
    return out


def _engine_files():
    return sorted((ROOT / "jaxmpm").rglob("*.py"))


def test_the_resolver_reads_relative_imports():
    """The walk below sees through relative imports (a check of the checker)."""
    found = {module: (names, absolute) for module, names, absolute in
             _resolved_imports(ROOT / "jaxmpm" / "studies" / "validation.py")}
    assert found["jaxmpm"] == (["scenes"], False) and "jaxmpm.simulate" in found and "jaxmpm.studies" in found
    assert _module_name(ROOT / "jaxmpm" / "scenes" / "__init__.py") == "jaxmpm.scenes"


def test_no_module_inside_jaxmpm_imports_the_package_face():
    """No module of jaxmpm reaches its own package's face (``import jaxmpm``, ``from jaxmpm
    import X``, ``from . import X`` where X is a name jaxmpm/__init__.py defines rather than a
    module): the face is built from the modules, so a module that imports it runs upward and
    depends on the order the face imports in. ``from . import io`` (a module) is fine."""
    submodules = {p.stem for p in (ROOT / "jaxmpm").glob("*.py")} | {
        p.name for p in (ROOT / "jaxmpm").iterdir() if (p / "__init__.py").exists()}
    upward = {}
    for path in _engine_files():
        if path == ROOT / "jaxmpm" / "__init__.py":
            continue
        bad = [f"{'' if absolute else 'relative '}{module}: {', '.join(names) or '(the package)'}"
               for module, names, absolute in _resolved_imports(path)
               if (module == "jaxmpm" and (absolute or set(names) - submodules))
               or (absolute and not names and module.split(".")[0] == "jaxmpm")]  # import jaxmpm(.x)
        if bad:
            upward[str(path.relative_to(ROOT))] = bad
    assert upward == {}


def test_the_core_never_imports_the_applications():
    """The core of jaxmpm (everything but studies/, cli.py and __main__.py) never imports the
    floors built on it: jaxmpm.studies and jaxmpm.cli."""
    applications = ("jaxmpm.studies", "jaxmpm.cli", "jaxmpm.__main__")
    on_top = {ROOT / "jaxmpm" / "cli.py", ROOT / "jaxmpm" / "__main__.py"}
    core = [p for p in _engine_files() if not (p.is_relative_to(ROOT / "jaxmpm" / "studies") or p in on_top)]
    assert ROOT / "jaxmpm" / "step.py" in core and ROOT / "jaxmpm" / "cli.py" not in core
    upward = {}
    for path in core:
        names = [module + ("." + name if name else "") for module, names, _ in _resolved_imports(path)
                 for name in (names or [""])]
        bad = [n for n in names if any(n == a or n.startswith(a + ".") for a in applications)]
        if bad:
            upward[str(path.relative_to(ROOT))] = bad
    assert upward == {}
