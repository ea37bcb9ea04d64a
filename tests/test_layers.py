"""The package's import graph: no module imports itself round a circle, and no lower layer imports a
higher one (function-level imports included: a lazy import is still a dependency)."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

# Lowest first. A module takes the layer of its longest matching prefix.
LAYERS = [
    ("meshseal.errors", "meshseal._lazy", "meshseal.threads", "meshseal.imaging", "meshseal.payload", "meshseal.versions",
     "meshseal.shipped", "meshseal.mesh_formats", "meshseal.messages"),
    ("meshseal.mesh",),
    ("meshseal.render", "meshseal.data"),
    ("meshseal.models", "meshseal.evaluation.metrics", "meshseal.evaluation.attacks", "meshseal.evaluation.paper_plan"),
    ("meshseal.reading",),
    ("meshseal.methods",),
    ("meshseal.training",),
    ("meshseal.api",),
    ("meshseal.evaluation",),
    ("meshseal.commands", "meshseal.cli", "meshseal"),
]


def _modules() -> dict[str, tuple[Path, bool]]:
    found = {}
    for path in (SRC / "meshseal").rglob("*.py"):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        package = parts[-1] == "__init__"
        found[".".join(parts[:-1] if package else parts)] = (path, package)
    return found


def _imports(name: str, path: Path, package: bool, known) -> set[str]:
    base = name if package else name.rsplit(".", 1)[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base.split(".")
                parts = parts[: len(parts) - node.level + 1]
                full = ".".join(parts + ([node.module] if node.module else []))
            else:
                full = node.module or ""
            for candidate in [full] + [f"{full}.{alias.name}" for alias in node.names]:
                if candidate in known and candidate != name:
                    targets.add(candidate)
        elif isinstance(node, ast.Import):
            targets |= {alias.name for alias in node.names if alias.name in known and alias.name != name}
    return targets


def _layer(name: str) -> int:
    best, rank = -1, None
    for index, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            if (name == prefix or name.startswith(prefix + ".")) and len(prefix) > best:
                best, rank = len(prefix), index
    assert rank is not None, f"{name} has no layer"
    return rank


def _graph() -> dict[str, set[str]]:
    known = _modules()
    graph = {name: _imports(name, path, package, known) for name, (path, package) in known.items()}
    # a package's __init__ naming its own submodules (lazy exports) is not a dependency on them
    return {name: {t for t in targets if not t.startswith(name + ".")} for name, targets in graph.items()}


def test_no_module_imports_a_higher_layer():
    wrong = sorted(f"{name} (layer {_layer(name)}) imports {target} (layer {_layer(target)})"
                   for name, targets in _graph().items() for target in targets
                   if _layer(target) > _layer(name) and target != "meshseal")
    assert not wrong, "\n".join(wrong)


def test_the_module_graph_has_no_circles():
    graph, state, circles = _graph(), {}, []

    def visit(name, trail):
        state[name] = "open"
        for target in sorted(graph[name]):
            if state.get(target) == "open":
                circles.append(" -> ".join(trail[trail.index(target):] + [target]))
            elif target not in state:
                visit(target, trail + [target])
        state[name] = "done"

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not circles, "\n".join(circles)
