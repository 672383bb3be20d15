"""Split reductions of the skeletal CUDA GEMMs (csrc/skeletal/launch_plan.h, cuda.cu), on the CPU emulator.

At MoDi's batch 16 the per-entity GEMMs are too few to fill an H100/H200 (132 SMs): the weight gradient puts each
row's k tiles in the grid and splits batch x time; the row / transposed GEMMs split each entity's k stages.  These
tests check the plans on the real Bandai hierarchy, that the kernels launch what the plans say, that split results
match the float64 reference bit-for-bit across schedules (partials summed in a fixed order), and that a planted split
boundary fault is caught.
"""
from __future__ import annotations


import pytest
import torch

from test_cuda_emulated import EMU, Problem, check_problem, close, emu, injected, sm_count  # noqa: F401  (emu: the fixture)

pytestmark = [pytest.mark.cuda_emulated, pytest.mark.usefixtures("one_torch_thread")]

H100_SMS = 132
BANDAI_PARENTS = [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1, 14, 15, 16, 1, 18, 19, 20]
FRAMES = (64, 32, 16, 8, 4)  # finest -> coarsest
CHANNELS = {"paper": (32, 64, 64, 128, 256), "small": (16, 32, 32, 64, 96)}  # finest -> coarsest
MIN_SPLIT_COLS, MIN_SPLIT_STAGES, MAX_SPLITS = 64, 8, 32  # launch_plan.h


def bandai_levels():
    """(rows, nnz) of each level's conv neighbourhood and of each pooling map (fine level lv -> lv + 1)."""
    from modi.core.skeleton_graph import build_hierarchy

    class _Skeleton:
        parents = BANDAI_PARENTS
        names = [f"j{i}" for i in range(len(BANDAI_PARENTS))]

    h = build_hierarchy(_Skeleton(), feet=[16, 20], neighbor_distance=1)
    conv = [(len(lv.neighbors), sum(len(r) for r in lv.neighbors)) for lv in h.levels]
    pool = [(len(p), sum(len(g) for g in p)) for p in h.pooling]
    return conv, pool


def gemms(preset: str, batch: int):
    """Every GEMM of a MoDi generator's skeletal ops at one batch: (name, wgrad args, [gemm args])."""
    conv, pool = bandai_levels()
    ch = CHANNELS[preset]
    out = []
    for lv, (rows, nnz) in enumerate(conv):
        c, n = ch[lv], batch * FRAMES[lv]
        # forward: row GEMM over rows; input gradient: transposed GEMM over the same entities
        out.append((f"conv{lv}", (n, rows, nnz, 3 * c, c), [(n, c, rows, nnz, 3 * c)] * 2))
    for lv, (rows, nnz) in enumerate(pool):
        cf, cc, tc = ch[lv], ch[lv + 1], FRAMES[lv + 1]
        nc, nf = batch * tc, batch * FRAMES[lv]
        fine = conv[lv][0]
        # down: out = coarse rows; its input gradient is the transposed GEMM over the fine entities
        out.append((f"down{lv}", (nc, rows, nnz, 3 * cf, cc), [(nc, cc, rows, nnz, 3 * cf),
                                                                (nf, cf, fine, nnz, 3 * cc)]))
        # up (coarse x in, fine out): forward is the transposed GEMM over the fine entities, its input gradient the
        # row GEMM; the weight gradient sums over the coarse input's columns
        out.append((f"up{lv}", (nc, rows, nnz, 3 * cf, cc), [(nf, cf, fine, nnz, 3 * cc),
                                                             (nc, cc, rows, nnz, 3 * cf)]))
    return out


# ------------------------------------------------------------------------------------------------ plans
def test_paper_conv_weight_gradient_fills_two_waves_at_batch_16():
    """The case that motivated the split: the paper preset's skeletal conv weight gradient at batch 16 launched
    100, 28, 10, 10, 4 blocks on 132 SMs (one per row x m tile x 256-column split).  Now every level whose
    reduction can be split (>= 2 x 64 batch x time columns) launches at least two waves."""
    for name, w, _ in gemms("paper", 16):
        if not name.startswith("conv"):
            continue
        p = EMU.wgrad_plan(*w, H100_SMS)
        if w[0] >= 2 * MIN_SPLIT_COLS:
            assert p["ctas"] >= 2 * H100_SMS, (name, p)
        assert p["ktiles"] * 64 >= w[2] * w[3], (name, p)  # the slots cover every k column


