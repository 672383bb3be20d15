"""The tensor-core (WMMA) backward of the skeletal ops and the TF32 forms (csrc/skeletal/mma_gemm.cuh), on the CPU
emulator.

With ``MODI_EXT_CUDA_MMA=1`` the input gradient runs on ``mma_gemm_kernel`` (conv / down: the transposed GEMM; up: the
row GEMM read through the blur's adjoint) and the weight gradient on ``mma_wgrad_kernel`` (fp32 partials per split of
batch x time, summed in split order); bf16 inputs use bf16 fragments (16 x 16 x 16), float32 inputs TF32 fragments
(16 x 16 x 8) while ``torch.backends.cudnn.allow_tf32`` is on, and the SIMT kernels when it is off.  The emulator's
WMMA (csrc/emu/wmma_emu.h) multiplies exactly and sums in fp32; for TF32 it rounds as ``cvt.rna.tf32.f32`` does
(``__float_to_tf32``) and refuses an operand the kernel did not round.

Tolerances, per element, derived from unit roundoffs and the reduction lengths, not tuned: u_op for the fragment
format (bf16 2^-8, TF32 2^-11), u_T for the tensor's dtype (bf16 2^-8, float32 2^-24), u = 2^-24 for fp32 sums.
Each operand of a product is rounded to the fragment format once after an fp32 computation of up to 12 terms (the
adjoint read, reflect folding, blur, a style / demodulation factor): relative error at most r = u_op + 16 u each (the
weight: 0 in bf16, where it is already exact, u_op in TF32).  With act, the incoming gradient is first scaled by the
activation's slope and stored in the dtype: r_act = u_T + 2 u.  A sum of K such products in fp32 (any order) is then
within rel = (1 + r_act)(1 + r_1)(1 + r_2)(1 + (K + c) u) - 1 of D, the sum of the products' absolute values
(computed in float64 by running the reference on absolute values; every coefficient of the ops -- blur taps, reflect
folds -- is positive), with c = 6 for the epilogue's few fp32 operations and c = 38 for the weight gradient's split
reduction (at most 32 partials).
  * input gradient: K = the largest reader (up: neighbour) count x Cout x U; error <= |s| (rel + u) D + u_T |result|.
  * style gradient: gs = sum over E x T of gx' x in fp32: sum |x| rel D + (E T + 2) u sum |x| (1 + rel) D, + u_T.
  * weight gradient: K = B x T of the gathered side; error <= rel D + u_T |result|.
  * scale gradient (SIMT, from the forward's stored output): gd = sum_t g (y_pre - b) / d with y_pre within
    r_y |pre| of the pre-activation (r_y = u_T, with act 2 u_T + 2 u: y and y / slope are each stored in the dtype).
The tests hand the backward the float64 forward rounded to the dtype, so each gradient's bound is its own.
"""
from __future__ import annotations

import contextlib
import math

import pytest
import torch

from modi_ext.act import GAIN, SLOPE
from test_cuda_emulated import EMU, Problem, emu, injected, schedules, sm_count  # noqa: F401  (emu: the fixture)
from test_cuda_emulated_mma import check_mma, k_max, mma_on

pytestmark = [pytest.mark.cuda_emulated, pytest.mark.usefixtures("one_torch_thread")]

U32 = torch.finfo(torch.float32).eps / 2
U_BF16 = torch.finfo(torch.bfloat16).eps / 2
U_TF32 = 2.0 ** -11
UNIT = {torch.bfloat16: U_BF16, torch.float32: U32}
OP_UNIT = {torch.bfloat16: U_BF16, torch.float32: U_TF32}  # the fragment format of each dtype
TNAME = {torch.bfloat16: "c10::BFloat16", torch.float32: "float"}


@contextlib.contextmanager
def tf32(on: bool):
    before = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = on
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32 = before


def gx_kernel(p: Problem) -> str:
    tr, blur = ("false", "true") if p.kind == "up" else ("true", "false")
    return f"mma_gemm_kernel<{TNAME[p.dtype]}, {tr}, {blur}>"


def gw_kernel(p: Problem) -> str:
    return f"mma_wgrad_kernel<{TNAME[p.dtype]}, {'true' if p.kind == 'up' else 'false'}>"


def mma_launches() -> int:
    return sum(n for k, n in EMU.launch_counts().items() if k.startswith(("mma_gemm_kernel", "mma_wgrad_kernel")))


