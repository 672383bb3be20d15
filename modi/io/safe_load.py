"""Reading files someone else may have written as data, never as code.

A torch file is a pickle, and unpickling calls whatever function the file names (``os.system`` included), so a
shared checkpoint could run anything the moment it is read. ``torch.load(weights_only=True)`` rebuilds only
tensors, plain containers and scalars, plus the classes a caller allows by name, and refuses any other global
before calling it. Every modi file (checkpoints, encoders, feature extractors, normalisers, the dataset cache) is
read through :func:`load_data`; a caller that must read a foreign format (the authors' checkpoints hold an
``argparse.Namespace``) passes exactly those classes as ``allowed``.
"""
from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
from numpy._core import multiarray
from torch.torch_version import TorchVersion

from modi.errors import CheckpointError, UnreadableFileError, UnsafeFileError

_GLOBAL = re.compile(r"GLOBAL ([\w.]+)")
_OPERAND = re.compile(r"Unsupported operand (\d+)")


def numpy_data_globals() -> list:
    """numpy's array and scalar reconstruction (numeric dtypes only; object arrays stay refused), under numpy 2's
    names and the ``numpy.core`` names files written with numpy 1 carry: data, safe to allow."""
    dtypes = [type(np.dtype(t)) for t in ("float64", "float32", "float16", "int64", "int32", "int16", "int8",
                                          "uint8", "bool")]
    return [multiarray._reconstruct, np.ndarray, np.dtype, *dtypes, multiarray.scalar,
            (multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),
            (multiarray.scalar, "numpy.core.multiarray.scalar")]


def earlier_modi_globals() -> list:
    """Data classes that files written by earlier modi drafts may hold: ``TorchVersion`` (a ``str`` subclass)
    and numpy arrays and scalars; every modi reader allows them."""
    return [TorchVersion, *numpy_data_globals()]


def refused_global(exc: BaseException) -> str | None:
    """The global a weights-only load refused (``posix.system``), or None when it failed for another reason."""
    text = str(exc)
    if "Weights only load failed" not in text and "WeightsUnpickler" not in text:
        return None
    m = _GLOBAL.search(text)
    if m:
        return m.group(1)
    # an opcode the data-only unpickler lacks (text, protocol >= 4 framing) is unreadable, not code; anything
    # else it refused (building an object of a class not allowed) is an object
    return None if _OPERAND.search(text) else "an object that is not data"


def _reason(exc: BaseException) -> str:
    """One short line for an unreadable file (never torch's advice to load it with ``weights_only=False``)."""
    m = _OPERAND.search(str(exc))
    if m:
        return f"not a file of plain data: pickle operation {m.group(1)} is not one a data-only load performs"
    first = (str(exc).strip().splitlines() or [""])[0]
    if len(first) > 100 and ". " in first:  # torch's zip reader appends advice after its first sentence
        first = first.split(". ", 1)[0]
    return first[:200] or type(exc).__name__


def load_data(path: str | os.PathLike, what: str = "modi file", allowed: Iterable[Any] = (),
              hint: str = "") -> Any:
    """``torch.load`` of ``path`` as data only (on the CPU), with the classes in ``allowed`` (as for
    ``torch.serialization.safe_globals``) also accepted. Raises one ``CheckpointError`` line: missing file,
    :class:`UnreadableFileError`, or :class:`UnsafeFileError` (``hint`` appended: what to do instead)."""
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"{p}: no such {what} file" if not p.is_dir() else f"{p}: is a folder, not a {what}")
    try:
        with torch.serialization.safe_globals(list(allowed)), warnings.catch_warnings():
            # torch warns on stderr about a pickle protocol it did not write; the outcome is reported below
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            return torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupt, truncated, foreign or code-bearing: all the user's file
        glob = refused_global(exc)
        if glob is not None:
            raise UnsafeFileError(f"{p}: not a {what}: it holds objects other than data ({glob}); refused without "
                                  f"running anything{hint}", p, glob) from None
        reason = _reason(exc)
        raise UnreadableFileError(f"{p}: not a readable {what} ({reason})", p, reason) from None


__all__ = ["load_data", "numpy_data_globals", "earlier_modi_globals", "refused_global", "UnsafeFileError", "UnreadableFileError"]
