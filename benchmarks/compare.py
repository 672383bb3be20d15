"""Time the dense reference against the C++ extension in one process and write the ratios as JSON.

    python benchmarks/compare.py --json benchmarks/results/cpu.json [--reps 15] [--threads N] [--only REGEX]
                                 [--clock wall|cpu] [--busy N]
    python benchmarks/compare.py --device cuda --dtype fp32,bf16 --json benchmarks/results/cuda_h100.json
    python benchmarks/compare.py --bf16 [--threads-list 1,2] [--repeats 7] [--only REGEX] [--json FILE]

Cases follow MoDi's generator hierarchy (paper Table 3 channels/frames: 32x64 at the finest level up to 256x4 at
the coarsest) on the Bandai-Namco 22-joint skeleton's pooling hierarchy (``modi.core.skeleton_graph`` when importable, a
built-in fallback otherwise), batch 16, fp32:

  skeletal_conv.<level>.{fwd,fwd_bwd}     in-place SkeletalConv (kernel 3, zero padding, bias)
  modulated_conv.<level>.{fwd,fwd_bwd}    ModulatedSkeletalConv, mode "same", demodulated
  scaler_up.<level>.{fwd,fwd_bwd}         SkeletalUpsample from the next coarser level into <level>
  scaler_down.<level>.{fwd,fwd_bwd}       SkeletalDownsample from <level> into the next coarser one
  modulated_up.<level>.{fwd,fwd_bwd}      ModulatedSkeletalConv, mode "up", demodulated
  <op>.finest.double                      forward, input gradient with create_graph=True, a scalar of it
                                          (its squared norm, as R1), backward to the input and every parameter
  {skeletal,modulated}_conv.finest.bwd    the backward alone (input and every parameter), through a graph built
                                          once and retained
  ganimator_conv.<clip>.{fwd,fwd_bwd,double}  GANimator's finest level (batch 1, kernel 5, reflect, distance-2
                                          neighbours of the real skeleton; ../shared/data needed): Salsa (29
                                          entities, 648 frames, 9 channels) and Crab (63 entities, 384 frames,
                                          5 channels); fwd_bwd also reports backward / forward time of each path
  fk.*                                    from benchmarks/bench_fk.py ``fk_cases()`` when present

Like the ``modi`` command, it imports modi_ext before torch, which picks the OpenMP spin for the machine it sees
(``modi_ext/runtime/omp_wait.py``; ``--busy N`` starts its load first); every row records the setting as ``omp_wait``.
Reference and extension runs are interleaved (ref, ext, ref, ext, ...) so machine load affects both alike; the
medians are reported.  The MoDi skeletal cases also time ``dense`` (``MODI_EXT_IMPL=dense``: one shared conv with
style and demodulation as scales) as a third interleaved side: ``dense_ms``, ``speedup_dense_vs_ref`` and
``speedup_ext_vs_dense``; ``modulated_conv.finest.fwd_bwd`` is checked against its targets (dense >= 5x the
grouped reference, ext >= 3x dense).  ``fwd_bwd`` differentiates w.r.t. the input and every parameter.

``--thread-ab N`` also times the extension alone at ``--threads`` and at N threads, alternated in blocks of a few
calls in this process (``--ab-reps`` timed calls each), for thread-scaling figures that machine drift cannot skew:
``ext_ms_threads`` (median ms per thread count) and ``ext_thread_ratio`` (time at ``--threads`` / time at N).

``--bf16`` (CPU) times each case in bfloat16 (the same modules and inputs cast to bf16, on ``auto``: the bf16
kernels where the CPU has AVX-512-BF16, else the ``dense`` path on oneDNN's GEMMs; ``MODI_EXT_CPU_KERNEL=bf16emu``
runs the kernels' emulation) against float32 on ``auto`` (the fp32 kernels), the two interleaved, ``--repeats``
times at each of ``--threads-list``: per case and thread count the bf16 / fp32 time ratio of each repeat, reported
as median, min and max (default cases: the finest skeletal and modulated conv, fwd_bwd), with the path each bf16
case ran on (``dispatch_report``).

Roofline (``benchmarks/roofline.py``): every case's FLOPs are counted once, untimed, on the extension's path with the
sparse per-pair formulas (``flops``), and this process times sgemm (``torch.mm`` 1024^3, same threads) at the start
and the end; each row gets ``{ref,ext,dense}_gflops`` and ``{ref,ext,dense}_frac_sgemm`` against the faster of the
two sgemm figures (``sgemm_gflops``; the printed fractions use the first one).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
# The checkout's packages, after PYTHONPATH's entries (``python -m modi_ext.validate --build`` points PYTHONPATH at a
# fresh build: inserted first, the checkout's unbuilt modi_ext would shadow it) and before site-packages.
sys.path.insert(1 + len([p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]), str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from busy import busy_cores, start_early  # noqa: E402  (benchmarks/busy.py: no torch)

# --busy N: the other job runs before this process loads anything, as on a shared machine; then modi_ext before
# torch, as the ``modi`` command does: it picks the OpenMP spin before libgomp loads (modi_ext/runtime/omp_wait.py)
_EARLY_BUSY = start_early(sys.argv) if __name__ == "__main__" else None
import modi_ext  # noqa: E402

import torch  # noqa: E402

from modi_ext import HAS_EXT  # noqa: E402
from modi_ext.layers import ModulatedSkeletalConv, SkeletalConv, SkeletalDownsample, SkeletalUpsample  # noqa: E402
from roofline import Sgemm, blas_at_conv_shapes, count_flops  # noqa: E402  (benchmarks/roofline.py)

# Bandai-Namco motion capture skeleton (22 joints), parents in file order.
BANDAI_PARENTS = [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1, 14, 15, 16, 1, 18, 19, 20]
BANDAI_FEET = [16, 20]
# MoDi Table 3, finest -> coarsest: (channels, frames)
MODI_LEVELS = [(32, 64), (64, 32), (64, 16), (128, 8), (256, 4)]
BATCH = 16
STYLE_DIM = 512


def bandai_hierarchy() -> tuple[list[list[list[int]]], list[list[list[int]]], str]:
    """(neighbors per level finest->coarsest, pooling maps, source description)."""
    try:
        from modi.core import skeleton_graph as topology

        class _Sk:
            parents = BANDAI_PARENTS
            names = [f"j{i}" for i in range(len(BANDAI_PARENTS))]

        h = topology.build_hierarchy(_Sk(), feet=BANDAI_FEET, neighbor_distance=1)
        return [lv.neighbors for lv in h.levels], [list(map(list, p)) for p in h.pooling], "modi.core.skeleton_graph"
    except Exception:  # noqa: BLE001 - fall back to a self-contained hierarchy
        return _fallback_hierarchy(), _fallback_pooling(), "built-in fallback"


def _fallback_levels() -> list[int]:
    return [25, 14, 10, 5, 1]


def _fallback_hierarchy() -> list[list[list[int]]]:
    """Chain-like neighbor lists with the entity counts of the real hierarchy (distance 1)."""
    out = []
    for n in _fallback_levels():
        out.append([[m for m in (j - 1, j, j + 1) if 0 <= m < n] for j in range(n)])
    return out


def _fallback_pooling() -> list[list[list[int]]]:
    counts = _fallback_levels()
    maps = []
    for fine, coarse in zip(counts[:-1], counts[1:]):
        groups = [[] for _ in range(coarse)]
        for f in range(fine):
            groups[min(coarse - 1, f * coarse // fine)].append(f)
        maps.append(groups)
    return maps


def level_names(n: int) -> list[str]:
    return ["finest"] + [f"level{i}" for i in range(1, n - 1)] + ["coarsest"]


@contextlib.contextmanager
def forced_env(values: dict[str, str]):
    """The environment variables ``values`` for the code run inside the block (the ops read them on every call)."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def forced_impl(impl: str):
    """MODI_EXT_IMPL=impl for the ops called inside the block."""
    return forced_env({"MODI_EXT_IMPL": impl})


