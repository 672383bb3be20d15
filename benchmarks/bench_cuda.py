"""CUDA benchmarks: the reference (MoDi's grouped per-sample form), the dense form (one shared cuDNN conv on the
masked weight, style/demodulation as scales: ``modi_ext.skeletal.dense``) and the modi_ext CUDA kernels.

``cuda_cases(dtype)`` returns ``{case: (ref_fn, ext_fn[, dense_fn])}`` of zero-argument callables for ``benchmarks/compare.py
--device cuda``; every callable ends with ``torch.cuda.synchronize()`` so a wall-clock timer measures the GPU work.
``cuda_case_info(dtype)`` gives the shapes behind each case.

Cases, on MoDi's generator hierarchy for the Bandai-Namco 22-joint skeleton (channels x frames of MoDi Table 3, the
hierarchy from ``benchmarks/compare.py``), batch 16 and 256, float32 (``fp32``) or bfloat16 (``bf16``):

  skeletal_conv.<level>.b<B>.<dt>.{fwd,fwd_bwd}    in-place skeletal conv (kernel 3, zero padding, bias)
  modulated_conv.<level>.b<B>.<dt>.{fwd,fwd_bwd}   the same with a per-sample style and demodulation
  scaler_up.<level>.b<B>.<dt>.{fwd,fwd_bwd}        coarse -> fine scaler into <level> (transposed conv + blur, bias)
  scaler_down.<level>.b<B>.<dt>.{fwd,fwd_bwd}      fine -> coarse scaler from <level> (bias)
  modulated_up.<level>.b<B>.<dt>.{fwd,fwd_bwd}     the up-scaler with style and demodulation
  fk.b4096.<dt>.{fwd,fwd_bwd}                      forward kinematics, B=4096 x T=64 samples, 22 joints

The cases call the ops directly (``modi_ext.skeletal.reference.*`` vs ``torch.ops.modi_ext.*``, the demodulation scale
included on the extension side) rather than through the layers, so bfloat16 runs too and both sides do the same
work; ``fwd_bwd`` differentiates w.r.t. the input, weight, bias and style with a fixed upstream gradient (FK: w.r.t.
rotations and root translation).  The reference runs with torch's default backend flags (cuDNN may use TF32 for
float32 convolutions).

    python benchmarks/bench_cuda.py --dtype fp32 --json benchmarks/results/cuda_fp32.json   # stand-alone
"""
from __future__ import annotations

import argparse
import datetime
import importlib.util
import re
import statistics
import sys
from pathlib import Path
from typing import Callable

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from modi_ext.skeletal import dense, ops, reference  # noqa: E402
from modi_ext.fk import fk_reference  # noqa: E402
from modi_ext.csr import csr_from_lists  # noqa: E402

BATCHES = (16, 256)
FK_B, FK_T = 4096, 64
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}

Fn = Callable[[], object]


def _compare_module():
    """benchmarks/compare.py, loaded by path (it owns the MoDi level table and the Bandai hierarchy)."""
    name = "_modi_bench_compare"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / "compare.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _tag(dtype: torch.dtype) -> str:
    for k, v in DTYPES.items():
        if v == dtype:
            return k
    raise ValueError(f"dtype must be one of {list(DTYPES.values())}, got {dtype}")


def _synced(fn: Callable[[], object]) -> Fn:
    def run():
        out = fn()
        torch.cuda.synchronize()
        return out
    return run


def _pair(ref: Callable[..., torch.Tensor], ext: Callable[..., torch.Tensor], leaves: list[torch.Tensor],
          bwd: bool, dense_fn: Callable[..., torch.Tensor] | None = None) -> tuple[Fn, ...]:
    """(ref_fn, ext_fn[, dense_fn]): forward under no_grad, or forward + grads of every leaf (fixed upstream grad)."""
    grad: list[torch.Tensor] = []

    def make(fn):
        def body():
            if not bwd:
                with torch.no_grad():
                    return fn(*leaves)
            y = fn(*leaves)
            if not grad:
                grad.append(torch.randn_like(y))
            return torch.autograd.grad(y, leaves, grad[0])
        return _synced(body)

    return (make(ref), make(ext)) + ((make(dense_fn),) if dense_fn is not None else ())


