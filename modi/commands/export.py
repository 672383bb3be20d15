"""``modi export-positions``: global joint positions of a BVH as a NumPy array (for other tools, FK cross-checks)."""
from __future__ import annotations

import argparse
import os

from modi import cli_types as ct
from modi.errors import UserError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export-positions",
        help="write a BVH's global joint positions to a .npy array (T, J, 3)",
        description="Run forward kinematics on a BVH exactly as the file means it (every position channel "
                    "honoured) and save the global joint positions as a float32 array of shape (frames, joints, 3), "
                    "in the file's units and joint order (the order of ROOT/JOINT in the file; End Sites excluded).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("input", metavar="IN.bvh", help="input BVH file")
    p.add_argument("output", metavar="OUT.npy", type=ct.output_file, help="output .npy file (written as named)")
    p.add_argument("--names", metavar="FILE", default=None, type=ct.output_file,
                   help="also write the joint names, one per line, to this text file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from modi.io import bvh
    from modi.kinematics import bvh_positions

    if os.path.isdir(args.input):
        raise UserError(f"{args.input}: is a folder, expected a .bvh file")
    if not os.path.exists(args.input):
        raise UserError(f"{args.input}: no such file")
    out_dir = os.path.dirname(os.path.abspath(args.output))
    if not os.path.isdir(out_dir):
        raise UserError(f"{args.output}: folder {out_dir} does not exist")
    ct.refuse_overwrite(args.output, [args.input])
    if args.names:
        ct.refuse_overwrite(args.names, [args.input], "--names")
        if os.path.abspath(args.names) == os.path.abspath(args.output):
            raise UserError(f"--names {args.names} is the output array's file; choose another name")
    b = bvh.load(args.input)
    pos = bvh_positions(b).astype(np.float32)
    tmp = f"{args.output}.tmp{os.getpid()}"
    try:
        with open(tmp, "wb") as fh:  # a file object, so numpy does not append ".npy" to the name
            np.save(fh, pos)
        os.replace(tmp, args.output)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    if args.names:
        with open(args.names, "w", encoding="utf-8") as fh:
            fh.write("\n".join(b.names) + "\n")
    print(f"{args.output}: {pos.shape[0]} frames x {pos.shape[1]} joints x 3 (float32, {b.fps:g} fps)")
    return 0
