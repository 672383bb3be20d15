"""bfloat16 skeletal ops on the CPU: the bf16 kernels (AVX-512-BF16 and their plain-C++ emulation) and the dense path,
against the float64 reference.

bf16 on the CPU runs on the bf16 kernels (``csrc/skeletal/bf16k.h``) where the CPU has AVX-512-BF16 (or with
``MODI_EXT_CPU_KERNEL=bf16emu``, on their emulation), else on ``modi_ext.skeletal.dense`` (torch's GEMMs: oneDNN's
bf16 units where the CPU has them, fp32 accumulation everywhere), never on the fp32 kernels; under CPU autocast a
skeletal op returns bf16, as torch's convs.  The kernel tests run both micro-kernel sets: the AVX-512-BF16 one where
the CPU has it (else skipped, naming the missing feature) and the emulated one always, so the layout and indexing
are covered on any CPU.

Tolerance, derived rather than tuned.  The inputs are rounded to bf16 first and the float64 reference runs on exactly
those values, so only the op's own roundings count.  bf16's unit roundoff is ``u = 2^-8`` (8 significant bits;
``torch.finfo(torch.bfloat16).eps / 2``).  Every value on a path is either a product/scale of rounded values or a
reduction of ``K`` products accumulated in fp32 (error <= ``K 2^-24`` of the sum of magnitudes) and then rounded to
bf16 (error <= ``u`` of the value).  The stages that round to bf16, counted from the code (``dense.py``,
``demod/dense.py``, ``reference.skeletal_up``):

* forward, conv/down: the style scale, the GEMM output, the demodulation coefficients, the demodulation scale, the
  bias add: 5; up adds the reflect fold (2 adds) and the blur: 8;
* backward: the demodulation scale of the incoming gradient, the GEMM output, the unfold/fold adjoint (<= 2 adds for
  U = 3), the style scale, the sum of the direct and demodulation terms, their fp32 -> bf16 conversions: <= 8.

The bf16 kernels round fewer times (``bf16k.cpp``; their epilogues -- scale, bias, fold, blur -- run in fp32):

* forward: x * style laid out in bf16, the demodulation coefficients (``demod/dense.py``), the output: 3;
* backward: gy * d and x * style laid out in bf16, the kernel's output, the demodulation coefficients, the
  demodulation branch of the weight / style gradient (torch ops, rounded to bf16) and its sum with the kernel's
  term: 6.

Each stage moves a value of at most the size of the result by at most ``u`` of it, so with ``N`` stages

    |z_bf16 - z_ref| <= (N u + K 2^-24) * scale,        scale = max |z_ref|

where ``max |z_ref|`` stands for ``c sqrt(K) S`` (K zero-mean terms of rms S, c the tail of the largest of the
outputs): it is measured on the reference rather than modelled, which keeps it valid through the demodulation (a
positive per-row scale).  The K products' own roundings (each term rounded once, as x * style is) add up like the
terms, to ``u`` of ``sqrt(K) S``: inside one stage.  Only the style gradient of a demodulated op is a near-cancelling
difference of two terms; its scale is the larger of them (the direct term, taken with the demodulation coefficients
held constant).
"""
from __future__ import annotations

import math
import random

import pytest
import torch

import modi_ext
from modi_ext.demod import dense as demod_dense
from modi_ext.demod import ops as demod_ops
from modi_ext.runtime import dispatch
from modi_ext.skeletal import dense, ops
from modi_ext.skeletal import reference as R
from skeletal_cases import KINDS, call, make_case

U_BF16 = 2.0 ** -8
U_FP32 = 2.0 ** -24
STAGES = 8


def bound(k: int, scale: float, stages: int = STAGES) -> float:
    return (stages * U_BF16 + k * U_FP32) * scale


