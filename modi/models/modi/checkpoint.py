"""MoDi checkpoint files: the format tag, reading with validation, atomic writing (``modi.faults``).

Shared by ``training`` and the released-checkpoint import (write, through :func:`checkpoint_dict`), ``sampling``
(reads) and the encoder, so none of them imports another for it.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

import torch

from modi._version import __version__ as modi_version
from modi.errors import CheckpointError
from modi.faults import atomic_torch_save  # the one atomic writer (disk full: one clear line)
from modi.io.safe_load import earlier_modi_globals, load_data

CHECKPOINT_FORMAT = "modi-checkpoint"
CHECKPOINT_VERSION = 1
REQUIRED_KEYS = ("config", "codec", "levels", "G_ema", "step")


def checkpoint_dict(*, config: Any, codec: Any, levels: list, G: torch.nn.Module, G_ema: torch.nn.Module,
                    D: torch.nn.Module, step: int, **extra: Any) -> dict[str, Any]:
    """The one writer of the format: what every MoDi checkpoint holds (enough to generate), plus ``extra`` keys
    (the trainer's optimiser and RNG states for an exact resume, an import's provenance).  Plain containers and
    tensors only, so the file loads with ``weights_only``."""
    return {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": config.to_dict(),
        "codec": codec.state_dict(),
        "skeleton": codec.skeleton.to_dict(),
        "levels": [lv.to_dict() for lv in levels],
        "G": G.state_dict(),
        "G_ema": G_ema.state_dict(),
        "D": D.state_dict(),
        "step": int(step),
        "torch_version": str(torch.__version__),
        "modi_version": modi_version,  # for 'modi info'
        **extra,
    }


def read_tagged(ckpt: str | os.PathLike | dict, noun: str, fmt: str, max_version: int, *,
                foreign: Callable[[Any], str] = lambda st: "", label: str | None = None,
                **load_kwargs: Any) -> tuple[dict[str, Any], str]:
    """``(state, where)`` of a modi file whose dict carries ``format: fmt`` and ``version <= max_version`` (or of
    such a dict itself), read as data only (``load_data``: a file naming code is refused unrun). ``noun`` names
    it in the one-line ``CheckpointError`` anything else raises (``label``, default "MoDi <noun>", in the unreadable
    file's); ``foreign(state)`` adds a hint to "not a ..."."""
    if isinstance(ckpt, dict):
        st, where = ckpt, noun
    else:
        path = Path(ckpt)
        where = str(path)
        if not path.exists():
            raise CheckpointError(f"{path}: no such {noun} file")
        if not path.is_file():
            raise CheckpointError(f"{path}: is not a file")
        st = load_data(path, label or f"MoDi {noun}", **load_kwargs)
    if not isinstance(st, dict) or st.get("format") != fmt:
        raise CheckpointError(f"{where}: not a MoDi {noun}{foreign(st)}")
    if int(st.get("version", 0)) > max_version:
        raise CheckpointError(f"{where}: {noun} version {st.get('version')} is newer than this modi "
                              f"(reads up to {max_version}); upgrade modi")
    return st, where


def load_checkpoint(ckpt: str | os.PathLike | dict) -> dict[str, Any]:
    """Read and validate a MoDi checkpoint; any unreadable or foreign file raises one ``CheckpointError``."""
    # as data only (plus TorchVersion, a str subclass early drafts stored)
    st, where = read_tagged(ckpt, "checkpoint", CHECKPOINT_FORMAT, CHECKPOINT_VERSION,
                            foreign=lambda st: f" (no '{CHECKPOINT_FORMAT}' format tag)",
                            allowed=earlier_modi_globals(),
                            hint="; only checkpoints written by 'modi train' load (the authors' released ones "
                                 "convert with 'modi import modi-released')")
    missing = [k for k in REQUIRED_KEYS if k not in st]
    if missing:
        raise CheckpointError(f"{where}: checkpoint is missing {', '.join(missing)}")
    return st


__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "REQUIRED_KEYS", "checkpoint_dict", "read_tagged", "load_checkpoint",
           "atomic_torch_save"]
