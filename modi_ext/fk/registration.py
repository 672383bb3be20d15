"""The fk op's registration with ``torch.library``: fake kernels (compile, meta, ``opcheck``) and autograd.

The schemas are C++ (``csrc/fk/schema.cpp``); this is what they need from Python, done on import when the extension
is built.  The backward is the C++ ``fk_backward``, or ``modi_ext.fk.gradfix.graph_backward`` when a graph of the
gradient is asked for.  The same rules make the op's eager ``autograd.Function`` (``kernels.EAGER``), which
``kernels.launch`` calls where the fast path applies.
"""
from __future__ import annotations

import torch

from modi_ext.fk.gradfix import graph_backward
from modi_ext.runtime import eager, kernels
from modi_ext.runtime.loader import HAS_EXT

__all__ = ["ops_defined"]


def ops_defined() -> bool:
    """Whether the C++ library defined the fk op's schemas (the extension is built)."""
    return HAS_EXT and hasattr(torch.ops.modi_ext, "fk") and hasattr(torch.ops.modi_ext, "fk_backward")


if ops_defined():

    @torch.library.register_fake("modi_ext::fk")
    def _fk_fake(local_quats, offsets, parents, root_positions):
        positions = local_quats.new_empty(tuple(local_quats.shape[:-1]) + (3,))
        return positions, torch.empty_like(local_quats)

    @torch.library.register_fake("modi_ext::fk_backward")
    def _fk_backward_fake(grad_positions, grad_global_quats, local_quats, global_quats, offsets, parents, offsets_grad):
        grad_root = local_quats.new_empty(tuple(local_quats.shape[:-2]) + (3,))
        return torch.empty_like(local_quats), grad_root, offsets.new_empty((offsets.shape[0], 3))

    def _fk_setup_context(ctx, inputs, output):
        local_quats, offsets, parents, _root = inputs
        _positions, global_quats = output
        ctx.save_for_backward(local_quats, global_quats, offsets)
        ctx.parents = parents
        # An unused output (usually the rotations) then arrives as None instead of a materialised zero tensor.
        ctx.set_materialize_grads(False)

    def _fk_backward(ctx, grad_positions, grad_global_quats):
        local_quats, global_quats, offsets = ctx.saved_tensors
        if grad_positions is None:
            grad_positions = local_quats.new_zeros(tuple(local_quats.shape[:-1]) + (3,))
        if torch.is_grad_enabled():  # create_graph=True: a differentiable formulation of the same gradients
            grad_q, grad_root, grad_off = graph_backward(grad_positions, grad_global_quats, local_quats, offsets,
                                                          ctx.parents, ctx.needs_input_grad)
        else:
            if grad_global_quats is not None:
                grad_global_quats = grad_global_quats.contiguous()
            grad_q, grad_root, grad_off = torch.ops.modi_ext.fk_backward(
                grad_positions.contiguous(), grad_global_quats, local_quats, global_quats, offsets,
                ctx.parents, bool(ctx.needs_input_grad[1]),
            )
        return (
            grad_q if ctx.needs_input_grad[0] else None,
            grad_off if ctx.needs_input_grad[1] else None,
            None,
            grad_root if ctx.needs_input_grad[3] else None,
        )

    torch.library.register_autograd("modi_ext::fk", _fk_backward, setup_context=_fk_setup_context)
    kernels.EAGER["fk"] = eager.make_function("fk_eager", lambda *a: kernels.KERNELS["fk"](*a), _fk_setup_context,
                                              _fk_backward)