def _bf16_case(kind: str, seed: int, style: bool, demod: bool, padding: str = None):
    args, kw = make_case(kind, random.Random(seed), dtype=torch.float64, n_joints=random.Random(seed).randint(6, 30),
                         U=3, B=3, cin=8, cout=6, T=16, style=style, demod=demod, padding=padding)
    r = lambda t: t.to(torch.bfloat16) if isinstance(t, torch.Tensor) and t.is_floating_point() else t  # noqa: E731
    a16, kw16 = tuple(r(a) for a in args), dict(kw, style=r(kw["style"]))
    up = lambda t: t.double() if isinstance(t, torch.Tensor) and t.is_floating_point() else t  # noqa: E731
    a64, kw64 = tuple(up(a) for a in a16), dict(kw16, style=up(kw16["style"]))  # exactly the bf16 values
    return a16, kw16, a64, kw64


def _k_forward(kind: str, args) -> int:
    """The longest forward reduction: Cin x U x (most pairs of one output entity; up: of one fine entity)."""
    x, w, index, offsets = args[0], args[1], args[3], args[4]
    if kind == "up":
        return x.shape[1] * w.shape[3] * int(torch.bincount(index).max()) * 2  # transposed conv + blur taps
    return x.shape[1] * w.shape[3] * int((offsets[1:] - offsets[:-1]).max())


def _leaves(args, kw):
    out = [args[0], args[1], args[2]] + ([kw["style"]] if kw["style"] is not None else [])
    return [t.detach().requires_grad_(True) for t in out]


def _with(args, kw, leaves):
    a = (leaves[0], leaves[1], leaves[2]) + tuple(args[3:])
    return a, dict(kw, style=leaves[3] if len(leaves) > 3 else None)


def _direct_style_grad(kind, args, kw, g):
    """The style gradient's direct term, the demodulation coefficients held constant (the scale of a cancelling
    difference): float64 dense form without demodulation, times the detached coefficients."""
    x, w, b, index, offsets = args[:5]
    n_out = args[5] if kind == "up" else offsets.numel() - 1
    s = kw["style"].detach().requires_grad_(True)
    d = demod_dense.demod_scale(w, index, offsets, s.detach(), kind == "up", n_out, x.shape[0])
    if kind == "up":
        y = dense.skeletal_up(x, w, None, index, offsets, n_out, s, False, kw["padding_mode"])
    else:
        fn = dense.skeletal_conv if kind == "conv" else dense.skeletal_down
        y = fn(x, w, None, index, offsets, s, False, kw["padding_mode"])
    (gs,) = torch.autograd.grad(y * d.unsqueeze(-1), s, g)
    return gs


