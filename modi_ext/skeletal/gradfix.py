"""The skeletal ops' gradients of any order on the kernels -- the design of StyleGAN2-ADA's ``conv2d_gradfix``.

R1, path length and WGAN-GP differentiate a gradient, so the backward of each op must itself be made of ops that
have an autograd formula.  Every skeletal op is bilinear in (input, weight): ``y = A_W x``.  Its two partial
backwards are ops of their own, registered here:

* ``skeletal_grad_input(g, W) = A_W^T g``  (the C++ input-gradient pass: a skeletal op over the transposed CSR);
* ``skeletal_grad_weight(g, x) = d<g, A_W x>/dW``  (the C++ weight-gradient pass: a per-pair correlation).

Both are again bilinear, and their gradients are the three ops themselves::

    grad_input(g, W):   d/dg = A_W gg           (forward)       d/dW = grad_weight(g, gg)
    grad_weight(g, x):  d/dg = A_gg x           (forward)       d/dx = grad_input(g, gg)

so ``create_graph=True`` stays on the kernels to any order, on every device the C++ ops are registered for.
Modulation and demodulation are elementwise scales around the unmodulated op (``graph_backward``), and the bias
gradient is a sum.  ``MODI_EXT_DOUBLE=ref`` builds that graph through the dense reference instead (a debugging and
benchmarking switch; the reference stays the oracle of the tests).
"""
from __future__ import annotations

import os

import torch

from modi_ext.act import backward_from_output, fused_leaky_relu
from modi_ext.runtime import eager, kernels
from modi_ext.runtime.eager import needed
from modi_ext.runtime.loader import HAS_EXT
from modi_ext.skeletal import reference
from modi_ext.skeletal.checks import KIND_DOWN, KIND_UP, NAMES, kernel_args

__all__ = ["graph_backward", "grad_input", "grad_weight", "plain_op", "skeletal_grad_input", "skeletal_grad_weight"]

# the partial backwards as registered ops (``_register``, when the C++ schemas are loaded)
skeletal_grad_input = skeletal_grad_weight = None


def plain_op(kind: int, x: torch.Tensor, weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor,
             n_out: int, padding_mode: str) -> torch.Tensor:
    """``A_W x`` (no bias, style or scale) on the kernels, differentiable to any order; no argument checks."""
    return kernels.launch(NAMES[kind], *kernel_args(kind, x, weight, None, index, offsets, n_out, None, None,
                                                    padding_mode))


def _weight_shape(kind: int, grad: torch.Tensor, x: torch.Tensor, nnz: int, taps: int) -> list[int]:
    c_out, c_in = grad.shape[1], x.shape[1]
    return [c_in, nnz, c_out, taps] if kind == KIND_UP else [c_out, nnz, c_in, taps]


def _grad_input_impl(grad: torch.Tensor, weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor,
                     kind: int, n_out: int, n_in: int, t_in: int, padding_mode: str) -> torch.Tensor:
    """``A_W^T grad``: the input gradient of an unmodulated skeletal op, shape ``(B, Cin, n_in, t_in)``."""
    c_in = weight.shape[0] if kind == KIND_UP else weight.shape[2]
    g = grad.contiguous()
    x_like = g.new_empty(g.shape[0], c_in, n_in, t_in)  # shape only: the kernel reads no input values here
    # ``out`` (read only for the scale gradient, not requested here) must merely have the output's shape
    return torch.ops.modi_ext.skeletal_backward(g, g, x_like, weight.contiguous(), None, index, offsets, None, None,
                                                padding_mode, kind, n_out, [True, False, False, False])[0]


def _grad_weight_impl(grad: torch.Tensor, x: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor,
                      kind: int, n_out: int, taps: int, padding_mode: str) -> torch.Tensor:
    """``d<grad, A_W x>/dW`` in the compact layout of ``W`` (``taps`` = the kernel width U)."""
    g = grad.contiguous()
    w_like = x.new_empty(_weight_shape(kind, g, x, index.shape[0], taps))  # shape only
    return torch.ops.modi_ext.skeletal_backward(g, g, x.contiguous(), w_like, None, index, offsets, None, None,
                                                padding_mode, kind, n_out, [False, True, False, False])[1]


