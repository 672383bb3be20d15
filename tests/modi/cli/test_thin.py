"""The CLI is a thin layer over ``modi.api``: a command module parses, makes one API call and prints.

Checked from the sources (ast, imports at any depth, lazy ones included): a module of ``modi/cli/commands`` may
import from modi only

* ``modi.api`` and its submodules -- where the work is (loading, computing, writing files);
* ``modi.cli`` -- the argparse types and checks (``modi.cli.types``) and sibling commands' option groups;
* ``modi.errors`` -- the ``UserError`` a parsing check raises;
* ``modi.io.formats.add_format_options`` and ``modi.viz.add_view_option`` -- option groups (``--format``,
  ``--no-view``) that every command writing motion shares; nothing else of those packages.

Never ``modi.models``, ``modi.evaluation``, ``modi.data``, ``modi.core``, ``modi.io`` readers, ``modi.interop``,
``modi.export`` or ``modi.faults``: a command that needs one of those holds logic a Python user needs too, and it
belongs in ``modi.api``. Parse-time facts (preset names, unit names, the contact rule) come through
``modi.api.options``. Every function-level import of a command module says why it is lazy."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
COMMANDS = REPO / "modi" / "cli" / "commands"

ALLOWED_MODULES = ("modi.api", "modi.cli", "modi.errors")  # and their submodules, any name
ALLOWED_NAMES = {"modi.io.formats": {"add_format_options"}, "modi.viz": {"add_view_option"}}

# commands not thinned yet, each with its reason (remove an entry when its command is thinned)
EXCEPTIONS: dict[str, str] = {}


def _imports(source: str, module: str) -> list[tuple[int, str, list[str], bool]]:
    """(line, module imported from, names, inside a function) for every import of ``modi`` in ``source``."""
    out = []
    tree = ast.parse(source)

    def walk(node: ast.AST, in_fn: bool) -> None:
        for ch in ast.iter_child_nodes(node):
            if isinstance(ch, ast.Import):
                out.extend((ch.lineno, a.name, [], in_fn) for a in ch.names if a.name.split(".")[0] == "modi")
            elif isinstance(ch, ast.ImportFrom):
                if ch.level:
                    base = module.split(".")[:-ch.level]
                    mod = ".".join(base + ([ch.module] if ch.module else []))
                else:
                    mod = ch.module or ""
                if mod.split(".")[0] == "modi":
                    out.append((ch.lineno, mod, [a.name for a in ch.names], in_fn))
            walk(ch, in_fn or isinstance(ch, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(tree, False)
    return out


def violations(source: str, module: str) -> list[str]:
    """The imports of one command module that reach past the allow-list, as ``line: text``."""
    bad = []
    for line, mod, names, _ in _imports(source, module):
        if any(mod == m or mod.startswith(m + ".") for m in ALLOWED_MODULES):
            continue
        if mod == "modi" and names and all(f"modi.{n}".startswith(ALLOWED_MODULES) for n in names):
            continue  # ``from modi import api``
        allowed = ALLOWED_NAMES.get(mod)
        if allowed is not None and names and set(names) <= allowed:
            continue
        bad.append(f"{line}: {mod} ({', '.join(names) or 'module'})")
    return bad


def _commands() -> list[Path]:
    return sorted(p for p in COMMANDS.glob("*.py") if p.stem != "__init__")


@pytest.mark.parametrize("path", _commands(), ids=lambda p: p.stem)
def test_command_imports_only_the_api_and_parsing_helpers(path):
    if path.stem in EXCEPTIONS:
        pytest.skip(f"not thinned yet: {EXCEPTIONS[path.stem]}")
    bad = violations(path.read_text(encoding="utf-8"), f"modi.cli.commands.{path.stem}")
    assert bad == [], (f"{path.relative_to(REPO)} reaches past modi.api (move the work into modi/api, see this "
                       "test's docstring):\n" + "\n".join(bad))


@pytest.mark.parametrize("path", _commands(), ids=lambda p: p.stem)
def test_every_lazy_import_of_a_command_says_why(path):
    if path.stem in EXCEPTIONS:
        pytest.skip(f"not thinned yet: {EXCEPTIONS[path.stem]}")
    sys.path.insert(0, str(REPO / "tests"))
    try:
        from test_import_graph import _commented
    finally:
        sys.path.remove(str(REPO / "tests"))
    lines = path.read_text(encoding="utf-8").splitlines()
    tree = ast.parse("\n".join(lines))
    silent = []
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                if isinstance(node, (ast.Import, ast.ImportFrom)) and not _commented(lines, node.lineno):
                    silent.append(f"{node.lineno}: {lines[node.lineno - 1].strip()}")
    assert silent == [], f"{path.name}: function-level imports without a comment saying why:\n" + "\n".join(silent)


def test_exceptions_name_real_commands():
    assert set(EXCEPTIONS) <= {p.stem for p in _commands()}


@pytest.mark.parametrize("source, found", [
    ("from modi.models.modi.sampling import write_outputs\n", True),
    ("def f():\n    from modi.evaluation import report  # lazy: x\n", True),
    ("import modi.data.dataset\n", True),
    ("from modi.io.formats import save_motion, add_format_options\n", True),
    ("from modi.viz.render import render_bvh\n", True),
    ("from modi import faults\n", True),
    ("from ...models import ganimator\n", True),
    (("from modi.api.latent import write_mean\nfrom modi.cli import types as ct\nfrom modi.errors import UserError\n"
      "from modi.io.formats import add_format_options\nfrom modi.viz import add_view_option\nimport argparse\n"), False),
    ("from . import data\n", False),
])
def test_the_check_catches_a_planted_import(source, found):
    """Not vacuous: an import of an internal is found, at module level or in a function, absolute or relative."""
    assert bool(violations(source, "modi.cli.commands.planted")) is found