@pytest.mark.parametrize("preset", sorted(CHANNELS))
@pytest.mark.parametrize("batch", (1, 16, 256))
def test_plans_reach_two_waves_or_their_bound(preset, batch):
    """For every GEMM of both presets: at least two waves on 132 SMs, unless the split is at its bound (64 columns
    per weight-gradient split, 8 mean k stages per GEMM split, 32 splits); splits never exceed what the reduction
    holds, and the plans are pure (same answer twice)."""
    for name, w, gs in gemms(preset, batch):
        p = EMU.wgrad_plan(*w, H100_SMS)
        assert p == EMU.wgrad_plan(*w, H100_SMS)
        n = w[0]
        assert p["n_chunk"] % 4 == 0 and (p["splits"] - 1) * p["n_chunk"] < n <= p["splits"] * p["n_chunk"]
        assert p["splits"] == 1 or p["n_chunk"] >= MIN_SPLIT_COLS, (name, p)
        # rounding the chunk to 4 columns may cost one split once more than 17 are asked for
        at_bound = p["splits"] >= max(1, n // MIN_SPLIT_COLS) - (p["splits"] > 17) or p["splits"] >= MAX_SPLITS - 1
        assert p["ctas"] >= 2 * H100_SMS or at_bound, (name, "wgrad", p)
        for g in gs:
            q = EMU.gemm_plan(*g, H100_SMS)
            mean_stages = -(-g[3] * g[4] // (g[2] * 16))
            assert q["splits"] <= max(1, mean_stages // MIN_SPLIT_STAGES), (name, q)
            at_bound = q["splits"] >= max(1, mean_stages // MIN_SPLIT_STAGES) or q["splits"] == MAX_SPLITS
            assert q["ctas"] >= 2 * H100_SMS or at_bound, (name, "gemm", q)


def test_plans_do_not_split_with_one_sm_or_short_reductions():
    assert EMU.wgrad_plan(100_000, 25, 87, 96, 32, 1)["splits"] == 1
    assert EMU.gemm_plan(128, 32, 1, 100, 960, 1)["splits"] == 1  # two column tiles: two waves of 1 SM
    assert EMU.wgrad_plan(127, 1, 1, 3, 5, 10_000)["splits"] == 1  # < 2 x 64 columns
    assert EMU.gemm_plan(64, 32, 1, 1, 127, 10_000)["splits"] == 1  # < 2 x 8 stages
    assert EMU.gemm_plan(64, 32, 1, 100, 960, 10_000)["splits"] == MAX_SPLITS


# ------------------------------------------------------------------------------------------------ kernels
def grids(prefix: str) -> list[tuple[int, int, int]]:
    return [g for k, g in EMU.last_grids().items() if k.startswith(prefix)]


# (kind, U, cin, cout, B, T, dtype): batch x time not a multiple of 16 nor of the split; cout 40 (a ragged 64-row
# tile); the weight's k runs misaligned for 4-vectors (C * U = 170) and aligned (320); the weight gradient's left
# operand rows of 70 frames (scalar fallback) and of 44 (4-vectors).
SPLIT_CASES = [
    ("conv", 5, 34, 40, 2, 67, torch.float64),
    ("down", 5, 64, 20, 2, 140, torch.float32),
    ("up", 5, 64, 20, 3, 44, torch.float32),
]


@pytest.mark.parametrize("case", SPLIT_CASES, ids=lambda c: "-".join(map(str, c[:6])))
def test_split_kernels_match_the_reference(case):
    """Forward and backward with several weight-gradient and GEMM splits (132 SMs) against the float64 reference,
    bitwise equal under two block / thread schedules; the launched grids are the plans'."""
    kind, U, cin, cout, B, T, dtype = case
    p = Problem(kind, "style_demod", "reflect", U=U, bias=True, dtype=dtype, seed=7 + U, B=B, cin=cin, cout=cout,
                T=T, n=5)
    EMU.reset_launch_counts()
    with sm_count(H100_SMS):
        check_problem(p)
    rows, nnz = p.offsets.numel() - 1, p.index.numel()
    up = kind == "up"
    n_w = B * (T if up else p.t_out)  # the weight gradient sums over the columns of the gathered side
    m_w, cu_w = (cin, U * cout) if up else (cout, U * cin)
    w = EMU.wgrad_plan(n_w, rows, nnz, cu_w, m_w, H100_SMS)
    assert w["splits"] > 1 and n_w % w["n_chunk"] and w["n_chunk"] % 16, w
    assert grids("wgrad_kernel") == [(w["ktiles"], w["mtiles"], w["splits"])]
    f = EMU.gemm_plan(B * p.t_out, cout, p.n_out if up else rows, nnz, U * cin, H100_SMS)
    assert f["splits"] > 1, f
    assert (f["ntiles"], f["mtiles"], f["ents"] * f["splits"]) in grids("tr_gemm" if up else "row_gemm"), f
    assert any(k.startswith("split_reduce_kernel") for k in EMU.launch_counts())


def test_split_results_are_bitwise_reproducible():
    """Two runs of the same split forward and backward give identical bits (no atomics; partials summed in split
    order)."""
    p = Problem("up", "style", "zeros", U=5, dtype=torch.float32, seed=3, B=2, cin=48, cout=20, T=66, n=5)
    with sm_count(H100_SMS):
        y1, y2 = p.forward(), p.forward()
        a, b = p.backward(y1), p.backward(y2)
    assert torch.equal(y1, y2)
    for u, v in zip(a, b):
        assert torch.equal(u, v)


# ------------------------------------------------------------------------------------------------ planted fault
def reference_grad_weight(p: Problem) -> torch.Tensor:
    w = p.w.clone().requires_grad_(True)
    return torch.autograd.grad(p.ref(p.x, w, p.b, p.s, p.d), w, p.gy)[0]


def test_split_boundary_fault_is_caught():
    """split_edge: every split but the first starts one step late (the weight gradient skips a batch x time column,
    the GEMMs a 16-deep k stage).  Values stay finite, so only the float64 comparison sees it -- and it does, in the
    forward (GEMM k split) and in the weight gradient.  With one SM nothing is split and the same fault is inert, so
    the cases above do cross split boundaries."""
    p = Problem("conv", "none", "zeros", U=5, bias=False, dtype=torch.float32, seed=2, B=2, cin=34, cout=8, T=70, n=4)
    gw_ref = reference_grad_weight(p)
    with sm_count(H100_SMS):
        check_problem(p, backward=False)
        y = p.forward()
        close(p.backward(y)[1], gw_ref, p.dtype, "clean grad weight")
        with injected("split_edge"):
            with pytest.raises(AssertionError, match="conv forward: max error"):
                check_problem(p, backward=False)
            gw = p.backward(y)[1]
    assert torch.isfinite(gw).all(), "the fault must stay finite: only the tolerance may catch it"
    with pytest.raises(AssertionError, match="grad weight: max error"):
        close(gw, gw_ref, p.dtype, "grad weight")
    with sm_count(1), injected("split_edge"):
        check_problem(p)
