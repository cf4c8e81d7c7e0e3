"""The layer rule: a package imports only from its layer or below (docs/architecture.md).

Layers, bottom to top: ``geoseg`` (the library: networks, synthetic world, filter,
relocalisation, inference), then ``training`` and ``slam_bridge`` side by side (each builds on
geoseg, neither on the other), then ``geoseg_cli`` (the ``geoseg`` command, which may use them
all). The test reads every module's source with :mod:`ast` (nothing is imported) and collects
what it imports: ``import``/``from`` statements anywhere (module level, inside functions, under
``TYPE_CHECKING``), ``importlib.import_module`` / ``__import__`` calls with a literal name, and
string literals that are dotted module paths of another package (the way a command table names
the modules it loads lazily, e.g. ``"training.seg"``).
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: package -> the packages it must not import (those above it or beside it)
FORBIDDEN: dict[str, frozenset[str]] = {
    "geoseg": frozenset({"training", "slam_bridge", "geoseg_cli"}),
    "training": frozenset({"slam_bridge", "geoseg_cli"}),
    "slam_bridge": frozenset({"training", "geoseg_cli"}),
    "geoseg_cli": frozenset(),
}

_DOTTED = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)+")


@dataclass(frozen=True)
class ImportEdge:
    """One import found in a source file: ``module`` (dotted) at ``file:line``."""

    file: Path
    line: int
    module: str
    how: str  # "import", "import_module" or "string"

    def describe(self) -> str:
        where = f"{self.file.relative_to(ROOT)}:{self.line}"
        what = {"import": "imports", "import_module": "loads", "string": "names the module"}
        return f"{where} {what[self.how]} {self.module}"


def imports_of(source: str, file: Path, package: str) -> list[ImportEdge]:
    """Every module ``source`` (a module of ``package``, at ``file``) imports or names."""
    tree = ast.parse(source, filename=str(file))
    parts = file.relative_to(ROOT).with_suffix("").parts
    edges = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            edges += [ImportEdge(file, node.lineno, a.name, "import") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against the file's own package
                base = list(parts[: len(parts) - node.level])
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            edges.append(ImportEdge(file, node.lineno, name, "import"))
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            arg = node.args[0]
            if called in ("import_module", "__import__") and isinstance(arg, ast.Constant):
                if isinstance(arg.value, str):
                    edges.append(ImportEdge(file, node.lineno, arg.value, "import_module"))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            text = node.value
            if _DOTTED.fullmatch(text) and text.split(".")[0] in FORBIDDEN:
                if text.split(".")[0] != package:
                    edges.append(ImportEdge(file, node.lineno, text, "string"))
    return edges


def package_files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def violations(package: str) -> list[str]:
    """``file:line imports X`` for each import of a package ``package`` must not use."""
    found = []
    for file in package_files(package):
        for edge in imports_of(file.read_text(encoding="utf-8"), file, package):
            if edge.module.split(".")[0] in FORBIDDEN[package]:
                found.append(edge.describe())
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_only_its_layer_or_below(package):
    assert len(package_files(package)) > 3, f"{package}: no modules found under {ROOT}"
    found = violations(package)
    if found:
        pytest.fail(
            f"{package} must not import {', '.join(sorted(FORBIDDEN[package]))} (the layer rule, "
            "docs/architecture.md: a package imports only from its layer or below); these "
            "imports break it:\n  " + "\n  ".join(found),
            pytrace=False,
        )


def test_the_walk_sees_lazy_and_string_imports():
    # the detector itself: function-level imports, importlib strings and command tables count
    source = (
        "import importlib\n"
        "def f():\n"
        "    from training.checkpoint import validate_checkpoint\n"
        "    return importlib.import_module('slam_bridge.image_slam')\n"
        "TABLE = {'seg': 'training.seg'}\n"
        "DOC = 'training.seg trains a network'\n"
    )
    file = ROOT / "geoseg" / "example.py"
    edges = {(e.line, e.module, e.how) for e in imports_of(source, file, "geoseg")}
    assert (3, "training.checkpoint", "import") in edges
    assert (4, "slam_bridge.image_slam", "import_module") in edges
    assert (5, "training.seg", "string") in edges
    assert not any(e[0] == 6 for e in edges)  # prose that mentions a module is no import
