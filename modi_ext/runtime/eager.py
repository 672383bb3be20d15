"""The eager fast path: the registered kernels called through plain ``torch.autograd.Function``s.

The ops are registered with ``torch.library`` (schemas in C++, autograd and fake kernels in Python) so that
``torch.compile``, ``opcheck`` and functorch see well-formed operators.  In eager mode that registration costs a
dispatcher round trip into Python on every call: the op's Python autograd kernel, ``fill_defaults``, a redispatch,
and for the Python-defined backward ops (``gradfix``) the ``custom_op`` wrappers -- ~50 us per layer forward and
backward on the 2-core machine, against ~100-500 us of kernel for GANimator's layers.

Where nothing but plain tensors is involved (no compile, no tracing, no functorch transform, no Python dispatch mode,
no tensor subclass), ``ops`` and ``gradfix`` call the same kernels through the Functions made here instead: the
forward runs the kernel below autograd, and the backward is the very ``setup_context`` / ``backward`` pair registered
for the op, so both paths compute the same gradients of every order.  ``MODI_EXT_EAGER=0`` turns the fast path off
(every call through the registered ops, as before).  The private torch internals this needs are looked up in one
place, :func:`torch_internals`; a torch without them leaves the fast path off (slower, same results).
"""
from __future__ import annotations

import os
from types import SimpleNamespace
from typing import Callable

import torch

_PLAIN = (torch.Tensor, torch.nn.Parameter)


def torch_internals() -> SimpleNamespace:
    """The private torch internals the fast path relies on: the only place it touches them.

    A torch release that renames one makes this raise ``AttributeError``: the fast path then stays off (every call
    through the registered ops) and ``tests/modi_ext/runtime/test_eager.py`` fails, naming it."""
    c = torch._C
    return SimpleNamespace(below_autograd=c._AutoDispatchBelowAutograd, tracing_state=c._get_tracing_state,
                           functorch_active=c._are_functorch_transforms_active,
                           dispatch_stack_len=c._len_torch_dispatch_stack,
                           will_engine_execute=c._will_engine_execute_node)


try:
    _TORCH: SimpleNamespace | None = torch_internals()
except AttributeError:  # a torch without them: the registered ops only
    _TORCH = None


def _enabled() -> bool:
    return os.environ.get("MODI_EXT_EAGER", "1").strip() != "0"


def usable(*tensors) -> bool:
    """Whether the plain-Function path may run these tensors (entries that are not tensors are ignored)."""
    if torch.compiler.is_compiling():  # first: dynamo folds it and never traces the checks below
        return False
    if _TORCH is None or _TORCH.tracing_state() is not None or _TORCH.functorch_active():
        return False
    if _TORCH.dispatch_stack_len() > 0:
        return False
    for t in tensors:
        if isinstance(t, torch.Tensor) and type(t) not in _PLAIN:
            return False
    return _enabled()


def make_function(name: str, run: Callable, setup_context: Callable, backward: Callable) -> type:
    """A ``torch.autograd.Function`` whose forward is ``run(*inputs)`` below autograd and whose backward is the op's
    registered rule (``setup_context(ctx, inputs, output)``, ``backward(ctx, *grads)``)."""

    def forward(ctx, *inputs):
        with _TORCH.below_autograd():  # only reached when usable(): _TORCH is set
            out = run(*inputs)
        setup_context(ctx, inputs, out)
        return out

    return type(name, (torch.autograd.Function,), {"forward": staticmethod(forward),
                                                   "backward": staticmethod(backward)})


def needed(ctx, i: int) -> bool:
    """Whether the backward running now must produce the gradient of input ``i``.

    ``ctx.needs_input_grad`` only says that the input requires grad.  ``torch.autograd.grad(score, interp,
    create_graph=True)`` -- the WGAN-GP and R1 -- asks for the input's gradient alone, yet every layer's weight also
    requires grad: computing (and building the graph of) a weight gradient that the engine then drops cost the
    GANimator D step a weight-gradient pass per layer.  So ask the engine whether it will run the node that the
    gradient goes to; when it cannot say (a leaf that ``autograd.grad`` captures, compiled autograd), compute it.
    """
    if not ctx.needs_input_grad[i]:
        return False
    try:
        node = ctx.next_functions[i][0]
        return node is None or _TORCH is None or bool(_TORCH.will_engine_execute(node))
    except (RuntimeError, AttributeError, IndexError):
        return True


__all__ = ["torch_internals", "usable", "make_function", "needed"]
