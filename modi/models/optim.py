"""What both systems' trainers share about optimisers and the loop's runtime (and the process's allocator)."""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import sys
from typing import Iterable, Iterator

import torch


def fused_adam(params: Iterable[torch.nn.Parameter], lr: float, betas: tuple[float, float], *,
               capturable: bool = False) -> torch.optim.Adam:
    """Adam with torch's fused kernel where it has one (CPU, CUDA), else the per-tensor loop.

    ``capturable`` (CUDA only) keeps every step's arithmetic on the device, so a CUDA graph may hold the step; a
    checkpoint's saved flag is replaced on load by :func:`set_capturable`. The fused kernel skips a step whose
    ``found_inf`` (a 0-d float tensor set as ``optimizer.found_inf``, 1.0 = skip) is set, on the device.

    The loop over a model's tensors is small work in many launches: ~5% of a MoDi CPU step over G's and D's ~120
    tensors (``benchmarks/profile_step.py``), and 3x the fused step for GANimator's small discriminators, stepped
    7-14 times an iteration. Same algorithm (within float rounding, ~1e-7 relative); a checkpoint keeps the setting
    it was saved with (``fused`` is part of the saved param groups)."""
    params = list(params)
    fused = bool(params) and all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
    return torch.optim.Adam(params, lr=lr, betas=betas, fused=fused or None, capturable=bool(capturable))


def set_capturable(opt: torch.optim.Optimizer, flag: bool) -> None:
    """Set every param group's ``capturable`` to ``flag`` (after ``load_state_dict``: a checkpoint's saved flag,
    written on another device, must not decide this run's), with the step counters where it then needs them (on
    the parameters' device, float32)."""
    for group in opt.param_groups:
        group["capturable"] = bool(flag)
        if not (flag or group.get("fused")):
            continue
        for p in group["params"]:
            st = opt.state.get(p)
            step = st.get("step") if st else None
            if isinstance(step, torch.Tensor) and (step.device != p.device or step.dtype != torch.float32):
                st["step"] = step.to(device=p.device, dtype=torch.float32)


def fused_groups(opt: torch.optim.Optimizer) -> bool:
    """Whether every param group runs the fused kernel (the one that honours ``found_inf``)."""
    return bool(opt.param_groups) and all(g.get("fused") for g in opt.param_groups)


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Leave the objects that exist when a training loop starts out of Python's cyclic-GC passes until it ends.

    By then ~300k long-lived objects exist (torch's and modi's modules, the data, the models); every full collection,
    which the autograd graphs of a few hundred steps trigger, re-walks them all, a cost a GANimator iteration
    shows (docs/results.md). Frozen, they are skipped, and given back to the collector afterwards. A freeze the
    caller already holds is left in place."""
    mine = gc.get_freeze_count() == 0
    if mine:
        gc.freeze()
    try:
        yield
    finally:
        if mine:
            gc.unfreeze()


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h>
_MMAP_THRESHOLD = 32 << 20  # glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit)
_TRIM_THRESHOLD = 1 << 30
_retained: list[bool] = []


def retain_freed_memory() -> bool:
    """Have glibc's malloc keep freed blocks of up to 32 MB for reuse instead of handing them back to the kernel.

    A CPU step allocates and frees activations of megabytes many times over. By default glibc maps the larger of
    them fresh (``mmap``) or trims its heap back once 2x the last such size lies free at its top, so the next
    allocation of that size page-faults its memory in again, zeroed by the kernel, a sizeable part of sampling's
    time (docs/results.md). With both thresholds set, such blocks stay in the heap; the process keeps its peak
    footprint instead of returning to it. Setting only the trim threshold would be far worse: it switches off
    glibc's adaptive mmap threshold, and every block over 128 KB would be mapped anew. Process-wide, once; the ``modi`` command calls it at
    start. Returns whether it applied (glibc on Linux only: elsewhere, a no-op)."""
    if _retained:
        return _retained[0]
    ok = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            ok = bool(libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and \
                bool(libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))
        except (OSError, AttributeError):  # not glibc (musl has no mallopt)
            ok = False
    _retained.append(ok)
    return ok
