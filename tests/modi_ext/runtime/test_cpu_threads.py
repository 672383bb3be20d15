"""CPU kernels under different thread counts: the same bits at 1, 2 and more threads than tasks, and tiny sizes.

The kernels claim tasks dynamically (csrc/common/tasks.h), so which thread computes what changes from run to run; the
tiling depends on the shapes only and every output element is written by one task, so the results must not change.
Each case is also checked against the dense reference, so agreement between thread counts cannot come from a
kernel that ignores its input.
"""
from __future__ import annotations

import random

import pytest
import torch

from modi_ext import HAS_EXT
from modi_ext.fk import fk, fk_reference
from modi_ext.skeletal import ops
from modi_ext.skeletal import reference as R
from modi_ext.csr import csr_from_lists

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
KINDS = ("conv", "down", "up")


def _neighbors(parents: list[int]) -> list[list[int]]:
    adj = [{j} for j in range(len(parents))]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].add(p)
            adj[p].add(j)
    return [sorted(a) for a in adj]


def _pooling(n_fine: int, rng: random.Random) -> list[list[int]]:
    fine = list(range(n_fine))
    rng.shuffle(fine)
    groups, i = [], 0
    while i < n_fine:
        k = rng.randint(1, 3)
        groups.append(sorted(fine[i:i + k]))
        i += k
    return groups


def _case(kind, seed, *, n, B, cin, cout, T, U, dtype, padding="zeros", style=True, demod=True):
    rng = random.Random(seed)
    g = torch.Generator().manual_seed(seed)
    if kind == "conv":
        topo = csr_from_lists(_neighbors([-1] + [rng.randrange(j) for j in range(1, n)]))
        x = torch.randn(B, cin, n, T, dtype=dtype, generator=g)
        w = torch.randn(cout, topo.nnz, cin, U, dtype=dtype, generator=g)
        extra = ()
    else:
        topo = csr_from_lists(_pooling(n, rng), require_cover=True)
        if kind == "down":
            x = torch.randn(B, cin, n, T, dtype=dtype, generator=g)
            w = torch.randn(cout, topo.nnz, cin, U, dtype=dtype, generator=g)
            extra = ()
        else:
            x = torch.randn(B, cin, topo.n_out, T, dtype=dtype, generator=g)
            w = torch.randn(cin, topo.nnz, cout, U, dtype=dtype, generator=g)
            extra = (n,)
    b = torch.randn(cout, dtype=dtype, generator=g)
    s = torch.randn(B, cin, dtype=dtype, generator=g) if style else None
    return (x, w, b, topo.index, topo.offsets) + extra, dict(style=s, demodulate=demod, padding_mode=padding)


def _run(kind, mod, args, kw, threads=None):
    """Output and the gradients w.r.t. x, weight, bias (and style) for a fixed output gradient."""
    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        leaves = [a.detach().clone().requires_grad_(True) for a in args[:3]]
        style = kw["style"].detach().clone().requires_grad_(True) if kw["style"] is not None else None
        full = tuple(leaves) + tuple(args[3:])
        if mod is ops:
            y = getattr(ops, f"skeletal_{kind}")(*full, style=style, demodulate=kw["demodulate"],
                                                  padding_mode=kw["padding_mode"])
        else:
            y = getattr(R, f"skeletal_{kind}")(*full, style, kw["demodulate"], kw["padding_mode"])
        gy = torch.randn(y.shape, dtype=y.dtype, generator=torch.Generator().manual_seed(5))
        wrt = leaves + ([style] if style is not None else [])
        return [y.detach()] + list(torch.autograd.grad(y, wrt, gy))
    finally:
        torch.set_num_threads(old)


def _tol(dtype):
    return dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-9)


# Shapes: the fp32 indirect kernels (>= 16 frames), the BLAS path (few frames, and every fp64 call), MoDi-like
# batches (batch tiles), GANimator-like batch 1 with narrow channels (entity tasks only, narrow weight gradient) and
# wide layers (the AVX-512 weight-gradient kernel where available, BLAS under "avx2").
SHAPES = [
    dict(n=12, B=5, cin=6, cout=8, T=20, U=3, dtype=torch.float32),
    dict(n=9, B=3, cin=5, cout=12, T=6, U=3, dtype=torch.float32),
    dict(n=10, B=4, cin=4, cout=5, T=9, U=5, dtype=torch.float64),
    dict(n=15, B=1, cin=7, cout=3, T=40, U=5, dtype=torch.float32, padding="reflect"),
    dict(n=7, B=2, cin=36, cout=40, T=17, U=3, dtype=torch.float32),  # wide: 32-row blocks + remainders
]


