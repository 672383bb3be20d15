"""Small helpers the public API shares: checked input paths, devices, torch threads."""
from __future__ import annotations

import torch

from modi.errors import UserError
from modi.faults import existing_file  # noqa: F401  (re-exported for the API modules)


def check_device(device: str | torch.device) -> torch.device:
    """A torch device that exists here (``UserError`` for CUDA without a CUDA device, or an unknown name)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise UserError(f"--device: unknown device {device!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda requested but torch has no CUDA device")
    return dev


def set_threads(threads: int | None) -> None:
    """``torch.set_num_threads`` when a count is given (``UserError`` below 1)."""
    if threads is None:
        return
    if threads < 1:
        raise UserError(f"--threads must be >= 1, got {threads}")
    torch.set_num_threads(int(threads))
