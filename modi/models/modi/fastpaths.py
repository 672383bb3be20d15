"""Faster forms of two steps of the released generator, with the same values to rounding.

The released MoDi normalises each styled conv's output by its standard deviation over (entities, frames) before the
bias and leaky ReLU.  ``std_entities_frames`` is that std in a form several times faster than torch's CPU ``std`` over
two dims (training and sampling); the other two are for sampling only (no graph): one per-row moment pass instead of
four, and the scale, bias and activation in place.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["std_entities_frames", "inv_std_entities_frames", "std_normalised_leaky_relu_"]

SQRT2 = math.sqrt(2.0)


def std_entities_frames(x: torch.Tensor) -> torch.Tensor:
    """``x.std((2, 3), keepdim=True)`` (unbiased) as a centred two-pass sum over the flattened (entity, frame)
    axis: the same value to rounding, and several times faster than torch's CPU ``std`` over two dims, which
    dominated sampling the released generator (docs/results.md)."""
    f = x.flatten(2)
    d = f - f.mean(-1, keepdim=True)
    return (torch.linalg.vecdot(d, d) / (f.shape[-1] - 1)).sqrt()[..., None, None]


def inv_std_entities_frames(x: torch.Tensor) -> torch.Tensor:
    """``1 / std_entities_frames(x)`` without a graph, from ATen's layer-norm row moments: one vectorised pass per
    (sample, channel) row, where the centred two-pass sum makes four passes over a tensor (11 MB at the finest
    level of a 64-motion batch) that no longer fits in L2 (what sampling gains: docs/results.md).  layer_norm's
    rstd is of the biased variance, hence the factor sqrt((n - 1) / n)."""
    n = x.shape[2] * x.shape[3]
    if n < 2:  # the unbiased std of one value is undefined (nan), as torch.std has it
        return std_entities_frames(x).reciprocal_()
    _, _, rstd = torch.native_layer_norm(x.flatten(2), [n], None, None, 0.0)
    return rstd.view(x.shape[0], x.shape[1], 1, 1).mul_(math.sqrt((n - 1) / n))


def std_normalised_leaky_relu_(x: torch.Tensor, bias: torch.Tensor, slope: float = 0.2) -> torch.Tensor:
    """``fused_leaky_relu(x / std_entities_frames(x), bias)`` for inference, in ``x``'s memory (a copy first only if
    ``x`` is not contiguous): sqrt(2) / std folds into one per-(sample, channel) factor, and the scale, the bias and
    the activation run in place, where the autograd form allocates a tensor at each of its six elementwise steps.
    Same values to float rounding; no graph (call it under ``torch.no_grad()``)."""
    x = x.contiguous()
    x.mul_(inv_std_entities_frames(x).mul_(SQRT2)).add_((bias * SQRT2).view(1, -1, 1, 1))
    return F.leaky_relu_(x, slope)