def _with_impl(impl: str, fn: Callable[[], object]) -> Callable[[], object]:
    def run():
        with forced_impl(impl):
            return fn()
    return run


def _case(module: torch.nn.Module, inputs: tuple[torch.Tensor, ...], bwd: bool, impls=("ref", "ext")):
    """(ref_fn, ext_fn[, dense_fn]) running the module forward (and backward w.r.t. input + parameters)."""
    params = [p for p in module.parameters() if p.requires_grad]
    x = inputs[0].detach().clone().requires_grad_(bwd)
    rest = inputs[1:]
    grad = None

    def body():
        nonlocal grad
        if not bwd:
            with torch.no_grad():
                return module(x, *rest)
        y = module(x, *rest)
        if grad is None:
            grad = torch.randn_like(y)
        return torch.autograd.grad(y, [x] + params, grad)

    return tuple(_with_impl(i, body) for i in impls)


def _double_case(module: torch.nn.Module, inputs: tuple[torch.Tensor, ...], impls=("ref", "ext")):
    """(ref_fn, ext_fn[, dense_fn]): forward, input grad with create_graph, ||grad||^2, backward to input + params."""
    params = [p for p in module.parameters() if p.requires_grad]
    x = inputs[0].detach().clone().requires_grad_(True)
    rest = inputs[1:]
    grad = None

    def body():
        nonlocal grad
        y = module(x, *rest)
        if grad is None:
            grad = torch.randn_like(y)
        (gx,) = torch.autograd.grad(y, x, grad, create_graph=True)
        return torch.autograd.grad(gx.pow(2).sum(), [x] + params, allow_unused=True)

    return tuple(_with_impl(i, body) for i in impls)


