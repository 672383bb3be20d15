"""The demod op's registration with ``torch.library``: fake kernels (compile, meta, ``opcheck``) and autograd.

The schemas are C++ (``csrc/demod/schema.cpp``); this is what they need from Python, done on import when the
extension is built.  The backward is the C++ ``demod_scale_backward``; a gradient that must itself be differentiable
(``create_graph``: path length, R1) is built in closed form from the saved coefficients (``graph_gradients``), in
torch ops whose graph leads back into this op, so every order of gradient stays exact.  The same rules make the op's eager ``autograd.Function`` (``kernels.EAGER``).
"""
from __future__ import annotations

import torch

from modi_ext.csr import pair_entity
from modi_ext.demod import dense
from modi_ext.runtime import eager, kernels
from modi_ext.runtime.eager import needed
from modi_ext.runtime.loader import HAS_EXT

__all__ = ["ops_defined"]


def ops_defined() -> bool:
    """Whether the C++ library defined the demod op's schemas (an extension built before it existed did not)."""
    return HAS_EXT and hasattr(torch.ops.modi_ext, "demod_scale") and hasattr(torch.ops.modi_ext,
                                                                              "demod_scale_backward")


def _setup_context(ctx, inputs, output) -> None:
    weight, style, index, offsets, up, n_out, _eps = inputs
    ctx.save_for_backward(weight, style, index, offsets, output)
    ctx.up, ctx.n_out = up, n_out


def graph_gradients(grad, d, weight, style, index, offsets, up: bool, n_out: int, want: tuple[bool, bool]):
    """The weight and style gradients of ``d = rsqrt(s^2 . Q + eps)`` as a differentiable graph (``create_graph``).

    With ``Q[o, j, i] = sum_{p in j, u} W[o, p, i, u]^2`` and ``k = g d^3`` (``d`` the op's saved output, whose own
    graph leads back into this op): ``grad_s = -s (k . Q)`` and ``grad_W = -W k[segment] s^2``, the signs carried by
    ``-s`` so that no op multiplies by a constant.  A handful of small ops each way, where re-running the torch form
    and differentiating it took about five times as many, each a launch on CUDA and each differentiated again by the
    step that asked for the graph (path length, R1).
    """
    dtype = weight.dtype
    if dtype in dense._HALF:  # summed in float32, as the torch form does
        grad, d, weight = grad.float(), d.float(), weight.float()
        style = style.float() if style is not None else None
    k = grad * d.pow(3)  # (Bs, Cout, E_out)
    segment = index if up else pair_entity(offsets, index.shape[0])
    neg_s = style.neg() if style is not None else None
    gw = gs = None
    if want[0]:
        if neg_s is None:  # s = 1
            kq = k.sum(0).neg()
            gq = kq.t().unsqueeze(0) if up else kq.unsqueeze(-1)
        else:
            s2 = style * neg_s  # -s^2
            # up: weight (Ci, nnz, Co, U), Q (Ci, Ef, Co); else weight (Co, nnz, Ci, U), Q (Co, Eo, Ci)
            gq = torch.einsum("bof,bi->ifo", k, s2) if up else torch.einsum("boj,bi->oji", k, s2)
        gw = (weight * gq.index_select(1, segment).unsqueeze(-1)).to(dtype)
    if want[1]:  # k . Q summed over the pairs and taps of W^2 directly: no segment sum
        kp = k.index_select(2, segment)  # (B, Cout, nnz)
        kq = (torch.einsum("bop,ipou->bi", kp, weight.square()) if up
              else torch.einsum("bop,opiu->bi", kp, weight.square()))
        gs = (neg_s * kq).to(dtype)
    return gw, gs


def _backward(ctx, grad):
    weight, style, index, offsets, d = ctx.saved_tensors
    want = (needed(ctx, 0), style is not None and needed(ctx, 1))
    none = (None,) * 5
    if not any(want):
        return (None, None) + none
    if torch.is_grad_enabled():  # create_graph: the gradient must have a graph
        gw, gs = graph_gradients(grad, d, weight, style, index, offsets, ctx.up, ctx.n_out, want)
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
