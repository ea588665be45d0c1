"""The package's layers hold: every module imports psonurbs modules of its own layer or
of the layers below it only (parsed with ``ast``, lazy imports inside functions included);
no import circle between files; no module imports another's private (``_x``) name or
reads one off it; no folder holds more than ``MAX_MODULES`` modules; and the linter
(ruff: pyflakes, import order, bugbear) is clean."""
from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# layer -> the layers it may import (besides itself)
ALLOWED = {
    "errors": set(),
    "progress": set(),  # the stage a long fit is at, for whoever shows progress
    "config": {"errors"},
    "geometry": {"errors"},
    "fitting": {"geometry", "config", "errors", "progress"},
    "formats": {"geometry", "config", "errors"},
    "objects": {"fitting", "formats", "geometry", "config", "errors", "progress"},  # whole objects: regions, faces, joins
    "run": {"objects", "fitting", "formats", "geometry", "config", "errors", "progress"},
    "cli": {"run", "formats", "config", "errors", "progress"},  # parses, calls and reports: no numerics
    "top": {"fitting", "formats", "geometry", "config", "errors", "progress"},  # psonurbs/__init__.py
}


MAX_MODULES = 12  # .py files of one folder of psonurbs/, __init__.py counted: a stage a newcomer can read
NAMEDTUPLE_API = {"_replace", "_asdict", "_fields", "_make", "_field_defaults"}  # public despite the underscore
VERSION = ("psonurbs", "psonurbs.__version__")  # the version is metadata, read from anywhere


def layer_of(module: str) -> str | None:
    """'psonurbs.fitting.leastsq.regularised' -> 'fitting'; other packages (and the version) -> None."""
    parts = module.split(".")
    if parts[0] != "psonurbs" or module in VERSION:
        return None
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else "top"


