"""``modi demo``: the README's main job -- procedural data, a few CPU minutes of MoDi training, sampled motions."""
from __future__ import annotations

import argparse

from modi.cli import types as ct
from modi.viz import add_view_option

DEFAULT_ITERS = 300  # ~0.65 s of CPU per iteration (small preset, 1 thread, modi_ext kernels): ~3.5 min in all


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="train a small MoDi on procedural motion and write sampled BVH + GIF previews",
        description="Write procedural walk/run/jump/wave/squat/idle clips (OUT/data), train the 'small' MoDi preset "
                    "on them for a few CPU minutes (OUT/run: checkpoint, TensorBoard, log.jsonl), then sample motions "
                    "(OUT/samples: BVH, contact labels, samples.gif) next to a GIF of real training windows "
                    "(OUT/training_examples.gif).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", default="demo_out", type=ct.output_dir, metavar="DIR", help="output folder")
    p.add_argument("--iters", type=ct.iters_int, default=DEFAULT_ITERS, help="training iterations")
    p.add_argument("--clips", type=ct.int_range(2, 10_000), default=48, help="procedural clips to write")
    p.add_argument("--n", type=ct.int_range(1, 1000), default=8, help="motions to sample")
    p.add_argument("--seed", type=ct.seed_int, default=0, help="seed for data, training and sampling")
    p.add_argument("--threads", type=ct.threads_int, default=1,
                   help="torch CPU threads; 1 is the robust choice for this small model (OpenMP workers spin and "
                        "slow down badly when the CPU is shared)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    add_view_option(p)


def run(args: argparse.Namespace) -> int:
    from modi.api.demo import run_demo  # lazy: torch

    demo = run_demo(args.out, iters=args.iters, clips=args.clips, n=args.n, seed=args.seed, threads=args.threads,
                    progress=not args.no_progress, log=lambda line: print(line, flush=True))
    if demo.interrupted:
        print(f"modi demo: interrupted; checkpoint at {demo.checkpoint}")
        return 130
    out, ckpt = demo.out, demo.checkpoint
    print(f"modi demo: done in {demo.seconds:.0f} s\n"
          f"  checkpoint       {ckpt}\n"
          f"  sampled motions  {len(demo.samples)} BVH in {out / 'samples'} (preview {out / 'samples' / 'samples.gif'})\n"
          f"  training clips   {out / 'training_examples.gif'}\n"
          f"  more samples     modi generate {ckpt} --n 64 --out {out / 'more'}\n"
          f"  curves           tensorboard --logdir {demo.run_dir / 'tb'}")
    return 0
