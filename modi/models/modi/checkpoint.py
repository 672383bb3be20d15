"""MoDi checkpoint files: the format tag, reading with validation, atomic writing (``modi.faults``).

Shared by ``training`` (writes), ``sampling`` (reads) and the encoder, so none of them imports another for it.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from modi.errors import CheckpointError
from modi.faults import atomic_torch_save  # the one atomic writer (disk full: one clear line)
from modi.io.safe_load import earlier_modi_globals, load_data

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
        # as data only (plus TorchVersion, a str subclass early drafts stored): a file naming any other code is
        # refused unrun (UnsafeFileError, one line)
        st = load_data(path, "MoDi checkpoint", allowed=earlier_modi_globals(),
                       hint="; only checkpoints written by 'modi train' load (the authors' released ones convert "
                            "with 'modi import modi-released')")
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