def _bwd_case(module: torch.nn.Module, inputs: tuple[torch.Tensor, ...], impls=("ref", "ext")):
    """(ref_fn, ext_fn[, dense_fn]): the backward alone (input + parameters) through a graph retained between calls;
    each path builds its own graph on its first call."""
    params = [p for p in module.parameters() if p.requires_grad]
    x = inputs[0].detach().clone().requires_grad_(True)
    rest = inputs[1:]
    graphs: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    def make(impl: str):
        def run():
            if impl not in graphs:
                with forced_impl(impl):
                    y = module(x, *rest)
                graphs[impl] = (y, torch.randn_like(y))
            y, grad = graphs[impl]
            with forced_impl(impl):
                return torch.autograd.grad(y, [x] + params, grad, retain_graph=True)
        return run

    return tuple(make(i) for i in impls)


GANIMATOR_SHAPES = {  # clip -> (BVH under ../shared/data/bvh/ganimator, channels per entity at the finest level)
    "salsa": ("Joe/Salsa-Dancing-6.bvh", 9),
    "crab": ("Crabnew/Crab-dance-long.bvh", 5),
}


def ganimator_cases() -> tuple[dict[str, tuple[Callable, Callable]], dict[str, dict]]:
    """GANimator's finest-level skeletal conv on the real skeletons (skipped when ../shared/data is absent)."""
    data = ROOT.parent / "shared" / "data" / "bvh" / "ganimator"
    cases: dict[str, tuple[Callable, Callable]] = {}
    info: dict[str, dict] = {}
    try:
        from modi.models.ganimator import config as gconfig
        from modi.models.ganimator.data import load_sequence, sequence_pyramid
        from modi.models.ganimator.networks import ganimator_neighbors
    except Exception as exc:  # noqa: BLE001
        print(f"compare: GANimator cases skipped ({type(exc).__name__}: {exc})", file=sys.stderr)
        return cases, info
    cfg = gconfig.preset("fast")
    for clip, (rel, ch) in GANIMATOR_SHAPES.items():
        if not (data / rel).is_file():
            print(f"compare: {data / rel} not found; ganimator_conv.{clip} cases skipped", file=sys.stderr)
            continue
        seq = load_sequence(data / rel, cfg)
        lengths, _ = sequence_pyramid([seq], cfg)
        nb = ganimator_neighbors(list(seq.skeleton.parents), list(seq.feet), cfg.neighbor_distance)
        e, t = len(nb), lengths[0][-1]
        torch.manual_seed(0)
        conv = SkeletalConv(ch, ch, nb, 5, padding_mode="reflect")
        x = torch.randn(1, ch, e, t)
        for kind in ("fwd", "fwd_bwd", "double"):
            key = f"ganimator_conv.{clip}.{kind}"
            cases[key] = _double_case(conv, (x,)) if kind == "double" else _case(conv, (x,), kind == "fwd_bwd")
            info[key] = {"input_shape": [1, ch, e, t], "kernel": 5, "padding": "reflect",
                         "pairs": int(sum(len(r) for r in nb))}
    return cases, info


