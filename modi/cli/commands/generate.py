"""``modi generate``: sample motions from a MoDi checkpoint as BVH + contact labels + a GIF preview."""
from __future__ import annotations

import argparse
import time

from modi.cli import types as ct
from modi.io.formats import add_format_options
from modi.viz import add_view_option


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "generate", help="generate motions from a MoDi checkpoint",
        description="Sample N motions from CKPT's EMA generator. Motion i of a seed is the same whatever N or the "
                    "batch size. Writes DIR/motion_NNNN.bvh on the training skeleton, DIR/motion_NNNN_contacts.npy "
                    "((T, F) 0/1 in the order of the contact joints) and DIR/samples.gif (the first --gif-max).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("ckpt", metavar="CKPT", help="checkpoint written by 'modi train'")
    p.add_argument("--n", type=ct.samples_int, default=16, help="number of motions")
    p.add_argument("--out", required=True, metavar="DIR", type=ct.output_dir, help="output folder (created if missing)")
    p.add_argument("--psi", type=ct.float_range(-2.0, 2.0), default=1.0,
                   help="truncation in [-2, 2]: 1 = none, 0 = the mean motion")
    p.add_argument("--seed", type=ct.seed_int, default=0, help="seed; motion i of a seed is fixed")
    p.add_argument("--ik", action="store_true", help="pin feet with IK while their contact label is on")
    p.add_argument("--batch", type=ct.sample_batch_int, default=256, help="motions per forward pass")
    p.add_argument("--gif-max", type=ct.int_range(0, 256), default=16, help="motions in the GIF grid (0: no GIF)")
    p.add_argument("--raw-weights", action="store_true", help="use the raw generator instead of its EMA")
    p.add_argument("--device", default="cpu", type=ct.device, help="cpu, cuda or cuda:N")
    add_format_options(p)
    p.set_defaults(func=run)
    add_view_option(p)


def run(args: argparse.Namespace) -> int:
    from modi.api.generator import open_generator  # lazy: torch

    t0 = time.perf_counter()
    gen = open_generator(args.ckpt, device=args.device, ema=not args.raw_weights)
    written, t_gen = gen.write_samples(args.out, args.n, seed=args.seed, psi=args.psi, ik=args.ik, batch=args.batch,
                                       gif_max=args.gif_max)
    what = f"{len(written)} motion files ({','.join(args.format)})" if written else f"{args.n} position arrays"
    print(f"modi generate: {what} in {args.out} (sampling {t_gen:.2f} s, {args.n / max(t_gen, 1e-9):.1f} motions/s; "
          f"total {time.perf_counter() - t0:.1f} s)")
    return 0
