"""Seconds per MoDi training iteration and generated motions per second, dense reference vs modi_ext, in one process.

    python benchmarks/train_step.py --json benchmarks/results/train_step_cpu.json            # paper size, batch 16
    python benchmarks/train_step.py --preset small --iters 6 --gen-batch 256 --threads 1
    python benchmarks/train_step.py --device cuda --json benchmarks/results/train_step_cuda.json

Two trainers with identical weights and seeds are built on the same data (Bandai-Namco-1 from ../shared/data when
present, else the built-in procedural clips); they advance in interleaved chunks (ref, ext, ref, ext, ...) so machine
load hits both alike, and the median seconds per iteration of each side is reported. A chunk is ``--chunk`` full
iterations (G step, D step, and the lazy R1 / path-length regularisers at their paper intervals, so a chunk of 16
contains one R1 step and four path-length steps). Generation times the EMA generator's forward pass, z -> normalised
motion tensor, at ``--gen-batch`` under ``no_grad``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from compare import forced_impl, machine, write_json  # noqa: E402  (benchmarks/compare.py)
from modi_ext import HAS_EXT  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="BVH folder (default: ../shared/data/bvh/bandai-namco-1, "
                    "else 'procedural')")
    ap.add_argument("--preset", default="paper", choices=["paper", "small"])
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--chunk", type=int, default=16, help="iterations per timed chunk (16 = one full lazy-reg cycle)")
    ap.add_argument("--reps", type=int, default=3, help="timed chunks per side")
    ap.add_argument("--gen-batch", type=int, default=256)
    ap.add_argument("--gen-reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    if not HAS_EXT:
        print("modi_ext is not built: nothing to compare (python setup.py build_ext --inplace)", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)

    from modi.modi_model.config import make_config
    from modi.modi_model.training import Trainer, prepare_data

    data_dir = args.data
    if data_dir is None:
        bandai = ROOT.parent / "shared" / "data" / "bvh" / "bandai-namco-1"
        data_dir = str(bandai) if bandai.is_dir() else "procedural"
    cfg = make_config(args.preset, **{"train.batch": args.batch})
    work = Path(tempfile.mkdtemp(prefix="modi_bench_"))
    data = prepare_data(data_dir, cfg, work_dir=work)
    trainers = {}
    for impl in ("ref", "ext"):
        with forced_impl(impl):
            trainers[impl] = Trainer(cfg, data, work / impl, device=device, progress=False, tensorboard=False,
                                     write_samples=False, log=lambda m: None)

    # warm-up: one full lazy-regularisation cycle each (allocator, oneDNN/cuDNN plans, kernel caches)
    for impl, tr in trainers.items():
        with forced_impl(impl):
            for _ in range(min(args.chunk, 16)):
                tr.train_step()
    step_times: dict[str, list[float]] = {"ref": [], "ext": []}
    for _ in range(args.reps):
        for impl, tr in trainers.items():
            with forced_impl(impl):
                _sync(device)
                t = time.perf_counter()
                for _ in range(args.chunk):
                    tr.train_step()
                _sync(device)
                step_times[impl].append((time.perf_counter() - t) / args.chunk)

    gen_times: dict[str, list[float]] = {"ref": [], "ext": []}
    g0 = trainers["ext"].G_ema
    z = torch.randn(args.gen_batch, g0.latent_dim, device=device)
    with torch.no_grad():
        for impl in ("ref", "ext"):
            with forced_impl(impl):
                trainers[impl].G_ema(z)  # warm-up
        for _ in range(args.gen_reps):
            for impl, tr in trainers.items():
                with forced_impl(impl):
                    _sync(device)
                    t = time.perf_counter()
                    tr.G_ema(z)
                    _sync(device)
                    gen_times[impl].append(time.perf_counter() - t)

    if device.type == "cuda":
        from bench_cuda import device_description

        desc = device_description()
    else:
        desc = machine()
    res = {"machine": desc, "date": time.strftime("%Y-%m-%d"), "device": str(device), "preset": args.preset,
           "batch": args.batch, "data": str(data_dir), "windows": list(data.windows.shape),
           "hierarchy": [lv.n_entities for lv in trainers["ext"].levels]}
    ref_s, ext_s = statistics.median(step_times["ref"]), statistics.median(step_times["ext"])
    res["train_step"] = {"ref_s_per_iter": round(ref_s, 4), "ext_s_per_iter": round(ext_s, 4),
                         "speedup": round(ref_s / ext_s, 3), "chunks": args.reps, "iters_per_chunk": args.chunk}
    ref_g, ext_g = statistics.median(gen_times["ref"]), statistics.median(gen_times["ext"])
    res["generate"] = {"batch": args.gen_batch, "ref_motions_per_s": round(args.gen_batch / ref_g, 1),
                       "ext_motions_per_s": round(args.gen_batch / ext_g, 1), "speedup": round(ref_g / ext_g, 3)}
    print(f"# {desc}; MoDi preset {args.preset}, batch {args.batch}, data {data_dir}")
    print(f"train step   ref {ref_s:.3f} s/it   ext {ext_s:.3f} s/it   {ref_s / ext_s:.2f}x")
    print(f"generate     ref {args.gen_batch / ref_g:.1f} motions/s   ext {args.gen_batch / ext_g:.1f} motions/s   "
          f"{ref_g / ext_g:.2f}x  (batch {args.gen_batch})")
    write_json(Path(args.json) if args.json else None, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