def skeletal_cases(dtype: torch.dtype = torch.float32, impls: tuple[str, ...] = ("ref", "ext", "dense")
                   ) -> tuple[dict[str, tuple[Callable, Callable]], dict[str, dict], str]:
    """The MoDi cases, one function per path of ``impls`` (default: ref, ext and dense), modules and inputs in
    ``dtype`` (the same values for every dtype: one seed, then a cast)."""
    torch.manual_seed(0)
    neigh, pools, source = bandai_hierarchy()
    names = level_names(len(neigh))
    cases: dict[str, tuple[Callable, Callable]] = {}
    info: dict[str, dict] = {}
    for lv, (nb, name) in enumerate(zip(neigh, names)):
        c, t = MODI_LEVELS[min(lv, len(MODI_LEVELS) - 1)]
        e = len(nb)
        x = torch.randn(BATCH, c, e, t)
        w = torch.randn(BATCH, STYLE_DIM)
        conv = SkeletalConv(c, c, nb, 3)
        mod = ModulatedSkeletalConv(c, c, STYLE_DIM, nb, 3, mode="same", demodulate=True)
        defs = [("skeletal_conv", conv, (x,)), ("modulated_conv", mod, (x, w))]
        if lv + 1 < len(neigh):
            c2, t2 = MODI_LEVELS[min(lv + 1, len(MODI_LEVELS) - 1)]
            e2 = len(neigh[lv + 1])
            xc = torch.randn(BATCH, c2, e2, t2)
            defs += [
                ("scaler_up", SkeletalUpsample(c2, c, pools[lv], 3), (xc,)),
                ("scaler_down", SkeletalDownsample(c, c2, pools[lv], 3), (x,)),
                ("modulated_up", ModulatedSkeletalConv(c2, c, STYLE_DIM, pools[lv], 3, mode="up"), (xc, w)),
            ]
        for op, module, inputs in defs:
            if dtype != torch.float32:
                module = module.to(dtype)
                inputs = tuple(t.to(dtype) for t in inputs)
            kinds = ("fwd", "fwd_bwd")
            if lv == 0:
                kinds += ("double",) + (("bwd",) if op in ("skeletal_conv", "modulated_conv") else ())
            for kind in kinds:
                key = f"{op}.{name}.{kind}"  # dense: modi_ext.skeletal.dense (one shared conv, style/demod scales)
                if kind == "double":
                    cases[key] = _double_case(module, inputs, impls)
                elif kind == "bwd":
                    cases[key] = _bwd_case(module, inputs, impls)
                else:
                    cases[key] = _case(module, inputs, kind == "fwd_bwd", impls)
                info[key] = {"input_shape": list(inputs[0].shape), "entities_out": e, "channels_out": c,
                             "pairs": int(sum(len(r) for r in (nb if op in ("skeletal_conv", "modulated_conv")
                                                           else pools[lv])))}
    return cases, info, source