def k_gx(p: Problem) -> int:
    """The input gradient's reduction length: conv / down read each input entity through its readers (transposed),
    up each coarse entity through its fine neighbours."""
    if p.kind == "up":
        deg = (p.offsets[1:] - p.offsets[:-1]).max().item()
    else:
        deg = torch.bincount(p.index, minlength=p.n_in).max().item()
    return deg * p.gy.shape[1] * p.U


def abs_or_none(t):
    return None if t is None else t.abs()


def grad_linear(f, leaf, gout):
    leaf = leaf.clone().requires_grad_(True)
    return torch.autograd.grad(f(leaf), leaf, gout)[0]


def backward_bounds(p: Problem):
    """Reference gradients (float64, act included), the rounded forward output to hand the kernels, and the
    per-element bounds of the module docstring: {name: (want, bound)}."""
    u_t, u_op = UNIT[p.dtype], OP_UNIT[p.dtype]
    leaves = [t.clone().requires_grad_(True) if t is not None else None for t in (p.x, p.w, p.b, p.s, p.d)]
    pre = p.pre(*leaves)
    y = p.ref(*leaves)
    need = {i: t for i, t in enumerate(leaves) if t is not None}
    want = dict(zip(need, torch.autograd.grad(y, list(need.values()), p.gy)))
    pre = pre.detach()
    gpre = p.gy * torch.where(pre > 0, GAIN, GAIN * SLOPE) if p.act else p.gy
    r_act = u_t + 2 * U32 if p.act else 0.0
    r_g = u_op + 16 * U32
    r_w = 0.0 if p.dtype == torch.bfloat16 else u_op
    absd, abss, absg = abs_or_none(p.d), abs_or_none(p.s), gpre.abs()
    out = {}
    # input gradient gx' (w.r.t. x * s), then gx = gx' s
    D_gx = grad_linear(lambda xl: p.pre(xl, p.w.abs(), None, None, absd), p.x, absg)
    rel = (1 + r_act) * (1 + r_w) * (1 + r_g) * (1 + (k_gx(p) + 6) * U32) - 1
    s = abss.view(*abss.shape, 1, 1) if abss is not None else 1.0
    e = s * (rel + U32) * D_gx
    out["x"] = (want[0], e + u_t * (want[0].abs() + e))
    if p.s is not None:
        ax = p.x.abs()
        n = p.x.shape[2] * p.x.shape[3]
        e = (ax * rel * D_gx).sum((2, 3)) + (n + 2) * U32 * (ax * (1 + rel) * D_gx).sum((2, 3))
        out["style"] = (want[3], e + u_t * (want[3].abs() + e))
    # weight gradient: both operands rounded to the fragment format, B x T products (+ split reduction)
    D_gw = grad_linear(lambda wl: p.pre(p.x.abs(), wl, None, abss, absd), p.w, absg)
    n_red = p.x.shape[0] * (p.x.shape[3] if p.kind == "up" else p.t_out)
    rel = (1 + r_act) * (1 + r_g) ** 2 * (1 + (n_red + 38) * U32) - 1
    e = rel * D_gw
    out["weight"] = (want[1], e + u_t * (want[1].abs() + e))
    if p.d is not None:  # scale gradient (SIMT), from the stored output
        r_y = 2 * u_t + 2 * U32 if p.act else u_t
        zb = (pre - (p.b.view(1, -1, 1, 1) if p.b is not None else 0.0)).abs()
        t_out = pre.shape[3]
        e = (absg * ((1 + r_act) * (1 + (t_out + 4) * U32) * (zb + r_y * pre.abs()) - zb)).sum(3) / absd
        out["scale"] = (want[4], e + u_t * (want[4].abs() + e))
    return out, y.detach().to(p.dtype)


def check_backward(p: Problem, gx_mma=True, gw_mma=True) -> dict:
    """The backward with the switch on, under both schedules (bitwise equal, finite), against float64 within the
    bounds; the tensor-core kernels must be the ones that ran.  Returns the worst error / bound ratio per gradient."""
    bounds, y = backward_bounds(p)
    counts = EMU.launch_counts()
    n0 = {k: counts.get(k, 0) for k in (gx_kernel(p), gw_kernel(p))}
    with mma_on():
        got = schedules(lambda: p.backward(y))
    counts = EMU.launch_counts()
    assert counts.get(gx_kernel(p), 0) == n0[gx_kernel(p)] + (2 if gx_mma else 0), "input gradient: wrong kernel"
    assert counts.get(gw_kernel(p), 0) == n0[gw_kernel(p)] + (2 if gw_mma else 0), "weight gradient: wrong kernel"
    ratios = {}
    for i, name in enumerate(("x", "weight", "bias", "style", "scale")):
        if name not in bounds:
            continue
        want, tol = bounds[name]
        g = got[i]
        assert g.dtype == p.dtype and g.shape == want.shape, name
        err = (g.double() - want).abs()
        ratio = torch.where(err == 0, 0.0, err / tol).max().item()
        worst = (err - tol).flatten().argmax().item()
        assert ratio <= 1.0, (f"{p.kind} mma grad {name}: max error / bound {ratio:.3g} (error "
                              f"{err.flatten()[worst].item():.3g}, bound {tol.flatten()[worst].item():.3g})")
        ratios[name] = ratio
    return ratios


