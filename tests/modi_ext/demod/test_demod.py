"""The C++ demodulation coefficients (``modi_ext.demod.ops``, ``csrc/demod/cpu.cpp``) against the torch form
(``dense.demod_scale``) on random trees: values and gradients in float64, gradcheck and gradgradcheck (the second
order goes through the torch form), opcheck of both ops, results independent of the thread count, the paths that must
fall back to the torch form, and clear errors on bad input."""
from __future__ import annotations

import random

import pytest
import torch
from skeletal_cases import KINDS, make_case

from modi_ext import HAS_EXT
from modi_ext.demod import dense
from modi_ext.demod import ops as demod
from modi_ext.skeletal import ops

needs_kernel = pytest.mark.skipif(not (HAS_EXT and demod.kernel_available()),
                                  reason="modi_ext C++ extension (with the demod op) not built")
pytestmark = needs_kernel


def _case(kind, seed, style=True, dtype=torch.float64, **kw):
    """(weight, style, index, offsets, up, n_out, batch) for demod_scale, as the ops call it."""
    args, kwargs = make_case(kind, random.Random(seed), dtype=dtype, style=style, demod=True, **kw)
    x, w, _, index, offsets = args[:5]
    n_out = args[5] if kind == "up" else offsets.numel() - 1
    s = kwargs["style"]
    return w, s, index, offsets, kind == "up", n_out, x.shape[0]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_kernel_matches_the_torch_form(kind, style, seed):
    w, s, index, offsets, up, n_out, batch = _case(kind, 100 * seed + len(kind), style=style)
    w.requires_grad_(True)
    inputs = [w] + ([s.requires_grad_(True)] if style else [])
    got = demod.demod_scale(w, index, offsets, s, up, n_out, batch)
    want = dense.demod_scale(w, index, offsets, s, up, n_out, batch)
    assert got.shape == want.shape == (batch, w.shape[2] if up else w.shape[0], n_out)
    if style:
        assert type(got.grad_fn).__name__ == "demod_scale_eagerBackward"  # the C++ op really ran
    torch.testing.assert_close(got, want, rtol=1e-13, atol=0)
    g = torch.randn_like(got)
    for a, b in zip(torch.autograd.grad(got, inputs, g), torch.autograd.grad(want, inputs, g)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck_and_gradgradcheck(kind):
    w, s, index, offsets, up, n_out, batch = _case(kind, 7, n_joints=9)
    w.requires_grad_(True)
    s.requires_grad_(True)

    def fn(w, s):
        return demod.demod_scale(w, index, offsets, s, up, n_out, batch)

    assert torch.autograd.gradcheck(fn, (w, s))
    assert torch.autograd.gradgradcheck(fn, (w, s))


def test_gradient_of_one_input_only():
    """The backward computes only what the engine asks for, and each part equals the torch form's."""
    w, s, index, offsets, up, n_out, batch = _case("conv", 11)
    w.requires_grad_(True)
    s.requires_grad_(True)
    g = torch.randn(batch, w.shape[0], n_out, dtype=w.dtype)
    for inp in (w, s):
        (a,) = torch.autograd.grad(demod.demod_scale(w, index, offsets, s, up, n_out, batch), inp, g)
        (b,) = torch.autograd.grad(dense.demod_scale(w, index, offsets, s, up, n_out, batch), inp, g)
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    gw, gs = torch.ops.modi_ext.demod_scale_backward(g, torch.ops.modi_ext.demod_scale(
        w.detach(), s.detach(), index, offsets, up, n_out, 1e-8), w.detach(), s.detach(), index, offsets, up, n_out,
        [False, True])
    assert gw.numel() == 0 and gs.shape == s.shape


@pytest.mark.parametrize("kind", KINDS)
def test_opcheck(kind):
    w, s, index, offsets, up, n_out, _ = _case(kind, 5, dtype=torch.float32)
    torch.library.opcheck(torch.ops.modi_ext.demod_scale.default, (w, s, index, offsets, up, n_out, 1e-8))
    torch.library.opcheck(torch.ops.modi_ext.demod_scale.default, (w, None, index, offsets, up, n_out, 1e-8))
    d = torch.ops.modi_ext.demod_scale(w, s, index, offsets, up, n_out, 1e-8)
    torch.library.opcheck(torch.ops.modi_ext.demod_scale_backward.default,
                          (torch.randn_like(d), d, w, s, index, offsets, up, n_out, [True, True]))


@pytest.mark.parametrize("kind", KINDS)
def test_bitwise_equal_at_any_thread_count(kind):
    """Large enough for the task pool (above the serial threshold): every thread count gives the same bits."""
    w, s, index, offsets, up, n_out, _ = _case(kind, 3, dtype=torch.float32, n_joints=30, B=32, cin=48, cout=48,
                                                U=3)
    d0 = torch.ops.modi_ext.demod_scale(w, s, index, offsets, up, n_out, 1e-8)
    g = torch.randn_like(d0)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            d = torch.ops.modi_ext.demod_scale(w, s, index, offsets, up, n_out, 1e-8)
            results.append((d,) + tuple(torch.ops.modi_ext.demod_scale_backward(
                g, d, w, s, index, offsets, up, n_out, [True, True])))
    finally:
        torch.set_num_threads(before)
    for r in results[1:]:
        for a, b in zip(r, results[0]):
            assert torch.equal(a, b)


def test_torch_form_where_the_kernel_does_not_apply(monkeypatch):
    w, s, index, offsets, up, n_out, batch = _case("conv", 13)
    s.requires_grad_(True)

    def path():
        return type(demod.demod_scale(w, index, offsets, s, up, n_out, batch).grad_fn).__name__

    def name():
        return demod.demod_scale(w, index, offsets, s, up, n_out, batch).grad_fn.name()

    assert path() == "demod_scale_eagerBackward"
    monkeypatch.setenv("MODI_EXT_EAGER", "0")  # the registered op (compile, dispatch modes): the kernel still
    assert "modi_ext_demod_scale" in name()
    monkeypatch.delenv("MODI_EXT_EAGER")
    monkeypatch.setenv("MODI_EXT_DEMOD", "torch")  # asked for by name: torch ops
    assert "demod_scale" not in name()
    monkeypatch.delenv("MODI_EXT_DEMOD")
    assert "demod_scale" not in demod.demod_scale(w, index, offsets, s, up, n_out, batch, impl="dense").grad_fn.name()
    half = demod.demod_scale(w.to(torch.bfloat16), index, offsets, s.detach().to(torch.bfloat16), up, n_out, batch)
    assert half.dtype == torch.bfloat16  # no bfloat16 CPU kernel: the torch form
    assert ops.demod_scale is demod.demod_scale  # the public name is this dispatcher


def test_bad_input_names_the_problem():
    w, s, index, offsets, up, n_out, _ = _case("conv", 17, dtype=torch.float32)
    op = torch.ops.modi_ext.demod_scale
    with pytest.raises(RuntimeError, match="style must have the weight's dtype"):
        op(w, s.double(), index, offsets, up, n_out, 1e-8)
    with pytest.raises(RuntimeError, match=r"style must be \(B, "):
        op(w, s[:, :1], index, offsets, up, n_out, 1e-8)
    with pytest.raises(RuntimeError, match="pairs but index has"):
        op(w[:, :-1], s, index, offsets, up, n_out, 1e-8)
    with pytest.raises(RuntimeError, match="float32 or float64"):
        op(w.half(), None, index, offsets, up, n_out, 1e-8)
    wu, su, iu, ou, _, nu, _ = _case("up", 17, dtype=torch.float32)
    with pytest.raises(RuntimeError, match="out of range"):
        op(wu, su, iu, ou, True, nu - 1, 1e-8)  # the pooling covers every fine entity: nu - 1 is in index
    d = op(w, s, index, offsets, up, n_out, 1e-8)
    with pytest.raises(RuntimeError, match="grad and d must be"):
        torch.ops.modi_ext.demod_scale_backward(d[:, :, :-1], d, w, s, index, offsets, up, n_out, [True, True])


@pytest.mark.parametrize("kind", ["conv", "up"])
def test_registered_op_and_eager_function_agree(monkeypatch, kind):
    """The op through the dispatcher (``MODI_EXT_EAGER=0``: what compile and dispatch modes see) and through its eager
    Function: the same values, first-order gradients and gradients of a gradient (the torch form's graph)."""
    w, s, index, offsets, up, n_out, batch = _case(kind, 21)

    def run():
        wl, sl = w.clone().requires_grad_(True), s.clone().requires_grad_(True)
        d = demod.demod_scale(wl, index, offsets, sl, up, n_out, batch)
        gw, gs = torch.autograd.grad((d * d).sum(), [wl, sl], create_graph=True)
        (gw.pow(2).sum() + gs.pow(2).sum()).backward()
        return d.grad_fn.name(), d, gw, gs, wl.grad, sl.grad

    eager = run()
    monkeypatch.setenv("MODI_EXT_EAGER", "0")
    registered = run()
    assert eager[0] == "demod_scale_eagerBackward" and "modi_ext_demod_scale" in registered[0]
    for a, b in zip(eager[1:], registered[1:]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style", [True, False])
def test_graph_gradients_match_the_torch_form(kind, style):
    """The ``create_graph`` gradient (closed form from the saved coefficients) against the torch form's autograd: the
    gradients and the gradients of a function of them, in float64, with and without a style."""
    w, s, index, offsets, up, n_out, batch = _case(kind, 31 + len(kind), style=style)

    def run(fn):
        wl = w.clone().requires_grad_(True)
        sl = s.clone().requires_grad_(True) if style else None
        d = fn(wl, index, offsets, sl, up, n_out, batch)
        inputs = [wl] + ([sl] if style else [])
        g = torch.autograd.grad((d.pow(3) * torch.linspace(0.5, 2.0, d.numel(), dtype=d.dtype).view_as(d)).sum(),
                                inputs, create_graph=True)
        second = torch.autograd.grad(sum((t.sin()).sum() for t in g), inputs)
        return g + second

    # float64, sums of a few hundred terms: errors of about 1e-13 of the largest term (the second-order gradients
    # reach several hundred), so the tolerance is relative to each tensor's largest element
    for a, b in zip(run(demod.demod_scale), run(dense.demod_scale)):
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-12 * b.abs().max().item())
