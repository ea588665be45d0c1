"""The package's layers hold: every module imports psonurbs modules of its own layer or
of the layers below it only (parsed with ``ast``, lazy imports inside functions included),
and the linter (ruff: pyflakes, import order, bugbear) is clean."""
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
    "config": {"errors"},
    "geometry": {"errors"},
    "fitting": {"geometry", "config", "errors"},
    "formats": {"geometry", "config", "errors"},
    "run": {"fitting", "formats", "geometry", "config", "errors"},
    "cli": {"run", "formats", "config", "errors"},  # parses, calls and reports: no numerics
    "top": {"fitting", "formats", "geometry", "config", "errors"},  # psonurbs/__init__.py
}


VERSION = ("psonurbs", "psonurbs.__version__")  # the version is metadata, read from anywhere


def layer_of(module: str) -> str | None:
    """'psonurbs.fitting.solve' -> 'fitting'; other packages (and the version) -> None."""
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


def test_the_check_sees_a_forbidden_import(tmp_path):
    bad = tmp_path / "psonurbs" / "geometry" / "bad.py"
    bad.parent.mkdir(parents=True)
    bad.write_text("from psonurbs.fitting.solve import RegularisedLeastSquares\nfrom .basis import x\n")
    found = imported(bad, "psonurbs.geometry.bad")
    assert found == [(1, "psonurbs.fitting.solve"), (2, "psonurbs.geometry.basis")]
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
