"""Second- and higher-order gradients on the sparse kernels (``modi_ext.skeletal.gradfix``): gradgradcheck in float64
on random trees for every op and option, equality with the dense reference's second-order gradients, opcheck of the
backward ops, the graph-building path never touching the reference, and the R1 / path-length / WGAN-GP parameter
gradients of tiny MoDi and GANimator models equal on both paths."""
from __future__ import annotations

import random

import pytest
import torch
from skeletal_cases import KINDS, call, make_case

from modi_ext import HAS_EXT
from modi_ext.skeletal import ops
from modi_ext.skeletal import reference as R
from modi_ext.csr import csr_from_lists

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
pytestmark = [needs_ext, pytest.mark.usefixtures("one_torch_thread")]

OPTIONS = [(False, False, "zeros"), (False, False, "reflect"), (True, False, "zeros"), (True, True, "reflect"),
           (False, True, "zeros"), (True, True, "zeros")]


def _inputs(kind, rng, style, demod, padding, **kw):
    args, kwargs = make_case(kind, rng, style=style, demod=demod, padding=padding, **kw)
    x, w, b = (t.requires_grad_(True) for t in args[:3])
    s = kwargs["style"].requires_grad_(True) if style else None
    return (x, w, b), s, args[3:], kwargs


def _fn(kind, rest, kwargs, impl_mod=ops):
    def fn(x, w, b, *maybe_s):
        return call(kind, impl_mod, (x, w, b) + rest, dict(kwargs, style=maybe_s[0] if maybe_s else None))
    return fn


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style,demod,padding", OPTIONS)
def test_gradgradcheck_fp64_random_trees(kind, style, demod, padding):
    rng = random.Random(hash((kind, style, demod, padding, "gg")) % 10_000)
    for n_joints in (1, rng.randint(3, 7)):  # a single-entity CSR too
        (x, w, b), s, rest, kwargs = _inputs(kind, rng, style, demod, padding, n_joints=n_joints, U=3, B=2, cin=2,
                                             cout=2, T=6)
        inputs = (x, w, b) + ((s,) if style else ())
        assert torch.autograd.gradgradcheck(_fn(kind, rest, kwargs), inputs, eps=1e-6, atol=1e-5, rtol=1e-4,
                                            fast_mode=True)


def _disconnected_conv_case(dtype=torch.float64):
    """Entities that read only themselves (a CSR that looks like no tree), an entity nobody else reads."""
    lists = [[0], [1, 2], [1, 2], [3], [0, 4]]
    topo = csr_from_lists(lists)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 2, 5, 7, dtype=dtype, generator=g)
    w = torch.randn(3, topo.nnz, 2, 5, dtype=dtype, generator=g)
    return x, w, topo


def test_gradgradcheck_disconnected_csr_kernel5_reflect():
    x, w, topo = _disconnected_conv_case()
    x.requires_grad_(True)
    w.requires_grad_(True)

    def fn(x, w):
        return ops.skeletal_conv(x, w, None, topo.index, topo.offsets, padding_mode="reflect")

    assert torch.autograd.gradgradcheck(fn, (x, w), eps=1e-6, atol=1e-5, rtol=1e-4)


def _second_order(kind, impl, monkeypatch, inputs_fn, seed):
    """R1-like: grad w.r.t. x with create_graph, a scalar of it (plus the output), backward to every input."""
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    (x, w, b), s, rest, kwargs = inputs_fn()
    y = call(kind, ops, (x, w, b) + rest, dict(kwargs, style=s))
    v = torch.randn(y.shape, dtype=y.dtype, generator=torch.Generator().manual_seed(seed))
    (gx,) = torch.autograd.grad((y * v).sum(), x, create_graph=True)
    loss = gx.pow(2).sum() + (y.tanh() * v).sum()
    params = [x, w, b] + ([s] if s is not None else [])
    return torch.autograd.grad(loss, params)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style,demod,padding", OPTIONS)
def test_second_order_matches_reference(kind, style, demod, padding, monkeypatch):
    seed = hash((kind, style, demod, padding, "so")) % 10_000

    def inputs():
        return _inputs(kind, random.Random(seed), style, demod, padding, n_joints=9, U=5, B=2, cin=3, cout=4, T=12)

    ext = _second_order(kind, "ext", monkeypatch, inputs, seed)
    ref = _second_order(kind, "ref", monkeypatch, inputs, seed)
    for name, a, r in zip("xwbs", ext, ref):
        torch.testing.assert_close(a, r, rtol=1e-9, atol=1e-9, msg=f"d/d{name}")


