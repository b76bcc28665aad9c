"""The lint configuration in pyproject.toml ([tool.ruff]) holds for the whole repository; CI runs
it through this test (ruff is in the test extra)."""

import functools
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
    functions, where a lazy import would hide the cycle). experiments_data/ is installed as
    jaxmpm.experiments_data, so its scripts count as the engine's."""
    files = sorted((ROOT / "jaxmpm").rglob("*.py")) + sorted((ROOT / "experiments_data").rglob("*.py"))
    assert ROOT / "experiments_data" / "generate.py" in files
    upward = {str(p.relative_to(ROOT)): [n for n in _imports(p) if n.split(".")[0] == "calibration"] for p in files}
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


# ---- the calibration package: floors by role, no loops, modules and functions a reader can hold ----------------
#: calibration's sub-packages from the ground up: a module imports its own floor or those below, never above.
CALIBRATION_FLOORS = ("data", "problem", "batch", "inference", "optim", "design", "studies", "plots", "cli")


def _runtime_imports(path: pathlib.Path) -> list[str]:
    """The calibration and jaxmpm modules (or packages) ``path`` imports at run time, also inside
    functions; imports under ``if TYPE_CHECKING:`` (annotations only) are not run and do not count."""
    import ast

    tree = ast.parse(path.read_text(), filename=str(path))
    typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(
        node.test) for n in ast.walk(node)}
    package = _module_name(path).split(".")[:None if path.name == "__init__.py" else -1]
    known = _known_modules()
    out = []
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join(base + (node.module.split(".") if node.module else []))
            out += [f"{module}.{a.name}" if f"{module}.{a.name}" in known else module for a in node.names]
    return [m for m in out if m.split(".")[0] in ("jaxmpm", "calibration")]


@functools.cache
def _known_modules() -> frozenset[str]:
    return frozenset(_module_name(p) for root in ("jaxmpm", "calibration") for p in (ROOT / root).rglob("*.py"))


def _calibration_files():
    return sorted((ROOT / "calibration").rglob("*.py"))


def test_the_calibration_floors_run_one_way():
    """A module of calibration/<floor>/ imports only its own floor and the ones below it
    (``CALIBRATION_FLOORS``), never the package's face; the face and ``__main__`` sit on top."""
    def floor(module):
        parts = module.split(".")
        return CALIBRATION_FLOORS.index(parts[1]) if len(parts) > 1 and parts[1] in CALIBRATION_FLOORS else None

    assert {p.name for p in (ROOT / "calibration").iterdir() if p.is_dir() and p.name != "__pycache__"} == set(
        CALIBRATION_FLOORS)
    upward = {}
    for path in _calibration_files():
        module = _module_name(path)
        if floor(module) is None:
            continue  # calibration/__init__.py and __main__.py: the top
        bad = [m for m in _runtime_imports(path) if m == "calibration"
               or (m.startswith("calibration.") and (floor(m) is None or floor(m) > floor(module)))]
        if bad:
            upward[module] = bad
    assert upward == {}


def test_no_import_loop_in_either_package():
    """No module of jaxmpm or calibration reaches itself through the modules it imports (lazy
    imports inside functions included: a loop hidden in a function is still a loop)."""
    files = _engine_files() + _calibration_files()
    graph = {_module_name(p): set(_runtime_imports(p)) for p in files}

    def reached(start):
        seen, todo = set(), list(graph.get(start, ()))
        while todo:
            m = todo.pop()
            if m == start:
                return True
            if m not in seen and m in graph:
                seen.add(m)
                todo += graph[m] - seen
        return False

    # A package imports its modules in its __init__: a module importing its own package is the loop
    # the face check above refuses; here only loops between modules.
    loops = sorted(m for m in graph if not m.endswith("__init__") and reached(m) and m not in ("jaxmpm", "calibration"))
    assert loops == []


#: Modules may run to this many lines and functions to this many, unless they say why.
MODULE_LINES, FUNCTION_LINES = 500, 80


def test_modules_and_functions_a_reader_can_hold():
    """No module of calibration or jaxmpm runs over ``MODULE_LINES`` lines and no function over
    ``FUNCTION_LINES`` unless it says why: a module in a docstring line starting "Long module:",
    a function in a comment line "# Long function: why" right above its ``def``."""
    import ast

    long = []
    for path in _engine_files() + _calibration_files():
        text = path.read_text()
        lines = text.splitlines()
        tree = ast.parse(text)
        if len(lines) > MODULE_LINES and "Long module:" not in (ast.get_docstring(tree) or ""):
            long.append(f"{path.relative_to(ROOT)}: {len(lines)} lines")
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                size = node.end_lineno - node.lineno + 1
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if size > FUNCTION_LINES and not lines[first - 2].strip().startswith("# Long function:"):
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {size} lines")
    assert long == []


#: The most modules the walk of a fitted key, from the command line to the return map, may cross.
WALK_MODULES = 12


def test_the_walk_of_beta_from_the_command_line_to_the_return_map():
    """``python -m calibration fit`` down to the first call of the return map (at the first trace
    of the run): the call stack at that moment, read as the modules it passes through, crosses at
    most ``WALK_MODULES`` modules, enters none twice and never climbs back: each module on the way
    down calls only modules it imports, directly or through others (a callback into a module
    above, such as an optimiser's loop calling back into the fit, would be a climb)."""
    import sys

    from helpers import S4_DATA, TINY_DX

    from calibration.cli import main

    class Arrived(BaseException):
        pass

    path = []

    def ours(frame):
        return frame.f_globals.get("__name__", "").split(".")[0] in ("jaxmpm", "calibration")

    def hook(frame, event, arg):
        if event == "call" and frame.f_code.co_name == "return_map_planes" and ours(frame):
            while frame is not None:
                name = frame.f_globals.get("__name__", "")
                if ours(frame) and (not path or path[-1] != name):
                    path.append(name)
                frame = frame.f_back
            path.reverse()
            raise Arrived

    import jax

    from calibration.problem.cache import BATCHES, MODEL_FUNCTIONS

    # The run must be traced here: an earlier test in this process may have compiled the same one.
    jax.clear_caches()
    for cache in (MODEL_FUNCTIONS, BATCHES):
        cache._entries.clear()
    argv = ["fit", "--scene", "cohesive-collapse", "--data", str(S4_DATA), "--fit", "beta", "--init", "beta=0.2",
            "--steps", "1", "--dx", str(TINY_DX), "--grid-check", "0", "--workers", "1", "--no-progress", "--json"]
    sys.setprofile(hook)
    try:
        main(argv)
    except Arrived:
        pass
    finally:
        sys.setprofile(None)
    assert path[-1] == "jaxmpm.materials.critical_state" and path[0].startswith("calibration.cli"), path
    graph = {_module_name(p): set(_runtime_imports(p)) for p in _engine_files() + _calibration_files()}

    def reaches(a, b):
        seen, todo = set(), [a]
        while todo:
            m = todo.pop()
            for d in graph.get(m, ()):
                parents = [".".join(d.split(".")[:i]) for i in range(1, d.count(".") + 2)]
                for x in parents:
                    if x == b:
                        return True
                    if x not in seen:
                        seen.add(x)
                        todo.append(x)
        return False

    climbs = [(a, b) for a, b in zip(path, path[1:]) if not reaches(a, b)]
    assert len(set(path)) == len(path) <= WALK_MODULES and climbs == [], (path, climbs)
