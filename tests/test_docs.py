"""The documentation: the site builds without a warning (``mkdocs build --strict``), its API
reference covers the packages' public surface, every list of modules in the docs names modules
that exist, no doc runs a file outside the repository, and no heading cites a tracker number.

The site's packages are in the test extra: a suite installed as the README says has them, so their
absence is a broken install and fails, never skips."""

import functools
import importlib
import pathlib
import re
import subprocess
import sys
import types

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
REFERENCE = DOCS / "reference"
PACKAGES = ("jaxmpm", "calibration")
# The pages a reader reads: the README and every Markdown page of the site (the example and result
# folders hold no page).
PAGES = [ROOT / "README.md"] + sorted(p for p in DOCS.rglob("*.md")
                                      if p.relative_to(DOCS).parts[0] not in ("scripts", "results", "five_keys",
                                                                              "tutorial"))
# The page that claims to list every module of both packages.
LAYOUT = DOCS / "layout.md"


def _markdown_parts(text: str) -> tuple[list[str], list[str]]:
    """(the lines outside fenced code blocks, the fenced code blocks' texts)."""
    prose, blocks, block = [], [], None
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            if block is None:
                block = []
            else:
                blocks.append("\n".join(block))
                block = None
        elif block is None:
            prose.append(line)
        else:
            block.append(line)
    return prose, blocks


def _require(module: str):
    try:
        return importlib.import_module(module)
    except ImportError as error:  # a broken install, not a reason to skip
        pytest.fail(f"{module} is not installed ({error}): pip install '.[test]' installs it")


def test_the_site_builds_strictly_and_renders_the_reference(tmp_path):
    _require("mkdocs")
    _require("material")
    _require("mkdocstrings_handlers.python")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-5000:]
    assert (tmp_path / "site" / "index.html").exists()
    # Every public name has its anchor in the rendered reference, where the directives put it.
    anchors = set()
    for html in (tmp_path / "site" / "reference").rglob("*.html"):
        anchors |= set(re.findall(r'id="([A-Za-z_][\w.]*)"', html.read_text()))
    rendered = _rendered()
    missing = sorted(public for public, target in _public_targets().items()
                     if not any(path in anchors for path, t in rendered.items() if t == target))
    assert missing == [], f"rendered nowhere in the reference: {missing}"


def _directives() -> list[tuple[str, list[str] | None]]:
    """Every ``::: identifier`` of the reference pages, with its ``members:`` list (None: all public)."""
    found = []
    for page in sorted(REFERENCE.glob("*.md")):
        text = page.read_text()
        for match in re.finditer(r"^::: (\S+)\n((?:[ \t]+.*\n?)*)", text, re.M):
            options = match.group(2)
            members = re.search(r"^\s*members:\s*(\[[^\]]*\]|false|true)", options, re.M)
            if members is None or members.group(1) == "true":
                found.append((match.group(1), None))
            elif members.group(1) == "false":
                found.append((match.group(1), []))
            else:
                found.append((match.group(1), [m.strip() for m in members.group(1)[1:-1].split(",") if m.strip()]))
    return found


def _target(package: types.ModuleType, name: str) -> str:
    """Where a package's public name is defined: the path its reference anchor carries."""
    obj = getattr(package, name)
    if isinstance(obj, types.ModuleType):
        return obj.__name__
    if hasattr(obj, "__qualname__") and hasattr(obj, "__module__"):
        return f"{obj.__module__}.{obj.__qualname__}"
    # A constant: the module that assigns it (read from the source by griffe, as mkdocstrings reads it).
    top, _, below = package.__name__.partition(".")
    member = _griffe_package(top)[f"{below}.{name}" if below else name]
    return member.final_target.path if member.is_alias else member.path


@functools.cache
def _griffe_package(name: str):
    griffe = _require("griffe")
    loader = griffe.GriffeLoader(search_paths=[str(ROOT)])
    package = loader.load(name)
    loader.resolve_aliases(external=False)
    return package


def _public_targets() -> dict[str, str]:
    targets = {}
    for package_name in PACKAGES:
        package = importlib.import_module(package_name)
        for name in package.__all__:
            targets[f"{package_name}.{name}"] = _target(package, name)
    return targets


def _rendered() -> dict[str, str]:
    """Each path the reference's directives render (``module.name``), with where it is defined."""
    rendered = {}
    for identifier, members in _directives():
        module = importlib.import_module(identifier)
        rendered[identifier] = identifier
        names = getattr(module, "__all__", []) if members is None else members  # all: the public names
        rendered |= {f"{identifier}.{name}": _target(module, name) for name in names}
    return rendered


def test_the_reference_covers_every_public_name():
    """Every name of ``jaxmpm.__all__`` and ``calibration.__all__`` is rendered by a directive of
    docs/reference/: a module's directive (all its public names, or a ``members:`` list naming it)
    of the module that defines it or of one that re-exports it."""
    rendered = _rendered()
    for package in PACKAGES:
        assert package in rendered, f"docs/reference has no page for {package}"
    missing = sorted(public for public, target in _public_targets().items() if target not in rendered.values())
    assert missing == [], f"public names with no reference: {missing}"