@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("style,demod", [(False, False), (True, False), (True, True), (False, True)])
@pytest.mark.parametrize("kind", KINDS)
def test_bf16_against_float64_reference(kind, style, demod, padding):
    a16, kw16, a64, kw64 = _bf16_case(kind, 100 + 7 * KINDS.index(kind) + 2 * style + demod, style, demod, padding)
    l16, l64 = _leaves(a16, kw16), _leaves(a64, kw64)
    y16 = call(kind, ops, *_with(a16, kw16, l16))
    y64 = call(kind, R, *_with(a64, kw64, l64))
    assert y16.dtype == torch.bfloat16 and y16.shape == y64.shape
    k = _k_forward(kind, a64)
    err, tol = float((y16.detach().double() - y64.detach()).abs().max()), bound(k, float(y64.detach().abs().max()))
    assert err <= tol, f"forward error {err:.3g} > {tol:.3g} (K={k})"
    assert err > 0  # it really ran in bf16 (a float32 path would be ~2^-16 off, within the bound but not exact)

    g64 = torch.randn(y64.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    g16 = g64.to(torch.bfloat16)
    g64 = g16.double()
    got = torch.autograd.grad(y16, l16, g16)
    want = torch.autograd.grad(y64, l64, g64)
    b, t = a64[0].shape[0], a64[0].shape[-1]
    # reduction lengths, upper bounds (they enter only through the fp32 accumulation term, K 2^-24)
    ks = {"x": y64.shape[1] * 3 * a64[3].numel(), "weight": 2 * b * t, "bias": y64[:, 0].numel(),
          "style": a64[0][0].numel() * 3}
    for name, gg, gw in zip(("x", "weight", "bias", "style"), got, want):
        assert gg.dtype == torch.bfloat16, name
        scale = float(gw.abs().max())
        if name == "style" and demod:
            scale = max(scale, float(_direct_style_grad(kind, a64, kw64, g64).abs().max()))
        err, tol = float((gg.double() - gw).abs().max()), bound(ks[name], scale)
        assert err <= tol, f"{name} gradient error {err:.3g} > {tol:.3g}"


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_double_backward(kind):
    """R1: the input gradient with create_graph, its squared norm differentiated again, in bf16 (the dense path's
    plain torch ops); against float64 with twice the stages (the second pass rounds as the first)."""
    a16, kw16, a64, kw64 = _bf16_case(kind, 40 + KINDS.index(kind), True, True, "zeros")
    res = []
    for a, kw in ((a16, kw16), (a64, kw64)):
        leaves = _leaves(a, kw)
        y = call(kind, ops if a is a16 else R, *_with(a, kw, leaves))
        (gx,) = torch.autograd.grad(y.sum(), leaves[0], create_graph=True)
        res.append(torch.autograd.grad(gx.pow(2).sum(), leaves[1]))
    (w16,), (w64,) = res
    assert w16.dtype == torch.bfloat16 and torch.isfinite(w16).all()
    err, tol = float((w16.double() - w64).abs().max()), bound(4096, float(w64.abs().max()), 2 * STAGES)
    assert err <= tol, f"double-backward weight gradient error {err:.3g} > {tol:.3g}"


@pytest.mark.parametrize("up", [False, True])
def test_bf16_demod_scale(up):
    """The demodulation op in bf16: reductions in fp32, one final rounding (<= u relative, plus the fp32 sums)."""
    kind = "up" if up else "conv"
    a16, kw16, a64, kw64 = _bf16_case(kind, 9, True, True)
    x, w, _, index, offsets = a16[:5]
    n_out = a16[5] if up else offsets.numel() - 1
    d16 = demod_ops.demod_scale(w, index, offsets, kw16["style"], up, n_out, x.shape[0])
    d64 = demod_dense.demod_scale(a64[1], index, offsets, kw64["style"], up, n_out, x.shape[0])
    assert d16.dtype == torch.bfloat16
    k = w.numel()
    rel = float(((d16.double() - d64) / d64).abs().max())
    assert rel <= U_BF16 + 4 * k * U_FP32, rel


@pytest.mark.parametrize("impl", ["auto", "ext"])
def test_bf16_never_reaches_the_fp32_kernels(monkeypatch, impl):
    """Where the bf16 kernels are not chosen (a CPU without AVX-512-BF16, no emulation asked for), bf16 routes to
    dense under auto and ext alike: no kernel call, no self-check."""
    monkeypatch.setenv("MODI_EXT_IMPL", impl)

    def boom(*_a):
        raise AssertionError("a bf16 call reached the fp32 kernels")

    dense_row = dict(dispatch.cpu_bf16_path(), path="dense", summary="bf16: dense (as on a CPU without bf16 units)")
    monkeypatch.setattr(dispatch, "cpu_bf16_path", lambda: dense_row)
    monkeypatch.setattr(dispatch, "KERNELS", {k: boom for k in dispatch.KERNELS})
    monkeypatch.setattr(dispatch, "SELFCHECK", lambda *a: pytest.fail("bf16 triggered the kernels' self-check"))
    dispatch.reset()
    try:
        for kind in KINDS:
            a16, kw16, _, _ = _bf16_case(kind, 3, True, True)
            leaves = _leaves(a16, kw16)
            y = call(kind, ops, *_with(a16, kw16, leaves))
            torch.autograd.grad(y.sum(), leaves)
        rows = modi_ext.dispatch_report()
        paths = {(r["op"], r["path"]) for r in rows
                 if r["kind"] == "path" and r["dtype"] == "bfloat16" and r["op"].startswith("skeletal")}
        assert paths == {(f"skeletal_{k}", "dense") for k in KINDS}
        (bf16,) = [r for r in rows if r["kind"] == "bf16"]
        assert bf16["path"] == "dense" and bf16["summary"].startswith("bf16: dense (")
        assert not [r for r in rows if r["kind"] == "selfcheck"]
    finally:
        dispatch.reset()


def test_bf16_report_names_the_cpu_units():
    row = dispatch.cpu_bf16_path()
    caps = torch.backends.cpu.get_cpu_capability()
    assert row["cpu_capability"] == caps
    avx512_bf16 = getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)()
    amx = getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)()
    onednn = torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    if onednn and amx:
        assert row["gemm"] == "oneDNN avx512_core_amx"
    elif onednn and avx512_bf16:
        assert row["gemm"] == "oneDNN avx512_core_bf16"
    else:
        assert "no bf16 units" in row["gemm"]


