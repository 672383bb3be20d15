"""Skeletal ops: the dense reference against naive loops, the C++ kernels against the reference
(forward fp32, gradients fp64, gradcheck, opcheck) on random trees and the real Bandai hierarchy, and errors."""
from __future__ import annotations

import random

import pytest
import torch

from modi_ext import HAS_EXT
from modi_ext.demod.reference import demod_coefficients
from modi_ext.skeletal import ops
from modi_ext.skeletal import reference as R
from modi_ext.csr import csr_from_lists
from skeletal_cases import KINDS, call, make_case

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
def check_fp32_against_reference(kind: str, args, kw) -> None:
    """float32 forward and every gradient (input, weight, bias, style) of the ext op against the reference, judged
    on an O(1) scale: demodulation makes the style gradient a near-cancelling sum."""
    leaves = [args[0], args[1], args[2]] + ([kw["style"]] if kw["style"] is not None else [])
    for t in leaves:
        t.requires_grad_(True)
    ye, yr = call(kind, ops, args, kw), call(kind, R, args, kw)
    torch.testing.assert_close(ye, yr, rtol=1e-4, atol=1e-4 * float(yr.abs().max()) + 1e-6)
    g = torch.randn_like(yr)
    for a, b in zip(torch.autograd.grad(ye, leaves, g), torch.autograd.grad(yr, leaves, g)):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4 * max(1.0, float(b.abs().max())))


# ----------------------------------------------------------------------------------------------- naive oracle
def naive_conv(x, dense, bias, style, demod, padding, stride):
    """Loops straight from ARCHITECTURE.md's formula; dense (Cout, Cin, Eo, Ei, U)."""
    B, Ci, Ei, T = x.shape
    Co, _, Eo, _, U = dense.shape
    h = U // 2
    To = T if stride == 1 else T // 2
    s = style if style is not None else torch.ones(B, Ci, dtype=x.dtype)
    y = torch.zeros(B, Co, Eo, To, dtype=x.dtype)
    for b in range(B):
        for o in range(Co):
            for j in range(Eo):
                d = 1.0
                if demod:
                    d = float(((dense[o, :, j] * s[b].view(-1, 1, 1)) ** 2).sum() + 1e-8) ** -0.5
                for t in range(To):
                    acc = 0.0
                    for u in range(U):
                        q = stride * t + u - h
                        if not 0 <= q < T:
                            if padding == "zeros":
                                continue
                            q = -q if q < 0 else 2 * (T - 1) - q
                        acc += float((dense[o, :, j, :, u] * s[b].view(-1, 1) * x[b, :, :, q]).sum())
                    y[b, o, j, t] = acc * d + (bias[o] if bias is not None else 0.0)
    return y


@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("stride", [1, 2])
def test_reference_matches_naive_loops(padding, stride):
    rng = random.Random(7 + stride)
    nb = [[0, 1], [0, 1, 2], [1, 2, 3], [2, 3]] if stride == 1 else [[0, 1], [2, 3], [1]]
    topo = csr_from_lists(nb, n_in=4)
    x = torch.randn(2, 3, 4, 9, dtype=torch.float64)
    w = torch.randn(5, topo.nnz, 3, 3, dtype=torch.float64)
    b, s = torch.randn(5, dtype=torch.float64), torch.randn(2, 3, dtype=torch.float64)
    dense = R.to_dense(w, topo.index, topo.offsets, 4)
    for style, demod in [(None, False), (s, True), (s, False), (None, True)]:
        fn = R.skeletal_conv if stride == 1 else R.skeletal_down
        got = fn(x, w, b, topo.index, topo.offsets, style, demod, padding)
        want = naive_conv(x, dense, b, style, demod, padding, stride)
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    del rng