def modules():
    """(path, dotted module name) of every module of the package and of cli/ (psonurbs.cli)."""
    for path in sorted((REPO / "psonurbs").rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        yield path, name if name != "psonurbs" else "psonurbs.__init__"
    for path in sorted((REPO / "cli").rglob("*.py")):
        parts = ("psonurbs",) + path.relative_to(REPO).with_suffix("").parts
        yield path, ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in the file, relative ones resolved."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            # "from psonurbs import x" may name a submodule: judge psonurbs.x
            names = [f"{target}.{a.name}" for a in node.names] if target == "psonurbs" else [target]
            out += [(node.lineno, name) for name in names]
    return out


def imported_modules(path: Path, module: str, known: set[str]) -> list[tuple[int, str]]:
    """(line, module of ``known``) of every import in the file that loads a file of
    ``known``: ``from package import name`` names the submodule ``package.name`` if
    there is one, else the package (or module) itself."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names if alias.name in known]
        elif isinstance(node, ast.ImportFrom):
            base = resolved(node, package)
            for alias in node.names:
                target = f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                if target in known:
                    out.append((node.lineno, target))
    return out


def resolved(node: ast.ImportFrom, package: str) -> str:
    """The absolute module a ``from ... import`` reads from."""
    if not node.level:
        return node.module
    base = package.split(".")
    base = base[:len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected set of more than one module (or a module importing
    itself) of the graph module -> modules it imports (Tarjan)."""
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph.get(v, ()):
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def module_graph(files: list[tuple[Path, str]]) -> dict[str, set[str]]:
    known = {name for _, name in files}
    return {name: {target for _, target in imported_modules(path, name, known)}
            for path, name in files}


def private_uses(path: Path, module: str) -> list[str]:
    """Where the file imports a private name of a project module (``from m import _x``)
    or reads one off an object other than ``self``/``cls`` (``m._x``, ``obj._x``)."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            source = resolved(node, package)
            if source.split(".")[0] in PROJECT:
                out += [f"{path.relative_to(REPO)}:{node.lineno}: imports {source}.{alias.name}"
                        for alias in node.names if private(alias.name)]
        elif isinstance(node, ast.Attribute) and private(node.attr) and node.attr not in NAMEDTUPLE_API:
            if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                out.append(f"{path.relative_to(REPO)}:{node.lineno}: reads {ast.unparse(node)}")
    return out


PROJECT = {"psonurbs", "benchmarks", "tests", "cli"}


def private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def project_files() -> list[tuple[Path, str]]:
    """(path, dotted name) of every module of psonurbs/, cli/, benchmarks/ and tests/."""
    files = list(modules())
    for folder in ("benchmarks", "tests"):
        for path in sorted((REPO / folder).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            files.append((path, ".".join(parts[:-1] if parts[-1] == "__init__" else parts)))
    return files


def test_the_check_sees_a_forbidden_import(tmp_path):
    bad = tmp_path / "psonurbs" / "geometry" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares\nfrom .basis import x\n")
    found = imported(bad, "psonurbs.geometry.bad")
    assert found == [(1, "psonurbs.fitting.leastsq.regularised"), (2, "psonurbs.geometry.basis")]
    assert layer_of(found[0][1]) not in ALLOWED["geometry"]


def test_every_import_stays_in_its_layer_or_below():
    violations = []
    for path, module in modules():
        own = layer_of(module)
        for line, target in imported(path, module):
            other = layer_of(target)
            if other is None or other == own or other in ALLOWED[own]:
                continue
            violations.append(f"{path.relative_to(REPO)}:{line}: {own} imports {target} ({other})")
    assert not violations, "layering broken:\n" + "\n".join(violations)


def test_ruff_is_clean():
    ruff = shutil.which("ruff")
    command = [ruff] if ruff else [sys.executable, "-m", "ruff"]
    try:
        result = subprocess.run([*command, "check", "--no-cache", str(REPO)], capture_output=True, text=True,
                                cwd=REPO)
    except FileNotFoundError:
        pytest.skip("ruff is not installed (pip install '.[test]')")
    if result.returncode != 0 and "No module named ruff" in result.stderr:
        pytest.skip("ruff is not installed (pip install '.[test]')")
    assert result.returncode == 0, result.stdout + result.stderr


def test_no_folder_of_the_package_holds_more_than_twelve_modules():
    folders = {}
    for path in (REPO / "psonurbs").rglob("*.py"):
        if not path.is_symlink() and "cli" not in path.relative_to(REPO / "psonurbs").parts:
            folders.setdefault(path.parent.relative_to(REPO), []).append(path.name)
    crowded = {str(folder): len(names) for folder, names in folders.items() if len(names) > MAX_MODULES}
    assert not crowded, f"folders over {MAX_MODULES} modules: {crowded}"


def test_every_package_folder_is_installed():
    """A plain ``pip install .`` ships the packages pyproject.toml lists, nothing else: a
    folder left off is missing from every install but an editable one. (tomllib is
    Python 3.11's; psonurbs runs on 3.10.)"""
    tomllib = pytest.importorskip("tomllib")
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {".".join(init.parent.relative_to(REPO).parts) for init in (REPO / "psonurbs").rglob("__init__.py")}
    folders |= {"psonurbs." + ".".join(init.parent.relative_to(REPO).parts) for init in (REPO / "cli").rglob("__init__.py")}
    assert folders - listed == set(), "package folders pyproject.toml does not install"
    assert listed - folders == set(), "packages pyproject.toml lists that have no folder"


def test_the_cycle_check_sees_a_circle_through_a_function_level_import(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from . import b\n")
    (tmp_path / "pkg" / "b.py").write_text("def f():\n    from pkg.c import g\n")
    (tmp_path / "pkg" / "c.py").write_text("from .a import x\n")
    (tmp_path / "pkg" / "d.py").write_text("from .a import x\n")
    files = [(tmp_path / "pkg" / "__init__.py", "pkg")] + [(tmp_path / "pkg" / f"{m}.py", f"pkg.{m}") for m in "abcd"]
    assert import_cycles(module_graph(files)) == [["pkg.a", "pkg.b", "pkg.c"]]


def test_no_import_circle_between_files():
    cycles = import_cycles(module_graph(list(modules())))
    assert not cycles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_private_check_sees_an_import_and_a_read(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    path = tmp_path / "tests" / "t.py"
    path.parent.mkdir()
    path.write_text("from psonurbs.geometry.net import _hidden\nx = layout._rows()\ny = self._own\nz = s._replace(a=1)\n")
    assert private_uses(path, "tests.t") == ["tests/t.py:1: imports psonurbs.geometry.net._hidden",
                                             "tests/t.py:2: reads layout._rows"]


def test_no_module_uses_a_private_name_of_another():
    found = [use for path, module in project_files() for use in private_uses(path, module)]
    assert not found, "private names used across modules:\n" + "\n".join(found)


def test_the_readme_is_a_guide_not_a_notebook():
    """The README is the user's guide: at most 25,000 bytes; results and history live elsewhere."""
    assert (REPO / "README.md").stat().st_size <= 25_000
