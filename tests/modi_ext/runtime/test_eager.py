"""The eager fast path (``modi_ext.runtime.eager``): the same kernels and gradients of every order as the registered
ops, taken only where nothing but plain tensors is involved; and backward passes that skip the gradients the engine will
not use (``gradfix.needed``)."""
from __future__ import annotations

import random

import pytest
import torch
from skeletal_cases import KINDS, call, make_case

from modi_ext import HAS_EXT
from modi_ext.skeletal import gradfix
from modi_ext.skeletal import ops

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
pytestmark = [needs_ext, pytest.mark.usefixtures("one_torch_thread")]

OPTIONS = [(False, False, "zeros"), (True, True, "reflect"), (True, False, "reflect"), (False, True, "zeros")]


def _leaves(kind, seed, style, demod, padding, dtype=torch.float64):
    args, kwargs = make_case(kind, random.Random(seed), dtype=dtype, style=style, demod=demod, padding=padding, B=2,
                             cin=3, cout=4, T=9, U=5 if padding == "reflect" else 3)
    x, w, b = (t.clone().requires_grad_(True) for t in args[:3])
    s = kwargs["style"].clone().requires_grad_(True) if style else None
    return x, w, b, s, args[3:], kwargs


def _all_orders(kind, seed, style, demod, padding, dtype=torch.float64):
    """Output, first-order gradients, and the gradients of a loss built on a gradient (R1-like)."""
    x, w, b, s, rest, kwargs = _leaves(kind, seed, style, demod, padding, dtype)
    y = call(kind, ops, (x, w, b) + rest, dict(kwargs, style=s))
    params = [x, w, b] + ([s] if s is not None else [])
    v = torch.randn(y.shape, dtype=y.dtype, generator=torch.Generator().manual_seed(seed))
    first = torch.autograd.grad((y * v).sum(), params, create_graph=True)
    loss = sum(g.pow(2).sum() for g in first) + (y.tanh() * v).sum()
    second = torch.autograd.grad(loss, params)
    return y, first, second, type(y.grad_fn).__name__


