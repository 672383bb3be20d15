"""modi_ext's modules import one way: reference -> dense -> kernels/loader -> selfcheck -> dispatch -> ops -> layers.

The graph is read from the sources (ast), module-level and function-level imports alike, so an import moved into a
function to dodge a cycle still counts as the edge it is."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[2] / "modi_ext"
NAME = "modi_ext"


def _modules() -> set[str]:
    return {p.stem for p in PKG.glob("*.py") if p.stem != "__init__"}


def _targets(node: ast.AST, modules: set[str]) -> set[str]:
    """The modi_ext submodules one import statement names (``from modi_ext import a, b``, ``from modi_ext.a import
    x``, ``import modi_ext.a``, relative forms); the package itself (``__init__``) is not an edge."""
    out: set[str] = set()
    if isinstance(node, ast.Import):
        for alias in node.names:
            parts = alias.name.split(".")
            if parts[0] == NAME and len(parts) > 1 and parts[1] in modules:
                out.add(parts[1])
    elif isinstance(node, ast.ImportFrom):
        mod = node.module or ""
        parts = mod.split(".") if mod else []
        if node.level == 1:  # relative to the package
            parts = [NAME] + parts
        if parts[:1] == [NAME]:
            if len(parts) > 1:
                if parts[1] in modules:
                    out.add(parts[1])
            else:
                out.update(a.name for a in node.names if a.name in modules)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for m in sorted(modules):
        tree = ast.parse((PKG / f"{m}.py").read_text(encoding="utf-8"))
        edges: set[str] = set()
        for node in ast.walk(tree):  # every import, at any depth (functions, try blocks, if blocks)
            edges |= _targets(node, modules)
        edges.discard(m)
        graph[m] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state:
                found = visit(d)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_the_graph_reader_sees_function_level_and_relative_imports():
    src = ("import torch\nfrom modi_ext import a, zz\nfrom modi_ext.b import f\nimport modi_ext.c\n"
           "def g():\n    from . import d\n    from .e import h\n")
    got = set()
    for node in ast.walk(ast.parse(src)):
        got |= _targets(node, {"a", "b", "c", "d", "e"})
    assert got == {"a", "b", "c", "d", "e"}
    assert find_cycle({"x": {"y"}, "y": {"z"}, "z": {"x"}}) == ["x", "y", "z", "x"]
    assert find_cycle({"x": {"y"}, "y": set()}) is None


def test_no_import_cycle_in_modi_ext():
    graph = import_graph()
    assert {"reference", "dense", "kernels", "selfcheck", "dispatch", "ops", "layers", "payload"} <= set(graph)
    cycle = find_cycle(graph)
    assert cycle is None, f"import cycle in modi_ext: {' -> '.join(cycle)}"


def test_reference_is_the_oracle_and_imports_nothing_of_the_package():
    assert import_graph()["reference"] == set()


@pytest.mark.parametrize("lower, upper", [("reference", "dense"), ("dense", "kernels"), ("kernels", "selfcheck"),
                                          ("selfcheck", "dispatch"), ("dispatch", "ops"), ("ops", "layers"),
                                          ("payload", "selfcheck")])
def test_the_layers_import_one_way(lower, upper):
    """``lower`` never reaches ``upper`` through any chain of imports."""
    graph = import_graph()
    seen, todo = set(), [lower]
    while todo:
        n = todo.pop()
        for d in graph.get(n, ()):
            if d not in seen:
                seen.add(d)
                todo.append(d)
    assert upper not in seen, f"modi_ext.{lower} reaches modi_ext.{upper}"