@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("U", [1, 3, 5])
def test_reference_up_is_blurred_adjoint_of_down(padding, U):
    """skeletal_up = blur([1,3,3,1]/4, pad 2|1) of the vector-Jacobian product of skeletal_down."""
    topo = csr_from_lists([[0, 2], [1, 3], [4]], require_cover=True)
    w = torch.randn(4, topo.nnz, 3, U, dtype=torch.float64)
    x = torch.randn(2, 3, 5, 10, dtype=torch.float64, requires_grad=True)
    g = torch.randn(2, 4, 3, 5, dtype=torch.float64)
    (vjp,) = torch.autograd.grad(R.skeletal_down(x, w, None, topo.index, topo.offsets, None, False, padding), x, g)
    up = R.skeletal_up(g, w, None, topo.index, topo.offsets, 5, None, False, padding)
    v = torch.nn.functional.pad(vjp, (2, 1))
    blurred = (v[..., :-3] + 3 * v[..., 1:-2] + 3 * v[..., 2:-1] + v[..., 3:]) / 4
    torch.testing.assert_close(up, blurred, rtol=1e-12, atol=1e-12)


def test_dense_roundtrip_and_mask():
    nb = [[0, 2], [1], [0, 1, 2]]
    topo = csr_from_lists(nb)
    w = torch.randn(4, topo.nnz, 3, 5)
    dense = R.to_dense(w, topo.index, topo.offsets, 3)
    assert dense.shape == (4, 3, 3, 3, 5)
    for j in range(3):
        for n in range(3):
            if n not in nb[j]:
                assert dense[:, :, j, n].abs().max() == 0
    assert torch.equal(dense[:, :, 2, 1], w[:, 4])  # pair 4 = (entity 2, neighbor 1)
    assert torch.equal(R.from_dense(dense, topo.index, topo.offsets), w)


def test_demod_scale_matches_per_sample_weights():
    rng = random.Random(3)
    for kind in ("conv", "up"):
        args, kw = make_case(kind, rng, style=True, demod=True)
        x, w, _, index, offsets = args[:5]
        if kind == "conv":
            dense = R.to_dense(w, index, offsets, x.shape[2])
            n_out = x.shape[2]
        else:
            n_out = args[5]
            dense = R.to_dense(w, index, offsets, n_out).permute(1, 0, 3, 2, 4)  # (Co, Ci, Ef, Ec, U)
        want = demod_coefficients(dense, kw["style"])
        got = ops.demod_scale(w, index, offsets, kw["style"], kind == "up", n_out, x.shape[0])
        torch.testing.assert_close(got, want, rtol=1e-10, atol=0)


@pytest.mark.parametrize("taps", [1, 3, 5])
def test_square_segment_sum_matches_autograd_of_the_plain_form(taps):
    """The demodulation's weight term (a Function with a hand-written backward) against ``w.pow(2).sum(-1)``
    segment-summed by autograd: values, gradients, and second-order gradients, with an empty segment included."""
    from modi_ext.demod.dense import segment_sum, square_segment_sum

    g = torch.Generator().manual_seed(taps)
    n_seg, nnz = 6, 11
    segment = torch.randint(0, n_seg - 1, (nnz,), generator=g)  # segment n_seg - 1 stays empty
    w = torch.randn(3, nnz, 4, taps, generator=g, dtype=torch.float64, requires_grad=True)
    plain = lambda w: segment_sum(w.pow(2).sum(-1), segment, n_seg)  # noqa: E731
    fused = lambda w: square_segment_sum(w, segment, n_seg)  # noqa: E731
    torch.testing.assert_close(fused(w), plain(w), rtol=1e-12, atol=0)
    assert fused(w)[:, -1].abs().max() == 0
    v = torch.randn(3, n_seg, 4, generator=g, dtype=torch.float64)
    (gf,) = torch.autograd.grad((fused(w) * v).sum(), w, create_graph=True)
    (gp,) = torch.autograd.grad((plain(w) * v).sum(), w, create_graph=True)
    torch.testing.assert_close(gf, gp, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.autograd.grad(gf.pow(3).sum(), w)[0], torch.autograd.grad(gp.pow(3).sum(), w)[0],
                               rtol=1e-12, atol=0)
    assert torch.autograd.gradcheck(fused, (w,))
    assert torch.autograd.gradgradcheck(fused, (w,))


