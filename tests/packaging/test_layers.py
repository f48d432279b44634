"""The package's import graph, read from the modules' source: no module imports itself through others (no
cycle), no subpackage imports itself through others (``config`` and ``data`` each above or below the other, never
both), and no engine or helper module imports the layers above it (the console scripts and the pipeline)."""

from __future__ import annotations

import ast
from pathlib import Path

import tracegs

PACKAGE_DIR = Path(tracegs.__file__).parent
# Top layer first: a module may import its own layer and the layers below it, never one above.
UPPER_LAYERS = ("tracegs.cli", "tracegs.pipeline")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for path in sorted(PACKAGE_DIR.rglob("*.py"))}


def imported_modules(name: str, path: Path, known: set[str]) -> set[str]:
    """The package modules ``name`` imports anywhere in its source (inside functions too): ``from a import b``
    counts as importing module ``a.b`` when that is a module, else ``a``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            found |= {f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names}
    return {module for module in found if module in known and module != name}


def import_graph() -> dict[str, set[str]]:
    found = modules()
    return {name: imported_modules(name, path, set(found)) for name, path in found.items()}


def package(module: str) -> str:
    """The subpackage a module belongs to (``tracegs.data.colmap`` -> ``tracegs.data``); a module of the top level
    (``tracegs.io``) is its own."""
    return ".".join(module.split(".")[:2])


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The module graph with each subpackage's modules merged into one node."""
    merged: dict[str, set[str]] = {}
    for module, targets in graph.items():
        merged.setdefault(package(module), set()).update(package(t) for t in targets if package(t) != package(module))
    return merged


def layer(module: str) -> int:
    """0 for the console scripts, 1 for the pipeline, 2 for everything below them."""
    for depth, prefix in enumerate(UPPER_LAYERS):
        if module == prefix or module.startswith(prefix + "."):
            return depth
    return len(UPPER_LAYERS)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_graph_is_read_from_the_source():
    graph = import_graph()
    assert "tracegs.pipeline.upstream" in graph["tracegs.pipeline.train"]
    assert "tracegs.location" in graph["tracegs.data.colmap"]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    # Two modules of different subpackages importing each other's package make a cycle of packages.
    assert cycles(package_graph({"t.a.x": {"t.b.y"}, "t.b.y": set(), "t.b.z": {"t.a.w"}, "t.a.w": set()})) == [
        ["t.a", "t.b"]]


def test_the_config_location_is_on_the_ground_floor():
    assert import_graph()["tracegs.location"] == set()


def test_the_stage_table_is_on_the_ground_floor():
    """Every package's config dataclasses read the product graph (through tracegs.products)."""
    assert import_graph()["tracegs.stages"] == {"tracegs.modes"}


def test_no_import_cycle():
    assert cycles(import_graph()) == []


def test_no_import_cycle_between_packages():
    assert cycles(package_graph(import_graph())) == []


def test_no_arrow_up_to_the_cli_or_the_pipeline():
    upward = [f"{module} -> {target}" for module, targets in import_graph().items() for target in sorted(targets)
              if layer(target) < layer(module)]
    assert upward == []
