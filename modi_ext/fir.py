"""StyleGAN2's FIR filter along time: the one definition of its taps, and the fast forms derived from them.

``FIR_TAPS`` is the [1, 3, 3, 1] binomial filter. Every place that filters time reads it from here: the skeletal
up-sampler's reference (``modi_ext.skeletal.reference.blur``), and the time-axis resamplers below that MoDi's
networks use (the skip path's upsampling, the discriminator's anti-alias blur, the pooling ablation's
downsampling). The C++ and CUDA kernels hard-code the same taps; the first-use self-check compares them with the
reference, which reads them from here.

The fast forms are depthwise convolutions over the rows of a ``(B, C, E, T)`` tensor viewed as ``(B, C*E, 1, T)``:
one op forward and one backward (a sum of shifted slices is about ten ops each way, each a launch on a GPU), and
on the CPU no slower at these sizes than the slices, unlike ``conv1d`` over ``(B*C*E, 1, T)``.  Their weights derive
from the taps, once per dtype and device; the taps' sum is 8, a power of two, so the scaled taps are exact.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

FIR_TAPS = (1.0, 3.0, 3.0, 1.0)
UP_GAIN = 2.0  # the up factor: keeps the DC gain after zero-stuffed upsampling (StyleGAN2's convention)

if FIR_TAPS != FIR_TAPS[::-1]:  # a conv correlates: the taps need no flip because they are symmetric
    raise AssertionError("FIR_TAPS must be symmetric")

_SUM = sum(FIR_TAPS)


_WEIGHTS: dict[tuple, torch.Tensor] = {}


def _weight(gain: float, x: torch.Tensor, groups: int, before: int = 0, after: int = 0) -> torch.Tensor:
    """The filter times ``gain / sum(taps)`` as a depthwise conv weight ``(groups, 1, 1, before + 4 + after)``, with
    ``before`` / ``after`` zero taps: made once per form, dtype and device (a tensor made per call would be a
    host-to-device copy per call on a GPU), then expanded."""
    key = (gain, before, after, x.dtype, x.device)
    w = _WEIGHTS.get(key)
    if w is None:
        taps = [0.0] * before + [t * gain / _SUM for t in FIR_TAPS] + [0.0] * after
        w = torch.tensor(taps, dtype=x.dtype, device=x.device).view(1, 1, 1, -1)
        _WEIGHTS[key] = w
    return w.expand(groups, 1, 1, w.shape[-1])


def _rows(x: torch.Tensor) -> tuple[torch.Tensor, int]:
    """``x`` as ``(N, G, 1, T)`` for a depthwise conv along time over its ``G`` rows per sample."""
    g = x[0].numel() // x.shape[-1] if x.ndim > 1 else 1
    return x.reshape(x.shape[0] if x.ndim > 1 else 1, g, 1, x.shape[-1]), g


def _filter(x: torch.Tensor, form: tuple) -> torch.Tensor:
    """One pass of the filter along the last axis.  ``form``: ``("corr", gain, pad_before, pad_after, stride)`` -- a
    correlation of the zero-padded signal, keeping every ``stride``-th frame -- or ``("trans", gain, length)`` -- zero
    insertion to ``length`` frames (``2T`` or ``2T + 1``) then the filter, as a transposed conv of stride 2."""
    r, g = _rows(x)
    if form[0] == "corr":
        # uneven zero padding as the conv's own even padding of a filter with zero taps on the short side: one op,
        # where a pad then a conv is two (each a launch on a GPU)
        pad = max(form[2], form[3])
        w = _weight(form[1], x, g, pad - form[2], pad - form[3])
        y = F.conv2d(r, w, stride=(1, form[4]), padding=(0, pad), groups=g)
    else:
        w = _weight(form[1], x, g)
        y = F.conv_transpose2d(r, w, stride=(1, 2), padding=(0, 1), output_padding=(0, form[2] - 2 * x.shape[-1]),
                               groups=g)
    return y.reshape(*x.shape[:-1], y.shape[-1])


def _adjoint(form: tuple, n: int) -> tuple:
    """The form of the transposed linear map, for an input of ``n`` frames (the taps are symmetric)."""
    if form[0] == "trans":
        return ("corr", form[1], 1, 1, 2)
    if form[4] == 1:
        return ("corr", form[1], form[3], form[2], 1)
    return ("trans", form[1], n)


class _Fir(torch.autograd.Function):
    """A filter pass whose backward is the adjoint pass, itself a ``_Fir``: one op each way, to any order (R1 and
    path length differentiate the discriminator's and generator's gradients; the autograd of a depthwise conv would
    run its double backward per group)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, form: tuple) -> torch.Tensor:
        ctx.form, ctx.n = form, x.shape[-1]
        return _filter(x, form)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return _Fir.apply(grad.contiguous(), _adjoint(ctx.form, ctx.n)), None


def upsample_time(x: torch.Tensor) -> torch.Tensor:
    """Double the last axis: zero insertion then the FIR with gain ``UP_GAIN`` (linear interpolation): frame 2i is
    0.25 x[i-1] + 0.75 x[i], frame 2i+1 is 0.75 x[i] + 0.25 x[i+1], x zero outside."""
    return _Fir.apply(x, ("trans", UP_GAIN, 2 * x.shape[-1]))


def downsample_time(x: torch.Tensor) -> torch.Tensor:
    """Halve the last axis: the FIR with unit gain (pad 1 each side) then stride 2 (anti-aliased downsampling)."""
    return _Fir.apply(x, ("corr", 1.0, 1, 1, 2))


def blur_time(x: torch.Tensor) -> torch.Tensor:
    """The FIR with unit gain, keeping the length (pad 1 before, 2 after): the anti-alias filter StyleGAN2 puts
    before every strided discriminator conv, so a stride-2 conv then centres coarse frame t on fine frame
    2t + 1/2."""
    return _Fir.apply(x, ("corr", 1.0, 1, 2, 1))


__all__ = ["FIR_TAPS", "UP_GAIN", "upsample_time", "downsample_time", "blur_time"]