@pytest.mark.parametrize("kind", KINDS)
def test_third_order_stays_on_kernels(kind, monkeypatch):
    """gradient of a gradient of a gradient, compared with the reference (gradfix is closed under autograd)."""
    seed = 17

    def third(impl):
        monkeypatch.setenv("MODI_EXT_IMPL", impl)
        (x, w, b), s, rest, kwargs = _inputs(kind, random.Random(seed), True, True, "reflect", n_joints=5, U=3,
                                             B=2, cin=2, cout=2, T=8)
        y = call(kind, ops, (x, w, b) + rest, dict(kwargs, style=s))
        (gx,) = torch.autograd.grad(y.pow(2).sum(), x, create_graph=True)
        (gw,) = torch.autograd.grad(gx.pow(2).sum(), w, create_graph=True)
        return torch.autograd.grad(gw.pow(2).sum(), [x, s])

    for a, r in zip(third("ext"), third("ref")):
        torch.testing.assert_close(a, r, rtol=1e-8, atol=1e-8)


def test_graph_path_never_calls_the_reference(monkeypatch):
    calls = []
    for name in ("skeletal_conv", "skeletal_down", "skeletal_up", "to_dense"):
        real = getattr(R, name)

        def counted(*a, _real=real, _name=name, **k):
            calls.append(_name)
            return _real(*a, **k)
        monkeypatch.setattr(R, name, counted)
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    for kind in KINDS:
        for style, demod, padding in OPTIONS:
            (x, w, b), s, rest, kwargs = _inputs(kind, random.Random(1), style, demod, padding, n_joints=6, U=3,
                                                 B=2, cin=2, cout=3, T=8)
            y = call(kind, ops, (x, w, b) + rest, dict(kwargs, style=s))
            (gx,) = torch.autograd.grad(y.sum(), x, create_graph=True)
            gx.pow(2).sum().backward()
            assert w.grad is not None and torch.isfinite(w.grad).all()
    assert calls == []


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
def test_opcheck_backward_ops(kind, padding):
    from modi_ext.skeletal import checks, gradfix

    rng = random.Random(5)
    (x, w, b), _, rest, _ = _inputs(kind, rng, False, False, padding, n_joints=6, U=3, B=2, cin=2, cout=3, T=8)
    index, offsets = rest[0], rest[1]
    n_out = rest[2] if kind == "up" else offsets.numel() - 1
    k = {"conv": checks.KIND_CONV, "down": checks.KIND_DOWN, "up": checks.KIND_UP}[kind]
    y = call(kind, ops, (x, w, None) + rest, dict(style=None, demodulate=False, padding_mode=padding))
    g = torch.randn_like(y).requires_grad_(True)
    wd, xd = w.detach().clone().requires_grad_(True), x.detach().clone().requires_grad_(True)
    torch.library.opcheck(torch.ops.modi_ext.skeletal_grad_input.default,
                          (g, wd, index, offsets, k, n_out, x.shape[2], x.shape[3], padding))
    torch.library.opcheck(torch.ops.modi_ext.skeletal_grad_weight.default,
                          (g, xd, index, offsets, k, n_out, w.shape[3], padding))


# ------------------------------------------------------------------------------------------- whole models


def _modi_pair():
    from modi.models.modi.config import ModelConfig
    from modi.models.modi.levels import build_levels
    from modi.models.modi.networks import Discriminator, Generator
    from modi.data.procedural import builtin_skeleton
    from modi.core.skeleton_graph import build_hierarchy

    sk = builtin_skeleton()
    h = build_hierarchy(sk, sk.detect_feet())
    cfg = ModelConfig(latent_dim=8, n_mlp=2, channels=tuple([4] * h.n_levels))
    levels = build_levels(h, cfg, 16)
    torch.manual_seed(0)
    g = Generator(cfg, levels, 4).double()
    d = Discriminator(cfg, levels, 4).double()
    return cfg, g, d


def _param_grads(module):
    return [p.grad.clone() if p.grad is not None else None for p in module.parameters()]