# (kind, B, cin, cout, T, U, padding, unread): M = Cin (input gradient) and Cout / Cin (weight gradient) off the
# 32-row tile, weight columns per row off the 64-column tile, B x T off the 16 / 8 stage depth; stride 2; up's fine
# entities that nobody reads (zero input gradient columns of down, no weight columns of up)
SIZES = {
    "conv": ("conv", 2, 5, 20, 21, 3, "reflect", False),
    "down": ("down", 2, 6, 9, 34, 3, "zeros", True),
    "up": ("up", 2, 7, 5, 13, 5, "reflect", True),
}
# (modulation, bias, act)
OPTIONS = {"plain": ("none", False, False), "style_demod_act": ("style_demod", True, True),
           "style_bias": ("style", True, False), "demod_act": ("demod", False, True)}


@pytest.mark.parametrize("options", sorted(OPTIONS))
@pytest.mark.parametrize("size", sorted(SIZES))
def test_mma_backward_bf16_matches_float64(size, options):
    kind, B, cin, cout, T, U, padding, unread = SIZES[size]
    mod, bias, act = OPTIONS[options]
    p = Problem(kind, mod, padding, U=U, bias=bias, dtype=torch.bfloat16, seed=len(size) * 7 + len(options), B=B,
                cin=cin, cout=cout, T=T, act=act, unread=unread)
    check_backward(p)


@pytest.mark.parametrize("size", sorted(SIZES))
def test_mma_backward_tf32_matches_float64(size):
    kind, B, cin, cout, T, U, padding, unread = SIZES[size]
    for k, options in enumerate(("style_demod_act", "plain")):
        mod, bias, act = OPTIONS[options]
        p = Problem(kind, mod, padding, U=U, bias=bias, dtype=torch.float32, seed=40 + k, B=B, cin=cin, cout=cout,
                    T=T, act=act, unread=unread)
        with tf32(True):
            check_backward(p)


def test_mma_weight_gradient_split_reduction_and_random_skeleton():
    """Many SMs: the weight gradient's batch x time range is split (fp32 partials, summed in split order by
    split_reduce_kernel); a larger random skeleton, two 32-row tiles in both GEMMs, several weight-column tiles per
    row."""
    p = Problem("conv", "style_demod", "reflect", U=3, bias=True, dtype=torch.bfloat16, seed=5, B=3, cin=33, cout=37,
                T=60, n=6, act=True)
    with sm_count(1000):
        plan = EMU.wgrad_plan(3 * 60, p.offsets.numel() - 1, p.index.numel(), 33 * 3, 37, 1000)
        before = sum(n for k, n in EMU.launch_counts().items() if k.startswith("split_reduce_kernel<c10::BFloat16"))
        check_backward(p)
        after = sum(n for k, n in EMU.launch_counts().items() if k.startswith("split_reduce_kernel<c10::BFloat16"))
    assert plan["splits"] > 1 and after == before + 2


@pytest.mark.parametrize("dtype", (torch.bfloat16, torch.float32), ids=str)
@pytest.mark.parametrize("kind", ("down", "up"))
def test_mma_partial_backwards_read_only_what_they_need(kind, dtype):
    """The two partial backwards modi_ext.skeletal.gradfix asks for: the input gradient with no x values and the
    weight gradient with no weight values (NaN here, so a read of them shows), each on its tensor-core kernel and
    within its bound."""
    p = Problem(kind, "none", "reflect", U=3, bias=False, dtype=dtype, seed=21, B=2, cin=6, cout=9, T=30)
    bounds, y = backward_bounds(p)
    nan_x = torch.full_like(p.cast(p.x), float("nan"))
    nan_w = torch.full_like(p.cast(p.w), float("nan"))
    n0 = mma_launches()
    with mma_on(), tf32(True):
        gx = schedules(lambda: p.backward(y, (True, False, False, False), x=nan_x))[0]
        gw = schedules(lambda: p.backward(y, (False, True, False, False), w=nan_w))[1]
    assert mma_launches() == n0 + 4
    for got, name in ((gx, "x"), (gw, "weight")):
        want, tol = bounds[name]
        err = (got.double() - want).abs()
        assert (err <= tol).all(), f"{kind} partial grad {name}: max error / bound {(err / tol).max().item():.3g}"


