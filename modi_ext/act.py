"""StyleGAN2's bias activation -- bias, leaky ReLU (slope 0.2), gain sqrt(2) -- the one definition in Python.

The gain keeps the activations' second moment at 1.  The skeletal ops can run it in their epilogue (``act=True``):
the C++ and CUDA kernels hard-code the same constants (``csrc/skeletal/skeletal.h``), and the first-use self-check
compares them with :func:`fused_leaky_relu` here.  Its backward needs only the output ``y``: ``y > 0`` exactly where
the pre-activation is (slope and gain are positive), so :func:`backward_from_output` reads the derivative off ``y``
and the op saves nothing more (StyleGAN2-ADA's ``bias_act`` does the same).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["SLOPE", "GAIN", "fused_leaky_relu", "backward_from_output"]

SLOPE = 0.2
GAIN = math.sqrt(2.0)


def fused_leaky_relu(x: torch.Tensor, bias: torch.Tensor | None, slope: float = SLOPE) -> torch.Tensor:
    """Bias + leaky ReLU + gain sqrt(2); ``bias`` ``(C,)`` is added along dimension 1.

    Computed as leaky_relu(sqrt(2) x + sqrt(2) b): leaky ReLU is positively homogeneous, so the gain moves inside,
    where the bias add applies it (``add``'s ``alpha``), and the activation runs in place on that fresh tensor:
    one elementwise pass and one allocation less than add, activation, multiply."""
    if bias is None:
        return F.leaky_relu(x * GAIN, slope, inplace=True)
    b = (bias * GAIN).view(1, -1, *([1] * (x.ndim - 2)))
    return F.leaky_relu(torch.add(b, x, alpha=GAIN), slope, inplace=True)


def backward_from_output(grad: torch.Tensor, y: torch.Tensor, pre: bool = False):
    """``dL/dpre`` from ``grad = dL/dy`` and the activation's output ``y`` (and, with ``pre``, the pre-activation
    ``y / (dy/dpre)``, else None), as a graph that differentiates to any order: the slope is a constant of the graph
    (``y`` enters detached where it only picks the slope: the activation's second derivative is zero almost
    everywhere), which is ``leaky_relu_backward``'s own rule with the output as its ``self``."""
    sel = y.detach()
    g = torch.ops.aten.leaky_relu_backward(grad, sel, SLOPE, True) * GAIN
    p = torch.ops.aten.leaky_relu_backward(y, sel, 1.0 / SLOPE, True) / GAIN if pre else None
    return g, p
