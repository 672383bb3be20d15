"""What an imported checkpoint records about where it came from (``imported_from``; ``modi info`` shows it).

An import keeps what the source files say, not modi's defaults: the authors' iteration, their options, their
data's window and stride, the files' names and SHA-256 digests (so the record names exactly which bytes were
converted), and the modi that converted them. Everything is plain data (str, int, float, bool, None, lists, dicts),
so a checkpoint holding it still loads with ``weights_only``.
"""
from __future__ import annotations

import argparse
import hashlib
import math
import os
import re
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from modi._version import __version__ as modi_version

KINDS = {"modi-released": "released MoDi checkpoint", "encoder-released": "released MoDi encoder checkpoint",
         "ganimator-released": "released GANimator run"}


def sha256_of(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_record(path: str | os.PathLike) -> dict[str, Any]:
    """``{name, path, bytes, sha256}`` of one source file."""
    p = Path(path)
    return {"name": p.name, "path": str(p.resolve()), "bytes": p.stat().st_size, "sha256": sha256_of(p)}


def folder_record(folder: str | os.PathLike, files: Iterable[str | os.PathLike]) -> dict[str, Any]:
    """A run folder as one source: its name, each file's record, and one digest over them (the SHA-256 of the
    sorted ``"name sha256"`` lines), so two folders with the same bytes have the same digest."""
    recs = sorted((file_record(f) for f in files), key=lambda r: r["name"])
    lines = "".join(f"{r['name']} {r['sha256']}\n" for r in recs)
    return {"name": Path(folder).name, "path": str(Path(folder).resolve()), "bytes": sum(r["bytes"] for r in recs),
            "sha256": hashlib.sha256(lines.encode()).hexdigest(), "files": recs}


def plain(value: Any) -> Any:
    """``value`` as plain data (their argparse values: numbers, strings, lists; anything else as its text)."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, argparse.Namespace):
        value = vars(value)
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return str(value)


def iteration_from_name(path: str | os.PathLike) -> int | None:
    """The iteration a released MoDi / encoder checkpoint is named by (``000041.pt``: their loop index when it was
    written, and what their ``--ckpt`` resume starts from), or None for another name."""
    m = re.fullmatch(r"(\d+)", Path(path).stem)
    return int(m.group(1)) if m else None


def adam_steps(optim_state: Any) -> int | None:
    """The largest Adam step count in an optimiser ``state_dict`` (None without one)."""
    try:
        steps = [float(s["step"]) for s in optim_state["state"].values() if "step" in s]
    except (KeyError, TypeError, AttributeError):
        return None
    return int(max(steps)) if steps else None


def iterations_from_steps(steps: int, reg_every: int) -> int | None:
    """Iterations of their loop from its optimiser's step count when every ``reg_every``-th iteration (from 0)
    takes one extra step (their lazy regularisation; ``reg_every`` 0: none). None when no count gives ``steps``."""
    for n in range(steps + 1):
        if n + (math.ceil(n / reg_every) if reg_every else 0) == steps:
            return n
    return None


def released_iterations(path: str | os.PathLike, optim_state: Any = None, reg_every: int = 0
                        ) -> tuple[int | None, str]:
    """(iterations their loop had run when it wrote ``path``, how that is known). Their ``train.py`` and
    ``train_encoder.py`` write ``{i:06d}.pt`` at the end of iteration ``i``, so the file name gives ``i + 1``;
    a renamed file falls back on the optimiser's step count."""
    i = iteration_from_name(path)
    if i is not None:
        return i + 1, f"from the file name {Path(path).name}, written at the end of their iteration {i}"
    steps = adam_steps(optim_state)
    if steps is not None:
        n = iterations_from_steps(steps, reg_every)
        if n is not None:
            return n, f"from their optimiser's step count ({steps} steps)"
    return None, "not recorded in the file"


def window_and_stride(motions: Sequence[Any]) -> tuple[int | None, int | None]:
    """(window, stride) of their preprocessed data (``split_to_fixed_length_clips``): the window is a clip's
    length; the stride is the shift between consecutive clips of one animation (the smallest at which their
    frames coincide), the most common over the file; None where no two clips overlap."""
    def frames(clip: Any) -> np.ndarray | None:
        try:
            rot = np.asarray(clip["rot_edge_no_root"], dtype=np.float64)
            pos = np.asarray(clip["pos_root"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            return None
        return np.concatenate([rot.reshape(rot.shape[0], -1), pos.reshape(pos.shape[0], -1)], axis=1)

    seqs = [frames(c) for c in motions]
    if not seqs or seqs[0] is None:
        return None, None
    window = int(seqs[0].shape[0])
    found: Counter = Counter()
    for a, b in zip(seqs, seqs[1:]):
        if a is None or b is None or a.shape != b.shape:
            continue
        for s in range(1, window):
            if window % s == 0 and np.array_equal(a[s:], b[:window - s]):  # their split asserts window % stride == 0
                found[s] += 1
                break
    return window, (found.most_common(1)[0][0] if found else None)


def record(kind: str, source: dict[str, Any], **fields: Any) -> dict[str, Any]:
    """The ``imported_from`` record: ``kind`` (a key of ``KINDS``), the ``source`` file's (or folder's) record,
    what the file says (``iterations``, ``args``, ``data``, ...) and the modi that imported it."""
    if kind not in KINDS:
        raise ValueError(f"unknown import kind {kind!r}")
    return {"kind": kind, "source": source, **{k: plain(v) for k, v in fields.items()}, "imported_by": modi_version}


__all__ = ["KINDS", "sha256_of", "file_record", "folder_record", "plain", "iteration_from_name", "adam_steps",
           "iterations_from_steps", "released_iterations", "window_and_stride", "record"]
