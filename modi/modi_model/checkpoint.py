"""MoDi checkpoint files: the format tag, reading with validation, atomic writing (``modi.faults``).

Shared by ``training`` (writes), ``sampling`` (reads) and the encoder, so none of them imports another for it.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from modi.errors import CheckpointError
from modi.faults import atomic_torch_save  # the one atomic writer (disk full: one clear line)

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


__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "REQUIRED_KEYS", "load_checkpoint", "atomic_torch_save"]