def test_the_private_torch_internals_it_needs_still_exist(monkeypatch):
    """The fast path's one contact with torch's private API (``eager.torch_internals``): a torch upgrade that renames
    one of them fails here by name, instead of the fast path silently switching off."""
    from modi_ext.runtime import eager

    found = eager.torch_internals()  # AttributeError naming the missing internal
    assert all(callable(v) for v in vars(found).values()), vars(found)
    assert eager._TORCH is not None
    monkeypatch.delenv("MODI_EXT_EAGER", raising=False)
    assert eager.usable(torch.zeros(2), None)

    class Sub(torch.Tensor):
        pass

    assert not eager.usable(torch.zeros(2).as_subclass(Sub))  # a subclass goes through the registered ops


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style,demod,padding", OPTIONS)
def test_eager_path_equals_the_registered_ops(kind, style, demod, padding, monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    seed = hash((kind, style, demod, padding, "eager")) % 10_000
    monkeypatch.setenv("MODI_EXT_EAGER", "1")
    fast = _all_orders(kind, seed, style, demod, padding)
    monkeypatch.setenv("MODI_EXT_EAGER", "0")
    slow = _all_orders(kind, seed, style, demod, padding)
    assert "eager" in fast[3] and "eager" not in slow[3], (fast[3], slow[3])  # each path really ran
    # bitwise, except that with demodulation the eager path takes its coefficients from the C++ op
    # (modi_ext.demod.ops) and the registered path from torch ops: the same sums in another order
    tol = 1e-13 if demod else 0.0
    torch.testing.assert_close(fast[0], slow[0], rtol=tol, atol=tol)
    for a, b in zip(fast[1] + fast[2], slow[1] + slow[2]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_eager_gradgradcheck_random_trees(kind, monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    monkeypatch.setenv("MODI_EXT_EAGER", "1")
    x, w, b, s, rest, kwargs = _leaves(kind, 29, True, True, "reflect")

    def fn(x, w, b, s):
        return call(kind, ops, (x, w, b) + rest, dict(kwargs, style=s))

    assert "eager" in type(fn(x, w, b, s).grad_fn).__name__
    assert torch.autograd.gradgradcheck(fn, (x, w, b, s), eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_registered_path_under_a_dispatch_mode_and_under_compile(monkeypatch):
    """A Python dispatch mode (what opcheck and FakeTensor use) or torch.compile sees the registered op."""
    from torch.utils._python_dispatch import TorchDispatchMode

    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    x, w, b, s, rest, kwargs = _leaves("conv", 3, False, False, "zeros", dtype=torch.float32)
    seen = []

    class Record(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            seen.append(str(func))
            return func(*args, **(kwargs or {}))

    with Record():
        y = call("conv", ops, (x, w, b) + rest, kwargs)
    assert any("modi_ext.skeletal_conv" in f for f in seen), seen
    ref = call("conv", ops, (x, w, b) + rest, kwargs)
    torch.testing.assert_close(y, ref, rtol=0, atol=0)

    fn = torch.compile(lambda x: call("conv", ops, (x, w, b) + rest, kwargs), backend="eager", fullgraph=True)
    torch.testing.assert_close(fn(x), ref, rtol=1e-6, atol=1e-6)


def _count_backward_masks(monkeypatch):
    masks = []
    real = torch.ops.modi_ext.skeletal_backward

    def counted(*a):
        masks.append(tuple(a[12]))  # output_mask
        return real(*a)
    monkeypatch.setattr(torch.ops.modi_ext, "skeletal_backward", counted)
    return masks


@pytest.mark.parametrize("eager", ["1", "0"])
def test_input_gradient_alone_skips_the_weight_gradient(eager, monkeypatch):
    """autograd.grad w.r.t. the input (R1, WGAN-GP) does not compute the weight's gradient, first order or graph."""
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    monkeypatch.setenv("MODI_EXT_EAGER", eager)
    masks = _count_backward_masks(monkeypatch)
    weight_graphs = []
    real_gw = gradfix.grad_weight
    monkeypatch.setattr(gradfix, "grad_weight", lambda *a: weight_graphs.append(1) or real_gw(*a))
    x, w, b, s, rest, kwargs = _leaves("conv", 11, False, False, "reflect")
    y = call("conv", ops, (x, w, b) + rest, kwargs)
    (gx,) = torch.autograd.grad(y.pow(2).sum(), x, retain_graph=True)
    assert masks == [(True, False, False, False)]  # the kernel computed the input gradient only
    (gx,) = torch.autograd.grad(y.pow(2).sum(), x, create_graph=True)
    assert weight_graphs == []
    gx.pow(2).sum().backward()  # the graph of the input gradient still reaches the weight
    assert w.grad is not None and float(w.grad.abs().sum()) > 0
    masks.clear()
    (gw,) = torch.autograd.grad(call("conv", ops, (x, w, b) + rest, kwargs).sum(), w)
    assert masks == [(False, True, False, False)]
    ref_w = w.detach().clone().requires_grad_(True)
    (ref,) = torch.autograd.grad(call("conv", ops, (x.detach(), ref_w, b) + rest, kwargs).sum(), ref_w)
    torch.testing.assert_close(gw, ref, rtol=0, atol=0)


def test_full_backward_still_computes_every_gradient(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    masks = _count_backward_masks(monkeypatch)
    x, w, b, s, rest, kwargs = _leaves("down", 5, True, True, "zeros")
    call("down", ops, (x, w, b) + rest, dict(kwargs, style=s)).sum().backward()
    assert masks == [(True, True, True, True)]
    assert all(t.grad is not None for t in (x, w, b, s))


def test_gradients_of_a_captured_leaf(monkeypatch):
    """autograd.grad whose inputs include the weight leaf itself: the engine cannot be asked, so it is computed."""
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    x, w, b, s, rest, kwargs = _leaves("up", 8, False, False, "reflect")
    y = call("up", ops, (x, w, b) + rest, kwargs)
    gx, gw = torch.autograd.grad(y.pow(2).sum(), [x, w], create_graph=True)
    monkeypatch.setenv("MODI_EXT_IMPL", "ref")
    yr = call("up", ops, (x, w, b) + rest, kwargs)
    rx, rw = torch.autograd.grad(yr.pow(2).sum(), [x, w], create_graph=True)
    torch.testing.assert_close(gx, rx, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(gw, rw, rtol=1e-10, atol=1e-10)
