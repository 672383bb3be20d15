"""The demod op: the coefficients the skeletal kernels are handed, one C++ call on the CPU, torch ops elsewhere.

``modi_ext.demod.dense.demod_scale`` computes ``d[b, o, j] = rsqrt(s[b]^2 . sum_{n in j, u} W^2 + eps)`` in about a
dozen small torch ops, and as many again in its backward.  Each is a parallel region of its own: together they cost a
modulated layer a few percent on a quiet machine, and as much as its two convolutions when another process holds a core
(every region waits for its slowest thread).  On the CPU, for plain float32/float64 tensors in eager mode
(``eager.usable``), the forward and the first-order backward here are one task-pool job each
(``csrc/demod/cpu.cpp``); bfloat16 runs them on its values widened to float32 and rounds the result once.  A backward that must itself be differentiable (``create_graph``: path length, R1) is
recomputed from the torch form, so every order of gradient stays exact.  Everywhere else (CUDA, half precision, compile,
``MODI_EXT_EAGER=0``) it is the torch form; ``MODI_EXT_DEMOD=torch`` asks for the torch form everywhere (for
comparisons).
"""
from __future__ import annotations

import os

import torch

from modi_ext.demod import dense
from modi_ext.demod.reference import DEMOD_EPS
from modi_ext.runtime import dispatch, eager
from modi_ext.runtime.eager import needed
from modi_ext.runtime.loader import HAS_EXT

__all__ = ["demod_scale", "kernel_available"]

_CPU_DTYPES = (torch.float32, torch.float64)


def kernel_available() -> bool:
    """Whether this build has the C++ demodulation op (an extension built before it existed does not)."""
    return HAS_EXT and hasattr(torch.ops.modi_ext, "demod_scale") and hasattr(torch.ops.modi_ext,
                                                                              "demod_scale_backward")


def _run(weight, style, index, offsets, up: bool, n_out: int) -> torch.Tensor:
    """``(Bs, Cout, E_out)`` coefficients from the C++ op; ``Bs`` is the style's batch, 1 without a style."""
    return torch.ops.modi_ext.demod_scale(weight, style, index, offsets, up, n_out, DEMOD_EPS)


def _setup_context(ctx, inputs, output) -> None:
    weight, style, index, offsets, up, n_out = inputs
    ctx.save_for_backward(weight, style, index, offsets, output)
    ctx.up, ctx.n_out = up, n_out


def _backward(ctx, grad):
    weight, style, index, offsets, d = ctx.saved_tensors
    want = (needed(ctx, 0), style is not None and needed(ctx, 1))
    if not any(want):
        return None, None, None, None, None, None
    if torch.is_grad_enabled():  # create_graph: the gradient must have a graph, so take it from the torch form
        inputs = [t for t, w in zip((weight, style), want) if w]
        with torch.enable_grad():
            d_t = _torch_form(weight, style, index, offsets, ctx.up, ctx.n_out)
            got = iter(torch.autograd.grad(d_t, inputs, grad, create_graph=True))
        gw, gs = (next(got) if w else None for w in want)
        return gw, gs, None, None, None, None
    gw, gs = torch.ops.modi_ext.demod_scale_backward(grad.contiguous(), d, weight, style, index, offsets, ctx.up,
                                                     ctx.n_out, list(want))
    return (gw if want[0] else None), (gs if want[1] else None), None, None, None, None


# the op below autograd with the rule above, as the skeletal ops' eager Functions (modi_ext.eager)
_DemodEager = eager.make_function("demod_scale_eager", _run, _setup_context, _backward)


def _torch_form(weight, style, index, offsets, up: bool, n_out: int) -> torch.Tensor:
    """``dense.demod_scale`` without the batch expansion: ``(Bs, Cout, E_out)``."""
    return dense.demod_scale(weight, index, offsets, style, up, n_out, style.shape[0] if style is not None else 1)


def demod_scale(weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor, style: torch.Tensor | None,
                up: bool, n_out: int, batch: int) -> torch.Tensor:
    """Demodulation coefficients ``(batch, Cout, E_out)``, as ``dense.demod_scale`` (same arguments and result)."""
    bf16 = weight.dtype == torch.bfloat16 and (style is None or style.dtype == weight.dtype)
    if (weight.device.type == "cpu" and (weight.dtype in _CPU_DTYPES or bf16)
            and (style is None or style.dtype == weight.dtype)
            and kernel_available() and os.environ.get("MODI_EXT_DEMOD", "auto") != "torch"
            and eager.usable(weight, style, index, offsets)):
        dispatch.record_path("demod_scale", weight, "ext")
        if bf16:  # summed in fp32, as the torch form sums half types; one rounding of the result
            w32, s32 = weight.float(), style.float() if style is not None else None
            d = _DemodEager.apply(w32, s32, index, offsets, up, n_out).to(torch.bfloat16)
        else:
            d = _DemodEager.apply(weight, style, index, offsets, up, n_out)
        return d if d.shape[0] == batch else d.expand(batch, -1, -1).contiguous()
    dispatch.record_path("demod_scale", weight, "dense")
    return dense.demod_scale(weight, index, offsets, style, up, n_out, batch)


def _register_fakes() -> None:
    """Shapes for FakeTensor, ``opcheck`` and ``torch.compile`` tracing of the C++ ops."""

    @torch.library.register_fake("modi_ext::demod_scale")
    def _fake(weight, style, index, offsets, up, n_out, eps):
        c_out, e_out = (weight.shape[2], n_out) if up else (weight.shape[0], offsets.shape[0] - 1)
        return weight.new_empty((style.shape[0] if style is not None else 1, c_out, e_out))

    @torch.library.register_fake("modi_ext::demod_scale_backward")
    def _fake_backward(grad, d, weight, style, index, offsets, up, n_out, output_mask):
        gw = torch.empty_like(weight) if output_mask[0] else weight.new_empty(0)
        gs = torch.empty_like(style) if (style is not None and output_mask[1]) else weight.new_empty(0)
        return gw, gs


if kernel_available():
    _register_fakes()
