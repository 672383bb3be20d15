"""Dense pure-torch reference of the skeletal operators: the test oracle and the fallback path.

Everything here scatters the compact weights into MoDi's masked dense tensor and runs a dense
``conv1d`` over the flattened (channel x entity) axis; modulation uses MoDi's per-sample weights and a
grouped conv.  Slow on purpose-free zeros, but obviously right.

Conventions (the C++ kernels match these exactly):

* Compact weight of ``skeletal_conv`` / ``skeletal_down``: ``(Cout, nnz, Cin, U)``; pair ``p`` of the CSR
  ``(index, offsets)`` (output entity j -> input entities) owns ``weight[:, p]``.  ``to_dense`` gives
  ``dense[o, i, j, n, u]`` (``(Cout, Cin, E_out, E_in, U)``).
* ``skeletal_conv``: ``y[b,o,j,t] = sum_{n,i,u} W[o,i,j,n,u] x[b,i,n,t+u-h] + bias[o]``, ``h = U // 2``;
  outside ``[0, T)`` x is zero (``"zeros"``) or mirrored without repeating the edge (``"reflect"``: x[-1] = x[1]).
* ``skeletal_down``: the same sum read at fine frame ``2t+u-h``; output length ``T // 2`` (an odd last frame is
  dropped).  Coarse frame ``t`` is centred on fine frame ``2t``.
* ``skeletal_up``: weight ``(Cin, nnz, Cout, U)`` -- the layout of the ``skeletal_down`` (Cout=Cin_up,
  Cin=Cout_up) it is the exact adjoint of, with the same CSR (coarse -> fine) and padding mode; output length
  ``2T``.  Then the StyleGAN2 FIR blur ``[1, 3, 3, 1] / 4`` (unit DC gain times the up factor 2), zero padded
  2 frames before and 1 after: ``out[t] = (v[t-2] + 3 v[t-1] + 3 v[t] + v[t+1]) / 4``.  Bias is added last.
* Modulation: ``style`` ``(B, Cin)`` scales input channels; ``demodulate`` multiplies output ``(b, o, j)`` by
  ``rsqrt(sum_{i, n, u} (W[o,i,j,n,u] s[b,i])^2 + 1e-8)`` (``s = 1`` without style), before the blur and bias.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from modi_ext.demod.reference import DEMOD_EPS
from modi_ext.fir import FIR_TAPS, UP_GAIN
from modi_ext.csr import pair_entity
PADDING_MODES = ("zeros", "reflect")


def to_dense(weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor, n_in: int) -> torch.Tensor:
    """Compact ``(C0, nnz, C1, U)`` -> masked dense ``(C0, C1, E_out, E_in, U)`` (zeros where no pair)."""
    c0, nnz, c1, u = weight.shape
    n_out = offsets.numel() - 1
    flat = pair_entity(offsets, nnz) * n_in + index  # (nnz,) position in E_out*E_in
    dense = weight.new_zeros(c0, n_out * n_in, c1, u)
    dense = dense.index_add(1, flat, weight)
    return dense.view(c0, n_out, n_in, c1, u).permute(0, 3, 1, 2, 4)


def from_dense(dense: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Masked dense ``(C0, C1, E_out, E_in, U)`` -> compact ``(C0, nnz, C1, U)``; entries off the mask are dropped."""
    c0, c1, n_out, n_in, u = dense.shape
    if offsets.numel() - 1 != n_out:
        raise ValueError(f"dense has {n_out} output entities but offsets describes {offsets.numel() - 1}")
    return dense[:, :, pair_entity(offsets, index.numel()), index, :].permute(0, 2, 1, 3).contiguous()


def pad_time(x: torch.Tensor, h: int, mode: str) -> torch.Tensor:
    if h == 0:
        return x
    if mode == "zeros":
        return F.pad(x, (h, h))
    if x.shape[-1] <= h:
        raise ValueError(f"reflect padding of {h} frames needs more than {h} frames, got {x.shape[-1]}")
    return F.pad(x, (h, h), mode="reflect")


def _fold_time(full: torch.Tensor, h: int, length: int, mode: str) -> torch.Tensor:
    """Adjoint of ``pad_time``: padded-domain values (length+2h) folded back onto ``[0, length)``."""
    centre = full[..., h:h + length]
    if mode == "zeros" or h == 0:
        return centre
    if length <= h:
        raise ValueError(f"reflect padding of {h} frames needs more than {h} frames, got {length}")
    left = full[..., :h].flip(-1)            # padded frame h-r mirrors frame r, r = 1..h
    right = full[..., h + length:].flip(-1)  # padded frame h+length+k mirrors frame length-2-k
    zl = centre.new_zeros(centre.shape[:-1] + (length - h - 1,))
    zr = centre.new_zeros(centre.shape[:-1] + (length - 1 - h,))
    head = centre.new_zeros(centre.shape[:-1] + (1,))
    tail = centre.new_zeros(centre.shape[:-1] + (1,))
    return centre + torch.cat([head, left, zl], -1) + torch.cat([zr, right, tail], -1)


