"""The bias activation in the skeletal ops' epilogue (``act=True``): the C++ kernels against the reference followed
by ``modi_ext.act.fused_leaky_relu`` -- forward, every gradient, gradcheck and gradgradcheck in float64, opcheck,
the bf16 kernels -- on random trees and poolings; and the layers that fuse it."""
from __future__ import annotations

import random

import pytest
import torch

from modi_ext import HAS_EXT
from modi_ext.act import GAIN, SLOPE, backward_from_output, fused_leaky_relu
from modi_ext.skeletal import ops
from modi_ext.skeletal import reference as R
from skeletal_cases import KINDS, call, make_case

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")


def oracle(kind, args, kw):
    """The reference op without its bias, then the Python bias activation: what ``act=True`` means."""
    x, w, b = args[:3]
    return fused_leaky_relu(call(kind, R, (x, w, None) + args[3:], kw), b)


def _leaves(args, kw):
    leaves = [t for t in (args[0], args[1], args[2], kw["style"]) if t is not None]
    for t in leaves:
        t.requires_grad_(True)
    return leaves


def test_the_python_activation_is_stylegan2s():
    x = torch.tensor([-2.0, -0.5, 0.0, 0.5, 3.0], dtype=torch.float64)
    b = torch.tensor([0.25], dtype=torch.float64)
    pre = x + 0.25
    want = torch.where(pre > 0, pre, SLOPE * pre) * GAIN
    torch.testing.assert_close(fused_leaky_relu(x.view(1, 1, 5), b).view(5), want, rtol=0, atol=1e-15)


def test_backward_from_output_matches_autograd_and_inverts():
    torch.manual_seed(0)
    pre = torch.randn(64, dtype=torch.float64, requires_grad=True)
    y = fused_leaky_relu(pre.view(1, 1, 64), None)
    g = torch.randn_like(y)
    (want,) = torch.autograd.grad(y, pre, g)
    got, got_pre = backward_from_output(g, y.detach(), pre=True)
    torch.testing.assert_close(got.view(64), want, rtol=1e-15, atol=0)
    torch.testing.assert_close(got_pre.view(64), pre.detach(), rtol=1e-15, atol=0)


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
def test_forward_and_gradients_fp64_random_trees(kind):
    rng = random.Random({"conv": 41, "down": 42, "up": 43}[kind])
    for i in range(20):
        args, kw = make_case(kind, rng, bias=i % 4 != 0)
        leaves = _leaves(args, kw)
        ye, yr = call(kind, ops, args, dict(kw, act=True)), oracle(kind, args, kw)
        torch.testing.assert_close(ye, yr, rtol=1e-10, atol=1e-10 * float(yr.abs().max()))
        g = torch.randn_like(yr)
        for a, b in zip(torch.autograd.grad(ye, leaves, g), torch.autograd.grad(yr, leaves, g)):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()))


@needs_ext
@pytest.mark.parametrize("cpu_kernel", ["auto", "blas"])
@pytest.mark.parametrize("kind", KINDS)
def test_fp32_kernels_match_reference(monkeypatch, kind, cpu_kernel):
    """float32 runs the fast CPU kernels (or the BLAS path when forced): the epilogue is in both."""
    monkeypatch.setenv("MODI_EXT_CPU_KERNEL", cpu_kernel)
    rng = random.Random({"conv": 51, "down": 52, "up": 53}[kind])
    for _ in range(8):
        args, kw = make_case(kind, rng, B=rng.randint(1, 5), cin=rng.randint(1, 9), cout=rng.randint(1, 9),
                             T=rng.randint(8, 40))
        leaves = _leaves(args, kw)
        yr = oracle(kind, args, kw)
        g = torch.randn_like(yr)
        gr = torch.autograd.grad(yr, leaves, g)
        f32 = [t.detach().float().requires_grad_(True) if t is not None else None for t in args[:3]]
        s32 = kw["style"].detach().float().requires_grad_(True) if kw["style"] is not None else None
        ye = call(kind, ops, tuple(f32) + args[3:], dict(kw, style=s32, act=True))
        torch.testing.assert_close(ye.double(), yr, rtol=1e-4, atol=1e-4 * float(yr.abs().max()) + 1e-6)
        ge = torch.autograd.grad(ye, [t for t in f32 + [s32] if t is not None], g.float())
        for a, b in zip(ge, gr):
            torch.testing.assert_close(a.double(), b, rtol=1e-3, atol=1e-3 * max(1.0, float(b.abs().max())))


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style,demod", [(False, False), (True, True)])
def test_gradcheck_and_gradgradcheck_fp64(kind, style, demod):
    """First and second order (R1 and path length differentiate through the fused activation)."""
    rng = random.Random(hash((kind, style, demod)) % 1000)
    args, kw = make_case(kind, rng, n_joints=4, distance=1, U=3, B=2, cin=2, cout=2, T=5, style=style,
                         demod=demod, padding="zeros")
    x, w, b = (t.requires_grad_(True) for t in args[:3])
    rest = args[3:]
    inputs = (x, w, b) + ((kw["style"].requires_grad_(True),) if style else ())

    def fn(x, w, b, *maybe_s):
        return call(kind, ops, (x, w, b) + rest, dict(kw, style=maybe_s[0] if maybe_s else None, act=True))

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=style)
    assert torch.autograd.gradgradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