@pytest.mark.parametrize("kind, cin", (("conv", 5), ("down", 5), ("up", 5), ("conv", 40)))
def test_tf32_forward_matches_float64(kind, cin):
    """The float32 forward on TF32 fragments: both operands rounded to TF32 (the weight too), K products summed in
    fp32: error <= ((1 + u_op)(1 + u_op + 16 u)(1 + (K + 6) u) - 1) D + 6 u |b|, times the activation's gain, + u_T.
    cin 40: K > 256, two resident weight panels of the TF32 kernel."""
    p = Problem(kind, "style_demod", "reflect", U=3, bias=True, dtype=torch.float32, seed=61, B=2, cin=cin, cout=20,
                T=23, act=True, unread=True, n=5 if cin > 32 else None)
    assert cin < 32 or k_max(p) > 256
    name = f"mma_gemm_kernel<float, {'true, true' if kind == 'up' else 'false, false'}>"
    n0 = EMU.launch_counts().get(name, 0)
    with tf32(True), mma_on():
        y = schedules(lambda: (p.forward(),))[0]
    assert EMU.launch_counts().get(name, 0) == n0 + 2
    D = p.pre(p.x.abs(), p.w.abs(), None, p.s.abs(), p.d.abs())
    rel = (1 + U_TF32) * (1 + U_TF32 + 16 * U32) * (1 + (k_max(p) + 6) * U32) - 1
    e = GAIN * (rel * D + 6 * U32 * p.b.abs().view(1, -1, 1, 1))
    want = p.ref(p.x, p.w, p.b, p.s, p.d)
    err = (y.double() - want).abs()
    tol = e + U32 * (want.abs() + e)
    assert (err <= tol).all(), f"tf32 forward: max error / bound {(err / tol).max().item():.3g}"
    # and the bound is not vacuous: TF32 is visibly coarser than the float32 SIMT kernels
    y_simt = p.forward()
    assert (y_simt.double() - want).abs().max() < err.max()


def test_tf32_follows_torch_switch_and_the_mma_switch():
    """float32 takes the tensor cores only with MODI_EXT_CUDA_MMA=1 and torch.backends.cudnn.allow_tf32; float64 and
    float16 never; bf16 regardless of the TF32 switch."""
    n0 = mma_launches()
    p32 = Problem("conv", "style", "zeros", dtype=torch.float32, seed=3)
    with tf32(False), mma_on():
        y = p32.forward()
        p32.backward(y)
        Problem("up", "style", "zeros", dtype=torch.float16, seed=3).forward()
        Problem("down", "style", "zeros", dtype=torch.float64, seed=3).forward()
    with tf32(True):
        p32.backward(p32.forward())
    assert mma_launches() == n0
    with tf32(True), mma_on():
        p32.backward(p32.forward())
    assert mma_launches() == n0 + 3  # forward, input gradient, weight gradient
    with tf32(False), mma_on():
        pb = Problem("conv", "style", "zeros", dtype=torch.bfloat16, seed=3)
        pb.backward(pb.forward())
    assert mma_launches() == n0 + 6


def test_tf32_rounds_to_nearest_ties_away():
    """The TF32 rounding of the operands (cvt.rna.tf32.f32: round to nearest on the 13 dropped bits, ties away from
    zero), seen through the float32 forward with one product per output and a unit weight: inputs on the TF32 grid
    come out exact, inputs halfway between two TF32 values come out rounded away from zero, for either sign."""
    p = Problem("conv", "none", "zeros", U=1, bias=False, dtype=torch.float32, seed=8, B=1, cin=1, cout=1, T=4,
                single=True)
    x = torch.tensor([[[[1.0, 1.0 + 2.0 ** -10, 1.0 + 2.0 ** -11, 1.0 + 3 * 2.0 ** -11]]]])
    w = torch.ones(1, 1, 1, 1)
    with tf32(True), mma_on():
        y = torch.ops.modi_ext_emu.skeletal_conv(x, w, None, p.index, p.offsets, None, None, "zeros", False)
    # 1 + 2^-11 is a tie between 1 and 1 + 2^-10: away from zero; 1 + 3 2^-11 ties between 1 + 2^-10 and 1 + 2^-9
    assert y.flatten().tolist() == [1.0, 1.0 + 2.0 ** -10, 1.0 + 2.0 ** -10, 1.0 + 2.0 ** -9]
    xn = -x
    with tf32(True), mma_on():
        yn = torch.ops.modi_ext_emu.skeletal_conv(xn, w, None, p.index, p.offsets, None, None, "zeros", False)
    assert yn.flatten().tolist() == [-1.0, -1.0 - 2.0 ** -10, -1.0 - 2.0 ** -10, -1.0 - 2.0 ** -9]