def fk_cases() -> dict[str, tuple[Callable, Callable]]:
    path = ROOT / "benchmarks" / "bench_fk.py"
    if not path.exists():
        print("compare: benchmarks/bench_fk.py not found; FK cases skipped", file=sys.stderr)
        return {}
    spec = importlib.util.spec_from_file_location("bench_fk", path)
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
        return dict(mod.fk_cases())
    except Exception as exc:  # noqa: BLE001 - report and keep the skeletal numbers
        print(f"compare: FK cases skipped ({type(exc).__name__}: {exc})", file=sys.stderr)
        return {}


def time_pair(ref: Callable, ext: Callable, reps: int, min_time: float,
              clock: Callable[[], float] = time.perf_counter) -> tuple[float, float, int]:
    """Interleaved medians (ms) of ref and ext; at least `reps` runs each and `min_time` s in total."""
    (rt, et), n = time_all((ref, ext), reps, min_time, clock)
    return rt, et, n


def time_all(fns, reps: int, min_time: float, clock: Callable[[], float] = time.perf_counter):
    """([median ms of each fn], runs): the fns interleaved (a, b, c, a, b, c, ...), >= `reps` runs each."""
    for _ in range(2):
        for fn in fns:
            fn()
    times: list[list[float]] = [[] for _ in fns]
    start = time.perf_counter()
    while len(times[0]) < reps or (time.perf_counter() - start < min_time and len(times[0]) < 200):
        for fn, acc in zip(fns, times):
            t0 = clock()
            fn()
            acc.append(clock() - t0)
    return [statistics.median(t) * 1e3 for t in times], len(times[0])