def _skeletal_defs(dtype: torch.dtype, batch: int, device: str):
    """Yield (op, level name, ref, ext, leaves, info, dense) for every MoDi level at one batch size."""
    cmp = _compare_module()
    neigh, pools, _ = cmp.bandai_hierarchy()
    names = cmp.level_names(len(neigh))
    levels = cmp.MODI_LEVELS
    g = torch.Generator(device="cpu").manual_seed(0)

    def rnd(*shape, scale=1.0):
        return (torch.randn(*shape, generator=g) * scale).to(device=device, dtype=dtype)

    for lv, (nb, name) in enumerate(zip(neigh, names)):
        c, t = levels[min(lv, len(levels) - 1)]
        e = len(nb)
        topo = csr_from_lists(nb, n_in=e)
        idx, off = topo.index.to(device), topo.offsets.to(device)
        nnz = idx.numel()
        x = rnd(batch, c, e, t)
        w = rnd(c, nnz, c, 3, scale=(3 * 3 * c) ** -0.5)
        b = rnd(c)
        s = 1 + 0.1 * rnd(batch, c)
        info = dict(batch=batch, input_shape=[batch, c, e, t], pairs=nnz)
        yield ("skeletal_conv", name,
               lambda x_, w_, b_, i=idx, o=off: reference.skeletal_conv(x_, w_, b_, i, o, None, False, "zeros"),
               lambda x_, w_, b_, i=idx, o=off: torch.ops.modi_ext.skeletal_conv(x_, w_, b_, i, o, None, None,
                                                                                 "zeros"),
               [x, w, b], info,
               lambda x_, w_, b_, i=idx, o=off: dense.skeletal_conv(x_, w_, b_, i, o, None, False, "zeros"))

        def ref_mod(x_, w_, s_, i=idx, o=off):
            return reference.skeletal_conv(x_, w_, None, i, o, s_, True, "zeros")

        def ext_mod(x_, w_, s_, i=idx, o=off, n=e):
            d = ops.demod_scale(w_, i, o, s_, False, n, x_.shape[0])
            return torch.ops.modi_ext.skeletal_conv(x_, w_, None, i, o, s_, d, "zeros")

        yield ("modulated_conv", name, ref_mod, ext_mod, [x, w, s], info,
               lambda x_, w_, s_, i=idx, o=off: dense.skeletal_conv(x_, w_, None, i, o, s_, True, "zeros"))
        if lv + 1 >= len(neigh):
            continue
        c2, t2 = levels[min(lv + 1, len(levels) - 1)]
        e2 = len(neigh[lv + 1])
        ptopo = csr_from_lists(pools[lv], n_in=e)
        pidx, poff = ptopo.index.to(device), ptopo.offsets.to(device)
        pnnz = pidx.numel()
        xc = rnd(batch, c2, e2, t2)
        wu = rnd(c2, pnnz, c, 3, scale=(3 * c2) ** -0.5)
        wd = rnd(c2, pnnz, c, 3, scale=(3 * 3 * c) ** -0.5)
        bu, bd = rnd(c), rnd(c2)
        su = 1 + 0.1 * rnd(batch, c2)
        up_info = dict(batch=batch, input_shape=[batch, c2, e2, t2], pairs=pnnz)
        yield ("scaler_up", name,
               lambda x_, w_, b_, i=pidx, o=poff, n=e: reference.skeletal_up(x_, w_, b_, i, o, n, None, False,
                                                                             "zeros"),
               lambda x_, w_, b_, i=pidx, o=poff, n=e: torch.ops.modi_ext.skeletal_up(x_, w_, b_, i, o, n, None,
                                                                                      None, "zeros"),
               [xc, wu, bu], up_info,
               lambda x_, w_, b_, i=pidx, o=poff, n=e: dense.skeletal_up(x_, w_, b_, i, o, n, None, False, "zeros"))
        yield ("scaler_down", name,
               lambda x_, w_, b_, i=pidx, o=poff: reference.skeletal_down(x_, w_, b_, i, o, None, False, "zeros"),
               lambda x_, w_, b_, i=pidx, o=poff: torch.ops.modi_ext.skeletal_down(x_, w_, b_, i, o, None, None,
                                                                                   "zeros"),
               [x, wd, bd], dict(batch=batch, input_shape=[batch, c, e, t], pairs=pnnz),
               lambda x_, w_, b_, i=pidx, o=poff: dense.skeletal_down(x_, w_, b_, i, o, None, False, "zeros"))

        def ref_up(x_, w_, s_, i=pidx, o=poff, n=e):
            return reference.skeletal_up(x_, w_, None, i, o, n, s_, True, "zeros")

        def ext_up(x_, w_, s_, i=pidx, o=poff, n=e):
            d = ops.demod_scale(w_, i, o, s_, True, n, x_.shape[0])
            return torch.ops.modi_ext.skeletal_up(x_, w_, None, i, o, n, s_, d, "zeros")

        yield ("modulated_up", name, ref_up, ext_up, [xc, wu, su], up_info,
               lambda x_, w_, s_, i=pidx, o=poff, n=e: dense.skeletal_up(x_, w_, None, i, o, n, s_, True, "zeros"))


