"""What an op does under ``torch.autocast``: one dtype for its inputs, autocast's dtype for its output.

The kernels and the checks take one floating dtype, and autocast does not cast the inputs of custom ops, so each op
casts them itself and runs with autocast off:

* on CUDA, to the autocast dtype, as torch's own convolutions;
* on the CPU under bf16 autocast, to bfloat16 where the bf16 kernels run (``dispatch.cpu_bf16_kernels``: AVX-512-BF16,
  or their emulation when asked for) and no input is float64;
* elsewhere on the CPU, to the widest input dtype and at least float32, so the fp32 kernels run (3.5x faster than the
  dense form on oneDNN's bf16 GEMMs, and more accurate); the output is then rounded to bfloat16 under bf16 autocast,
  autocast's rule for convolutions, unless an input is float64 (autocast leaves float64 alone).  Explicit bf16 inputs
  outside autocast still take the bf16 path.
"""
from __future__ import annotations

import torch

__all__ = ["autocast_device", "cast"]


def autocast_device(x) -> str | None:
    """The device type whose autocast is on for ``x`` (None: off, or ``x`` is not a tensor)."""
    if not isinstance(x, torch.Tensor):
        return None
    dev = x.device.type
    try:
        return dev if torch.is_autocast_enabled(dev) else None
    except (RuntimeError, TypeError):  # a device type autocast does not know
        return None


def cast(dev: str, *tensors, bf16_kernels: bool = False):
    """``(tensors cast to the op's one dtype, output dtype or None for "the inputs'")``; non-float entries pass.
    ``bf16_kernels``: the op's CPU kernels take bfloat16 (then bf16 autocast runs them in bf16)."""
    floats = [t for t in tensors if isinstance(t, torch.Tensor) and t.is_floating_point()]
    target, out = torch.get_autocast_dtype(dev), None
    if dev != "cuda":
        if target == torch.bfloat16 and all(t.dtype != torch.float64 for t in floats):
            if dev == "cpu" and bf16_kernels:
                return tuple(t.to(target) if isinstance(t, torch.Tensor) and t.is_floating_point() else t
                             for t in tensors), None
            out = torch.bfloat16
        target = torch.float32
        for t in floats:
            target = torch.promote_types(target, t.dtype)
    return tuple(t.to(target) if isinstance(t, torch.Tensor) and t.is_floating_point() else t
                 for t in tensors), out
