"""slam_bridge is built in layers: a module imports only from its own layer or the layers below.

The layers, bottom to top (``docs/architecture.md``, "slam_bridge"): base, geometry, bundle
adjustment, factors, front end, SLAM, evaluation, system, experiments and test support. Every
import counts, at module level or inside a function, under ``TYPE_CHECKING`` or not.
"""

from __future__ import annotations

import ast
from pathlib import Path

import slam_bridge

#: Bottom to top; a module belongs to the layer of the longest prefix that names it.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("base", ("slam_bridge", "slam_bridge.errors", "slam_bridge.csv_columns")),
    ("geometry", ("slam_bridge.geometry",)),
    ("bundle adjustment", ("slam_bridge.ba",)),
    ("factors", ("slam_bridge.factors",)),
    # the front end reads the map through its own protocol (frontend.base.MapView)
    ("front end", ("slam_bridge.frontend",)),
    ("slam", ("slam_bridge.slam", "slam_bridge.bridge")),
    ("evaluation", ("slam_bridge.evaluation",)),
    ("system", ("slam_bridge.system",)),
    ("experiments", ("slam_bridge.experiments", "slam_bridge.testing")),
]

ROOT = Path(slam_bridge.__file__).parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> int | None:
    best, best_len = None, -1
    for rank, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            # the bare package prefix "slam_bridge" names only the package itself
            if module == prefix or (prefix != "slam_bridge" and module.startswith(prefix + ".")):
                if len(prefix) > best_len:
                    best, best_len = rank, len(prefix)
    return best


def _is_module(name: str) -> bool:
    rel = Path(*name.split("."))
    return (ROOT.parent / rel.with_suffix(".py")).is_file() or (ROOT.parent / rel).is_dir()


def _imports(path: Path, module: str) -> list[tuple[int, str]]:
    """``(line, imported slam_bridge module)`` of every import in the file."""
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [
                (node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "slam_bridge"
            ]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "slam_bridge":
                continue
            for alias in node.names:  # ``from pkg import module`` imports that module
                sub = f"{target}.{alias.name}"
                out.append((node.lineno, sub if _is_module(sub) else target))
    return out


def _modules() -> list[tuple[Path, str]]:
    return [(p, _module_name(p)) for p in sorted(ROOT.rglob("*.py"))]


def test_every_module_has_a_layer() -> None:
    missing = [m for _, m in _modules() if _layer(m) is None]
    assert not missing, f"modules in no layer of tests/slam_bridge/test_layers.py: {missing}"


def test_modules_import_only_their_layer_or_below() -> None:
    offences = []
    for path, module in _modules():
        own = _layer(module)
        for line, target in _imports(path, module):
            theirs = _layer(target)
            if own is not None and theirs is not None and theirs > own:
                offences.append(
                    f"{module} ({LAYERS[own][0]} layer) imports {target} ({LAYERS[theirs][0]} "
                    f"layer) at {path.relative_to(ROOT.parent)}:{line}"
                )
    assert not offences, "a module imports only from its layer or below:\n" + "\n".join(offences)


def test_no_import_circle_between_modules() -> None:
    graph = {m: {t for _, t in _imports(p, m) if t != m} for p, m in _modules()}
    state: dict[str, int] = {}  # 1 on the current path, 2 done

    def visit(m: str, path: list[str]) -> list[str] | None:
        state[m] = 1
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                return [*path[path.index(t) :], t] if t in path else [*path, t]
            if t not in state and (cycle := visit(t, [*path, t])):
                return cycle
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (cycle := visit(m, [m])):
            raise AssertionError("import circle: " + " -> ".join(cycle))


def test_the_walk_resolves_module_and_relative_imports(tmp_path: Path) -> None:
    """Guards the test itself: ``from pkg import module``, relative and lazy imports are seen."""
    fake = tmp_path / "fake.py"
    fake.write_text(
        "from slam_bridge.system import image_slam\n"
        "from ..ba import state\n"
        "def f():\n"
        "    import slam_bridge.evaluation.metrics\n"
    )
    found = {t for _, t in _imports(fake, "slam_bridge.factors.fake")}
    assert found == {
        "slam_bridge.system.image_slam",
        "slam_bridge.ba.state",
        "slam_bridge.evaluation.metrics",
    }
    assert [_layer(t) for t in sorted(found)] == [2, 6, 7]
    assert _layer("slam_bridge.frontend.base") == 4 and _layer("slam_bridge.slam.map") == 5
    assert _layer("slam_bridge.factors.fake") == 3
    assert _layer("slam_bridge.csv_columns") == 0
    assert _layer("slam_bridge") == 0