@pytest.mark.parametrize("impl", ["auto", "dense", "ref"])
@pytest.mark.parametrize("kind", KINDS)
def test_autocast_output_is_bf16(monkeypatch, impl, kind):
    """Under CPU autocast (bf16) a skeletal op returns bf16, as torch's convolutions, on every path; float32 outside
    autocast is unchanged."""
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    args, kw = make_case(kind, random.Random(11), dtype=torch.float32, n_joints=9, U=3, T=8, style=True, demod=True)
    want = call(kind, ops, args, kw)
    assert want.dtype == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = call(kind, ops, args, kw)
        y64 = call(kind, ops, tuple(a.double() if isinstance(a, torch.Tensor) and a.is_floating_point() else a
                                    for a in args), dict(kw, style=kw["style"].double()))
    assert y.dtype == torch.bfloat16
    assert y64.dtype == torch.float64  # autocast leaves float64 alone (and so does the op)
    # the inputs were rounded to bf16 by the cast: relative error up to ~K u on the output's scale
    k = _k_forward(kind, args)
    assert float((y.float() - want).abs().max()) <= (STAGES + 2 * math.sqrt(k)) * U_BF16 * float(want.abs().max())


def test_autocast_float32_outside_is_bitwise_unchanged():
    args, kw = make_case("conv", random.Random(12), dtype=torch.float32, n_joints=9, U=3, T=8, style=True,
                         demod=True)
    a = call("conv", ops, args, kw)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=False):
        b = call("conv", ops, args, kw)
    assert torch.equal(a, b)


@pytest.mark.parametrize("what,match", [
    ("weight", "weight dtype torch.float32 differs from x dtype torch.bfloat16"),
    ("bias", "bias dtype torch.float32 differs from x dtype torch.bfloat16"),
    ("style", "style dtype torch.float32 differs from x dtype torch.bfloat16"),
    ("x16", "x must be float32, float64 or bfloat16"),
])
def test_mixed_dtypes_error_clearly(what, match):
    args, kw = make_case("conv", random.Random(13), dtype=torch.float32, n_joints=6, U=3, T=8, style=True)
    args = list(args)
    if what == "x16":
        args[0], args[1], args[2] = args[0].half(), args[1].half(), args[2].half()
        kw["style"] = kw["style"].half()
    else:
        args[0] = args[0].to(torch.bfloat16)
        for i, name in ((1, "weight"), (2, "bias")):
            if name != what:
                args[i] = args[i].to(torch.bfloat16)
        if what != "style":
            kw["style"] = kw["style"].to(torch.bfloat16)
    with pytest.raises(TypeError, match=match):
        call("conv", ops, tuple(args), kw)


