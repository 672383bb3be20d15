"""The tensor-core (WMMA) bf16 forward of the skeletal ops (csrc/skeletal/mma_gemm.cuh), on the CPU emulator.

The backward and the TF32 forms: test_cuda_emulated_mma_backward.py.

The kernel is opt-in (``MODI_EXT_CUDA_MMA=1``) and takes bf16: operands are rounded to bf16 once in shared memory and
multiplied by ``nvcuda::wmma`` 16 x 16 x 16 fragments with fp32 accumulation.  The emulator gives WMMA a plain
implementation (csrc/emu/wmma_emu.h: exact bf16 products, fp32 sums, warp-collective and alignment checks), so what
runs here is the kernel's tiling and indexing: ragged M / K / N edges, the resident weight panels, a block walking
several column tiles, the up op's transposed operand (adjoint read, blur, entities nobody reads), and the SIMT kernels'
epilogue (demodulation, style, bias, bias activation).

Tolerance, per element, from the formats' unit roundoffs (u_bf16 = 2^-8, u_fp32 = 2^-24) and K, not tuned:
with D = |d| * sum_k |w_k| |x_k s_k| (the sum of the absolute products) the kernel's error before the output store
is at most (r_in + (K + 6) u_fp32) D + 6 u_fp32 |b| -- r_in the rounding of the gathered operand to bf16: u_bf16 +
u_fp32 for conv / down with a style (x * s; without one x is already bf16), u_bf16 + 16 u_fp32 for up (its adjoint
read and blur sum up to 12 terms in fp32 first); K + 6 fp32 roundings of the sum and the epilogue -- times the
activation's gain, plus u_bf16 of the stored value for the bf16 output.  K: the largest neighbour (up: reader) count
x Cin x U.
"""
from __future__ import annotations

import contextlib
import math
import os

import pytest
import torch

from test_cuda_emulated import EMU, Problem, emu, injected, schedules, sm_count  # noqa: F401  (emu: the fixture)

pytestmark = [pytest.mark.cuda_emulated, pytest.mark.usefixtures("one_torch_thread")]

MMA = {"conv": "mma_gemm_kernel<c10::BFloat16, false, false>", "down": "mma_gemm_kernel<c10::BFloat16, false, false>",
       "up": "mma_gemm_kernel<c10::BFloat16, true, true>"}
U_BF16 = torch.finfo(torch.bfloat16).eps / 2
U_FP32 = torch.finfo(torch.float32).eps / 2


@contextlib.contextmanager
def mma_on():
    before = os.environ.get("MODI_EXT_CUDA_MMA")
    os.environ["MODI_EXT_CUDA_MMA"] = "1"
    try:
        yield
    finally:
        if before is None:
            del os.environ["MODI_EXT_CUDA_MMA"]
        else:
            os.environ["MODI_EXT_CUDA_MMA"] = before


def mma_launches() -> int:
    return sum(n for k, n in EMU.launch_counts().items() if k.startswith(("mma_gemm_kernel", "mma_wgrad_kernel")))


def k_max(p: Problem) -> int:
    if p.kind == "up":  # readers of a fine entity
        deg = torch.bincount(p.index, minlength=p.n_out).max().item()
    else:
        deg = (p.offsets[1:] - p.offsets[:-1]).max().item()
    return deg * p.x.shape[1] * p.U


def bound(p: Problem) -> torch.Tensor:
    """The per-element error bound of the module docstring, in float64."""
    absw = p.w.abs()
    d = p.d.abs() if p.d is not None else None
    s = p.s.abs() if p.s is not None else None
    D = p.pre(p.x.abs(), absw, None, s, d)  # |d| * sum |w| |x s|, reflect / zero padding as the op reads it
    b = p.b.abs().view(1, -1, 1, 1) if p.b is not None else 0.0
    r_in = U_BF16 + 16 * U_FP32 if p.kind == "up" else (U_BF16 + U_FP32 if p.s is not None else 0.0)
    pre = (r_in + (k_max(p) + 6) * U_FP32) * D + 6 * U_FP32 * b
    gain = math.sqrt(2.0) if p.act else 1.0
    want = p.ref(p.x, p.w, p.b, p.s, p.d)
    return gain * pre + U_BF16 * (want.abs() + gain * pre)


def check_mma(p: Problem) -> float:
    """The MMA forward under both schedules (bitwise equal, finite) against the float64 reference within the
    bound, elementwise; returns the worst error / bound ratio.  The MMA kernel must be the one that ran."""
    assert p.dtype == torch.bfloat16
    n0 = EMU.launch_counts().get(MMA[p.kind], 0)
    with mma_on():
        y = schedules(lambda: (p.forward(),))[0]
    assert EMU.launch_counts().get(MMA[p.kind], 0) == n0 + 2, "the tensor-core kernel did not run"
    want = p.ref(p.x, p.w, p.b, p.s, p.d)
    assert y.dtype == torch.bfloat16 and y.shape == want.shape
    err = (y.double() - want).abs()
    tol = bound(p)
    ratio = torch.where(err == 0, 0.0, err / tol).max().item()  # exact outputs (bias only) may have a zero bound
    worst = (err - tol).flatten().argmax().item()
    assert ratio <= 1.0, (f"{p.kind} mma forward: max error / bound {ratio:.3g} (error "
                          f"{err.flatten()[worst].item():.3g}, bound {tol.flatten()[worst].item():.3g}, K {k_max(p)})")
    return ratio