def test_opcheck(kind):
    rng = random.Random(61)
    for style, demod in [(False, False), (True, True)]:
        args, kw = make_case(kind, rng, dtype=torch.float32, n_joints=4, U=3, B=2, cin=2, cout=3, T=6,
                             style=style, demod=demod, padding="zeros")
        x, w, b, index, offsets = args[:5]
        n_out = args[5] if kind == "up" else offsets.numel() - 1
        scale = ops.demod_scale(w, index, offsets, kw["style"], kind == "up", n_out, x.shape[0]) if demod else None
        for t in (x, w, b):
            t.requires_grad_(True)
        sty = kw["style"].requires_grad_(True) if style else None
        scale = scale.detach().requires_grad_(True) if scale is not None else None
        op = getattr(torch.ops.modi_ext, f"skeletal_{kind}").default
        op_args = (x, w, b, index, offsets) + (args[5:] if kind == "up" else ()) + (sty, scale, "zeros", True)
        torch.library.opcheck(op, op_args)


@needs_ext
@pytest.mark.parametrize("cpu_kernel", ["auto", "bf16emu"])
@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels(monkeypatch, kind, cpu_kernel):
    """bf16 in, fp32 accumulation, the activation in fp32 before the one rounding: within the format's epsilon x K of
    the float64 oracle on the bf16-rounded inputs."""
    monkeypatch.setenv("MODI_EXT_CPU_KERNEL", cpu_kernel)
    rng = random.Random({"conv": 71, "down": 72, "up": 73}[kind])
    for _ in range(4):
        args, kw = make_case(kind, rng, B=2, cin=rng.randint(2, 8), cout=rng.randint(2, 8), T=rng.randint(8, 24),
                             demod=False)
        bf = [t.to(torch.bfloat16) for t in args[:3]]
        sty = kw["style"].to(torch.bfloat16) if kw["style"] is not None else None
        y = call(kind, ops, tuple(bf) + args[3:], dict(kw, style=sty, act=True, impl="ext"))
        assert y.dtype == torch.bfloat16
        rounded = tuple(t.double() for t in bf) + args[3:]
        want = oracle(kind, rounded, dict(kw, style=sty.double() if sty is not None else None))
        k = args[1].shape[1] * args[1].shape[2] * args[1].shape[3]
        eps = torch.finfo(torch.bfloat16).eps
        torch.testing.assert_close(y.double(), want, rtol=2 * eps, atol=(k + 2) * eps * float(want.abs().max()))


def test_layer_with_its_own_bias_refuses_act():
    from modi_ext.layers import FusedLeakyReLU, SkeletalConv

    conv = SkeletalConv(2, 3, [[0, 1], [0, 1]], bias=True)
    with pytest.raises(ValueError, match="bias=False"):
        conv(torch.randn(1, 2, 2, 4), act=FusedLeakyReLU(3))


@pytest.mark.parametrize("impl", ["ext", "ref"])
def test_layers_fused_equal_unfused(monkeypatch, impl):
    """A bias-free layer with ``act=`` equals the layer followed by the activation module."""
    if impl == "ext" and not HAS_EXT:
        pytest.skip("modi_ext C++ extension not built")
    from modi_ext.layers import FusedLeakyReLU, ModulatedSkeletalConv, SkeletalConv, SkeletalDownsample, \
        SkeletalUpsample

    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    torch.manual_seed(3)
    nb, pool = [[0, 1], [0, 1, 2], [1, 2]], [[0, 1], [2]]
    act = FusedLeakyReLU(4).double()
    with torch.no_grad():
        act.bias.normal_()
    x3, x2 = torch.randn(2, 3, 3, 8, dtype=torch.float64), torch.randn(2, 3, 2, 8, dtype=torch.float64)
    for layer, x in ((SkeletalConv(3, 4, nb, bias=False), x3), (SkeletalDownsample(3, 4, pool, bias=False), x3),
                     (SkeletalUpsample(3, 4, pool, bias=False), x2)):
        layer = layer.double()
        torch.testing.assert_close(layer(x, act=act), act(layer(x)), rtol=1e-12, atol=1e-12)
    mod = ModulatedSkeletalConv(3, 4, 5, nb).double()
    w = torch.randn(2, 5, dtype=torch.float64)
    torch.testing.assert_close(mod(x3, w, act=act), act(mod(x3, w)), rtol=1e-12, atol=1e-12)
