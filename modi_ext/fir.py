"""StyleGAN2's FIR filter along time: the one definition of its taps, and the fast forms derived from them.

``FIR_TAPS`` is the [1, 3, 3, 1] binomial filter. Every place that filters time reads it from here: the skeletal
up-sampler's reference (``modi_ext.skeletal.reference.blur``), and the time-axis resamplers below that MoDi's
networks use (the skip path's upsampling, the discriminator's anti-alias blur, the pooling ablation's
downsampling). The C++ and CUDA kernels hard-code the same taps; the first-use self-check compares them with the
reference, which reads them from here.

The fast forms are sums of shifted slices rather than a convolution: the filter has four taps, so a few
elementwise ops at the signal's length beat ``conv1d``'s setup at these sizes. Their coefficients are derived from
the taps once, at import; the taps' sum is 8, a power of two, so multiplying by its reciprocal is exact.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

FIR_TAPS = (1.0, 3.0, 3.0, 1.0)
UP_GAIN = 2.0  # the up factor: keeps the DC gain after zero-stuffed upsampling (StyleGAN2's convention)

if FIR_TAPS != FIR_TAPS[::-1]:  # the fast forms below use the symmetry (outer, inner, inner, outer)
    raise AssertionError("FIR_TAPS must be symmetric")

_SUM = sum(FIR_TAPS)
_RATIO = FIR_TAPS[1] / FIR_TAPS[0]  # inner over outer tap: 3
_NORM = FIR_TAPS[0] / _SUM  # the outer tap of the unit-gain filter: 1/8
_UP_OUTER, _UP_INNER = (k * UP_GAIN / _SUM for k in FIR_TAPS[:2])  # 0.25, 0.75


def upsample_time(x: torch.Tensor) -> torch.Tensor:
    """Double the last axis: zero insertion then the FIR with gain ``UP_GAIN`` (linear interpolation).

    On the zero-inserted signal every output frame has two nonzero taps: frame 2i is 0.25 x[i-1] + 0.75 x[i] and
    frame 2i+1 is 0.75 x[i] + 0.25 x[i+1] (x zero outside). They are computed so, at the input's length, and
    interleaved: the same values bit for bit as filtering the zero-inserted signal (the skipped terms are exact
    zeros, the sums in the same order), in fewer elementwise ops, each at half the output's length."""
    xp = F.pad(x, (1, 1))
    inner = _UP_INNER * x
    return torch.stack([_UP_OUTER * xp[..., :-2] + inner, inner + _UP_OUTER * xp[..., 2:]], dim=-1).flatten(-2)


def _filter(y: torch.Tensor, n: int) -> torch.Tensor:
    """The unit-gain FIR over ``n`` output frames of the padded signal ``y`` (a valid correlation), as
    ``(y0 + 3 y1 + 3 y2 + y3) / 8``: two multiplies fewer than weighting every tap, on tensors of the signal's size."""
    return (y[..., 0:n] + _RATIO * y[..., 1 : n + 1] + _RATIO * y[..., 2 : n + 2] + y[..., 3 : n + 3]) * _NORM


def downsample_time(x: torch.Tensor) -> torch.Tensor:
    """Halve the last axis: the FIR with unit gain (pad 1 each side) then stride 2 (anti-aliased downsampling)."""
    y = F.pad(x, (1, 1))
    return _filter(y, y.shape[-1] - 3)[..., ::2]


def blur_time(x: torch.Tensor) -> torch.Tensor:
    """The FIR with unit gain, keeping the length (pad 1 before, 2 after): the anti-alias filter StyleGAN2 puts
    before every strided discriminator conv, so a stride-2 conv then centres coarse frame t on fine frame
    2t + 1/2."""
    return _filter(F.pad(x, (1, 2)), x.shape[-1])


__all__ = ["FIR_TAPS", "UP_GAIN", "upsample_time", "downsample_time", "blur_time"]
