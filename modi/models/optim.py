"""What both systems' trainers share about optimisers."""
from __future__ import annotations

from typing import Iterable

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