def _modules(package: str) -> set[str]:
    folder = ROOT / package
    names = {p.stem for p in folder.glob("*.py") if p.stem != "__init__" and not p.stem.startswith("_")}
    names |= {p.parent.name + "/" for p in folder.glob("*/__init__.py")}
    return names | ({"__main__"} if (folder / "__main__.py").exists() else set())


_MODULE = re.compile(r"(?<![\w/.-])([A-Za-z_]\w*)\.py\b|(?<![\w/.-])([a-z_]+/)(?=\s)")


def _module_lists() -> dict[str, dict[str, set[str]]]:
    """The module lists of the pages: fenced blocks naming three or more ``name.py`` (not paths);
    a line starting with ``jaxmpm/`` or ``calibration/`` switches the package the names belong to."""
    lists = {}
    for page in PAGES:
        for number, block in enumerate(_markdown_parts(page.read_text())[1]):
            named = {package: set() for package in PACKAGES + ("",)}
            package = ""
            for line in block.splitlines():
                head = line.split()[0] if line.split() else ""
                if head in (f"{p}/" for p in PACKAGES):
                    package, line = head[:-1], line[len(head):]
                elif line and not line[0].isspace():
                    package = ""  # another folder of the repository, or none
                for match in _MODULE.finditer(line):
                    named[package].add(match.group(1) or match.group(2))
            if sum(len(v) for v in named.values()) >= 3:
                lists[f"{page.relative_to(ROOT)} block {number}"] = named
    return lists


def test_every_module_list_names_modules_that_exist():
    modules = {package: _modules(package) for package in PACKAGES}
    lists = _module_lists()
    assert any("layout.md" in where for where in lists) and any("calibration.md" in where for where in lists)
    wrong = {}
    for where, named in lists.items():
        for package, names in named.items():
            known = modules[package] if package else modules["jaxmpm"] | modules["calibration"]
            if package == "" and "README.md" in where:
                continue  # the repository's other folders (experiments_data/, tests/, docs/)
            unknown = {n for n in names if n.rstrip("/") not in {k.rstrip("/") for k in known}}
            if unknown:
                wrong[f"{where} ({package or 'either package'})"] = sorted(unknown)
    assert wrong == {}, f"module lists naming modules that do not exist: {wrong}"


def test_the_layout_page_lists_every_module():
    """docs/layout.md says it lists every module of both packages: it does, and no other."""
    named = {package: set() for package in PACKAGES}
    for where, found in _module_lists().items():
        if where.startswith(str(LAYOUT.relative_to(ROOT))):
            for package in PACKAGES:
                named[package] |= found[package]
    for package in PACKAGES:
        assert {n.rstrip("/") for n in named[package]} == {m.rstrip("/") for m in _modules(package)}, package


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for part in parts[i:]:
                obj = getattr(obj, part)
        except AttributeError:
            return False
        return True
    return False


def test_every_dotted_name_in_the_docs_exists():
    """A module, class, function or constant a page names as ``jaxmpm.…`` or ``calibration.…``
    exists under that name (a moved or renamed one leaves no stale name behind)."""
    stale = {}
    for page in PAGES:
        for match in re.finditer(r"(?<![\w./-])((?:jaxmpm|calibration)(?:\.[A-Za-z_]\w*)+)", page.read_text()):
            name = match.group(1)
            if not name.endswith((".md", ".py", ".toml", ".csv", ".h5", ".json", ".png")) and not _resolves(name):
                stale.setdefault(name, set()).add(str(page.relative_to(ROOT)))
    assert stale == {}, f"names in the docs that do not exist: {stale}"


def test_no_doc_runs_a_file_outside_the_repository():
    """A command in a doc runs inside the repository: no ``../`` in a code block or code span."""
    found = []
    for page in PAGES:
        prose, blocks = _markdown_parts(page.read_text())
        spans = [s for line in prose for s in re.findall(r"`([^`]+)`", line)]
        found += [f"{page.relative_to(ROOT)}: {code.strip()[:80]}" for code in blocks + spans if "../" in code]
    assert found == []


_TRACKER = re.compile(r"\b(issue|issues|stop|item|ticket|pr|pull request|milestone)\s*#?\s*\d+|#\d+", re.I)


def test_no_heading_cites_a_tracker_number():
    """A reader cannot follow a tracker number: a heading names the question its section answers."""
    found = []
    for page in PAGES:
        for line in _markdown_parts(page.read_text())[0]:
            if re.match(r"#{1,6} ", line) and _TRACKER.search(line.lstrip("#")):
                found.append(f"{page.relative_to(ROOT)}: {line}")
    assert found == []