def _fk_pairs(dtype: torch.dtype, device: str, tag: str) -> dict[str, tuple[Fn, Fn]]:
    cmp = _compare_module()
    parents = list(cmp.BANDAI_PARENTS)
    J = len(parents)
    g = torch.Generator(device="cpu").manual_seed(0)
    q = torch.randn(FK_B, FK_T, J, 4, generator=g)
    q = (q / q.norm(dim=-1, keepdim=True)).to(device=device, dtype=dtype)
    off = (torch.randn(J, 3, generator=g) * 0.2).to(device=device, dtype=dtype)
    root = torch.randn(FK_B, FK_T, 3, generator=g).to(device=device, dtype=dtype)
    qg, rg = q.clone().requires_grad_(), root.clone().requires_grad_()
    grad = torch.randn(FK_B, FK_T, J, 3, generator=g).to(device=device, dtype=dtype)

    def ref(a, r):
        return fk_reference(a, off, parents, r)

    def ext(a, r):
        return torch.ops.modi_ext.fk(a, off, parents, r)[0]

    def fwd(fn):
        def body():
            with torch.no_grad():
                return fn(q, root)
        return _synced(body)

    def fwd_bwd(fn):
        def body():
            return torch.autograd.grad(fn(qg, rg), (qg, rg), grad)
        return _synced(body)

    return {f"fk.b{FK_B}.{tag}.fwd_bwd": (fwd_bwd(ref), fwd_bwd(ext)),
            f"fk.b{FK_B}.{tag}.fwd": (fwd(ref), fwd(ext))}


def _build(dtype: torch.dtype) -> tuple[dict[str, tuple[Fn, Fn]], dict[str, dict]]:
    if not torch.cuda.is_available():
        raise RuntimeError("bench_cuda: no CUDA device")
    if not torch._C._dispatch_has_kernel_for_dispatch_key("modi_ext::skeletal_conv", "CUDA"):
        raise RuntimeError("bench_cuda: modi_ext was built without its CUDA kernels")
    tag = _tag(dtype)
    cases: dict[str, tuple[Fn, Fn]] = {}
    info: dict[str, dict] = {}
    for batch in BATCHES:
        for op, level, ref, ext, leaves, meta, dense_fn in _skeletal_defs(dtype, batch, "cuda"):
            for bwd in (False, True):
                key = f"{op}.{level}.b{batch}.{tag}.{'fwd_bwd' if bwd else 'fwd'}"
                leaves_i = [t.detach().clone().requires_grad_(bwd) for t in leaves]
                cases[key] = _pair(ref, ext, leaves_i, bwd, dense_fn)
                info[key] = {**meta, "dtype": tag}
    for key, pair in _fk_pairs(dtype, "cuda", tag).items():
        cases[key] = pair
        info[key] = {"batch": FK_B, "frames": FK_T, "joints": 22, "dtype": tag}
    return cases, info


