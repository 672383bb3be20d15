"""``modi synth``: write a folder of procedural BVH clips (the built-in data set the demo and tests use)."""
from __future__ import annotations

import argparse
import time

from modi.cli import types as ct
from modi.errors import UserError
from modi.io.formats import add_format_options


def register(subparsers) -> None:
    from modi.data.procedural import KINDS

    p = subparsers.add_parser(
        "synth", help="write procedural walk/run/jump/wave/squat/idle BVH clips",
        description="Write N procedural clips on the built-in 22-joint humanoid as BVH files plus labels.json "
                    "({file: kind}). Clip i depends only on (seed, i), so the same seed gives the same files.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("out_dir", metavar="OUT_DIR", type=ct.output_dir, help="folder to write (created if missing)")
    p.add_argument("--n", type=ct.int_range(1, ct.MAX_SAMPLES), default=32, help="number of clips")
    p.add_argument("--frames", type=ct.frames_int, default=128, help="frames per clip")
    p.add_argument("--fps", type=ct.fps_float, default=30.0, help="frame rate")
    p.add_argument("--seed", type=ct.seed_int, default=0, help="random seed")
    p.add_argument("--kinds", default=",".join(KINDS), help="comma-separated clip kinds, used in turn")
    add_format_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from modi.data.procedural import KINDS, write_dataset

    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise UserError(f"--kinds: unknown kind(s) {', '.join(bad) or '(none given)'}; choose from {', '.join(KINDS)}")
    if args.n < 1:
        raise UserError(f"--n must be >= 1, got {args.n}")
    if args.frames < 2:
        raise UserError(f"--frames must be >= 2, got {args.frames}")
    if not args.fps > 0:
        raise UserError(f"--fps must be > 0, got {args.fps}")
    start = time.perf_counter()
    paths = write_dataset(args.out_dir, n_clips=args.n, frames=args.frames, seed=args.seed, fps=args.fps,
                          kinds=kinds)
    print(f"wrote {len(paths)} clips ({args.frames} frames at {args.fps:g} fps) and labels.json to {args.out_dir} "
          f"in {time.perf_counter() - start:.2f} s")
    return 0