@needs_ext
@pytest.mark.parametrize("demod", [False, True])
@pytest.mark.parametrize("pool", ["omp", "own"])
@pytest.mark.parametrize("kernel", ["auto", "avx2"])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("shape", range(len(SHAPES)))
def test_identical_at_1_2_and_many_threads(kind, shape, kernel, pool, demod, monkeypatch):
    """kernel "avx2": the AVX2 micro-kernels even where AVX-512 is available (MODI_EXT_CPU_KERNEL=avx2);
    pool "own": the kernels' own helper threads (the default under modi_ext's short OpenMP spin); "omp": torch's
    OpenMP team (MODI_EXT_CPU_POOL=omp, the default when torch was imported first).

    The kernels give bit-identical results at any thread count, demodulation included: its coefficients come from
    the C++ op (``modi_ext.demod.ops``), whose sums run in one order whatever the thread count.  (torch's own small
    matrix product, which computed them before, rounds differently at 1 and 2 threads on AMD EPYC: 5e-7.)"""
    if kernel == "avx2":
        monkeypatch.setenv("MODI_EXT_CPU_KERNEL", "avx2")
    monkeypatch.setenv("MODI_EXT_CPU_POOL", pool)
    spec = dict(SHAPES[shape])
    args, kw = _case(kind, 300 + shape, demod=demod, **spec)
    one = _run(kind, ops, args, kw, threads=1)
    ref = _run(kind, R, args, kw)
    for a, b in zip(one, ref):
        torch.testing.assert_close(a, b, **_tol(spec["dtype"]))
    for threads in (2, 7):  # 7: more threads than the tasks of the smaller passes
        for a, b in zip(_run(kind, ops, args, kw, threads=threads), one):
            assert torch.equal(a, b), f"{kind} differs between 1 and {threads} threads"


@needs_ext
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tiny_sizes_match_reference_on_any_thread_count(kind, dtype):
    """One entity, one channel, one batch element, one to three frames: fewer tasks than threads everywhere."""
    for seed, (n, T, U) in enumerate([(1, 2, 1), (2, 2, 3), (3, 3, 1), (1, 4, 3)]):
        args, kw = _case(kind, 400 + seed, n=n, B=1, cin=1, cout=1, T=T, U=U, dtype=dtype, demod=False)
        ref = _run(kind, R, args, kw)
        for threads in (1, 2, 5):
            for a, b in zip(_run(kind, ops, args, kw, threads=threads), ref):
                torch.testing.assert_close(a, b, **_tol(dtype))


def _fk_run(q, off, parents, root, threads):
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        leaves = [t.detach().clone().requires_grad_(True) for t in (q, off, root)]
        pos = fk(leaves[0], leaves[1], parents, leaves[2], impl="ext")
        gp = torch.randn(pos.shape, dtype=pos.dtype, generator=torch.Generator().manual_seed(1))
        return [pos.detach()] + list(torch.autograd.grad(pos, leaves, gp))
    finally:
        torch.set_num_threads(old)


@needs_ext
@pytest.mark.parametrize("lead", [(1, 1), (3, 2), (16, 40)])
def test_fk_identical_at_1_2_and_many_threads(lead):
    g = torch.Generator().manual_seed(sum(lead))
    parents = [-1, 0, 1, 2, 1, 4, 0, 6]
    J = len(parents)
    q = torch.randn(*lead, J, 4, generator=g)
    q = q / q.norm(dim=-1, keepdim=True)
    off = torch.randn(J, 3, generator=g)
    root = torch.randn(*lead, 3, generator=g)
    one = _fk_run(q, off, parents, root, 1)
    torch.testing.assert_close(one[0], fk_reference(q, off, parents, root), rtol=1e-4, atol=1e-4)
    for threads in (2, 9):
        for a, b in zip(_fk_run(q, off, parents, root, threads), one):
            assert torch.equal(a, b), f"fk differs between 1 and {threads} threads"


def _forward_only(args, threads):
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            return ops.skeletal_conv(*args)
    finally:
        torch.set_num_threads(old)