def _modulated(dense: torch.Tensor, style: torch.Tensor | None, demodulate: bool, in_axis: int,
               out_entity_axis: int):
    """Per-sample dense weights (B or 1, *dense.shape) and the demodulation coefficients used."""
    w = dense.unsqueeze(0)
    if style is not None:
        shape = [style.shape[0]] + [1] * dense.dim()
        shape[1 + in_axis] = style.shape[1]
        w = w * style.reshape(shape)
    if demodulate:
        # sum over every axis except batch, the output-channel axis and the output-entity axis
        out_ch_axis = 1 - in_axis
        keep = {0, 1 + out_ch_axis, 1 + out_entity_axis}
        dims = [a for a in range(w.dim()) if a not in keep]
        # in fp32 for half inputs: in fp16 the epsilon rounds to 0 and an all-zero row would give inf * 0 = NaN
        wf = w.float() if w.dtype in (torch.float16, torch.bfloat16) else w
        d = torch.rsqrt(wf.pow(2).sum(dims, keepdim=True) + DEMOD_EPS)
        w = w * d.to(w.dtype)
    return w


def skeletal_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """In-place skeletal conv (x ``(B, Cin, E, T)`` -> ``(B, Cout, E, T)``); see the module docstring."""
    return _forward(x, weight, bias, index, offsets, style, demodulate, padding_mode, stride=1)


def skeletal_down(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """Convolutional scaler fine -> coarse (``(B, Cin, E_fine, T)`` -> ``(B, Cout, E_coarse, T//2)``)."""
    return _forward(x, weight, bias, index, offsets, style, demodulate, padding_mode, stride=2)


def _forward(x, weight, bias, index, offsets, style, demodulate, padding_mode, stride):
    b, cin, n_in, t = x.shape
    cout, _, _, u = weight.shape
    h = u // 2
    n_out = offsets.numel() - 1
    dense = to_dense(weight, index, offsets, n_in)  # (Cout, Cin, Eo, Ei, U)
    xp = pad_time(x.reshape(b, cin * n_in, t), h, padding_mode)
    t_out = t if stride == 1 else t // 2
    if style is None and not demodulate:
        wmat = dense.permute(0, 2, 1, 3, 4).reshape(cout * n_out, cin * n_in, u)
        y = F.conv1d(xp, wmat, stride=stride)[..., :t_out]
    else:
        w = _modulated(dense, style, demodulate, in_axis=1, out_entity_axis=2)  # (B|1, Co, Ci, Eo, Ei, U)
        nb = w.shape[0]
        w = w.expand(b, *w.shape[1:]) if nb == 1 else w
        wmat = w.permute(0, 1, 3, 2, 4, 5).reshape(b * cout * n_out, cin * n_in, u)
        y = F.conv1d(xp.reshape(1, b * cin * n_in, -1), wmat, stride=stride, groups=b)[..., :t_out]
    y = y.reshape(b, cout, n_out, t_out)
    if bias is not None:
        y = y + bias.view(1, -1, 1, 1)
    return y


def skeletal_up(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                offsets: torch.Tensor, n_out: int, style: torch.Tensor | None = None, demodulate: bool = False,
                padding_mode: str = "zeros") -> torch.Tensor:
    """Coarse -> fine: exact adjoint of ``skeletal_down`` (weight ``(Cin, nnz, Cout, U)``) then the FIR blur.

    ``(B, Cin, E_coarse, T)`` -> ``(B, Cout, n_out, 2T)``; ``(index, offsets)`` is the coarse -> fine pooling map.
    """
    b, cin, n_c, t = x.shape
    _, _, cout, u = weight.shape
    h = u // 2
    t_out = 2 * t
    dense = to_dense(weight, index, offsets, n_out)  # (Cin, Cout, Ec, Ef, U): the down op's dense weight
    if style is None and not demodulate:
        wmat = dense.permute(0, 2, 1, 3, 4).reshape(cin * n_c, cout * n_out, u)
        full = F.conv_transpose1d(x.reshape(b, cin * n_c, t), wmat, stride=2)
    else:
        w = _modulated(dense, style, demodulate, in_axis=0, out_entity_axis=3)  # (B|1, Ci, Co, Ec, Ef, U)
        w = w.expand(b, *w.shape[1:]) if w.shape[0] == 1 else w
        wmat = w.permute(0, 1, 3, 2, 4, 5).reshape(b * cin * n_c, cout * n_out, u)
        full = F.conv_transpose1d(x.reshape(1, b * cin * n_c, t), wmat, stride=2, groups=b)
    full = full.reshape(b, cout * n_out, -1)
    need = t_out + 2 * h
    full = F.pad(full, (0, need - full.shape[-1])) if full.shape[-1] < need else full[..., :need]
    v = _fold_time(full, h, t_out, padding_mode)
    y = blur(v).reshape(b, cout, n_out, t_out)
    if bias is not None:
        y = y + bias.view(1, -1, 1, 1)
    return y


def blur(v: torch.Tensor) -> torch.Tensor:
    """The up-sampler's FIR (``modi_ext.fir.FIR_TAPS``, ``[1,3,3,1] / 4``) along the last axis, zero padded (2 before,
    1 after)."""
    shape = v.shape
    k = torch.tensor(FIR_TAPS, dtype=v.dtype, device=v.device)
    k = (k * (UP_GAIN / k.sum())).view(1, 1, 4)
    flat = F.pad(v.reshape(-1, 1, shape[-1]), (2, 1))
    return F.conv1d(flat, k).reshape(shape)