# ------------------------------------------------------------------------------------------------ the bf16 kernels

KERNEL_STAGES_FWD = 3  # module docstring: the bf16 kernels' roundings
KERNEL_STAGES_BWD = 6
HAS_BF16_KERNELS = modi_ext.HAS_EXT and hasattr(torch.ops.modi_ext, "skeletal_cpu_bf16_kernel")
needs_bf16_kernels = pytest.mark.skipif(not HAS_BF16_KERNELS, reason="this modi_ext build has no bf16 CPU kernels")


def _cpu_has_avx512_bf16() -> bool:
    return bool(getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)())


@pytest.fixture(params=["avx512_bf16", "emulated"])
def bf16_kernel(request, monkeypatch):
    """Runs a test on one micro-kernel set of the bf16 kernels: AVX-512-BF16 (skipped where the CPU lacks it) or the
    plain-C++ emulation (MODI_EXT_CPU_KERNEL=bf16emu, any CPU)."""
    if not HAS_BF16_KERNELS:
        pytest.skip("this modi_ext build has no bf16 CPU kernels")
    if request.param == "avx512_bf16":
        if not _cpu_has_avx512_bf16():
            pytest.skip("the CPU lacks the avx512_bf16 instructions (vdpbf16ps): the emulated kernels run instead")
        monkeypatch.delenv("MODI_EXT_CPU_KERNEL", raising=False)
    else:
        monkeypatch.setenv("MODI_EXT_CPU_KERNEL", "bf16emu")
    dispatch.reset()
    assert torch.ops.modi_ext.skeletal_cpu_bf16_kernel() == request.param
    assert dispatch.cpu_bf16_path()["path"] == "ext"
    yield request.param
    dispatch.reset()


def _kernel_case(kind: str, seed: int, style: bool, demod: bool, padding: str, size: str):
    """Random skeleton; "small" (one column tile, fewer than 9 rows), "wide" (odd channel counts -- a zero channel
    in the pairs -- more than 9 output rows, several 48-column tiles and batch tiles, U = 5) or "split" (few entities
    and many channels: the weight gradient split into row blocks, several 32-row transposed blocks)."""
    rng = random.Random(seed)
    joints = rng.randint(6, 30)
    if size == "small":
        dims = dict(U=3, B=3, cin=8, cout=6, T=16)
    elif size == "wide":
        dims = dict(U=5, B=5, cin=13, cout=19, T=37)
    else:
        dims = dict(U=3, B=2, cin=40, cout=70, T=9)
        joints = rng.randint(3, 6)
    args, kw = make_case(kind, rng, dtype=torch.float64, n_joints=joints, style=style, demod=demod,
                         padding=padding, **dims)
    r = lambda t: t.to(torch.bfloat16) if isinstance(t, torch.Tensor) and t.is_floating_point() else t  # noqa: E731
    a16, kw16 = tuple(r(a) for a in args), dict(kw, style=r(kw["style"]))
    up = lambda t: t.double() if isinstance(t, torch.Tensor) and t.is_floating_point() else t  # noqa: E731
    return a16, kw16, tuple(up(a) for a in a16), dict(kw16, style=up(kw16["style"]))


