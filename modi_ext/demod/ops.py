"""The public demod op: the coefficients the skeletal kernels are handed -- check, pick the implementation, call it.

``modi_ext.demod.dense.demod_scale`` computes ``d[b, o, j] = rsqrt(s[b]^2 . sum_{n in j, u} W^2 + eps)`` in about a
dozen small torch ops, and as many again in its backward: on the CPU each is a parallel region of its own (together a
few percent of a modulated layer on a quiet machine, as much as its two convolutions when another process holds a
core), on CUDA each is a launch.  The kernels do it in one call each way: ``csrc/demod/cpu.cpp`` (one task-pool job,
float32/float64) and ``csrc/demod/cuda.cu`` (one or two launches, every CUDA float type).  ``dispatch.route`` picks
the path as for every op (``MODI_EXT_IMPL``, or this call's ``impl=``; the first-use self-check covers these
kernels); ``ref`` and ``dense`` are both the torch form, which is also the oracle.  CPU bfloat16 runs the float32
op on its values widened, and rounds the result once.  ``MODI_EXT_DEMOD=torch`` asks for
the torch form everywhere (for comparisons).  Autograd: ``modi_ext.demod.registration``.

The skeletal ops check the arguments before they call this (``modi_ext.skeletal.checks``); the C++ ops check them
again.
"""
from __future__ import annotations

import os

import torch

from modi_ext.demod import dense, registration
from modi_ext.demod.reference import DEMOD_EPS
from modi_ext.runtime import dispatch, kernels

__all__ = ["demod_scale", "kernel_available"]


def kernel_available() -> bool:
    """Whether this build has the C++ demodulation op (an extension built before it existed does not)."""
    return registration.ops_defined()


def demod_scale(weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor, style: torch.Tensor | None,
                up: bool, n_out: int, batch: int, *, impl: str | None = None) -> torch.Tensor:
    """Demodulation coefficients ``(batch, Cout, E_out)``, as ``dense.demod_scale`` (same arguments and result)."""
    if weight.dtype == torch.bfloat16 and weight.device.type == "cpu" and kernel_available():
        # the CPU op takes float32/float64: the values widened, summed in fp32 (as the torch form sums half types),
        # the result rounded once
        widened = style.float() if style is not None else None
        return demod_scale(weight.float(), index, offsets, widened, up, n_out, batch, impl=impl).to(torch.bfloat16)
    if os.environ.get("MODI_EXT_DEMOD", "auto") == "torch" or not kernel_available():
        path = "dense"
        dispatch.record_path("demod_scale", weight, path)
    else:
        path = dispatch.route("demod_scale", weight, "demod", impl=impl, record=True)
    if path != "ext":  # 'dense' and 'ref': the torch form
        return dense.demod_scale(weight, index, offsets, style, up, n_out, batch)
    d = kernels.launch("demod_scale", weight, style, index, offsets, up, n_out, DEMOD_EPS)
    return d if d.shape[0] == batch else d.expand(batch, -1, -1).contiguous()