def grad_input(grad, weight, index, offsets, kind: int, n_out: int, n_in: int, t_in: int,
               padding_mode: str) -> torch.Tensor:
    """``skeletal_grad_input``, on the eager fast path where it applies (``modi_ext.runtime.eager``)."""
    if eager.usable(grad, weight, index, offsets):
        return _GradInputEager.apply(grad, weight, index, offsets, kind, n_out, n_in, t_in, padding_mode)
    return skeletal_grad_input(grad, weight, index, offsets, kind, n_out, n_in, t_in, padding_mode)


def grad_weight(grad, x, index, offsets, kind: int, n_out: int, taps: int, padding_mode: str) -> torch.Tensor:
    """``skeletal_grad_weight``, on the eager fast path where it applies (``modi_ext.runtime.eager``)."""
    if eager.usable(grad, x, index, offsets):
        return _GradWeightEager.apply(grad, x, index, offsets, kind, n_out, taps, padding_mode)
    return skeletal_grad_weight(grad, x, index, offsets, kind, n_out, taps, padding_mode)


def _partial_setup(ctx, inputs, output):
    """``setup_context`` of both partial backwards, whose inputs are
    ``(grad, weight or x, index, offsets, kind, n_out, <shape ints>, padding_mode)``."""
    ctx.save_for_backward(*inputs[:4])
    ctx.meta = (inputs[4], inputs[5], inputs[-1])


def _grad_input_backward(ctx, gg):
    grad, weight, index, offsets = ctx.saved_tensors
    kind, n_out, padding_mode = ctx.meta
    gg = gg.contiguous()
    d_grad = plain_op(kind, gg, weight, index, offsets, n_out, padding_mode) if needed(ctx, 0) else None
    d_weight = (grad_weight(grad, gg, index, offsets, kind, n_out, weight.shape[3], padding_mode)
                if needed(ctx, 1) else None)
    return d_grad, d_weight, None, None, None, None, None, None, None


def _grad_weight_backward(ctx, gg):
    grad, x, index, offsets = ctx.saved_tensors
    kind, n_out, padding_mode = ctx.meta
    gg = gg.contiguous()
    d_grad = plain_op(kind, x.contiguous(), gg, index, offsets, n_out, padding_mode) if needed(ctx, 0) else None
    d_x = (grad_input(grad, gg, index, offsets, kind, n_out, x.shape[2], x.shape[3], padding_mode)
           if needed(ctx, 1) else None)
    return d_grad, d_x, None, None, None, None, None, None


_GradInputEager = eager.make_function("skeletal_grad_input_eager", _grad_input_impl, _partial_setup,
                                      _grad_input_backward)
_GradWeightEager = eager.make_function("skeletal_grad_weight_eager", _grad_weight_impl, _partial_setup,
                                       _grad_weight_backward)


