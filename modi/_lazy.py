"""Lazy exports: a package's public names, each imported from its module on first use.

``import modi`` must not import torch (the CLI takes Ctrl-C at start-up and ``modi --help`` stays fast), and
importing one light submodule must not import every model, so the packages that gather names from heavy modules
(``modi``, ``modi.api``, ``modi.models.modi``) resolve them on first access instead, through the module-level
``__getattr__`` and ``__dir__`` that :func:`lazy_exports` makes.
"""
from __future__ import annotations

import importlib
import sys
from typing import Any, Callable, Mapping


def lazy_exports(package: str, table: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``: ``table`` maps each public name to the module defining it
    (absolute, or relative to ``package`` with a leading dot). A name is imported once, then kept in the
    package's namespace; any other name is an ``AttributeError``, as for a plain module."""

    def __getattr__(name: str) -> Any:
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, package), name)
        setattr(sys.modules[package], name, value)  # resolved once
        return value

    def __dir__() -> list[str]:
        ns = vars(sys.modules[package])
        return sorted(set(ns) | set(ns.get("__all__", ())) | set(table))

    return __getattr__, __dir__