# (kind, B, cin, cout, T, U, padding, unread): Cout, K and N = B x T_out off the 16 / 32 / 64 tile grid, two row tiles,
# two column tiles, stride 2, up's fine entities that no coarse one reads (K = 0: bias only)
SIZES = {
    "conv.small": ("conv", 2, 3, 5, 21, 3, "zeros", False),
    "conv.two_row_tiles": ("conv", 3, 7, 37, 29, 5, "reflect", False),
    "down.reflect": ("down", 2, 6, 20, 34, 3, "reflect", False),
    "down.wide": ("down", 4, 5, 9, 40, 1, "zeros", False),
    "up.unread": ("up", 2, 3, 5, 11, 3, "zeros", True),
    "up.reflect": ("up", 2, 6, 20, 17, 5, "reflect", False),
}
# (modulation, bias, act)
OPTIONS = (("none", False, False), ("style", True, False), ("style_demod", True, True), ("demod", False, True))


@pytest.mark.parametrize("size", sorted(SIZES))
def test_mma_forward_matches_float64(size):
    kind, B, cin, cout, T, U, padding, unread = SIZES[size]
    for k, (mod, bias, act) in enumerate(OPTIONS):
        p = Problem(kind, mod, padding, U=U, bias=bias, dtype=torch.bfloat16, seed=100 + k, B=B, cin=cin,
                    cout=cout, T=T, act=act, unread=unread)
        check_mma(p)


def test_mma_block_walks_column_tiles_with_resident_weight_panels():
    """One SM: each block walks all column tiles; K = deg x 60 x 3 > 512 needs two weight panels, reloaded per
    column tile.  The launch grid is what launch_mma_gemm says: (1, row tiles, entities)."""
    p = Problem("conv", "style_demod", "reflect", U=3, bias=True, dtype=torch.bfloat16, seed=7, B=2, cin=60, cout=24,
                T=40, n=5, act=True)
    assert k_max(p) > 512
    with sm_count(1):
        check_mma(p)
    assert EMU.last_grids()[MMA["conv"]] == (1, 1, p.n_out)


def test_mma_is_opt_in():
    """Without MODI_EXT_CUDA_MMA=1 the bf16 forward and backward stay on the SIMT kernels; float32 takes the
    tensor-core path only while torch allows TF32, float16 never."""
    n0 = mma_launches()
    assert os.environ.get("MODI_EXT_CUDA_MMA") != "1"
    for kind in ("conv", "up"):
        p = Problem(kind, "style", "zeros", dtype=torch.bfloat16, seed=3)
        p.backward(p.forward())
    before = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    try:
        with mma_on():
            Problem("conv", "style", "zeros", dtype=torch.float32, seed=3).forward()
            Problem("up", "style", "zeros", dtype=torch.float16, seed=3).forward()
    finally:
        torch.backends.cudnn.allow_tf32 = before
    assert mma_launches() == n0


@pytest.mark.parametrize("kind", ("conv", "up"))
@pytest.mark.parametrize("defect", ("mma_fragment_offset", "mma_tile_edge"))
def test_mma_planted_faults_are_caught(defect, kind):
    """mma_fragment_offset: each warp reads its two B fragments at each other's column offset; mma_tile_edge: the
    gathered operand's k edge is one short, so the last product of every output is dropped.  Both stay finite (no
    poison to trip over): only the bound against float64 sees them, while the clean kernel passes the same case."""
    p = Problem(kind, "none", "zeros", U=3, bias=True, dtype=torch.bfloat16, seed=11, B=2, cin=3, cout=20, T=25)
    check_mma(p)
    with injected(defect):
        with mma_on():
            y = p.forward()
        assert torch.isfinite(y.double()).all(), "the planted fault must stay finite"
        with pytest.raises(AssertionError, match="max error / bound"):
            check_mma(p)
    check_mma(p)


def test_selfcheck_passes_with_the_mma_forward():
    """The first-use self-check in bf16 with the switch on: its forwards (and backwards) run on the tensor-core
    kernels and pass the payload's bf16 tolerance."""
    from modi_ext.runtime import selfcheck

    n0 = mma_launches()
    with mma_on():
        res = selfcheck.run("cpu", torch.bfloat16, lib="modi_ext_emu")
    assert res["ok"], res["errors"]
    assert res["ok"] and mma_launches() > n0
