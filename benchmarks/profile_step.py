"""Where the time of a MoDi training step goes: a few iterations under ``torch.profiler`` on the CPU.

    python benchmarks/profile_step.py --preset paper --batch 16 --iters 16 [--threads 2] [--json out.json]
    python benchmarks/profile_step.py --preset small --iters 4 --data procedural

Rows (ms per step and % of the step's wall time):

* ``modi_ext kernels``   self time of the ops registered by modi_ext (``modi_ext::*``: the skeletal, demodulation and
                         FK kernels and the partial backward ops of a double backward);
* ``torch: <op>``        the other torch ops with the largest self time (``--top``), then the rest of them;
* ``Adam``, ``EMA``, ``data``  everything inside the optimiser steps (``Optimizer.step#Adam.step``), the EMA update
                         (``modi.models.modi.training._accumulate``) and the real-batch draw (``Trainer._real_batch``);
* ``Python + autograd``  the step's wall time minus all of the above: interpreter, autograd engine and its nodes, the
                         profiler's own cost per op (so it reads high under the profiler; ``wall_unprofiled_ms`` is the
                         same loop timed without it);
* ``logging + checkpoint (amortised)``  one ``log.jsonl`` line and one checkpoint, timed apart, divided by
                         ``log_every`` and ``ckpt_every`` (what ``modi train`` pays per step for them).

The profiled steps start on a lazy-regularisation boundary, so 16 iterations of the paper preset hold one R1 step and
four path-length steps in their true proportions. Nothing here is a test: a machine's speed is never asserted.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(1 + len([p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]), str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import modi_ext  # noqa: E402,F401  (before torch, as the modi command: the OpenMP spin)

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile, record_function  # noqa: E402

from compare import machine  # noqa: E402  (benchmarks/compare.py)
from modi.models.modi import training  # noqa: E402
from modi.models.modi.config import make_config  # noqa: E402

REGIONS = {"modi::data": "data", "modi::ema": "EMA"}
ADAM_PREFIX = "Optimizer.step#"


def _wrap(fn, label: str):
    def run(*a, **k):
        with record_function(label):
            return fn(*a, **k)
    return run


def _region_of(ev) -> str | None:
    """The labelled region an event runs in (itself included), or None."""
    while ev is not None:
        if ev.name in REGIONS:
            return REGIONS[ev.name]
        if ev.name.startswith(ADAM_PREFIX):
            return "Adam"
        ev = ev.cpu_parent
    return None


def breakdown(events, wall_ms: float, steps: int, top: int = 6,
              kernel_ops: dict[str, float] | None = None) -> list[dict]:
    """Rows ``{"row", "ms_per_step", "percent"}`` from the profiler's events; they add up to the wall time.
    ``kernel_ops``, when given, receives the kernel row split by op (ms per step)."""
    region_ms: dict[str, float] = defaultdict(float)
    kernels = 0.0
    by_kernel: dict[str, float] = defaultdict(float)
    ops: dict[str, float] = defaultdict(float)
    for ev in events:
        region = _region_of(ev)
        if region is not None:
            if ev.name in REGIONS or ev.name.startswith(ADAM_PREFIX):
                top_level = _region_of(ev.cpu_parent) is None if ev.cpu_parent is not None else True
                if top_level:
                    region_ms[region] += ev.cpu_time_total / 1e3
            continue
        if ev.name.startswith("modi_ext::"):
            kernels += ev.self_cpu_time_total / 1e3
            by_kernel[ev.name] += ev.self_cpu_time_total / 1e3
        elif ev.name.startswith(("aten::", "prim::")):
            ops[ev.name] += ev.self_cpu_time_total / 1e3
    rows = [("modi_ext kernels", kernels)]
    if kernel_ops is not None:
        kernel_ops.update({k: round(v / steps, 3) for k, v in sorted(by_kernel.items(), key=lambda kv: -kv[1])})
    ranked = sorted(ops.items(), key=lambda kv: -kv[1])
    rows += [(f"torch: {name}", ms) for name, ms in ranked[:top]]
    rows.append(("torch: other ops", sum(ms for _, ms in ranked[top:])))
    rows += [(name, region_ms.get(name, 0.0)) for name in ("Adam", "EMA", "data")]
    counted = sum(ms for _, ms in rows)
    rows.append(("Python + autograd", max(0.0, wall_ms - counted)))
    return [{"row": name, "ms_per_step": round(ms / steps, 3), "percent": round(100.0 * ms / wall_ms, 2)}
            for name, ms in rows]


def amortised_io(tr, cfg, work: Path) -> dict[str, float]:
    """ms per step of logging and checkpointing, at the config's ``log_every`` / ``ckpt_every``."""
    tc = cfg.train
    losses = dict(tr.last_losses or {"d": 0.0, "g": 0.0})
    t = time.perf_counter()
    tr._log_scalars(losses)
    log_ms = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    tr.save_checkpoint(work / "profile_ckpt.pt")
    ckpt_ms = (time.perf_counter() - t) * 1e3
    return {"log_ms": log_ms, "ckpt_ms": ckpt_ms,
            "per_step_ms": log_ms / max(1, tc.log_every) + (ckpt_ms / tc.ckpt_every if tc.ckpt_every else 0.0)}