# ----------------------------------------------------------------------------------------------- ext vs reference
@needs_ext
@pytest.mark.parametrize("kind", KINDS)
def test_forward_fp32_matches_reference_random_trees(kind):
    rng = random.Random({"conv": 1, "down": 2, "up": 3}[kind])
    for _ in range(40):
        args, kw = make_case(kind, rng, dtype=torch.float32, B=rng.randint(1, 3), cin=rng.randint(1, 6),
                             cout=rng.randint(1, 6))
        got = call(kind, ops, args, kw)
        want = call(kind, R, args, kw)
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.abs().max()) + 1e-6)


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
def test_gradients_fp64_match_reference_random_trees(kind):
    rng = random.Random({"conv": 11, "down": 12, "up": 13}[kind])
    for _ in range(25):
        args, kw = make_case(kind, rng)
        leaves = [args[0], args[1], args[2]] + ([kw["style"]] if kw["style"] is not None else [])
        for t in leaves:
            t.requires_grad_(True)
        ye, yr = call(kind, ops, args, kw), call(kind, R, args, kw)
        g = torch.randn_like(yr)
        ge = torch.autograd.grad(ye, leaves, g)
        gr = torch.autograd.grad(yr, leaves, g)
        for a, b in zip(ge, gr):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()))


@needs_ext
@pytest.mark.parametrize("threads", [1, 3, 4])
@pytest.mark.parametrize("kind", KINDS)
def test_gradients_independent_of_thread_count(kind, threads):
    # The kernels change strategy with the thread count (direct vs thread-local weight gradients, cost-balanced
    # entity order); every strategy must give the reference's gradients.
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rng = random.Random(100 + threads)
        for _ in range(8):
            args, kw = make_case(kind, rng, B=rng.randint(1, 4))
            leaves = [args[0], args[1], args[2]] + ([kw["style"]] if kw["style"] is not None else [])
            for t in leaves:
                t.requires_grad_(True)
            ye, yr = call(kind, ops, args, kw), call(kind, R, args, kw)
            g = torch.randn_like(yr)
            for a, b in zip(torch.autograd.grad(ye, leaves, g), torch.autograd.grad(yr, leaves, g)):
                torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9 * float(b.abs().max()))
    finally:
        torch.set_num_threads(old)


@needs_ext
@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("kind", KINDS)
def test_narrow_layers_fp32_match_reference(kind, threads):
    """GANimator's shapes (1-9 channels, kernel 5, reflect, batch 1-2, enough frames for the AVX2 kernels): the
    narrow-layer weight gradient and the partial-panel rows, with direct and thread-local accumulation."""
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rng = random.Random(200 + threads)
        for _ in range(6):
            args, kw = make_case(kind, rng, dtype=torch.float32, n_joints=rng.randint(2, 30), distance=2, U=5,
                                 B=rng.randint(1, 2), cin=rng.randint(2, 9), cout=rng.randint(1, 9),
                                 T=rng.randint(17, 48), padding="reflect")
            # (cin >= 2: with one input channel, demodulation makes the output independent of the style, and its
            # float32 style gradient is pure cancellation noise around 0)
            check_fp32_against_reference(kind, args, kw)
    finally:
        torch.set_num_threads(old)


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
def test_batch_tiles_fp32_match_reference(kind):
    """Batches of 13-16 at 30-66 frames: the fast path splits the batch into tiles whose sizes follow the kernels'
    column step (MoDi's finest level at batch 16: tiles of 8 forward, 7 + 7 + 2 for the input gradient), so
    uneven last tiles and products without a narrow last column tile are both exercised."""
    rng = random.Random({"conv": 41, "down": 42, "up": 43}[kind])
    for B, T in ((16, 64), (13, 62), (16, 30)):
        args, kw = make_case(kind, rng, dtype=torch.float32, n_joints=rng.randint(6, 14), distance=1, U=3, B=B,
                             cin=12, cout=12, T=T, padding="zeros")
        check_fp32_against_reference(kind, args, kw)


