"""The demod op's registration with ``torch.library``: fake kernels (compile, meta, ``opcheck``) and autograd.

The schemas are C++ (``csrc/demod/schema.cpp``); this is what they need from Python, done on import when the
extension is built.  The backward is the C++ ``demod_scale_backward``; a gradient that must itself be differentiable
(``create_graph``: path length, R1) is recomputed from the torch form (``modi_ext.demod.dense``), so every order of
gradient stays exact.  The same rules make the op's eager ``autograd.Function`` (``kernels.EAGER``).
"""
from __future__ import annotations

import torch

from modi_ext.demod import dense
from modi_ext.runtime import eager, kernels
from modi_ext.runtime.eager import needed
from modi_ext.runtime.loader import HAS_EXT

__all__ = ["ops_defined"]


def ops_defined() -> bool:
    """Whether the C++ library defined the demod op's schemas (an extension built before it existed did not)."""
    return HAS_EXT and hasattr(torch.ops.modi_ext, "demod_scale") and hasattr(torch.ops.modi_ext,
                                                                              "demod_scale_backward")


def torch_form(weight, style, index, offsets, up: bool, n_out: int) -> torch.Tensor:
    """``dense.demod_scale`` without the batch expansion: ``(Bs, Cout, E_out)``, as the C++ op returns it."""
    return dense.demod_scale(weight, index, offsets, style, up, n_out, style.shape[0] if style is not None else 1)


def _setup_context(ctx, inputs, output) -> None:
    weight, style, index, offsets, up, n_out, _eps = inputs
    ctx.save_for_backward(weight, style, index, offsets, output)
    ctx.up, ctx.n_out = up, n_out


def _backward(ctx, grad):
    weight, style, index, offsets, d = ctx.saved_tensors
    want = (needed(ctx, 0), style is not None and needed(ctx, 1))
    none = (None,) * 5
    if not any(want):
        return (None, None) + none
    if torch.is_grad_enabled():  # create_graph: the gradient must have a graph, so take it from the torch form
        inputs = [t for t, w in zip((weight, style), want) if w]
        with torch.enable_grad():
            d_t = torch_form(weight, style, index, offsets, ctx.up, ctx.n_out)
            got = iter(torch.autograd.grad(d_t, inputs, grad, create_graph=True))
        gw, gs = (next(got) if w else None for w in want)
        return (gw, gs) + none
    gw, gs = torch.ops.modi_ext.demod_scale_backward(grad.contiguous(), d, weight, style, index, offsets, ctx.up,
                                                     ctx.n_out, list(want))
    return (gw if want[0] else None, gs if want[1] else None) + none


def _register() -> None:
    @torch.library.register_fake("modi_ext::demod_scale")
    def _fake(weight, style, index, offsets, up, n_out, eps):
        c_out, e_out = (weight.shape[2], n_out) if up else (weight.shape[0], offsets.shape[0] - 1)
        return weight.new_empty((style.shape[0] if style is not None else 1, c_out, e_out))

    @torch.library.register_fake("modi_ext::demod_scale_backward")
    def _fake_backward(grad, d, weight, style, index, offsets, up, n_out, output_mask):
        gw = torch.empty_like(weight) if output_mask[0] else weight.new_empty(0)
        gs = torch.empty_like(style) if (style is not None and output_mask[1]) else weight.new_empty(0)
        return gw, gs

    torch.library.register_autograd("modi_ext::demod_scale", _backward, setup_context=_setup_context)
    kernels.EAGER["demod_scale"] = eager.make_function(
        "demod_scale_eager", lambda *a: kernels.KERNELS["demod_scale"](*a), _setup_context, _backward)


if ops_defined():
    _register()
