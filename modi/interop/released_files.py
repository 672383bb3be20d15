"""Reading checkpoint files written by the authors' released code: as data, never as code.

Their ``train.py`` pickles an ``argparse.Namespace`` of its options and numpy arrays (normalisation statistics)
beside the state dicts. ``torch.load(weights_only=True)`` with exactly those classes allowed reads them; any other
global in the file (a function, a module) is refused, so a file from someone else cannot run code.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from modi.errors import CheckpointError


def _numpy_globals() -> list:
    """numpy's array-reconstruction globals under their numpy 2 names and the numpy 1 names old files carry."""
    from numpy._core import multiarray

    dtypes = [type(np.dtype(t)) for t in ("float64", "float32", "int64", "int32", "bool", "uint8")]
    out: list = [multiarray._reconstruct, np.ndarray, np.dtype, *dtypes, multiarray.scalar]
    out += [(multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),
            (multiarray.scalar, "numpy.core.multiarray.scalar")]
    return out


ALLOWED_GLOBALS = [argparse.Namespace, *_numpy_globals()]


def load_released_file(path: str | os.PathLike, what: str = "released checkpoint") -> dict[str, Any]:
    """A released checkpoint's top-level dict; one ``CheckpointError`` line for anything unreadable or foreign."""
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"{p}: no such {what} file")
    try:
        with torch.serialization.safe_globals(ALLOWED_GLOBALS):
            st = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupt, truncated, or holding code we refuse to run
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if "Unsupported global" in str(exc):
            glob = str(exc).split("Unsupported global:", 1)[1].strip().split()[1] if "GLOBAL" in str(exc) else "?"
            first = f"it holds {glob}, which is code, not data; refusing to load it"
        raise CheckpointError(f"{p}: not a readable {what} ({first[:200]})") from None
    if not isinstance(st, dict):
        raise CheckpointError(f"{p}: not a {what} (top level is {type(st).__name__}, not a dict)")
    return st


__all__ = ["ALLOWED_GLOBALS", "load_released_file"]
