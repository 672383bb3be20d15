"""The plan of the house, enforced: the import graph of ``modi`` and ``modi_ext`` has no cycle and no upward edge.

The graph is read from the sources (ast), with imports at any depth -- an import moved into a function to dodge a
cycle is still the edge it is. Layers, lowest first (a module may import its own layer or any lower one):

    modi_ext                       the extension; never imports modi
    modi._version, modi.errors,    leaves
    modi._lazy
    modi.faults                    signals, atomic writes, locks
    modi.core                      rotations, kinematics, skeleton, topology, body, contacts, ik
    modi.io                        file formats
    modi.data                      Motion, representation, datasets
    modi.viz, modi.evaluation      looking at and measuring motion
    modi.models                    MoDi (with latent, encoder) and GANimator
    modi.interop, modi.export      the authors' released checkpoints; models as files others run (ONNX)
    modi.api                       the public Python API (what ``import modi`` gives)
    modi.cli, modi.blender, modi   the command line, the add-on, the package's front door

Function-level imports outside the CLI and the add-on are few and each says why it is lazy (a comment on its line
or the line above): an optional dependency, an import cost, or a backend that must be chosen first."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("modi", "modi_ext")
LAYERS = [
    ("modi_ext",),
    ("modi._version", "modi.errors", "modi._lazy"),
    ("modi.faults",),
    ("modi.core",),
    ("modi.io",),
    ("modi.data",),
    ("modi.viz", "modi.evaluation"),
    ("modi.models",),
    ("modi.interop", "modi.export"),
    ("modi.api",),
    ("modi.cli", "modi.blender", "modi.__main__", "modi"),
]
LAZY_ALLOWED_IN = ("modi.cli", "modi.blender", "modi.__main__")  # lazy imports keep `modi --help` fast there
MAX_LAZY = 40
EXTENSIONS = {"modi_ext._C", "modi_ext._C_emu"}  # compiled modules: leaves of the graph


def _modules(root: Path = REPO) -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (root / pkg).rglob("*.py"):
            parts = p.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = p
    return out


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _targets(node: ast.AST, current: str, is_pkg: bool, modules: dict[str, Path]) -> set[str]:
    """The modules of ours one import statement loads (the submodule where ``from pkg import sub`` names one)."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name.split(".")[0] in PACKAGES and a.name in modules}
    base = current.split(".") if is_pkg else current.split(".")[:-1]
    if node.level:
        base = base[: len(base) - (node.level - 1)]
        mod = ".".join(base + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    if mod.split(".")[0] not in PACKAGES:
        return set()
    out = set()
    for a in node.names:
        if f"{mod}.{a.name}" in EXTENSIONS:
            continue
        out.add(f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod)
    return {m for m in out if m in modules}


def import_graph(root: Path = REPO) -> tuple[dict[str, set[str]], list[tuple[str, int, str, bool]]]:
    """(edges, function-level imports as (module, line, text, has_comment))."""
    modules = _modules(root)
    edges: dict[str, set[str]] = {m: set() for m in modules}
    lazy = []
    for name, path in modules.items():
        src = path.read_text(encoding="utf-8")
        lines = src.splitlines()
        tree = ast.parse(src)

        def walk(node: ast.AST, in_fn: bool) -> None:
            for ch in ast.iter_child_nodes(node):
                if isinstance(ch, (ast.Import, ast.ImportFrom)):
                    edges[name] |= _targets(ch, name, _is_package(path), modules) - {name}
                    if in_fn:
                        lazy.append((name, ch.lineno, lines[ch.lineno - 1].strip(), _commented(lines, ch.lineno)))
                walk(ch, in_fn or isinstance(ch, (ast.FunctionDef, ast.AsyncFunctionDef)))

        walk(tree, False)
    return edges, lazy


def _commented(lines: list[str], lineno: int) -> bool:
    """A comment on the import's line, on the line above, or on an import of the same run just above it."""
    i = lineno - 1
    if "#" in lines[i]:
        return True
    while i > 0:
        above = lines[i - 1].strip()
        if above.startswith("#") or (above.startswith(("import ", "from ")) and "#" in above):
            return True
        if not above.startswith(("import ", "from ")):
            return False
        i -= 1
    return False


def layer_of(module: str) -> int:
    best, rank = -1, None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    if rank is None:
        raise AssertionError(f"{module} is in no layer of tests/test_import_graph.py: add its package to LAYERS")
    return rank


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as a path (first == last), or None."""
    colour: dict[str, int] = {}
    stack: list[str] = []

    def visit(v: str) -> list[str] | None:
        colour[v] = 1
        stack.append(v)
        for w in sorted(edges.get(v, ())):
            if colour.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in colour:
                found = visit(w)
                if found:
                    return found
        stack.pop()
        colour[v] = 2
        return None

    for v in sorted(edges):
        if v not in colour:
            found = visit(v)
            if found:
                return found
    return None


def upward_edges(edges: dict[str, set[str]]) -> list[str]:
    return [f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)})"
            for a, targets in sorted(edges.items()) for b in sorted(targets) if layer_of(b) > layer_of(a)]


def test_no_import_cycle():
    edges, _ = import_graph()
    cycle = find_cycle(edges)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_upward_import():
    edges, _ = import_graph()
    assert upward_edges(edges) == []


def test_modi_ext_never_imports_modi():
    edges, _ = import_graph()
    bad = [f"{a} -> {b}" for a, ts in edges.items() if a.startswith("modi_ext") for b in ts
           if b.split(".")[0] == "modi"]
    assert bad == []


def test_few_lazy_imports_each_with_its_reason():
    _, lazy = import_graph()
    counted = [x for x in lazy if not any(x[0] == p or x[0].startswith(p + ".") for p in LAZY_ALLOWED_IN)]
    assert len(counted) <= MAX_LAZY, f"{len(counted)} function-level imports (at most {MAX_LAZY})"
    silent = [f"{m}:{line}: {text}" for m, line, text, commented in counted if not commented]
    assert silent == [], "function-level imports without a comment saying why they are lazy:\n" + "\n".join(silent)


@pytest.mark.parametrize("plant", ["cycle", "upward", "silent_lazy"])
def test_the_checks_catch_a_planted_fault(tmp_path, plant):
    """The checks above are not vacuous: plant each fault in a copy of the tree and see it found."""
    import shutil

    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    if plant == "cycle":
        (tmp_path / "modi" / "core" / "_plant_a.py").write_text("from modi.core import _plant_b\n")
        (tmp_path / "modi" / "core" / "_plant_b.py").write_text("def f():\n    from modi.core import _plant_a  # x\n")
        edges, _ = import_graph(tmp_path)
        assert find_cycle(edges) is not None
    elif plant == "upward":
        (tmp_path / "modi" / "core" / "_plant.py").write_text("import modi.models.ganimator\n")
        edges, _ = import_graph(tmp_path)
        assert any("modi.core._plant" in e for e in upward_edges(edges))
    else:
        (tmp_path / "modi" / "core" / "_plant.py").write_text("def f():\n    import json\n    return json\n")
        _, lazy = import_graph(tmp_path)
        assert ("modi.core._plant", 2, "import json", False) in lazy
