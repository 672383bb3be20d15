"""``modi synth``: write a folder of procedural BVH clips (the built-in data set the demo and tests use)."""
from __future__ import annotations

import argparse
import time

from modi.cli import types as ct
from modi.io.formats import add_format_options


def register(subparsers) -> None:
    from modi.api.options import PROCEDURAL_KINDS as KINDS  # lazy: torch (read when the parser is built)

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
    from modi.api.data import write_procedural  # lazy: torch

    start = time.perf_counter()
    paths = write_procedural(args.out_dir, n=args.n, frames=args.frames, fps=args.fps, seed=args.seed,
                             kinds=[k.strip() for k in args.kinds.split(",") if k.strip()])
    print(f"wrote {len(paths)} clips ({args.frames} frames at {args.fps:g} fps) and labels.json to {args.out_dir} "
          f"in {time.perf_counter() - start:.2f} s")
    return 0