@pytest.mark.parametrize("size", ["small", "wide", "split"])
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("style,demod", [(False, False), (True, False), (True, True), (False, True)])
@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels_against_float64_reference(bf16_kernel, kind, style, demod, padding, size):
    """The bf16 kernels (forced: impl="ext"), forward and every gradient, against the float64 reference."""
    seed = 300 + 7 * KINDS.index(kind) + 2 * style + demod + 50 * ["small", "wide", "split"].index(size)
    a16, kw16, a64, kw64 = _kernel_case(kind, seed, style, demod, padding, size)
    l16, l64 = _leaves(a16, kw16), _leaves(a64, kw64)
    y16 = call(kind, ops, *_with(a16, dict(kw16, impl="ext"), l16))
    y64 = call(kind, R, *_with(a64, kw64, l64))
    assert y16.dtype == torch.bfloat16 and y16.shape == y64.shape
    k = _k_forward(kind, a64)
    err = float((y16.detach().double() - y64.detach()).abs().max())
    tol = bound(k, float(y64.detach().abs().max()), KERNEL_STAGES_FWD)
    assert err <= tol, f"forward error {err:.3g} > {tol:.3g} (K={k})"
    assert err > 0  # it really ran in bf16

    g64 = torch.randn(y64.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    g16 = g64.to(torch.bfloat16)
    g64 = g16.double()
    got = torch.autograd.grad(y16, l16, g16)
    want = torch.autograd.grad(y64, l64, g64)
    b, t, u = a64[0].shape[0], a64[0].shape[-1], a64[1].shape[-1]
    ks = {"x": y64.shape[1] * u * a64[3].numel(), "weight": 2 * b * t, "bias": y64[:, 0].numel(),
          "style": a64[0][0].numel() * u}
    for name, gg, gw in zip(("x", "weight", "bias", "style"), got, want):
        assert gg.dtype == torch.bfloat16, name
        scale = float(gw.abs().max())
        if name == "style" and demod:
            scale = max(scale, float(_direct_style_grad(kind, a64, kw64, g64).abs().max()))
        err, tol = float((gg.double() - gw).abs().max()), bound(ks[name], scale, KERNEL_STAGES_BWD)
        assert err <= tol, f"{name} gradient error {err:.3g} > {tol:.3g}"
    paths = {(r["op"], r["path"]) for r in modi_ext.dispatch_report()
             if r["kind"] == "path" and r["dtype"] == "bfloat16" and r["op"].startswith("skeletal")}
    assert paths == {(f"skeletal_{kind}", "ext")}


KIND_ID = {"conv": 0, "down": 1, "up": 2}


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels_scale_gradient_and_masks(bf16_kernel, kind):
    """The C++ backward op itself, every output-mask combination and the demodulation-scale gradient, against the
    float64 kernels on the same bf16 values (the float64 kernels are checked against the reference elsewhere)."""
    a16, kw16, a64, kw64 = _kernel_case(kind, 77 + KINDS.index(kind), True, False, "reflect", "wide")
    x, w, b, index, offsets = a16[:5]
    n_out = a16[5] if kind == "up" else 0
    e_out = n_out if kind == "up" else offsets.numel() - 1
    d = (torch.rand(x.shape[0], w.shape[2] if kind == "up" else w.shape[0], e_out,
                    generator=torch.Generator().manual_seed(3), dtype=torch.float64) + 0.5).to(torch.bfloat16)
    s = kw16["style"]
    op = getattr(torch.ops.modi_ext, f"skeletal_{kind}")
    extra = (n_out,) if kind == "up" else ()
    y16 = op(x, w, b, index, offsets, *extra, s, d, "reflect")
    g16 = torch.randn(y16.shape, generator=torch.Generator().manual_seed(4)).to(torch.bfloat16)
    dd = lambda t: t.double()  # noqa: E731
    for mask in ([True, True, True, True], [True, False, False, False], [False, True, False, False],
                 [False, False, True, False], [False, False, False, True]):
        got = torch.ops.modi_ext.skeletal_backward(g16, y16, x, w, b, index, offsets, s, d, "reflect", KIND_ID[kind],
                                                   n_out, mask)
        want = torch.ops.modi_ext.skeletal_backward(dd(g16), dd(y16), dd(x), dd(w), dd(b), index, offsets, dd(s), dd(d),
                                                    "reflect", KIND_ID[kind], n_out, mask)
        for name, gg, gw in zip(("x", "weight", "bias", "style", "scale"), got, want):
            assert gg.shape == gw.shape, (name, mask)
            if gw.numel():
                # one stage each for gy * d, x * style and the output (the scale's: the output y, an input here)
                err, tol = float((gg.double() - gw).abs().max()), bound(4096, float(gw.abs().max()), 3)
                assert err <= tol, f"{name} gradient (mask {mask}) error {err:.3g} > {tol:.3g}"


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels_double_backward(bf16_kernel, kind):
    """R1 on the bf16 kernels: gradfix's partial backward ops in bf16 (create_graph), against float64."""
    a16, kw16, a64, kw64 = _bf16_case(kind, 40 + KINDS.index(kind), True, True, "zeros")
    res = []
    for a, kw, mod in ((a16, dict(kw16, impl="ext"), ops), (a64, kw64, R)):
        leaves = _leaves(a, kw)
        y = call(kind, mod, *_with(a, kw, leaves))
        (gx,) = torch.autograd.grad(y.sum(), leaves[0], create_graph=True)
        res.append(torch.autograd.grad(gx.pow(2).sum(), leaves[1]))
    (w16,), (w64,) = res
    assert w16.dtype == torch.bfloat16 and torch.isfinite(w16).all()
    err, tol = float((w16.double() - w64).abs().max()), bound(4096, float(w64.abs().max()), 2 * KERNEL_STAGES_BWD)
    assert err <= tol, f"double-backward weight gradient error {err:.3g} > {tol:.3g}"


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels_opcheck(bf16_kernel, kind):
    for style, demod in [(False, False), (True, True)]:
        args, kw = make_case(kind, random.Random(21), dtype=torch.float32, n_joints=5, U=3, B=2, cin=3, cout=4, T=6,
                             style=style, demod=demod, padding="zeros")
        args = tuple(a.to(torch.bfloat16) if isinstance(a, torch.Tensor) and a.is_floating_point() else a
                     for a in args)
        x, w, b, index, offsets = args[:5]
        sty = kw["style"].to(torch.bfloat16).requires_grad_(True) if style else None
        scale = None
        if demod:
            n_out = args[5] if kind == "up" else offsets.numel() - 1
            scale = ops.demod_scale(w, index, offsets, sty.detach(), kind == "up", n_out, x.shape[0])
            scale = scale.detach().requires_grad_(True)
        for t in (x, w, b):
            t.requires_grad_(True)
        op = getattr(torch.ops.modi_ext, f"skeletal_{kind}").default
        torch.library.opcheck(op, (x, w, b, index, offsets) + (args[5:] if kind == "up" else ()) +
                              (sty, scale, "zeros"))


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels_thread_count_invariant(bf16_kernel, kind):
    """Every output element is written by one task in a fixed order: the same bits for 1 and 2 threads."""
    a16, kw16, _, _ = _kernel_case(kind, 8, True, True, "reflect", "wide")
    x = a16[0].repeat(8, 1, 1, 1)  # enough work to use the threads
    args = (x,) + a16[1:]
    kw = dict(kw16, style=kw16["style"].repeat(8, 1), impl="ext")
    before = torch.get_num_threads()
    outs = []
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            leaves = _leaves(args, kw)
            y = call(kind, ops, *_with(args, kw, leaves))
            outs.append((y,) + torch.autograd.grad(y, leaves, torch.ones_like(y)))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*outs):
        assert torch.equal(a, b)