def profile_modi(preset: str, batch: int, iters: int, data_dir: str | None, warmup: int = 1, top: int = 6,
                 overrides: dict | None = None) -> dict:
    """Profile ``iters`` training steps (after ``warmup``) and return the table and its context."""
    if data_dir is None:
        bandai = ROOT.parent / "shared" / "data" / "bvh" / "bandai-namco-1"
        data_dir = str(bandai) if bandai.is_dir() else "procedural"
    cfg = make_config(preset, **{"train.batch": batch, **(overrides or {})})
    work = Path(tempfile.mkdtemp(prefix="modi_profile_"))
    data = training.prepare_data(data_dir, cfg, work_dir=work)
    torch.manual_seed(0)
    tr = training.Trainer(cfg, data, work / "run", progress=False, tensorboard=False, write_samples=False,
                          log=lambda m: None)
    tr._real_batch = _wrap(tr._real_batch, "modi::data")
    accumulate = training._accumulate
    training._accumulate = _wrap(accumulate, "modi::ema")
    try:
        for _ in range(warmup):
            tr.train_step()
        cycle = max(cfg.train.d_reg_every, cfg.train.g_reg_every)
        tr.step = -(-tr.step // cycle) * cycle  # the kinds of step in their proportions (step counter only)
        start = tr.step
        t = time.perf_counter()
        for _ in range(iters):
            tr.train_step()
        unprofiled_ms = (time.perf_counter() - t) * 1e3 / iters
        tr.step = start
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            t = time.perf_counter()
            for _ in range(iters):
                tr.train_step()
            wall_ms = (time.perf_counter() - t) * 1e3
    finally:
        training._accumulate = accumulate
    kernel_ops: dict[str, float] = {}
    rows = breakdown(prof.events(), wall_ms, iters, top, kernel_ops)
    io = amortised_io(tr, cfg, work)
    step_ms = wall_ms / iters
    rows.append({"row": "logging + checkpoint (amortised)", "ms_per_step": round(io["per_step_ms"], 3),
                 "percent": round(100.0 * io["per_step_ms"] / step_ms, 2)})
    return {"machine": machine(), "preset": preset, "batch": batch, "iters": iters, "data": str(data_dir),
            "threads": torch.get_num_threads(), "wall_ms_per_step": round(step_ms, 3),
            "wall_unprofiled_ms_per_step": round(unprofiled_ms, 3),
            "log_ms": round(io["log_ms"], 3), "ckpt_ms": round(io["ckpt_ms"], 3),
            "log_every": cfg.train.log_every, "ckpt_every": cfg.train.ckpt_every, "rows": rows,
            "kernel_ops_ms_per_step": kernel_ops}


def print_table(res: dict) -> None:
    print(f"# {res['machine']}")
    print(f"# MoDi preset {res['preset']}, batch {res['batch']}, {res['iters']} steps, data {res['data']}: "
          f"{res['wall_ms_per_step']:.1f} ms/step profiled, {res['wall_unprofiled_ms_per_step']:.1f} without the "
          f"profiler")
    print(f"{'row':42s} {'ms/step':>9s} {'% step':>7s}")
    for r in res["rows"]:
        print(f"{r['row']:42s} {r['ms_per_step']:9.2f} {r['percent']:6.1f}%")
        if r["row"] == "modi_ext kernels":
            for name, ms in res.get("kernel_ops_ms_per_step", {}).items():
                print(f"  {name:40s} {ms:9.2f} {100.0 * ms / res['wall_ms_per_step']:6.1f}%")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="paper", choices=["paper", "small"])
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--iters", type=int, default=16, help="profiled steps (16: one lazy-regularisation cycle)")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--data", default=None, help="BVH folder or 'procedural' (default: ../shared/data Bandai-Namco-1)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--top", type=int, default=6, help="torch ops listed by name")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    res = profile_modi(args.preset, args.batch, args.iters, args.data, args.warmup, args.top)
    print_table(res)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