@needs_ext
@pytest.mark.parametrize("cpu_kernel", ["auto", "avx2"])
@pytest.mark.parametrize("kind", KINDS)
def test_coarse_levels_fp32_match_reference(monkeypatch, kind, cpu_kernel):
    """Every frame count from 1 to 15 (MoDi's coarse levels, below the fast path's usual threshold), where the up
    forward runs the indirect kernels at any size and the conv backward from 8 frames: the values and gradients
    against the reference, with both paddings (reflect where the frames allow it), on random skeletons."""
    monkeypatch.setenv("MODI_EXT_CPU_KERNEL", cpu_kernel)
    rng = random.Random({"conv": 51, "down": 52, "up": 53}[kind])
    for T in range(1, 16):
        U = rng.choice([1, 3, 5])
        frames = 2 * T if kind == "up" else T  # the frames reflect padding needs more of than U // 2
        padding = rng.choice(["zeros", "reflect"]) if U // 2 < frames else "zeros"
        if kind == "down" and T < 2:
            continue
        args, kw = make_case(kind, rng, dtype=torch.float32, B=rng.randint(1, 5), cin=rng.randint(1, 12),
                             cout=rng.randint(1, 12), T=T, U=U, padding=padding)
        check_fp32_against_reference(kind, args, kw)


@needs_ext
@pytest.mark.parametrize("cpu_kernel", ["auto", "blas"])
@pytest.mark.parametrize("kind", KINDS)
def test_gradients_fp32_match_reference(monkeypatch, kind, cpu_kernel):
    """float32 runs the AVX2 indirect-GEMM kernels (or BLAS when forced); both must agree with the reference."""
    monkeypatch.setenv("MODI_EXT_CPU_KERNEL", cpu_kernel)
    rng = random.Random({"conv": 31, "down": 32, "up": 33}[kind])
    for _ in range(12):
        args, kw = make_case(kind, rng, dtype=torch.float32, B=rng.randint(1, 5), cin=rng.randint(1, 9),
                             cout=rng.randint(1, 9), T=rng.randint(3, 40))
        check_fp32_against_reference(kind, args, kw)


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("style,demod,padding", [(False, False, "zeros"), (True, True, "reflect"),
                                                 (True, False, "zeros"), (False, True, "reflect")])
def test_gradcheck_fp64(kind, style, demod, padding):
    rng = random.Random(hash((kind, style, demod, padding)) % 1000)
    args, kw = make_case(kind, rng, n_joints=4, distance=1, U=3, B=2, cin=2, cout=2, T=5, style=style,
                         demod=demod, padding=padding)
    x, w, b = (t.requires_grad_(True) for t in args[:3])
    s = kw["style"].requires_grad_(True) if style else None
    rest = args[3:]

    def fn(x, w, b, *maybe_s):
        return call(kind, ops, (x, w, b) + rest, dict(kw, style=maybe_s[0] if maybe_s else None))

    inputs = (x, w, b) + ((s,) if style else ())
    # full Jacobians for the plain op, random projections (fast mode) for the modulated variants
    fast = style or demod
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=fast)