@needs_bf16_kernels
def test_bf16_report_names_the_kernels(monkeypatch):
    monkeypatch.delenv("MODI_EXT_CPU_KERNEL", raising=False)
    row = dispatch.cpu_bf16_path()
    if _cpu_has_avx512_bf16():
        assert row["kernel"] == "avx512_bf16" and row["path"] == "ext"
        assert row["summary"] == "bf16: ext (avx512_bf16 kernels)"
    else:
        assert row["kernel"] == "emulated" and row["path"] == "dense" and "no avx512_bf16" in row["summary"]
    monkeypatch.setenv("MODI_EXT_CPU_KERNEL", "bf16emu")
    row = dispatch.cpu_bf16_path()
    assert row["kernel"] == "emulated" and row["path"] == "ext" and "emulated" in row["summary"]


@pytest.mark.parametrize("kind", KINDS)
def test_autocast_runs_the_bf16_kernels(bf16_kernel, monkeypatch, kind):
    """Under CPU bf16 autocast the inputs are cast to bf16 and the bf16 kernels run (the report's path row)."""
    monkeypatch.setenv("MODI_EXT_IMPL", "auto")
    dispatch.reset()
    args, kw = make_case(kind, random.Random(11), dtype=torch.float32, n_joints=9, U=3, T=8, style=True, demod=True)
    want = call(kind, ops, args, kw)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = call(kind, ops, args, kw)
    assert y.dtype == torch.bfloat16
    paths = {(r["op"], r["path"]) for r in modi_ext.dispatch_report()
             if r["kind"] == "path" and r["dtype"] == "bfloat16" and r["op"].startswith("skeletal")}
    assert paths == {(f"skeletal_{kind}", "ext")}
    k = _k_forward(kind, args)
    assert float((y.float() - want).abs().max()) <= (STAGES + 2 * math.sqrt(k)) * U_BF16 * float(want.abs().max())


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_kernels_opcheck_partial_backward_ops(bf16_kernel, kind):
    """gradfix's partial backward ops (gradients of any order) in bf16."""
    from modi_ext.skeletal import checks

    (x, w, b, index, offsets, *rest), kw, _, _ = _bf16_case(kind, 5, False, False, "zeros")
    n_out = rest[0] if kind == "up" else offsets.numel() - 1
    k = {"conv": checks.KIND_CONV, "down": checks.KIND_DOWN, "up": checks.KIND_UP}[kind]
    y = call(kind, ops, (x, w, None, index, offsets, *rest), dict(kw, impl="ext"))
    g = torch.randn(y.shape, generator=torch.Generator().manual_seed(6)).to(torch.bfloat16).requires_grad_(True)
    wd, xd = w.detach().clone().requires_grad_(True), x.detach().clone().requires_grad_(True)
    torch.library.opcheck(torch.ops.modi_ext.skeletal_grad_input.default,
                          (g, wd, index, offsets, k, n_out, x.shape[2], x.shape[3], "zeros"))
    torch.library.opcheck(torch.ops.modi_ext.skeletal_grad_weight.default,
                          (g, xd, index, offsets, k, n_out, w.shape[3], "zeros"))


