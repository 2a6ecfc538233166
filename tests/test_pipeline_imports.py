"""``swiftjax.pipeline`` has no import circle: its modules form a layered graph.

Every import of a pipeline module by another counts -- at module level, inside functions and
under ``if TYPE_CHECKING`` -- so a circle cannot hide behind a deferred import.
"""

from __future__ import annotations

import ast
import pathlib

import swiftjax.pipeline

PACKAGE = "swiftjax.pipeline"
ROOT = pathlib.Path(swiftjax.pipeline.__file__).parent


def _modules() -> dict[str, ast.Module]:
    return {p.stem: ast.parse(p.read_text(), str(p)) for p in sorted(ROOT.glob("*.py")) if p.stem != "__init__"}


def _imported(tree: ast.Module, names: set[str]) -> set[str]:
    """The pipeline modules ``tree`` imports anywhere (``ast.walk`` visits function bodies and
    ``if TYPE_CHECKING`` blocks alike)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.ImportFrom):  # relative: from . import x / from .x import y
            base = node.module or ""
            targets = [f"{PACKAGE}.{base}"] + [f"{PACKAGE}.{base + '.' if base else ''}{a.name}" for a in node.names]
        else:
            continue
        for target in targets:
            parts = target.split(".")
            if parts[:2] == ["swiftjax", "pipeline"] and len(parts) > 2 and parts[2] in names:
                found.add(parts[2])
    return found


def import_graph() -> dict[str, set[str]]:
    trees = _modules()
    return {name: _imported(tree, set(trees)) - {name} for name, tree in trees.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (depth-first search), or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(u: str) -> list[str] | None:
        state[u] = 1
        stack.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == 1:
                return stack[stack.index(v) :] + [v]
            if v not in state and (found := visit(v)):
                return found
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state and (found := visit(u)):
            return found
    return None


def test_the_walker_sees_deferred_imports():
    tree = ast.parse(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from swiftjax.pipeline.a import X\n"
        "def f():\n    from swiftjax.pipeline import b\n    import swiftjax.pipeline.c\n"
    )
    assert _imported(tree, {"a", "b", "c", "d"}) == {"a", "b", "c"}
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_pipeline_import_graph_is_acyclic():
    graph = import_graph()
    assert len(graph) >= 10
    circle = _cycle(graph)
    assert circle is None, "import circle in swiftjax/pipeline: " + " -> ".join(circle)


def test_results_is_at_the_bottom():
    """``results`` imports no other pipeline module: every stage can import it."""
    assert import_graph()["results"] == set()
