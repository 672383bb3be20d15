"""The demodulation coefficients in torch ops: the dense form of ``demod_scale`` (and its building blocks).

``d[b, o, j] = rsqrt(s[b]^2 . sum_{n in j, u} W^2 + eps)`` computed from the compact weight without a per-sample
weight tensor: the squared taps summed per output entity (``square_segment_sum``, a one-hot matmul: deterministic on
every device), then one small product with the squared style.  Plain torch ops, differentiable to any order.  It is
what ``modi_ext.skeletal.dense`` scales its shared conv by, and what ``modi_ext.demod.ops`` runs wherever the C++ op
does not (CUDA, half precision, compile) and checks its own against.
"""
from __future__ import annotations

import torch

from modi_ext.demod.reference import DEMOD_EPS
from modi_ext.csr import pair_entity

__all__ = ["demod_scale", "segment_sum", "square_segment_sum"]

_HALF = (torch.float16, torch.bfloat16)


def segment_sum(values: torch.Tensor, segment: torch.Tensor, n_segments: int) -> torch.Tensor:
    """``out[a, j, c] = sum_{p: segment[p] == j} values[a, p, c]`` as a one-hot matmul.

    Deterministic on every device (``index_add`` uses atomics on CUDA, whose summation order varies run to run) and
    differentiable to any order.  ``values`` is ``(A, nnz, C)``; the one-hot matrix is ``(n_segments, nnz)``, tiny.
    """
    rows = torch.arange(n_segments, device=segment.device).unsqueeze(1)
    onehot = (segment.unsqueeze(0) == rows).to(values.dtype)
    return torch.einsum("jp,apc->ajc", onehot, values)


class _SquareSegmentSum(torch.autograd.Function):
    """``out[a, j, c] = sum_{p in segment j} sum_u w[a, p, c, u]^2``: the weight term of the demodulation.

    Why a Function: as ``w.pow(2).sum(-1)`` autograd runs a pow, a reduction over a last axis of 3-5 taps (a slow
    layout for torch's reducer), then in the backward an expand, two multiplies and a pow again, every one a pass over
    the whole weight and, on a loaded machine, every one a parallel region waiting for its slowest thread.  Here the
    forward is one pass per tap and the backward one broadcast multiply, ``2 w g[segment]``; it is written in torch
    ops, so it is differentiable again (R1, path length).
    """

    @staticmethod
    def forward(w: torch.Tensor, segment: torch.Tensor, n_segments: int) -> torch.Tensor:
        q = w[..., 0].square()
        for u in range(1, w.shape[-1]):
            q = q + w[..., u].square()
        return segment_sum(q, segment, n_segments)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        w, segment, _ = inputs
        ctx.save_for_backward(w, segment)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        w, segment = ctx.saved_tensors
        return w * (2.0 * grad.index_select(1, segment)).unsqueeze(-1), None, None


def square_segment_sum(w: torch.Tensor, segment: torch.Tensor, n_segments: int) -> torch.Tensor:
    """``(A, nnz, C, U) -> (A, n_segments, C)``: squared taps summed over ``u`` and over each segment's pairs."""
    return _SquareSegmentSum.apply(w, segment, n_segments)


def demod_scale(weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor, style: torch.Tensor | None,
                up: bool, n_out: int, batch: int) -> torch.Tensor:
    """Demodulation coefficients ``(B, Cout, E_out)`` without a per-sample weight: ``s^2 @ sum_{n,u} W^2``.

    Half inputs are summed in float32 (in fp16 the 1e-8 epsilon rounds to 0, so an all-zero row would give
    ``rsqrt(0) = inf`` and ``inf * 0 = NaN``); the result is returned in the weight's dtype (``rsqrt(1e-8) = 1e4``
    fits fp16).
    """
    out_dtype = weight.dtype
    if out_dtype in _HALF:
        weight = weight.float()
        style = style.float() if style is not None else None
    if up:
        acc = square_segment_sum(weight, index, n_out)  # (Ci, Ef, Co)
        a = (torch.einsum("bi,ifo->bof", style.pow(2), acc) if style is not None
             else acc.sum(0).transpose(0, 1).unsqueeze(0))
    else:
        acc = square_segment_sum(weight, pair_entity(offsets, index.shape[0]), n_out)  # (Co, Eo, Ci)
        a = torch.einsum("bi,oji->boj", style.pow(2), acc) if style is not None else acc.sum(2).unsqueeze(0)
    d = torch.rsqrt(a + DEMOD_EPS)
    return d.to(out_dtype).expand(batch, -1, -1).contiguous()