def _child_conv(args, q):
    """In a forked child the parent's helper threads do not exist: the kernels must start their own.  (Only the
    kernel runs here: torch's OpenMP team does not survive fork.)"""
    q.put(_forward_only(args, 2).numpy())


@needs_ext
def test_kernels_work_in_a_forked_child(monkeypatch):
    """MODI_EXT_CPU_POOL=own: the kernels' own helper threads are re-created in a forked child (libgomp's team, the
    pool used when OpenMP keeps its long spin, does not survive fork)."""
    import multiprocessing as mp

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("fork start method unavailable on this platform")
    monkeypatch.setenv("MODI_EXT_CPU_POOL", "own")
    args, _ = _case("conv", 500, **SHAPES[0])
    parent = _forward_only(args, 2)  # the helpers now exist in this process
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_child_conv, args=(args, q))
    p.start()
    child = q.get(timeout=60)
    p.join(60)
    assert p.exitcode == 0
    assert torch.equal(torch.from_numpy(child), parent)


@needs_ext
def test_concurrent_callers_get_the_same_results():
    """Two Python threads calling the kernels at once (the helpers serve one call at a time; the other runs on its
    own thread): every result equals the single-caller one."""
    import threading

    cases = [_case(kind, 600 + i, **SHAPES[0]) for i, kind in enumerate(KINDS)]
    expected = [_run(kind, ops, args, kw, threads=2) for kind, (args, kw) in zip(KINDS, cases)]
    results: dict[int, list] = {}
    errors: list[BaseException] = []

    def worker(w: int) -> None:
        try:
            results[w] = [_run(kind, ops, args, kw) for _ in range(3) for kind, (args, kw) in zip(KINDS, cases)]
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        threads = [threading.Thread(target=worker, args=(w,)) for w in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
    finally:
        torch.set_num_threads(old)
    assert not errors, errors
    for w in range(2):
        for i, got in enumerate(results[w]):
            for a, b in zip(got, expected[i % len(KINDS)]):
                assert torch.equal(a, b)


def _thread_cpu_sets() -> dict[int, set[int]]:
    """CPUs each thread of this process may run on (Linux: /proc/self/task/*/status)."""
    import os
    from pathlib import Path

    out = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            status = (task / "status").read_text()
        except OSError:
            continue  # a thread that just ended
        for line in status.splitlines():
            if line.startswith("Cpus_allowed_list:"):
                cpus: set[int] = set()
                for part in line.split(":", 1)[1].strip().split(","):
                    lo, _, hi = part.partition("-")
                    cpus.update(range(int(lo), int(hi or lo) + 1))
                out[int(task.name)] = cpus
    assert os.getpid() in out
    return out


@needs_ext
def test_helpers_are_kept_off_the_callers_cpu(monkeypatch):
    """With the kernels' own helpers (the busy-machine pool), each job keeps the helpers off the CPU its caller runs
    on, so that Linux cannot stack a woken helper beside its caller; MODI_EXT_HELPER_AFFINITY=0 gives them back the
    whole CPU set.  The results do not change either way."""
    import os
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("helper placement is Linux-only (sched_setaffinity)")
    allowed = os.sched_getaffinity(0)
    if len(allowed) < 2:
        pytest.skip(f"this process may use {len(allowed)} CPU; placement needs two")
    monkeypatch.setenv("MODI_EXT_CPU_POOL", "own")
    args, _ = _case("conv", 700, n=25, B=16, cin=32, cout=32, T=64, U=3, dtype=torch.float32, demod=False)
    monkeypatch.delenv("MODI_EXT_HELPER_AFFINITY", raising=False)
    placed = _forward_only(args, 2)  # a parallel job: the helpers exist and are placed
    narrowed = [cpus for cpus in _thread_cpu_sets().values() if cpus < allowed and len(cpus) == len(allowed) - 1]
    assert narrowed, "no helper thread was kept off one CPU"
    monkeypatch.setenv("MODI_EXT_HELPER_AFFINITY", "0")
    free = _forward_only(args, 2)
    assert all(cpus == allowed for cpus in _thread_cpu_sets().values() if cpus <= allowed), \
        "MODI_EXT_HELPER_AFFINITY=0 left a helper off a CPU"
    assert torch.equal(placed, free)