def graph_backward(kind: int, grad: torch.Tensor, out: torch.Tensor, x: torch.Tensor, weight: torch.Tensor,
                   bias: torch.Tensor | None, index: torch.Tensor, offsets: torch.Tensor,
                   style: torch.Tensor | None, scale: torch.Tensor | None, padding_mode: str, n_out: int,
                   need: dict[str, bool], act: bool = False) -> dict[str, torch.Tensor | None]:
    """Gradients of ``y = scale * A_W (x * style) + bias`` (then, with ``act``, the bias activation) as a
    differentiable graph (``create_graph=True``).

    ``out`` is the saved ``y``: the scale gradient reads ``A_W (x * style) = (y - bias) / scale`` from it instead of
    recomputing the op (``scale`` is a demodulation factor, ``rsqrt(...) > 0``); with ``act``, the gradient and
    ``y`` are first taken back through the activation (``modi_ext.act.backward_from_output``).  ``MODI_EXT_DOUBLE=ref``:
    through the dense reference instead.
    """
    if os.environ.get("MODI_EXT_DOUBLE", "ext").strip().lower() == "ref":
        return _reference_graph_backward(kind, grad, x, weight, bias, index, offsets, style, scale, padding_mode,
                                         n_out, need, act)
    if act:
        grad, out = backward_from_output(grad, out, pre=bool(need["scale"] and scale is not None))
    res: dict[str, torch.Tensor | None] = dict.fromkeys(need)
    if need["bias"] and bias is not None:
        res["bias"] = grad.sum((0, 2, 3))
    if need["scale"] and scale is not None:
        core = out - bias.view(1, -1, 1, 1) if bias is not None else out
        res["scale"] = (grad * core).sum(-1) / scale
    gz = grad * scale.unsqueeze(-1) if scale is not None else grad
    gz = gz.contiguous()
    want_x = need["x"] or (need["style"] and style is not None)
    if want_x:
        gxs = grad_input(gz, weight, index, offsets, kind, n_out, x.shape[2], x.shape[3], padding_mode)
        if style is not None:
            s = style.view(style.shape[0], style.shape[1], 1, 1)
            if need["x"]:
                res["x"] = gxs * s
            if need["style"]:
                res["style"] = (gxs * x).sum((2, 3))
        elif need["x"]:
            res["x"] = gxs
    if need["weight"]:
        xs = x * style.view(style.shape[0], style.shape[1], 1, 1) if style is not None else x
        res["weight"] = grad_weight(gz, xs.contiguous(), index, offsets, kind, n_out, weight.shape[3], padding_mode)
    return res


def _reference_graph_backward(kind, grad, x, weight, bias, index, offsets, style, scale, padding_mode, n_out, need,
                              act):
    """Gradients as a differentiable graph by re-running the op on the dense reference (slow, exact)."""
    args = dict(x=x, weight=weight, bias=bias, style=style, scale=scale)
    wanted = [k for k, v in need.items() if v and args[k] is not None]
    res = dict.fromkeys(need)
    if not wanted:
        return res
    if kind == KIND_UP:
        y = reference.skeletal_up(x, weight, None, index, offsets, n_out, style, False, padding_mode)
    elif kind == KIND_DOWN:
        y = reference.skeletal_down(x, weight, None, index, offsets, style, False, padding_mode)
    else:
        y = reference.skeletal_conv(x, weight, None, index, offsets, style, False, padding_mode)
    if scale is not None:
        y = y * scale.unsqueeze(-1)
    if act:
        y = fused_leaky_relu(y, bias)
    elif bias is not None:
        y = y + bias.view(1, -1, 1, 1)
    grads = torch.autograd.grad(y, [args[k] for k in wanted], grad, create_graph=True, allow_unused=True)
    res.update(zip(wanted, grads))
    return res


def _register() -> None:
    """The two partial backwards as ``torch.library`` ops (for compile, functorch and ``opcheck``), with their fake
    kernels and autograd."""
    global skeletal_grad_input, skeletal_grad_weight
    lib = torch.library
    skeletal_grad_input = lib.custom_op("modi_ext::skeletal_grad_input", mutates_args=())(_grad_input_impl)
    skeletal_grad_weight = lib.custom_op("modi_ext::skeletal_grad_weight", mutates_args=())(_grad_weight_impl)

    @skeletal_grad_input.register_fake
    def _grad_input_fake(grad, weight, index, offsets, kind, n_out, n_in, t_in, padding_mode):
        c_in = weight.shape[0] if kind == KIND_UP else weight.shape[2]
        return grad.new_empty(grad.shape[0], c_in, n_in, t_in)

    @skeletal_grad_weight.register_fake
    def _grad_weight_fake(grad, x, index, offsets, kind, n_out, taps, padding_mode):
        return x.new_empty(_weight_shape(kind, grad, x, index.shape[0], taps))

    skeletal_grad_input.register_autograd(_grad_input_backward, setup_context=_partial_setup)
    skeletal_grad_weight.register_autograd(_grad_weight_backward, setup_context=_partial_setup)


if HAS_EXT and hasattr(torch.ops.modi_ext, "skeletal_backward"):
    _register()