def _run_modi_regularisers(impl, monkeypatch):
    from modi.models.modi.losses import d_r1_penalty, path_length_penalty

    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    cfg, g, d = _modi_pair()
    torch.manual_seed(1)
    real = torch.randn(2, 4, g(torch.randn(1, cfg.latent_dim, dtype=torch.float64)).shape[2], 16,
                       dtype=torch.float64).requires_grad_(True)
    d_r1_penalty(d(real), real).backward()
    z = torch.randn(2, cfg.latent_dim, dtype=torch.float64)
    fake, wplus = g(z, return_latents=True)
    penalty, _, _ = path_length_penalty(fake, wplus, 0.0)
    penalty.backward()
    return _param_grads(d), _param_grads(g)


def test_modi_r1_and_path_length_gradients_match_reference(monkeypatch):
    ext_d, ext_g = _run_modi_regularisers("ext", monkeypatch)
    ref_d, ref_g = _run_modi_regularisers("ref", monkeypatch)
    assert sum(a is not None for a in ext_g) > 4 and sum(a is not None for a in ext_d) > 4
    for a, r in zip(ext_d + ext_g, ref_d + ref_g):
        assert (a is None) == (r is None)
        if a is not None:
            torch.testing.assert_close(a, r, rtol=1e-8, atol=1e-10)


def _run_wgan_gp(impl, monkeypatch):
    from modi.models.ganimator.networks import PatchDiscriminator, ganimator_neighbors
    from modi.models.ganimator.training import gradient_penalty

    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    parents = [-1, 0, 1, 2, 0, 4, 5, 0, 7]
    nb = ganimator_neighbors(parents, [3, 6], distance=2)
    torch.manual_seed(0)
    d = PatchDiscriminator(nb, base_channels=16, n_layers=3).double()
    real = torch.randn(1, 6, len(nb), 20, dtype=torch.float64)
    fake = torch.randn(1, 6, len(nb), 20, dtype=torch.float64)
    torch.manual_seed(2)
    gradient_penalty(d, real, fake).backward()
    return _param_grads(d)


def test_ganimator_wgan_gp_gradients_match_reference(monkeypatch):
    ext, ref = _run_wgan_gp("ext", monkeypatch), _run_wgan_gp("ref", monkeypatch)
    assert sum(a is not None for a in ext) >= len(ext) - 1  # the head's bias does not reach the input gradient
    for a, r in zip(ext, ref):
        assert (a is None) == (r is None)
        if a is not None:
            torch.testing.assert_close(a, r, rtol=1e-8, atol=1e-10)


def test_double_backward_reference_switch(monkeypatch):
    """MODI_EXT_DOUBLE=ref (the pre-gradfix path, kept for comparison) really uses the reference, same answer."""
    seed = 4

    def inputs():
        return _inputs("conv", random.Random(seed), True, True, "reflect", n_joints=6, U=3, B=2, cin=2, cout=3, T=8)

    fast = _second_order("conv", "ext", monkeypatch, inputs, seed)
    calls = []
    real = R.skeletal_conv
    monkeypatch.setattr(R, "skeletal_conv", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setenv("MODI_EXT_DOUBLE", "ref")
    slow = _second_order("conv", "ext", monkeypatch, inputs, seed)
    assert calls
    for a, r in zip(fast, slow):
        torch.testing.assert_close(a, r, rtol=1e-9, atol=1e-9)


def test_backward_ops_accept_non_contiguous_inputs():
    """The registered backward ops are public: strided gradients and weights are made contiguous, not refused."""
    from modi_ext.skeletal import checks, gradfix

    x, w, topo = _disconnected_conv_case()
    y = ops.skeletal_conv(x, w, None, topo.index, topo.offsets)
    g = torch.randn(y.shape[::-1], dtype=y.dtype).permute(3, 2, 1, 0)  # same shape, transposed strides
    assert not g.is_contiguous()
    gx = gradfix.skeletal_grad_input(g, w, topo.index, topo.offsets, checks.KIND_CONV, 5, 5, 7, "zeros")
    gw = gradfix.skeletal_grad_weight(g, x, topo.index, topo.offsets, checks.KIND_CONV, 5, 5, "zeros")
    ref_gx, ref_gw = torch.autograd.grad(
        R.skeletal_conv(x.requires_grad_(True), w.requires_grad_(True), None, topo.index, topo.offsets), [x, w],
        g.contiguous())
    torch.testing.assert_close(gx, ref_gx, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(gw, ref_gw, rtol=1e-9, atol=1e-9)
