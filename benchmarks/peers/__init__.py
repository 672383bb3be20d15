"""Harnesses that run the authors' released code (``../shared/peers``) beside modi: equality and speed.

They patch the released sources at run time (CPU device, torch forms of their fused CUDA ops) and never copy them.
What the released sources import at run time is declared in setup.py's ``peers`` extra
(``pip install -e '.[peers]'``); a harness whose imports are missing says which package to install.
"""
from __future__ import annotations

import importlib.util


def missing_imports(modules: dict[str, str]) -> list[str]:
    """The packages (pip names) of ``modules`` (import name -> pip name) that cannot be imported here."""
    out = []
    for name, package in modules.items():
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a parent package missing, or a module set to None in sys.modules
            found = False
        if not found:
            out.append(package)
    return out


def unavailable_reason(who: str, modules: dict[str, str]) -> str | None:
    """One line naming what the released ``who`` imports that is not installed, or None when all is there."""
    missing = missing_imports(modules)
    if not missing:
        return None
    return (f"the authors' {who} imports {', '.join(missing)}, not installed here "
            f"(pip install {' '.join(missing)}, or modi's 'peers' extra: pip install -e '.[peers]')")
