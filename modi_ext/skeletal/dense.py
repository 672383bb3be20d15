"""The best dense form of each skeletal op: one shared conv, style and demodulation as elementwise scales.

``reference`` spells out MoDi's math literally (per-sample modulated weights, one grouped conv over the batch): the
oracle.  This module computes the same result the way a tuned dense library wants it: the input scaled by the style,
ONE conv with the masked dense weight shared by the whole batch (conv/down: a single GEMM over batch x time on the
time-unfolded input; up: ``reference``'s unmodulated transposed conv), the output scaled by the demodulation
coefficients ``d[b, o, j]`` (``modi_ext.demod.dense``).  No ``(B x weight)`` tensor is ever formed, so at MoDi's finest
modulated level this is several times faster than the grouped form.  Plain torch ops only: every order of gradient
works (R1, path length, WGAN-GP), on any device and dtype torch's convs support.  It is the package's fallback when
the C++ extension is not built, ``MODI_EXT_IMPL=dense``, and the path ``auto`` measures the kernels against on CUDA.
"""
from __future__ import annotations

import torch

from modi_ext.demod.dense import demod_scale
from modi_ext.skeletal import reference

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up"]

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
    xp = reference.pad_time(x.reshape(b, cin * n_in, t), u // 2, padding_mode)
    cols = xp.unfold(-1, u, stride)[:, :, :t_out]  # (B, Cin*E_in, T_out, U)
    cols = cols.permute(1, 3, 0, 2).reshape(cin * n_in * u, b * t_out)
    y = (wmat @ cols).view(cout, n_out, b, t_out)
    return y.permute(2, 0, 1, 3)


def skeletal_conv(x, weight, bias, index, offsets, style=None, demodulate=False, padding_mode="zeros"):
    """In-place skeletal conv: the arguments and semantics of ``reference.skeletal_conv``."""
    return _forward(x, weight, bias, index, offsets, style, demodulate, padding_mode, stride=1)


def skeletal_down(x, weight, bias, index, offsets, style=None, demodulate=False, padding_mode="zeros"):
    """Convolutional scaler fine -> coarse: the arguments and semantics of ``reference.skeletal_down``."""
    return _forward(x, weight, bias, index, offsets, style, demodulate, padding_mode, stride=2)


def _forward(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
             offsets: torch.Tensor, style: torch.Tensor | None, demodulate: bool, padding_mode: str,
             stride: int) -> torch.Tensor:
    y = _shared_conv(_styled(x, style), weight, index, offsets, padding_mode, stride)
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
