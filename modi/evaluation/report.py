"""Evaluation reports: the full results as JSON, and a short Markdown summary for notes and READMEs.

A result is a nested dict. Top-level dict values become Markdown sections (a two-column table of their
scalar entries); lists of per-item dicts (per file, per sequence) stay in the JSON only, counted in the
Markdown, so the summary remains readable with 2,000 samples.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from modi.faults import OutputError, atomic_write, describe_os_error

__all__ = ["write_json", "to_markdown", "write_markdown", "write_reports"]


def _plain(x: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays to Python, NaN/inf to None (JSON has no NaN)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def _atomic_write(path: str | os.PathLike, text: str) -> None:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(describe_os_error(exc, path), exc.errno) from None
    atomic_write(path, text)


def write_json(results: dict[str, Any], path: str | os.PathLike) -> None:
    """Write ``results`` as indented JSON (atomically: temp file + rename)."""
    _atomic_write(path, json.dumps(_plain(results), indent=2, sort_keys=False) + "\n")


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a"
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.3e}"
        return f"{v:.4f}"
    return str(v)


def _table(d: dict[str, Any]) -> list[str]:
    rows = ["| metric | value |", "| --- | --- |"]
    extra: list[str] = []
    for k, v in d.items():
        if isinstance(v, dict):
            extra += ["", f"**{k}**", ""] + _table(v)
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            rows.append(f"| {k} | {len(v)} entries (in the JSON) |")
        elif isinstance(v, list):
            rows.append(f"| {k} | {', '.join(_fmt(x) for x in v)} |")
        else:
            rows.append(f"| {k} | {_fmt(v)} |")
    return rows + extra


def to_markdown(results: dict[str, Any], title: str = "Evaluation") -> str:
    """A Markdown summary: scalars of the top level first, then one section per nested dict."""
    results = _plain(results)
    lines = [f"# {title}", ""]
    top = {k: v for k, v in results.items() if not isinstance(v, dict)}
    if top:
        lines += _table(top) + [""]
    for k, v in results.items():
        if isinstance(v, dict):
            lines += [f"## {k}", ""] + _table(v) + [""]
    return "\n".join(lines).rstrip() + "\n"


def write_markdown(results: dict[str, Any], path: str | os.PathLike, title: str = "Evaluation") -> None:
    _atomic_write(path, to_markdown(results, title))


def write_reports(results: dict[str, Any], json_path: str | os.PathLike | None,
                  md_path: str | os.PathLike | None, title: str = "Evaluation") -> None:
    """Write whichever of the two reports has a path."""
    if json_path is not None:
        write_json(results, json_path)
    if md_path is not None:
        write_markdown(results, md_path, title)
