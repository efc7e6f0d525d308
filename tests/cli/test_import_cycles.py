"""No module of the package takes part in an import cycle.

A static check: every module under `python/dmlo` is parsed and each import of another dmlo module is an
edge, wherever it stands (module level, inside a function, under `if TYPE_CHECKING:`): a cycle hidden behind
`TYPE_CHECKING` or a lazy import is still two modules that cannot be understood, or moved, one without the
other. Shared types go to a module of their own (`odometry/pair.py`, `simulator/street.py`).

An import names the deepest module it reaches: `from dmlo.odometry.config import X` is an edge to
`dmlo.odometry.config`, not to `dmlo.odometry` (whose `__init__` Python runs first, but which only gathers
its submodules' names); `from dmlo.odometry import Odometry` is an edge to `dmlo.odometry` itself.
"""

from __future__ import annotations

import ast
from pathlib import Path
from support import REPO

PACKAGE = REPO / "python" / "dmlo"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    paths = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
    modules = set(paths)

    def deepest(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        is_package = path.name == "__init__.py"
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = name.split(".") if is_package else name.split(".")[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{alias.name}" for alias in node.names]
            for target in targets:
                if target == "dmlo" or target.startswith("dmlo."):
                    reached = deepest(target)
                    if reached is not None and reached != name:
                        edges.add(reached)
        graph[name] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as the list of its modules (the first repeated at the end), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    stack: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        stack.append(module)
        for imported in sorted(graph.get(module, ())):
            if state.get(imported) == 1:
                return stack[stack.index(imported):] + [imported]
            if imported not in state:
                found = visit(imported)
                if found:
                    return found
        stack.pop()
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state:
            found = visit(module)
            if found:
                return found
    return None


def test_the_graph_sees_the_package() -> None:
    graph = import_graph()
    assert "dmlo.odometry.pipeline" in graph["dmlo.odometry"]
    assert "dmlo.odometry.pair" in graph["dmlo.odometry.pipeline"]
    assert "dmlo.simulator.street" in graph["dmlo.simulator.traffic"]


def test_the_check_finds_a_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_module_takes_part_in_an_import_cycle() -> None:
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])
