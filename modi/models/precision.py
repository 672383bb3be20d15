"""The precision both trainers run their forward passes in (``--precision``, docs/precision.md).

Not part of a model's config: a resumed run may change it, and a checkpoint records it beside the config.  Weights,
gradients, optimiser states and checkpoints stay fp32 in every precision; bf16 runs the forward passes under
autocast, and the losses take the outputs widened back to fp32.
"""
from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import torch

from modi.errors import UserError

__all__ = ["PRECISIONS", "DEFAULT_PRECISION", "check_precision", "precision_autocast", "widened"]

PRECISIONS = ("fp32", "bf16")
DEFAULT_PRECISION = "fp32"  # also what a checkpoint without the field was trained in


def check_precision(precision: str) -> str:
    """``precision`` if it is one of :data:`PRECISIONS`, else one ``UserError`` naming the choices."""
    if precision not in PRECISIONS:
        raise UserError(f"precision {precision!r}: choose one of {', '.join(PRECISIONS)}")
    return precision


def precision_autocast(precision: str, device: torch.device | str) -> AbstractContextManager:
    """The context of a trainer's forward passes: bf16 autocast on ``device``'s type, or nothing for fp32 (the
    fp32 step runs exactly the ops it ran before the option existed)."""
    if check_precision(precision) == "fp32":
        return nullcontext()
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)


def widened(t: torch.Tensor) -> torch.Tensor:
    """``t`` as the losses take a network's output: fp32 when autocast left it in bf16 (or fp16); an fp32 or float64
    tensor unchanged (the same object: fp32 and float64 runs compute exactly as without autocast)."""
    return t.float() if t.dtype in (torch.bfloat16, torch.float16) else t
