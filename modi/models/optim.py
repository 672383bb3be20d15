"""What both systems' trainers share about optimisers and the loop's runtime."""
from __future__ import annotations

import contextlib
import gc
from typing import Iterable, Iterator

import torch


def fused_adam(params: Iterable[torch.nn.Parameter], lr: float, betas: tuple[float, float]) -> torch.optim.Adam:
    """Adam with torch's fused kernel where it has one (CPU, CUDA), else the per-tensor loop.

    The loop over a model's tensors is small work in many launches: ~5% of a MoDi CPU step over G's and D's ~120
    tensors (``benchmarks/profile_step.py``), and 3x the fused step for GANimator's small discriminators, stepped
    7-14 times an iteration. Same algorithm (within float rounding, ~1e-7 relative); a checkpoint keeps the setting
    it was saved with (``fused`` is part of the saved param groups)."""
    params = list(params)
    fused = bool(params) and all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
    return torch.optim.Adam(params, lr=lr, betas=betas, fused=fused or None)


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Leave the objects that exist when a training loop starts out of Python's cyclic-GC passes until it ends.

    By then ~300k long-lived objects exist (torch's and modi's modules, the data, the models); every full collection,
    which the autograd graphs of a few hundred steps trigger, re-walks them all. Frozen, they are skipped, and given
    back to the collector afterwards: GANimator's coarse levels 1.7% faster an iteration (in-process A/B;
    ``gc_collect_main`` was 1.9% of a ``modi ganimator train`` run in ``perf``). A freeze the caller already holds
    is left in place."""
    mine = gc.get_freeze_count() == 0
    if mine:
        gc.freeze()
    try:
        yield
    finally:
        if mine:
            gc.unfreeze()
