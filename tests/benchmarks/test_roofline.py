"""The benchmarks' FLOP counts (benchmarks/roofline.py) and the step profile (benchmarks/profile_step.py).

A FLOP formula is checked against torch's own count of the plain-torch equivalent, where the skeletal op has one: a
skeletal conv whose every entity neighbours every entity *is* a dense conv1d over (channel x entity) rows. No timing
is asserted anywhere.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import roofline as R  # noqa: E402  (benchmarks/roofline.py)
from modi_ext import HAS_EXT  # noqa: E402
from modi_ext.layers import ModulatedSkeletalConv, SkeletalConv, SkeletalDownsample  # noqa: E402

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")

B, CI, CO, E, T, U = 2, 3, 5, 4, 12, 3
FULL = [list(range(E)) for _ in range(E)]
CHAIN = [[m for m in (j - 1, j, j + 1) if 0 <= m < E] for j in range(E)]


def _torch_conv_flops(conv: SkeletalConv, x: torch.Tensor) -> int:
    """torch's count of the same conv as one dense conv1d over (channel x entity) rows."""
    dense = conv.dense_weight().permute(0, 2, 1, 3, 4).reshape(CO * E, CI * E, U)
    xr = x.reshape(B, CI * E, T)
    return R.count_flops(lambda: F.conv1d(xr, dense, padding=U // 2))[0]


@needs_ext
def test_dense_case_equals_torch_count():
    torch.manual_seed(0)
    conv = SkeletalConv(CI, CO, FULL, U, bias=False)
    x = torch.randn(B, CI, E, T)
    with torch.no_grad():
        ours = R.count_flops(lambda: conv(x))[0]
    assert ours == _torch_conv_flops(conv, x) == R.conv1d_dense_flops(B, CO * E, CI * E, T, U)


@needs_ext
def test_sparse_case_counts_only_the_pairs():
    torch.manual_seed(0)
    conv = SkeletalConv(CI, CO, CHAIN, U, bias=False)
    x = torch.randn(B, CI, E, T)
    with torch.no_grad():
        ours = R.count_flops(lambda: conv(x))[0]
    pairs = sum(len(r) for r in CHAIN)
    assert ours * E * E == _torch_conv_flops(conv, x) * pairs  # the masked zeros are not work
    assert ours == 2 * B * T * pairs * CO * CI * U


@needs_ext
@pytest.mark.parametrize("topology", [FULL, CHAIN])
def test_backward_is_twice_forward(topology):
    torch.manual_seed(0)
    conv = SkeletalConv(CI, CO, topology, U)
    x = torch.randn(B, CI, E, T, requires_grad=True)
    fwd = R.count_flops(lambda: conv(x))[0]
    both = R.count_flops(lambda: torch.autograd.grad(conv(x).sum(), [x, conv.weight]))[0]
    assert both == 3 * fwd


@needs_ext
def test_downsample_and_modulated_counts():
    torch.manual_seed(0)
    pool = [[0, 1], [2, 3]]
    down = SkeletalDownsample(CI, CO, pool, U, bias=False)
    x = torch.randn(B, CI, E, T)
    with torch.no_grad():
        assert R.count_flops(lambda: down(x))[0] == 2 * B * (T // 2) * 4 * CO * CI * U
    mod = ModulatedSkeletalConv(CI, CO, 8, CHAIN, U, demodulate=False)
    w = torch.randn(B, 8)
    with torch.no_grad():
        by_op = R.flops_by_op(lambda: mod(x, w))
    pairs = sum(len(r) for r in CHAIN)
    # the conv over the pairs plus one multiply per input element for the style
    assert by_op["modi_ext.skeletal_conv"] == 2 * B * T * pairs * CO * CI * U + B * CI * E * T


def test_sgemm_rate_is_positive_and_fractions_are_ratios():
    s = R.Sgemm(n=128, min_time=0.0)
    assert s.gflops > 0
    gf, frac = s.rate(2e9, 1000.0)
    assert gf == pytest.approx(2.0) and frac == pytest.approx(2.0 / s.gflops)


def test_blas_at_conv_shapes_times_the_three_products(monkeypatch):
    """Each of the three products is timed at the conv's sizes: the FLOPs it divides by are 2 * E * Cout * K * N
    with K = round(nnz / E) * Cin * taps (a spy on torch.bmm sees those operand shapes)."""
    seen = []
    real = torch.bmm

    def spy(a, b):
        seen.append((tuple(a.shape), tuple(b.shape)))
        return real(a, b)

    monkeypatch.setattr(R.torch, "bmm", spy)
    rates = R.blas_at_conv_shapes(n_out=5, nnz=14, c_out=4, c_in=3, taps=3, batch=2, frames=8, min_time=0.0)
    assert set(rates) == {"fwd", "grad_input", "grad_weight"} and all(v > 0 for v in rates.values())
    k, n = 3 * 3 * 3, 16
    assert {(5, 4, k), (5, k, n)} <= {s for pair in seen for s in pair}
    assert set(seen) == {((5, 4, k), (5, k, n)), ((5, k, 4), (5, 4, n)), ((5, 4, n), (5, n, k))}


@needs_ext
def test_profile_step_runs_and_rows_fit_in_the_wall_time(tmp_path):
    import profile_step

    tiny = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
            "data.stride": 8, "train.d_reg_every": 2, "train.g_reg_every": 2}
    res = profile_step.profile_modi("small", 4, 2, "procedural", warmup=1, top=3, overrides=tiny)
    names = [r["row"] for r in res["rows"]]
    assert names[0] == "modi_ext kernels" and "Adam" in names and "EMA" in names and "Python + autograd" in names
    step_rows = [r for r in res["rows"] if "amortised" not in r["row"]]
    assert all(r["ms_per_step"] >= 0 for r in res["rows"])
    assert sum(r["ms_per_step"] for r in step_rows) <= res["wall_ms_per_step"] * 1.001 + 1e-3
    kernel_ms = next(r for r in res["rows"] if r["row"] == "modi_ext kernels")["ms_per_step"]
    assert kernel_ms > 0
    by_op = res["kernel_ops_ms_per_step"]
    assert "modi_ext::skeletal_conv" in by_op and sum(by_op.values()) == pytest.approx(kernel_ms, rel=1e-3, abs=0.01)
