"""The demodulation coefficients as MoDi writes them: the oracle of the ``modi_ext.demod`` op.

StyleGAN2's demodulation multiplies output channel ``o`` of output entity ``j`` by
``d[b, o, j] = rsqrt(sum_{i, n, u} (W[o, i, j, n, u] s[b, i])^2 + DEMOD_EPS)`` (``s = 1`` without a style), summed in
float32 for half inputs (in fp16 the epsilon rounds to 0, and an all-zero row would give ``inf * 0 = NaN``).
``modi_ext.skeletal.reference`` applies the same formula to its per-sample weights.
"""
from __future__ import annotations

import torch

DEMOD_EPS = 1e-8

__all__ = ["DEMOD_EPS", "demod_coefficients"]


def demod_coefficients(dense: torch.Tensor, style: torch.Tensor | None) -> torch.Tensor:
    """``d[b, o, j]`` for a dense ``(Cout, Cin, E_out, E_in, U)`` weight (``b`` is 1 without style)."""
    w = dense.unsqueeze(0)
    if style is not None:
        w = w * style.view(style.shape[0], 1, -1, 1, 1, 1)
    wf = w.float() if w.dtype in (torch.float16, torch.bfloat16) else w
    return torch.rsqrt(wf.pow(2).sum((2, 4, 5)) + DEMOD_EPS).to(w.dtype)