def time_threads(fn: Callable[[], object], threads: tuple[int, ...], reps: int,
                 clock: Callable[[], float] = time.perf_counter, block: int = 4) -> tuple[list[float], int]:
    """([median ms at each thread count], timed runs per count): fn at each thread count in turn, in blocks of
    `block` timed calls, each block after one untimed call (threads that slept while the other count ran wake up,
    caches refill), until `reps` timed calls per count; torch's thread count is restored afterwards."""
    before = torch.get_num_threads()
    times: list[list[float]] = [[] for _ in threads]
    try:
        while len(times[0]) < reps:
            for n, acc in zip(threads, times):
                torch.set_num_threads(n)
                fn()
                for _ in range(min(block, reps - len(acc))):
                    t0 = clock()
                    fn()
                    acc.append(clock() - t0)
    finally:
        torch.set_num_threads(before)
    return [statistics.median(t) * 1e3 for t in times], len(times[0])


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} logical CPUs, torch {torch.__version__}, {torch.get_num_threads()} threads"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, help="write results here")
    ap.add_argument("--reps", type=int, default=15, help="minimum timed runs per side")
    ap.add_argument("--min-time", type=float, default=1.0, help="minimum seconds per case")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--only", default=None, help="regex: run matching cases only")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="wall: elapsed time; cpu: process CPU time of all threads (robust on a loaded machine)")
    ap.add_argument("--thread-ab", type=int, default=0, metavar="N",
                    help="also time the extension at --threads and at N threads, alternated in blocks")
    ap.add_argument("--ab-reps", type=int, default=40, help="calls per thread count with --thread-ab")
    ap.add_argument("--busy", type=int, default=0, metavar="N",
                    help="keep N cores busy with spinning helper processes while timing (a loaded machine)")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                    help="cuda: the GPU cases of benchmarks/bench_cuda.py (batch 16 and 256, FK at B=4096)")
    ap.add_argument("--dtype", default="fp32,bf16",
                    help="with --device cuda: comma-separated dtypes among fp32, bf16, fp16 (default: fp32,bf16)")
    ap.add_argument("--bf16", action="store_true",
                    help="CPU: bf16 / fp32 time ratio per case (both on auto), --repeats at each --threads-list")
    ap.add_argument("--threads-list", default="1,2", help="with --bf16: thread counts (default 1,2)")
    ap.add_argument("--repeats", type=int, default=7, help="with --bf16: interleaved timings per thread count")
    args = ap.parse_args(argv)
    if not HAS_EXT:
        print("compare: the modi_ext C++ extension is not built; nothing to compare", file=sys.stderr)
        return 2
    if args.device == "cuda":
        return _main_cuda(args)
    if args.bf16:
        return _main_bf16(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    cases, info, source = skeletal_cases()
    more, more_info = ganimator_cases()
    cases.update(more)
    info.update(more_info)
    cases.update(fk_cases())
    pattern = re.compile(args.only) if args.only else None
    desc = machine()
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    omp_wait = modi_ext.omp_wait_policy()
    sgemm = Sgemm()
    print(f"# {desc}; skeletal hierarchy from {source}; batch {BATCH}, fp32; {args.clock} clock; OpenMP wait {omp_wait}")
    print(f"# sgemm (torch.mm 1024^3, {sgemm.threads} threads): {sgemm.gflops:.1f} GF/s; GF/s = counted FLOPs / median "
          f"time, frac = GF/s / sgemm")
    print(f"{'case':40s} {'ref ms':>10s} {'ext ms':>10s} {'speedup':>8s} {'GF/s':>7s} {'frac':>5s} {'ref fr':>6s} "
          f"{'dense ms':>10s} {'ref/dense':>9s} {'dense/ext':>9s} {'dns fr':>6s}")
    results: dict[str, dict] = {}
    busy = contextlib.ExitStack()
    busy_list = busy.enter_context(_EARLY_BUSY or busy_cores(args.busy))
    if args.busy:
        print(f"# {args.busy} core(s) kept busy by spinning helper processes (pinned to {busy_list})")
    for name, fns in cases.items():
        if pattern and not pattern.search(name):
            continue
        ms, n = time_all(fns, args.reps, args.min_time, clock)
        ref_ms, ext_ms = ms[0], ms[1]
        results[name] = {"ref_ms": round(ref_ms, 4), "ext_ms": round(ext_ms, 4),
                         "speedup": round(ref_ms / ext_ms, 3), "runs": n, "threads": torch.get_num_threads(),
                         "clock": args.clock, "busy": args.busy, "busy_cores": busy_list,
                         "omp_wait": omp_wait, "machine": desc, **info.get(name, {})}
        flops, _ = count_flops(fns[1])  # untimed, after the timing: the graph of a ``bwd`` case exists by now
        results[name]["flops"] = flops
        gf, frac = sgemm.rate(flops, ext_ms)
        roof = f" {gf:7.1f} {frac:5.2f} {sgemm.rate(flops, ref_ms)[1]:6.2f}"
        extra = ""
        if len(ms) > 2:  # the dense path (modi_ext.skeletal.dense) as a third side
            results[name].update(dense_ms=round(ms[2], 4), speedup_dense_vs_ref=round(ref_ms / ms[2], 3),
                                 speedup_ext_vs_dense=round(ms[2] / ext_ms, 3))
            extra = f" {ms[2]:10.3f} {ref_ms / ms[2]:8.2f}x {ms[2] / ext_ms:8.2f}x {sgemm.rate(flops, ms[2])[1]:6.2f}"
        if args.thread_ab:
            main_threads = torch.get_num_threads()
            (at_main, at_other), m = time_threads(fns[1], (main_threads, args.thread_ab), args.ab_reps, clock)
            results[name].update(ext_ms_threads={str(main_threads): round(at_main, 4),
                                                 str(args.thread_ab): round(at_other, 4)},
                                 ext_thread_ratio=round(at_main / at_other, 4), thread_ab_runs=m)
            extra += f"   ext {main_threads}t {at_main:.3f} / {args.thread_ab}t {at_other:.3f} ms"
        print(f"{name:40s} {ref_ms:10.3f} {ext_ms:10.3f} {ref_ms / ext_ms:7.2f}x{roof}{extra}", flush=True)
    busy.close()
    sgemm.remeasure()
    _roofline(results, sgemm)
    if any(n.startswith(("skeletal_conv.finest", "modulated_conv.finest")) for n in results):
        _blas_bound(results, sgemm, info)
    _backward_over_forward(results)
    _targets(results)
    write_json(args.json, results)
    return 0


def _blas_bound(results: dict, sgemm: Sgemm, info: dict) -> None:
    """torch's sgemm at the finest skeletal conv's own GEMM shapes (``roofline.blas_at_conv_shapes``), and each
    finest-level conv row's rate as a fraction of it (``ext_frac_blas_shape``): what a GEMM library reaches on the
    products the conv is made of."""
    neigh, _, _ = bandai_hierarchy()
    c, t = MODI_LEVELS[0]
    nb = neigh[0]
    shapes = dict(n_out=len(nb), nnz=sum(len(v) for v in nb), c_out=c, c_in=c, taps=3, batch=BATCH, frames=t)
    rates = blas_at_conv_shapes(**shapes)
    best = max(rates.values())
    print(f"# torch sgemm at the finest conv's GEMM shapes ({shapes['n_out']} x {c} x "
          f"{round(shapes['nnz'] / shapes['n_out']) * c * 3} x {BATCH * t}): "
          + ", ".join(f"{k} {v:.1f} GF/s ({v / sgemm.gflops:.2f} of sgemm)" for k, v in rates.items()))
    row: dict = {"shapes": shapes}
    for k, v in rates.items():
        row[f"{k}_gflops"], row[f"{k}_frac_sgemm"] = round(v, 2), round(v / sgemm.gflops, 4)
    results["blas_at_conv_shapes.finest"] = {**row, **sgemm.describe()}
    for name, r in results.items():
        if name.startswith(("skeletal_conv.finest", "modulated_conv.finest")) and "ext_gflops" in r:
            r["ext_frac_blas_shape"] = round(r["ext_gflops"] / best, 4)
            print(f"#   {name:36s} ext {r['ext_gflops']:6.1f} GF/s = {r['ext_frac_blas_shape']:.2f} "
                  "of the best of those")


def _roofline(results: dict, sgemm: Sgemm) -> None:
    """GF/s and fraction of sgemm of every timed path of every row, against this run's sgemm reference."""
    print(f"# sgemm samples (start, end): {', '.join(f'{g:.1f}' for g in sgemm.samples)} GF/s; the JSON's fractions "
          f"use {sgemm.gflops:.1f}")
    for r in results.values():
        for side in ("ref", "ext", "dense"):
            if f"{side}_ms" in r and "flops" in r:
                gf, frac = sgemm.rate(r["flops"], r[f"{side}_ms"])
                r[f"{side}_gflops"], r[f"{side}_frac_sgemm"] = round(gf, 3), round(frac, 4)
        r.update(sgemm.describe())


def _backward_over_forward(results: dict) -> None:
    """For each ``X.fwd_bwd`` with a matching ``X.fwd``: (fwd_bwd - fwd) / fwd on each path, stored and printed."""
    for name, r in results.items():
        if not name.endswith(".fwd_bwd") or name[:-len("fwd_bwd")] + "fwd" not in results:
            continue
        f = results[name[:-len("fwd_bwd")] + "fwd"]
        r["ref_bwd_over_fwd"] = round((r["ref_ms"] - f["ref_ms"]) / f["ref_ms"], 3)
        r["ext_bwd_over_fwd"] = round((r["ext_ms"] - f["ext_ms"]) / f["ext_ms"], 3)
        if name.startswith("ganimator_conv."):
            print(f"{name}: backward / forward  ref {r['ref_bwd_over_fwd']:.2f}  ext {r['ext_bwd_over_fwd']:.2f}")


TARGET_CASE = "modulated_conv.finest.fwd_bwd"  # the targets: dense >= 5x the grouped reference, ext >= 3x dense


def _targets(results: dict) -> None:
    r = results.get(TARGET_CASE)
    if r is None or "dense_ms" not in r:
        return
    r["target_dense_vs_ref"], r["target_ext_vs_dense"] = 5.0, 3.0
    r["targets_met"] = bool(r["speedup_dense_vs_ref"] >= 5.0 and r["speedup_ext_vs_dense"] >= 3.0)
    print(f"{TARGET_CASE}: dense is {r['speedup_dense_vs_ref']:.2f}x faster than the grouped reference "
          f"(target 5x), ext {r['speedup_ext_vs_dense']:.2f}x faster than dense (target 3x)")


def write_json(path: Path | None, results: dict) -> None:
    if not path:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)  # atomic: an interrupted run never leaves half a file
    print(f"wrote {path}")


