"""The best dense form of each skeletal op: one shared conv, style and demodulation as elementwise scales.

``reference`` spells out MoDi's math literally (per-sample modulated weights, one grouped conv over the batch): the
oracle.  This module computes the same result the way a tuned dense library wants it: the input scaled by the style,
ONE conv with the masked dense weight shared by the whole batch (conv/down: a single GEMM over batch x time on the
time-unfolded input; up: ``reference``'s unmodulated transposed conv), the output scaled by the demodulation
coefficients ``d[b, o, j]``.  No ``(B x weight)`` tensor is ever formed, so at MoDi's finest
modulated level this is several times faster than the grouped form.  Plain torch ops only: every order of gradient
works (R1, path length, WGAN-GP), on any device and dtype torch's convs support.  It is the package's fallback when
the C++ extension is not built, ``MODI_EXT_IMPL=dense``, and the path ``auto`` measures the kernels against on CUDA.
"""
from __future__ import annotations

import torch

from modi_ext.skeletal import reference
from modi_ext.topology import pair_entity

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up", "demod_scale", "segment_sum"]

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
    d = torch.rsqrt(a + reference.DEMOD_EPS)
    return d.to(out_dtype).expand(batch, -1, -1).contiguous()


def _styled(x: torch.Tensor, style: torch.Tensor | None) -> torch.Tensor:
    return x * style.view(style.shape[0], style.shape[1], 1, 1) if style is not None else x


def _finish(y: torch.Tensor, d: torch.Tensor | None, bias: torch.Tensor | None) -> torch.Tensor:
    if d is not None:
        y = y * d.unsqueeze(-1)
    if bias is not None:
        y = y + bias.view(1, -1, 1, 1)
    return y


def _shared_conv(x: torch.Tensor, weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor,
                 padding_mode: str, stride: int) -> torch.Tensor:
    """``conv1d`` of ``x (B, Cin, E_in, T)`` with the masked dense weight, as ONE GEMM over batch x time.

    ``(Cout*E_out, Cin*E_in*U) @ (Cin*E_in*U, B*T_out)`` on the time-unfolded input: the forward and both backward
    products are single large GEMMs (on the CPU markedly faster than the convolution's own backward, and on CUDA
    cuBLAS's best case), and it is all plain differentiable torch ops.
    """
    b, cin, n_in, t = x.shape
    cout, _, _, u = weight.shape
    n_out = offsets.shape[0] - 1
    t_out = t if stride == 1 else t // 2
    wmat = reference.to_dense(weight, index, offsets, n_in).permute(0, 2, 1, 3, 4).reshape(cout * n_out, -1)
    xp = reference._pad_time(x.reshape(b, cin * n_in, t), u // 2, padding_mode)
    cols = xp.unfold(-1, u, stride)[:, :, :t_out]  # (B, Cin*E_in, T_out, U)
    cols = cols.permute(1, 3, 0, 2).reshape(cin * n_in * u, b * t_out)
    y = (wmat @ cols).view(cout, n_out, b, t_out)
    return y.permute(2, 0, 1, 3)


def skeletal_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """In-place skeletal conv, same semantics as ``reference.skeletal_conv``."""
    y = _shared_conv(_styled(x, style), weight, index, offsets, padding_mode, 1)
    d = demod_scale(weight, index, offsets, style, False, offsets.shape[0] - 1, x.shape[0]) if demodulate else None
    return _finish(y, d, bias).contiguous()


def skeletal_down(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """Convolutional scaler fine -> coarse, same semantics as ``reference.skeletal_down``."""
    y = _shared_conv(_styled(x, style), weight, index, offsets, padding_mode, 2)
    d = demod_scale(weight, index, offsets, style, False, offsets.shape[0] - 1, x.shape[0]) if demodulate else None
    return _finish(y, d, bias).contiguous()


def skeletal_up(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                offsets: torch.Tensor, n_out: int, style: torch.Tensor | None = None, demodulate: bool = False,
                padding_mode: str = "zeros") -> torch.Tensor:
    """Coarse -> fine (transposed conv + blur), same semantics as ``reference.skeletal_up``.

    ``d`` is constant along time, so scaling after the (linear, per-row) blur equals the reference's before it.
    """
    y = reference.skeletal_up(_styled(x, style), weight, None, index, offsets, n_out, None, False, padding_mode)
    d = demod_scale(weight, index, offsets, style, True, n_out, x.shape[0]) if demodulate else None
    return _finish(y, d, bias)
