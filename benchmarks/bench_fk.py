"""FK benchmarks: the fused C++ kernel vs the dense torch reference at B=256, T=64 on a Bandai-like 22-joint rig.

``fk_cases()`` gives ``{case: (ref_fn, ext_fn)}`` of zero-argument callables for ``benchmarks/compare.py``
(which times both in one process); the pytest-benchmark tests below time the same callables:

    pytest benchmarks/bench_fk.py --benchmark-only
    python benchmarks/bench_fk.py            # quick stand-alone medians and ratios
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import pytest
import torch

from modi_ext import HAS_EXT
from modi_ext.fk import fk

# Bandai-Namco skeleton topology: root, hips, spine chain, arms off the chest, legs off the hips.
BANDAI_PARENTS = [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1, 14, 15, 16, 1, 18, 19, 20]
B, T = 256, 64


def _inputs(dtype: torch.dtype = torch.float32, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    J = len(BANDAI_PARENTS)
    q = torch.randn(B, T, J, 4, generator=g)
    q = (q / q.norm(dim=-1, keepdim=True)).to(dtype)
    off = (torch.randn(J, 3, generator=g) * 20.0).to(dtype)
    root = (torch.randn(B, T, 3, generator=g) * 100.0).to(dtype)
    grad = torch.randn(B, T, J, 3, generator=g).to(dtype)
    return q, off, root, grad


def fk_cases(dtype: torch.dtype = torch.float32) -> dict[str, tuple[Callable[[], object], Callable[[], object]]]:
    """``{"fk.fwd_bwd": (ref_fn, ext_fn), "fk.fwd": (ref_fn, ext_fn)}`` at B=256, T=64, 22 joints.

    Both go through the public ``fk`` (same argument checks): ref_fn with ``impl="ref"`` (the dense torch
    reference), ext_fn with ``impl="ext"`` (the C++ kernel; raises if it is not built). fwd_bwd differentiates
    the positions w.r.t. rotations and root translation with a fixed upstream gradient.
    """
    if not HAS_EXT:
        raise RuntimeError("modi_ext C++ extension is not built: no FK kernel to benchmark")
    q, off, root, grad = _inputs(dtype)
    qg, rg = q.clone().requires_grad_(), root.clone().requires_grad_()

    def ref(*args):
        return fk(*args, impl="ref")

    def ext(*args):
        return fk(*args, impl="ext")

    def fwd(fn):
        def run():
            with torch.no_grad():
                return fn(q, off, BANDAI_PARENTS, root)
        return run

    def fwd_bwd(fn):
        def run():
            pos = fn(qg, off, BANDAI_PARENTS, rg)
            return torch.autograd.grad(pos, (qg, rg), grad)
        return run

    return {
        "fk.fwd_bwd": (fwd_bwd(ref), fwd_bwd(ext)),
        "fk.fwd": (fwd(ref), fwd(ext)),
    }


# ---- pytest-benchmark ----

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")


@needs_ext
@pytest.mark.parametrize("case", ["fk.fwd_bwd", "fk.fwd"])
@pytest.mark.parametrize("impl", ["ref", "ext"])
def test_fk(benchmark, case, impl):
    ref_fn, ext_fn = fk_cases()[case]
    fn = ref_fn if impl == "ref" else ext_fn
    benchmark.group = case
    benchmark.pedantic(fn, warmup_rounds=2, rounds=15, iterations=1)



def _median_ms(fn: Callable[[], object], repeats: int = 21) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


if __name__ == "__main__":
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, B={B} T={T} J={len(BANDAI_PARENTS)} fp32")
    for name, (ref_fn, ext_fn) in fk_cases().items():
        # interleave ref and ext so background load hits both alike
        ref_ms, ext_ms = [], []
        for _ in range(3):
            ref_ms.append(_median_ms(ref_fn, 7))
            ext_ms.append(_median_ms(ext_fn, 7))
        r, e = statistics.median(ref_ms), statistics.median(ext_ms)
        print(f"{name:12s} ref {r:9.2f} ms   ext {e:8.2f} ms   speedup {r / e:6.1f}x")
