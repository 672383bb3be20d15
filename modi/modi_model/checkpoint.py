"""MoDi checkpoint files: the format tag, reading with validation, atomic writing.

Shared by ``training`` (writes), ``sampling`` (reads) and the encoder, so none of them imports another for it.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from modi.errors import CheckpointError

CHECKPOINT_FORMAT = "modi-checkpoint"
CHECKPOINT_VERSION = 1
REQUIRED_KEYS = ("config", "codec", "levels", "G_ema", "step")


def load_checkpoint(ckpt: str | os.PathLike | dict) -> dict[str, Any]:
    """Read and validate a MoDi checkpoint; any unreadable or foreign file raises one ``CheckpointError``."""
    if isinstance(ckpt, dict):
        st, where = ckpt, "checkpoint"
    else:
        path = Path(ckpt)
        where = str(path)
        if not path.exists():
            raise CheckpointError(f"{path}: no such checkpoint file")
        if not path.is_file():
            raise CheckpointError(f"{path}: is not a file")
        try:
            from torch.torch_version import TorchVersion  # a str subclass early drafts stored; harmless to allow

            with torch.serialization.safe_globals([TorchVersion]):
                st = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - truncated, corrupt, pickle-bearing or non-torch files
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise CheckpointError(f"{path}: not a readable MoDi checkpoint ({first[:200]})") from None
    if not isinstance(st, dict) or st.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{where}: not a MoDi checkpoint (no '{CHECKPOINT_FORMAT}' format tag)")
    if int(st.get("version", 0)) > CHECKPOINT_VERSION:
        raise CheckpointError(f"{where}: checkpoint version {st.get('version')} is newer than this modi "
                              f"(reads up to {CHECKPOINT_VERSION}); upgrade modi")
    missing = [k for k in REQUIRED_KEYS if k not in st]
    if missing:
        raise CheckpointError(f"{where}: checkpoint is missing {', '.join(missing)}")
    return st


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` to a temp file in the same folder, fsync, then ``os.replace``: readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(obj, fh)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "REQUIRED_KEYS", "load_checkpoint", "atomic_torch_save"]