def cuda_cases(dtype: torch.dtype = torch.float32) -> dict[str, tuple[Fn, Fn]]:
    """``{case: (ref_fn, ext_fn)}`` for every MoDi level (batch 16 and 256) and FK (B=4096), in ``dtype``."""
    return _build(dtype)[0]


def cuda_case_info(dtype: torch.dtype = torch.float32) -> dict[str, dict]:
    """Shapes behind each case of ``cuda_cases(dtype)`` (input shape, batch, pairs, dtype)."""
    return _build(dtype)[1]


def device_description() -> str:
    p = torch.cuda.get_device_properties(torch.cuda.current_device())
    return (f"{p.name} ({p.multi_processor_count} SMs, {p.total_memory / 2**30:.0f} GiB), torch {torch.__version__}, "
            f"CUDA {torch.version.cuda}, {datetime.date.today().isoformat()}")


def time_pair_cuda(ref: Fn, ext: Fn, reps: int = 20, warmup: int = 3) -> tuple[float, float]:
    """Interleaved medians (ms) with CUDA events (the callables synchronise at their end)."""
    rt, et = time_cuda((ref, ext), reps, warmup)
    return rt, et


def time_cuda(fns, reps: int = 20, warmup: int = 3) -> list[float]:
    """Interleaved medians (ms) of every callable, with CUDA events."""
    for _ in range(warmup):
        for fn in fns:
            fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(reps):
        for fn, acc in zip(fns, times):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            acc.append(start.elapsed_time(end))
    return [statistics.median(t) for t in times]


def main(argv: list[str] | None = None) -> int:
    """Also ``benchmarks/compare.py --device cuda``, which forwards its options here."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dtype", default="fp32,bf16",
                    help=f"comma-separated input dtypes among {', '.join(DTYPES)} (default: fp32,bf16)")
    ap.add_argument("--json", type=Path, help="write {case: {ref_ms, ext_ms, speedup, ...}} here")
    ap.add_argument("--reps", type=int, default=20, help="timed runs per side (default: 20)")
    ap.add_argument("--only", default=None, help="regex: run matching cases only")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("bench_cuda: torch sees no CUDA device", file=sys.stderr)
        return 2
    names = [d.strip() for d in args.dtype.split(",") if d.strip()]
    if not names or any(d not in DTYPES for d in names):
        print(f"bench_cuda: --dtype must list some of {', '.join(DTYPES)}, got {args.dtype!r}", file=sys.stderr)
        return 2
    desc = device_description()
    pattern = re.compile(args.only) if args.only else None
    print(f"# {desc}")
    print(f"{'case':48s} {'ref ms':>10s} {'ext ms':>10s} {'speedup':>8s} {'dense ms':>10s} {'dense/ext':>9s}")
    results: dict[str, dict] = {}
    for name in names:
        cases, info = _build(DTYPES[name])
        for case, fns in cases.items():
            if pattern and not pattern.search(case):
                continue
            ms = time_cuda(fns, args.reps)
            ref_ms, ext_ms = ms[0], ms[1]
            results[case] = {"ref_ms": round(ref_ms, 4), "ext_ms": round(ext_ms, 4),
                             "speedup": round(ref_ms / ext_ms, 3), "runs": args.reps, "machine": desc, **info[case]}
            extra = ""
            if len(ms) > 2:
                results[case].update(dense_ms=round(ms[2], 4), speedup_dense_vs_ref=round(ref_ms / ms[2], 3),
                                     speedup_ext_vs_dense=round(ms[2] / ext_ms, 3))
                extra = f" {ms[2]:10.3f} {ms[2] / ext_ms:8.2f}x"
            print(f"{case:48s} {ref_ms:10.3f} {ext_ms:10.3f} {ref_ms / ext_ms:7.2f}x{extra}", flush=True)
    _compare_module().write_json(args.json, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