def test_bf16_kernels_under_torch_compile(bf16_kernel):
    """torch.compile of a modulated bf16 call on the bf16 kernels: the values are eager's but for the demodulation
    coefficients, which compile takes from the torch form (another fp32 summation order, then the same rounding):
    one stage of difference each way."""
    (x, w, b, index, offsets), kw, _, _ = _bf16_case("conv", 12, True, True, "zeros")

    def f(x, w, b, s):
        return ops.skeletal_conv(x, w, b, index, offsets, style=s, demodulate=True)

    leaves = [t.detach().requires_grad_(True) for t in (x, w, b, kw["style"])]
    want = f(*leaves)
    got = torch.compile(f)(*leaves)
    assert got.dtype == torch.bfloat16
    assert dispatch.route("skeletal_conv", leaves[0]) == "ext"  # the choice compile folds in as a constant
    k = _k_forward("conv", (x, w, b, index, offsets))
    err = float((got.double() - want.double()).abs().max())
    assert err <= bound(k, float(want.abs().max()), 2)
    for name, a, c in zip(("x", "weight", "bias", "style"),
                          torch.autograd.grad(got, leaves, torch.ones_like(got)),
                          torch.autograd.grad(want, leaves, torch.ones_like(want))):
        err = float((a.double() - c.double()).abs().max())
        assert err <= bound(4096, float(c.abs().max()), 2 * KERNEL_STAGES_BWD), name
