"""``modi import``: checkpoints written by the authors' released code (MoDi, its encoder, GANimator) as modi runs.

The files are read as data (weights only, an explicit allow-list): converting needs neither the authors' code nor
trust in whoever sent the file.
"""
from __future__ import annotations

import argparse

from modi.cli import types as ct


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import", help="convert a checkpoint of the authors' released code into a modi run",
        description="Convert a checkpoint written by the authors' released code into a modi run folder "
                    "(RUN/checkpoint.pt) that 'modi generate', 'modi latent', 'modi apply', 'modi view' and "
                    "'modi export' read like one of modi's own.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sub = p.add_subparsers(dest="import_kind", metavar="KIND")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    m = sub.add_parser(
        "modi-released", help="a released MoDi train.py checkpoint (generator, EMA generator, discriminator)",
        description="Convert a released MoDi checkpoint (their train.py's NNNNNN.pt). Dense masked weights become "
                    "modi's per-pair weights (refused, with the offending entries, if any weight is non-zero "
                    "outside its skeletal mask); the topology is read from the masks; normalisation statistics "
                    "from the checkpoint; the skeleton from --data (the .npy their preprocessing wrote, which "
                    "their train.py read with --path).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    m.add_argument("ckpt", metavar="CKPT", help="released MoDi checkpoint (.pt)")
    m.add_argument("--data", metavar="DIR", required=True,
                   help="the released training data: their edge_rot_*.npy, or the folder holding it")
    m.add_argument("--out", metavar="RUN", required=True, type=ct.output_dir, help="modi run folder to write")
    m.add_argument("--fps", type=ct.float_range(1.0, 1000.0), default=30.0, help="frame rate of the data")
    m.set_defaults(func=run_modi)

    e = sub.add_parser(
        "encoder-released", help="a released MoDi train_encoder.py checkpoint, with the MoDi model it inverts",
        description="Convert a released MoDi encoder checkpoint (their train_encoder.py's NNNNNN.pt) together "
                    "with the generator checkpoint it was trained against (--generator, converted as "
                    "'modi-released' does) into a modi encoder run.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    e.add_argument("ckpt", metavar="CKPT", help="released encoder checkpoint (.pt)")
    e.add_argument("--generator", metavar="CKPT", required=True, help="the released MoDi checkpoint it inverts")
    e.add_argument("--data", metavar="DIR", required=True, help="the released training data (.npy or its folder)")
    e.add_argument("--out", metavar="RUN", required=True, type=ct.output_dir, help="modi encoder run folder")
    e.add_argument("--fps", type=ct.float_range(1.0, 1000.0), default=30.0, help="frame rate of the data")
    e.set_defaults(func=run_encoder)

    g = sub.add_parser(
        "ganimator-released", help="a released GANimator checkpoint",
        description="Convert a released GANimator checkpoint into a modi GANimator run.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    g.add_argument("ckpt", metavar="CKPT", help="released GANimator checkpoint")
    g.add_argument("--data", metavar="BVH", default=None, help="the BVH the model was trained on")
    g.add_argument("--out", metavar="RUN", required=True, type=ct.output_dir, help="modi run folder to write")
    g.set_defaults(func=run_ganimator)


def run_modi(args) -> int:
    from modi.api.conversion import import_released  # lazy: torch

    out = import_released("modi-released", args.ckpt, args.out, data=args.data, fps=args.fps)
    print(f"modi import: released MoDi model -> {out} (sample it with 'modi generate {out} --out DIR')")
    return 0


def run_encoder(args) -> int:
    from modi.api.conversion import import_released  # lazy: torch

    out = import_released("encoder-released", args.ckpt, args.out, generator=args.generator, data=args.data,
                          fps=args.fps)
    print(f"modi import: released MoDi encoder -> {out}")
    return 0


def run_ganimator(args) -> int:
    from modi.api.conversion import import_released  # lazy: torch

    out = import_released("ganimator-released", args.ckpt, args.out, data=args.data)
    print(f"modi import: released GANimator model -> {out}")
    return 0