@needs_ext
def test_gradgradcheck_modulated_conv():
    """Second order (R1 / path-length regularisation) on the kernels (modi_ext.skeletal.gradfix; more in
    test_double_backward)."""
    rng = random.Random(5)
    args, kw = make_case("conv", rng, n_joints=3, distance=1, U=3, B=1, cin=2, cout=1, T=4, style=True,
                         demod=True)
    x, w = (t.requires_grad_(True) for t in args[:2])
    s = kw["style"].requires_grad_(True)

    def fn(x, w, s):
        return call("conv", ops, (x, w, None) + args[3:], dict(kw, style=s))

    assert torch.autograd.gradgradcheck(fn, (x, w, s), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
def test_opcheck(kind):
    rng = random.Random(21)
    for style, demod in [(False, False), (True, True)]:
        args, kw = make_case(kind, rng, dtype=torch.float32, n_joints=4, U=3, B=2, cin=2, cout=3, T=6,
                             style=style, demod=demod, padding="zeros")
        x, w, b, index, offsets = args[:5]
        scale = None
        if demod:
            n_out = args[5] if kind == "up" else offsets.numel() - 1
            scale = ops.demod_scale(w, index, offsets, kw["style"], kind == "up", n_out, x.shape[0])
        x.requires_grad_(True)
        w.requires_grad_(True)
        b.requires_grad_(True)
        sty = kw["style"].requires_grad_(True) if style else None
        if scale is not None:
            scale = scale.detach().requires_grad_(True)
        op = getattr(torch.ops.modi_ext, f"skeletal_{kind}").default
        op_args = (x, w, b, index, offsets) + (args[5:] if kind == "up" else ()) + (sty, scale, "zeros")
        torch.library.opcheck(op, op_args)


@needs_ext
def test_real_bandai_hierarchy(shared_data):
    topology = pytest.importorskip("modi.core.skeleton_graph")
    bvh = pytest.importorskip("modi.io.bvh")
    files = sorted((shared_data / "bvh").rglob("*.bvh"))
    if not files:
        pytest.skip("no BVH files under shared data")
    bandai = [f for f in files if "bandai" in str(f).lower()] or files
    skeleton = bvh.load(bandai[0]).skeleton()
    for distance in (1, 2):
        h = topology.build_hierarchy(skeleton, neighbor_distance=distance)
        for lv, level in enumerate(h.levels):
            nb = csr_from_lists(level.neighbors)
            x = torch.randn(2, 4, level.n_entities, 8, dtype=torch.float64, requires_grad=True)
            w = torch.randn(3, nb.nnz, 4, 3, dtype=torch.float64, requires_grad=True)
            s = torch.randn(2, 4, dtype=torch.float64)
            ye = ops.skeletal_conv(x, w, None, nb.index, nb.offsets, style=s, demodulate=True)
            yr = R.skeletal_conv(x, w, None, nb.index, nb.offsets, s, True, "zeros")
            torch.testing.assert_close(ye, yr, rtol=1e-10, atol=1e-10)
            g = torch.randn_like(yr)
            for a, b in zip(torch.autograd.grad(ye, (x, w), g), torch.autograd.grad(yr, (x, w), g)):
                torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
            if lv + 1 < len(h.levels):
                pool = csr_from_lists(h.pooling[lv], n_in=level.n_entities, require_cover=True)
                wd = torch.randn(3, pool.nnz, 4, 3, dtype=torch.float64)
                torch.testing.assert_close(
                    ops.skeletal_down(x, wd, None, pool.index, pool.offsets),
                    R.skeletal_down(x, wd, None, pool.index, pool.offsets, None, False, "zeros"))
                xc = torch.randn(2, 4, pool.n_out, 8, dtype=torch.float64)
                wu = torch.randn(4, pool.nnz, 3, 3, dtype=torch.float64)
                torch.testing.assert_close(
                    ops.skeletal_up(xc, wu, None, pool.index, pool.offsets, level.n_entities),
                    R.skeletal_up(xc, wu, None, pool.index, pool.offsets, level.n_entities, None, False, "zeros"))


def test_impl_switch_ref_matches(monkeypatch):
    rng = random.Random(9)
    args, kw = make_case("conv", rng, dtype=torch.float64)
    monkeypatch.setenv("MODI_EXT_IMPL", "ref")
    y_ref = call("conv", ops, args, kw)
    torch.testing.assert_close(y_ref, call("conv", R, args, kw), rtol=0, atol=0)
    monkeypatch.setenv("MODI_EXT_IMPL", "bogus")
    with pytest.raises(ValueError, match="MODI_EXT_IMPL"):
        call("conv", ops, args, kw)


# ----------------------------------------------------------------------------------------------- bad input
def _good(kind="conv"):
    args, kw = make_case(kind, random.Random(4), dtype=torch.float32, n_joints=5, U=3, T=8, style=True,
                         demod=True, padding="zeros")
    return list(args), kw


@pytest.mark.parametrize("impl", ["ref", "ext"])
@pytest.mark.parametrize("mutate,exc,match", [
    (lambda a, k: a.__setitem__(0, a[0][0]), ValueError, "x must be 4-D"),
    (lambda a, k: a.__setitem__(0, a[0].double()), TypeError, "weight dtype"),
    (lambda a, k: a.__setitem__(0, a[0].int()), TypeError, "x must be float"),
    (lambda a, k: a.__setitem__(0, a[0].transpose(2, 3).contiguous().transpose(2, 3)), ValueError, "x must be contig"),
    (lambda a, k: a.__setitem__(0, a[0][:0]), ValueError, "empty batch"),
    (lambda a, k: a.__setitem__(0, a[0][..., :0]), ValueError, "zero frames"),
    (lambda a, k: a.__setitem__(0, a[0][:, :0].contiguous()), ValueError, "no channels"),
    (lambda a, k: a.__setitem__(0, a[0][:, :2].contiguous()), ValueError, "channels"),
    (lambda a, k: a.__setitem__(0, a[0][:, :, :3].contiguous()), ValueError, "entities"),
    (lambda a, k: a.__setitem__(1, a[1][..., :2].contiguous()), ValueError, "odd"),
    (lambda a, k: a.__setitem__(1, a[1][:, :-1].contiguous()), ValueError, "pairs"),
    (lambda a, k: a.__setitem__(2, a[2][:-1]), ValueError, "bias"),
    (lambda a, k: a.__setitem__(3, a[3].clone().fill_(99)), ValueError, "index"),
    (lambda a, k: a.__setitem__(3, a[3].int()), TypeError, "index must be int64"),
    (lambda a, k: a.__setitem__(4, torch.cat([a[4][:1], a[4][:1], a[4][1:-1]])), ValueError, "offsets"),
    (lambda a, k: k.__setitem__("style", k["style"][:, :1]), ValueError, "style"),
    (lambda a, k: k.__setitem__("padding_mode", "circular"), ValueError, "padding_mode"),
    (lambda a, k: a.__setitem__(0, a[0].to("meta")), ValueError, "weight is on"),
])
def test_bad_input_names_argument(monkeypatch, impl, mutate, exc, match):
    if impl == "ext" and not HAS_EXT:
        pytest.skip("extension not built")
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    args, kw = _good()
    mutate(args, kw)
    with pytest.raises(exc, match=match):
        ops.skeletal_conv(*args, **kw)


def test_entity_without_neighbors_is_rejected():
    with pytest.raises(ValueError, match=r"neighbors\[1\] is empty"):
        csr_from_lists([[0], [], [2]])
    with pytest.raises(ValueError, match="out of range"):
        csr_from_lists([[0, 3], [1]], n_in=2)
    with pytest.raises(ValueError, match="twice"):
        csr_from_lists([[0, 0]])
    with pytest.raises(ValueError, match="does not cover"):
        csr_from_lists([[0], [2]], n_in=3, require_cover=True)


@pytest.mark.parametrize("kind", KINDS)
def test_reflect_needs_enough_frames(kind):
    args, kw = make_case(kind, random.Random(2), dtype=torch.float32, n_joints=4, U=5, T=2, padding="reflect")
    if kind == "up":
        args = (args[0][..., :1].contiguous(),) + args[1:]
    with pytest.raises(ValueError, match="reflect padding"):
        call(kind, ops, args, kw)


@needs_ext
def test_raw_ops_reject_bad_input_with_runtime_error():
    """The C++ kernels check their own arguments (callers may bypass modi_ext.skeletal.ops)."""
    args, kw = _good()
    x, w, b, index, offsets = args
    op = torch.ops.modi_ext.skeletal_conv
    with pytest.raises(RuntimeError, match="index"):
        op(x, w, b, index.clone().fill_(-1), offsets, None, None, "zeros")
    bad_offsets = offsets.clone()
    bad_offsets[1] = 0  # entity 0 gets no neighbors
    with pytest.raises(RuntimeError, match="no neighbors"):
        op(x, w, b, index, bad_offsets, None, None, "zeros")
    with pytest.raises(RuntimeError, match="x must be contiguous"):
        op(x.transpose(2, 3).contiguous().transpose(2, 3), w, b, index, offsets, None, None, "zeros")
    with pytest.raises(RuntimeError, match="scale"):
        op(x, w, b, index, offsets, None, torch.ones(1, 1, 1), "zeros")
    with pytest.raises(RuntimeError, match="padding_mode"):
        op(x, w, b, index, offsets, None, None, "wrap")
    with pytest.raises(RuntimeError, match="empty batch"):
        op(x[:0], w, b, index, offsets, None, None, "zeros")
    with pytest.raises(RuntimeError, match="no channels"):
        op(x[:, :0].contiguous(), w, b, index, offsets, None, None, "zeros")
