"""The skeletal ops' registration with ``torch.library``: fake kernels (compile, meta, ``opcheck``) and autograd.

The schemas are C++ (``csrc/skeletal/schema.cpp``); this is what they need from Python, done on import when the
extension is built.  The backward is the fused C++ ``skeletal_backward`` for the inputs whose gradient the engine will
use (``needed``), or ``modi_ext.skeletal.gradfix.graph_backward`` when a graph of the gradient is asked for.  The same
rules make each op's eager ``autograd.Function`` (``kernels.EAGER``), which ``kernels.launch`` calls where the fast
path applies.
"""
from __future__ import annotations

import torch

from modi_ext.runtime import eager, kernels
from modi_ext.runtime.eager import needed
from modi_ext.runtime.loader import HAS_EXT
from modi_ext.skeletal.checks import KIND_CONV, KIND_DOWN, KIND_UP, NAMES
from modi_ext.skeletal.gradfix import graph_backward

__all__ = ["ops_defined"]


def ops_defined() -> bool:
    """Whether the C++ library defined the skeletal ops' schemas (the extension is built)."""
    return HAS_EXT and hasattr(torch.ops.modi_ext, "skeletal_conv")


def _out_shape(kind, x, weight, offsets, n_out):
    b, _, _, t = x.shape
    if kind == KIND_UP:
        return (b, weight.shape[2], n_out, 2 * t)
    return (b, weight.shape[0], offsets.shape[0] - 1, t if kind == KIND_CONV else t // 2)


def _autograd_rules(kind: int):
    """``(setup_context, backward)`` of one op: registered with torch.library and reused by its eager Function."""
    up = kind == KIND_UP

    def setup_context(ctx, inputs, output):
        if up:
            x, weight, bias, index, offsets, n_out, style, scale, padding_mode, act = inputs
        else:
            x, weight, bias, index, offsets, style, scale, padding_mode, act = inputs
            n_out = offsets.shape[0] - 1
        ctx.save_for_backward(x, weight, bias, index, offsets, style, scale, output)
        ctx.meta = (padding_mode, n_out, act)

    def backward(ctx, grad):
        x, weight, bias, index, offsets, style, scale, out = ctx.saved_tensors
        padding_mode, n_out, act = ctx.meta
        want = lambda i: needed(ctx, i)  # noqa: E731  (not just requires_grad: what the engine will use)
        s = 6 if up else 5  # the style's position; the scale's is next
        need = dict(x=want(0), weight=want(1), bias=want(2), style=want(s), scale=want(s + 1))
        if torch.is_grad_enabled():  # create_graph: a differentiable backward made of the kernels themselves
            res = graph_backward(kind, grad, out, x, weight, bias, index, offsets, style, scale, padding_mode,
                                 n_out, need, act)
            gx, gw, gb, gs, gd = res["x"], res["weight"], res["bias"], res["style"], res["scale"]
        else:
            mask = [bool(need["x"]), bool(need["weight"]), bool(need["style"]), bool(need["scale"])]
            gx, gw, gb, gs, gd = torch.ops.modi_ext.skeletal_backward(
                grad.contiguous(), out, x, weight, bias, index, offsets, style, scale, padding_mode, kind,
                n_out, mask, act)
            gx = gx if need["x"] else None
            gw = gw if need["weight"] else None
            gb = gb if (need["bias"] and bias is not None) else None
            gs = gs if (need["style"] and style is not None) else None
            gd = gd if (need["scale"] and scale is not None) else None
        if up:
            return gx, gw, gb, None, None, None, gs, gd, None, None
        return gx, gw, gb, None, None, gs, gd, None, None

    return setup_context, backward


def _make_fake(kind: int):
    if kind == KIND_UP:
        def fake(x, weight, bias, index, offsets, n_out, style, scale, padding_mode, act=False):
            return x.new_empty(_out_shape(kind, x, weight, offsets, n_out))
    else:
        def fake(x, weight, bias, index, offsets, style, scale, padding_mode, act=False):
            return x.new_empty(_out_shape(kind, x, weight, offsets, None))
    return fake


def _register() -> None:
    lib = torch.library
    for kind in (KIND_CONV, KIND_DOWN, KIND_UP):
        lib.register_fake(f"modi_ext::{NAMES[kind]}")(_make_fake(kind))

    @lib.register_fake("modi_ext::skeletal_backward")
    def _bwd_fake(grad, out, x, weight, bias, index, offsets, style, scale, padding_mode, kind, n_out, output_mask,
                  act=False):
        gx = torch.empty_like(x) if output_mask[0] else x.new_empty(0)
        gw = torch.empty_like(weight) if output_mask[1] else x.new_empty(0)
        gb = x.new_empty(bias.shape) if bias is not None else x.new_empty(0)
        gs = torch.empty_like(style) if (style is not None and output_mask[2]) else x.new_empty(0)
        gd = torch.empty_like(scale) if (scale is not None and output_mask[3]) else x.new_empty(0)
        return gx, gw, gb, gs, gd

    for kind, name in NAMES.items():
        setup_context, backward = _autograd_rules(kind)
        lib.register_autograd(f"modi_ext::{name}", backward, setup_context=setup_context)
        kernels.EAGER[name] = eager.make_function(
            f"{name}_eager", lambda *a, n=name: kernels.KERNELS[n](*a), setup_context, backward)


if ops_defined():
    _register()
