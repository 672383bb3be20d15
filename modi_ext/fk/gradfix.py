"""FK's gradient of any order: the backward as torch ops with a graph, when one is asked for (``create_graph``).

The C++ backward (``fk_backward``) is first order.  A gradient that must itself be differentiable (R1, path length
through FK) is built from the torch loop ``fk_reference`` instead, so second-order gradients through FK are exact.
"""
from __future__ import annotations

import torch

from modi_ext.fk.reference import fk_reference

__all__ = ["graph_backward"]


def graph_backward(grad_positions, grad_global_quats, local_quats, offsets, parents, needs):
    """``fk_backward`` as torch ops with a graph: vector-Jacobian products of ``fk_reference``.

    The root translation enters every joint's position additively, so its gradient is the sum over joints and the
    recomputation can start from a zero root."""
    q = local_quats if local_quats.requires_grad else local_quats.detach().requires_grad_()
    off = offsets if offsets.requires_grad else offsets.detach().requires_grad_()
    with torch.enable_grad():
        root = q.new_zeros(tuple(q.shape[:-2]) + (3,))
        pos, rot = fk_reference(q, off, parents, root, return_rotations=True)
        outs, grads = [pos], [grad_positions]
        if grad_global_quats is not None:
            outs.append(rot)
            grads.append(grad_global_quats)
        want = [t for t, n in ((q, needs[0]), (off, needs[1])) if n]
        got = iter(torch.autograd.grad(outs, want, grads, create_graph=True, allow_unused=True,
                                       materialize_grads=True)) if want else iter(())
    grad_q = next(got) if needs[0] else None
    grad_off = next(got) if needs[1] else None
    return grad_q, grad_positions.sum(-2), grad_off