BF16_CASES = r"^(skeletal_conv|modulated_conv)\.finest\.fwd_bwd$"


def _main_bf16(args: argparse.Namespace) -> int:
    """Each case in bf16 against fp32, both on ``auto``, interleaved; the path the bf16 calls took is reported."""
    pattern = re.compile(args.only or BF16_CASES)
    fp32, info, source = skeletal_cases(torch.float32, ("auto",))
    bf16, _, _ = skeletal_cases(torch.bfloat16, ("auto",))
    names = [n for n in fp32 if pattern.search(n)]
    from modi_ext.runtime.dispatch import cpu_bf16_path, dispatch_report

    path = cpu_bf16_path()["summary"]

    def ran_on() -> str:
        """The paths this process's bf16 skeletal calls took so far (every call is counted, warm-ups included)."""
        rows = [r for r in dispatch_report() if r["kind"] == "path" and r["dtype"] == "bfloat16"
                and r["op"].startswith("skeletal")]
        return ", ".join(sorted({f"{r['op']}: {r['path']}" for r in rows})) or "-"
    print(f"# {machine()}; skeletal hierarchy from {source}; batch {BATCH}; {path}; fp32 on auto; "
          f"{args.repeats} repeats of >= {args.reps} interleaved runs (>= {args.min_time} s) per thread count")
    print(f"{'case':34s} {'thr':>3s} {'fp32 ms':>9s} {'bf16 ms':>9s} {'bf16/fp32 median [min, max]':>30s}")
    results: dict[str, dict] = {}
    before = torch.get_num_threads()
    try:
        for threads in (int(t) for t in args.threads_list.split(",")):
            torch.set_num_threads(threads)
            for name in names:
                t32, t16, ratios = [], [], []
                for _ in range(args.repeats):
                    (a, b), _n = time_all((fp32[name][0], bf16[name][0]), args.reps, args.min_time)
                    t32.append(a)
                    t16.append(b)
                    ratios.append(b / a)
                row = {"fp32_ms": _spread(t32), "bf16_ms": _spread(t16), "bf16_over_fp32": _spread(ratios),
                       "threads": threads, "repeats": args.repeats, "bf16_path": path, "bf16_ran_on": ran_on(),
                       "machine": machine(),
                       **info.get(name, {})}
                results[f"{name}.{threads}t"] = row
                r = row["bf16_over_fp32"]
                print(f"{name:34s} {threads:3d} {row['fp32_ms']['median']:9.3f} {row['bf16_ms']['median']:9.3f} "
                      f"{r['median']:12.3f} [{r['min']:.3f}, {r['max']:.3f}]   bf16 ran on {row['bf16_ran_on']}",
                      flush=True)
    finally:
        torch.set_num_threads(before)
    write_json(args.json, results)
    return 0


def _spread(values: list[float]) -> dict:
    return {"median": round(statistics.median(values), 4), "min": round(min(values), 4),
            "max": round(max(values), 4), "n": len(values)}


def _main_cuda(args: argparse.Namespace) -> int:
    """GPU comparison: benchmarks/bench_cuda.py (timed with CUDA events), given this command's options."""
    spec = importlib.util.spec_from_file_location("bench_cuda", Path(__file__).with_name("bench_cuda.py"))
    bench_cuda = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench_cuda)
    argv = ["--dtype", args.dtype, "--reps", str(max(args.reps, 5))]
    argv += ["--json", str(args.json)] if args.json else []
    argv += ["--only", args.only] if args.only else []
    return bench_cuda.main(argv)


if __name__ == "__main__":
    raise SystemExit(main())