def test_emulator_refuses_unrounded_tf32_operands():
    """A kernel that loads float32 into TF32 fragments without __float_to_tf32 computes with bits a tensor core does
    not read: the emulator's mma_sync names the rule instead."""
    with pytest.raises(RuntimeError, match="tf32 operand was not rounded with __float_to_tf32"):
        torch.ops.modi_ext_emu.emu_selftest("tf32_unrounded", 32)


@pytest.mark.parametrize("kind", ("conv", "up"))
@pytest.mark.parametrize("defect", ("mma_wgrad_fragment_offset", "mma_wgrad_tile_edge"))
def test_mma_wgrad_planted_faults_are_caught(defect, kind):
    """mma_wgrad_fragment_offset: each warp reads its two B fragments at each other's column offset (gradients land in
    the wrong weight columns); mma_wgrad_tile_edge: every split's batch x time range ends one column short (one product
    of every gradient element dropped).  Both stay finite: only the bound against float64 sees them, while the clean
    kernel passes the same case, and the input gradient (another kernel) stays within its bound."""
    p = Problem(kind, "style", "zeros", U=3, bias=True, dtype=torch.bfloat16, seed=12, B=2, cin=6, cout=20, T=25)
    check_backward(p)
    with injected(defect):
        with mma_on():
            got = p.backward(p.cast(p.ref(p.x, p.w, p.b, p.s, p.d)))
        assert all(bool(torch.isfinite(t.double()).all()) for t in got if t.numel()), "the fault must stay finite"
        with pytest.raises(AssertionError, match="mma grad weight: max error / bound"):
            check_backward(p)
    check_backward(p)


@pytest.mark.parametrize("defect", ("mma_fragment_offset", "mma_tile_edge"))
def test_mma_input_gradient_planted_faults_are_caught(defect):
    """The forward's planted faults live in mma_gemm_kernel, which the input gradient shares: they fail it too."""
    p = Problem("down", "none", "zeros", U=3, bias=False, dtype=torch.bfloat16, seed=13, B=2, cin=20, cout=6, T=50)
    check_backward(p)
    with injected(defect), pytest.raises(AssertionError, match="mma grad x: max error / bound"):
        check_backward(p)


def test_tf32_planted_faults_are_caught():
    """The planted faults under TF32 fragments (16 x 16 x 8): the forward's and the weight gradient's."""
    p = Problem("conv", "style", "zeros", U=3, bias=True, dtype=torch.float32, seed=14, B=2, cin=3, cout=20, T=25)
    with tf32(True):
        check_backward(p)
        for defect, what in (("mma_wgrad_tile_edge", "weight"), ("mma_tile_edge", "x")):
            with injected(defect), pytest.raises(AssertionError, match=f"mma grad {what}: max error / bound"):
                check_backward(p)


def test_selfcheck_passes_with_the_mma_backward():
    """The first-use self-check with the switch on: bf16 forwards and backwards on the tensor-core kernels within the
    payload's bf16 tolerance; float32 with TF32 on within TF32_TOL (the bf16 tolerance scaled by u_tf32 / u_bf16),
    which it needs: its errors exceed the float32 tolerance the SIMT kernels meet with TF32 off."""
    from modi_ext.runtime import selfcheck

    n0 = mma_launches()
    with mma_on():
        res = selfcheck.run("cpu", torch.bfloat16, lib="modi_ext_emu")
    assert res["ok"], res["errors"]
    assert mma_launches() > n0
    assert any(k.startswith("mma_wgrad_kernel<c10::BFloat16") for k in EMU.launch_counts())
    n0 = mma_launches()
    with mma_on(), tf32(True):
        assert selfcheck.tolerance("cpu", torch.float32, "modi_ext_emu") == selfcheck.TF32_TOL
        assert selfcheck.tolerance("cpu", torch.float32) == selfcheck.TOL[torch.float32]  # the CPU kernels
        res = selfcheck.run("cpu", torch.float32, lib="modi_ext_emu")
    assert res["ok"], res["errors"]
    assert mma_launches() > n0 and max(res["max_error"].values()) > selfcheck.TOL[torch.float32]
    with mma_on(), tf32(False):
        assert selfcheck.tolerance("cpu", torch.float32, "modi_ext_emu") == selfcheck.TOL[torch.float32]
