"""``modi demo``: the README's main job -- procedural data, a few CPU minutes of MoDi training, sampled motions."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from modi.cli import types as ct
from modi.errors import UserError
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
    import torch

    from modi.models.modi.config import make_config
    from modi.api.generator import ModiGenerator
    from modi.models.modi.sampling import render_gif, write_outputs
    from modi.models.modi.training import Trainer, prepare_data, write_procedural_data

    if args.iters < 0:
        raise UserError(f"--iters must be >= 0, got {args.iters}")
    if args.clips < 2:
        raise UserError(f"--clips must be >= 2, got {args.clips}")
    if args.n < 1:
        raise UserError(f"--n must be >= 1, got {args.n}")
    if args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    run_dir = out / "run"
    if (run_dir / "checkpoint.pt").exists():
        raise UserError(f"{out} already holds a demo run; choose another --out or delete it")
    t0 = time.perf_counter()
    cfg = make_config("small", **{"train.iters": args.iters, "train.seed": args.seed, "train.sample_every": 0,
                                  "train.ckpt_every": max(50, args.iters // 4 or 1), "train.log_every": 10})
    data_dir = write_procedural_data(out / "data", n_clips=args.clips, seed=args.seed, fps=cfg.data.fps)
    data = prepare_data(data_dir, cfg, cache=False)
    print(f"modi demo: {args.clips} procedural clips -> {data.windows.shape[0]} training windows "
          f"{tuple(data.windows.shape[1:])}; hierarchy {data.hierarchy.entity_counts}; "
          f"training the small preset for {args.iters} iterations", flush=True)
    trainer = Trainer(cfg, data, run_dir, progress=not args.no_progress, write_samples=False)
    result = trainer.train()
    if result.interrupted:
        print(f"modi demo: interrupted; checkpoint at {result.checkpoint}")
        return 130

    real = data.windows[torch.linspace(0, data.windows.shape[0] - 1, args.n).long()]
    dec = data.codec.decode(real)
    render_gif(data.codec, [p.numpy() for p in dec["positions"]], [(c > 0.5).numpy() for c in dec["contacts"]],
               out / "training_examples.gif", view="training_examples.html")
    gen = ModiGenerator.from_checkpoint(result.checkpoint)
    written = write_outputs(gen.codec, gen.sample_tensors(args.n, seed=args.seed), out / "samples", gif=True,
                            gif_name="samples.gif")
    print(f"modi demo: done in {time.perf_counter() - t0:.0f} s\n"
          f"  checkpoint       {result.checkpoint}\n"
          f"  sampled motions  {len(written)} BVH in {out / 'samples'} (preview {out / 'samples' / 'samples.gif'})\n"
          f"  training clips   {out / 'training_examples.gif'}\n"
          f"  more samples     modi generate {result.checkpoint} --n 64 --out {out / 'more'}\n"
          f"  curves           tensorboard --logdir {run_dir / 'tb'}")
    return 0
