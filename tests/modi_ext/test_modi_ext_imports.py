"""modi_ext's import graph: no cycle, no import of ``modi``, no upward import, lazy imports documented.

The graph is read from the sources (ast) of every module of the package, recursively, with imports at any depth
(functions, ``try`` and ``if`` blocks alike), so an import moved into a function to dodge a cycle still counts as the
edge it is.  Importing ``modi_ext.a.b`` from outside ``modi_ext.a`` first runs ``modi_ext/a/__init__.py``, so that
edge is in the graph too; the root ``modi_ext/__init__.py`` is the composition root (it runs before every module).

The layers, lowest first; a module imports only from its own layer or below (``LAYERS``):

0. ``runtime.omp_wait``: the standard library only (it must run before torch is imported);
1. the light package ``__init__``s (``runtime``, ``demod``), ``csr`` (neighbor lists -> CSR maps), ``fir`` (the
   time filter's taps and its fast forms) and ``act`` (the bias activation);
2. the references, the oracles: ``fk.reference`` (the one Python FK), ``demod.reference``, ``skeletal.reference``;
3. the dense forms: ``demod.dense``, ``skeletal.dense``, ``fk.dense``;
4. the runtime that finds a call's path: ``runtime.loader``, ``eager``, ``kernels``, ``amp``, ``dispatch``;
5. the ops: ``demod.registration`` / ``ops``, ``skeletal.checks`` / ``gradfix`` / ``registration`` / ``ops``, ``fk.checks`` /
   ``gradfix`` / ``registration`` / ``ops``, and the ``skeletal`` and ``fk`` packages (their ``__init__`` re-exports
   the ops);
6. the runtime that checks the kernels: ``runtime.payload``, ``runtime.selfcheck`` (they run the references and the
   demod op; ``dispatch`` is handed the self-check by the root instead of importing it);
7. ``layers`` (the ``nn.Module``s);
8. ``validate`` (the GPU validation command).
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NAME = "modi_ext"
LAYERS: list[set[str]] = [
    {"runtime.omp_wait"},
    {"runtime", "demod", "csr", "fir", "act"},
    {"fk.reference", "demod.reference", "skeletal.reference"},
    {"demod.dense", "skeletal.dense", "fk.dense"},
    {"runtime.loader", "runtime.eager", "runtime.kernels", "runtime.amp", "runtime.dispatch"},
    {"demod.registration", "demod.ops", "skeletal.checks", "skeletal.gradfix", "skeletal.registration", "skeletal.ops",
     "skeletal", "fk.checks", "fk.gradfix", "fk.registration", "fk.ops", "fk"},
    {"runtime.payload", "runtime.selfcheck"},
    {"layers"},
    {"validate"},
]
RANK = {f"{NAME}.{m}": i for i, layer in enumerate(LAYERS) for m in layer}
LAZY = re.compile(r"#.*\blazy\b", re.IGNORECASE)  # the comment that documents an import inside a function


def modules(pkg_dir: Path, name: str = NAME) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of the package, recursively (``__init__`` is the package)."""
    out = {}
    for path in sorted(pkg_dir.rglob("*.py")):
        parts = [name, *path.relative_to(pkg_dir).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _package_of(module: str, path: Path) -> str:
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def imports(module: str, path: Path, known: set[str]) -> list[tuple[str, str | None, ast.stmt, bool]]:
    """Every import statement of ``module``, at any depth: ``(target module, name imported from it or None, node,
    inside a function)``.  ``from pkg import sub`` targets the submodule ``pkg.sub`` when it is one."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = _package_of(module, path)
    found: list[tuple[str, str | None, ast.stmt, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.extend((alias.name, None, child, in_function) for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    anchor = package.split(".")
                    anchor = anchor[:len(anchor) - (child.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                for alias in child.names:
                    sub = f"{base}.{alias.name}"
                    found.append((sub, None, child, in_function) if sub in known else
                                 (base, alias.name, child, in_function))
            visit(child, inner)

    visit(tree, False)
    return found


def _ancestors(module: str) -> list[str]:
    parts = module.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def import_graph(pkg_dir: Path, name: str = NAME) -> dict[str, set[str]]:
    """``{module: modules it imports}`` within the package, with the ``__init__`` of every package an import enters
    (those of the importer's own packages already run before it); the root package is not an edge."""
    mods = modules(pkg_dir, name)
    graph: dict[str, set[str]] = {}
    for m, path in mods.items():
        own = set(_ancestors(m)) | {_package_of(m, path)}
        edges: set[str] = set()
        for target, _, _, _ in imports(m, path, set(mods)):
            for t in [*_ancestors(target), target]:
                if t in mods and t != name and t not in own:
                    edges.add(t)
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


def _reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for d in graph.get(todo.pop(), ()):
            if d not in seen:
                seen.add(d)
                todo.append(d)
    return seen


PKG = ROOT / NAME
MODULES = modules(PKG)
GRAPH = import_graph(PKG)


# ------------------------------------------------------------------------------------------------ the reader itself
def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root


def test_the_reader_sees_every_form_and_depth(tmp_path):
    pkg = _write(tmp_path / "p", {"__init__.py": "", "a.py": "", "b.py": "", "c.py": "", "d.py": "", "e.py": "",
                                  "sub/__init__.py": "", "sub/f.py": "from .. import a\nfrom ..b import x\n",
                                  "z.py": "import torch\nfrom p import a, zz\nfrom p.b import f\nimport p.c\n"
                                          "def g():\n    from . import d\n    from .e import h\n"
                                          "    from p.sub import f\n"})
    graph = import_graph(pkg, "p")
    assert graph["p.z"] == {"p.a", "p.b", "p.c", "p.d", "p.e", "p.sub", "p.sub.f"}
    assert graph["p.sub.f"] == {"p.a", "p.b"}  # relative imports resolve against the package
    assert find_cycle({"x": {"y"}, "y": {"z"}, "z": {"x"}}) == ["x", "y", "z", "x"]
    assert find_cycle({"x": {"y"}, "y": set()}) is None


def test_a_cycle_through_a_package_init_is_found(tmp_path):
    """``low`` imports ``pkg.ref``, which first runs ``pkg/__init__``, which imports ``pkg.op``, which imports
    ``low``: a cycle, though no module imports one that imports it back directly."""
    pkg = _write(tmp_path / "p", {"__init__.py": "", "low.py": "from p.pkg.ref import x\n",
                                  "pkg/__init__.py": "from p.pkg.op import y\n", "pkg/ref.py": "x = 1\n",
                                  "pkg/op.py": "from p import low\nfrom p.pkg.ref import x\n"})
    graph = import_graph(pkg, "p")
    assert graph["p.pkg.op"] == {"p.low", "p.pkg.ref"}  # its own package's __init__ has already run
    assert find_cycle(graph) is not None


# ------------------------------------------------------------------------------------------------ modi_ext
def test_every_module_has_a_layer():
    assert set(RANK) == set(MODULES) - {NAME}, "place each new module in LAYERS (and the docstring)"


def test_no_import_cycle_in_modi_ext():
    cycle = find_cycle(GRAPH)
    assert cycle is None, f"import cycle in modi_ext: {' -> '.join(cycle)}"


def test_no_upward_import():
    up = [f"{m} (layer {RANK[m]}) imports {d} (layer {RANK[d]})"
          for m, deps in GRAPH.items() if m != NAME for d in deps if RANK[d] > RANK[m]]
    assert not up, "\n".join(up)


def test_modi_ext_never_imports_modi():
    bad = [f"{m}:{node.lineno} imports {target}" for m, path in MODULES.items()
           for target, _, node, _ in imports(m, path, set(MODULES)) if target.split(".")[0] == "modi"]
    assert not bad, "modi_ext is the lower layer: " + "; ".join(bad)


def test_omp_wait_imports_only_the_standard_library():
    """It decides the OpenMP spin before anything loads libgomp: no torch, no numpy, nothing of the package."""
    m = f"{NAME}.runtime.omp_wait"
    targets = {t.split(".")[0] for t, _, _, _ in imports(m, MODULES[m], set(MODULES))}
    assert targets <= {"__future__", "os", "sys", "time"}, targets


@pytest.mark.parametrize("ref", ["fk.reference", "demod.reference", "skeletal.reference"])
def test_the_references_are_plain_torch(ref):
    """The oracles reach no runtime, kernel, dense form or op: only each other, the CSR maps and light inits."""
    reached = _reachable(GRAPH, f"{NAME}.{ref}")
    assert all(RANK[d] <= RANK[f"{NAME}.{ref}"] for d in reached), sorted(reached)


def test_imports_in_functions_are_documented_lazy_ones():
    """An import of a modi_ext module inside a function needs a comment saying why (``# lazy: ...``): an optional
    dependency, or the import cost of a command's ``--help``; everything else belongs at the top."""
    bad = []
    for m, path in MODULES.items():
        lines = path.read_text(encoding="utf-8").splitlines()
        for target, _, node, in_function in imports(m, path, set(MODULES)):
            if in_function and target.split(".")[0] == NAME:
                near = lines[node.lineno - 2:node.end_lineno]
                if not any(LAZY.search(line) for line in near):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {target}")
    assert not bad, "\n".join(bad)


def test_no_module_the_root_runs_imports_the_roots_names():
    """``modi_ext/__init__.py`` defines its names after importing the modules it needs: those modules (and what they
    import) must take names from submodules, never from the half-initialised root."""
    under_root = _reachable(GRAPH, NAME)
    bad = [f"{m}:{node.lineno} imports {name!r} from {NAME}" for m in sorted(under_root)
           for target, name, node, _ in imports(m, MODULES[m], set(MODULES))
           if target == NAME and (name is None or not name.startswith("_C"))]
    assert not bad, "\n".join(bad)

