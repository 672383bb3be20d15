"""``modi data ...``: inspect a folder of BVH files as a training dataset."""
from __future__ import annotations

import argparse
from typing import Any

from modi.cli import types as ct
from modi.errors import UserError


def add_dataset_arguments(p: argparse.ArgumentParser) -> None:
    """The dataset options, shared with any command that builds a dataset (e.g. ``modi train``)."""
    from modi.api.options import DatasetConfig  # lazy: torch (read when the parser is built)

    d = DatasetConfig()
    p.add_argument("--fps", type=ct.fps_float, default=d.fps, help="resample every clip to this frame rate")
    p.add_argument("--window", type=ct.int_range(1, ct.MAX_FRAMES), default=d.window, help="frames per training window")
    p.add_argument("--stride", type=ct.int_range(1, ct.MAX_FRAMES), default=d.stride, help="frames between consecutive window starts")
    p.add_argument("--test-fraction", type=ct.float_range(0.0, 1.0, hi_inclusive=False), default=d.test_fraction, help="fraction of FILES held out")
    p.add_argument("--seed", type=ct.seed_int, default=d.seed, help="seed of the train/test file split")
    p.add_argument("--drop", nargs="+", metavar="REGEX", default=None,
                   help="drop joints whose names match any of these regexes; none given = fingers and face joints")
    p.add_argument("--keep", nargs="+", metavar="JOINT", default=None, help="joints never dropped")
    p.add_argument("--keep-all-joints", action="store_true", help="no joint reduction at all")
    p.add_argument("--feet", nargs="+", metavar="JOINT", default=None,
                   help="contact joints; none given = toe per side by name, else the lowest leaves of the rest pose")
    p.add_argument("--root", choices=["velocity", "position"], default=d.root, help="root-motion entity encoding")
    p.add_argument("--rotation", choices=["quat", "6d"], default=d.rotation, help="rotation features (K=4 or 6)")
    p.add_argument("--no-cache", action="store_true", help="rebuild instead of reading/writing the cache")
    p.add_argument("--cache-dir", default=None, type=ct.output_dir, help="cache folder (default: $MODI_CACHE or ~/.cache/modi)")


def config_from_args(args: argparse.Namespace) -> Any:
    from modi.api.options import DatasetConfig  # lazy: torch

    ct.unique_names("--feet", args.feet)
    return DatasetConfig(
        fps=args.fps, window=args.window, stride=args.stride, test_fraction=args.test_fraction, seed=args.seed,
        drop_patterns=args.drop, keep_joints=args.keep, keep_all_joints=args.keep_all_joints, feet=args.feet,
        rotation=args.rotation, root=args.root,
    )


def _info(args: argparse.Namespace) -> int:
    from modi.api.data import dataset_info  # lazy: torch

    info = dataset_info(args.dir, config_from_args(args), cache=not args.no_cache, cache_dir=args.cache_dir,
                        progress=args.progress)
    ds, elapsed, dropped = info.dataset, info.seconds, info.dropped
    s = ds.summary()
    sk, src = ds.skeleton, ds.source_skeleton
    print(f"folder:      {args.dir}")
    print(f"clips:       {s['clips']} ({s['train_clips']} train / {s['test_clips']} test, split by file, seed {args.seed})")
    fps_src = ", ".join(f"{f:g}" for f in s["source_fps"])
    print(f"frames:      {s['source_frames']} at {fps_src} fps -> {s['frames']} at {s['fps']:g} fps "
          f"({s['frames'] / s['fps']:.1f} s)")
    print(f"skeleton:    {src.n_joints} joints in file -> {sk.n_joints} used"
          + (f" (dropped {len(dropped)}: {', '.join(dropped[:8])}{', ...' if len(dropped) > 8 else ''})" if dropped else ""))
    print(f"root:        {sk.names[0]}; height {s['height']:.4g} (skeleton units)")
    print(f"feet:        {', '.join(s['feet']) or '(none)'}")
    print(f"entities:    {s['entities']} = {sk.n_joints} edges + 1 root motion + {len(ds.feet)} contacts; "
          f"K = {ds.representation.K}")
    print(f"pooling:     entities {' -> '.join(map(str, s['hierarchy_entities']))} "
          f"(edges {' -> '.join(map(str, s['hierarchy_edges']))})")
    short = sum(c.n_windows == 0 for c in ds.clips)
    print(f"windows:     {s['train_windows']} train / {s['test_windows']} test of {s['window']} frames, stride "
          f"{s['stride']}; tensor (N, {', '.join(map(str, s['tensor_shape']))})"
          + (f"; {short} clips shorter than a window" if short else ""))
    print(f"built in:    {elapsed:.2f} s ({'cache' if ds.from_cache else 'from BVH'})")
    if args.verbose:
        print()
        print(f"{'split':5s} {'frames':>7s} {'fps':>7s} {'->':>6s} {'windows':>7s}  path")
        for c in ds.clips:
            print(f"{c.split:5s} {c.source_frames:7d} {c.source_fps:7.3f} {c.frames:6d} {c.n_windows:7d}  {c.path}")
    return 0


def register(subparsers: Any) -> None:
    fmt = argparse.ArgumentDefaultsHelpFormatter
    data = subparsers.add_parser("data", help="dataset tools (info)", description="Dataset tools.",
                                 formatter_class=fmt)
    sub = data.add_subparsers(dest="data_command", metavar="SUBCOMMAND")

    def _missing(args: argparse.Namespace) -> int:
        raise UserError("modi data: give a subcommand, e.g. 'modi data info DIR'")

    data.set_defaults(func=_missing)
    info = sub.add_parser(
        "info", formatter_class=fmt,
        help="print clips, frames, skeleton, windows and split of a BVH folder",
        description="Load every BVH under DIR as a training dataset (joint reduction, resampling, windows, "
                    "80/20 split by file) and print what it contains.",
    )
    info.add_argument("dir", metavar="DIR", help="folder of .bvh files (searched recursively)")
    add_dataset_arguments(info)
    info.add_argument("--verbose", "-v", action="store_true", help="also list every clip")
    info.add_argument("--progress", action="store_true", help="show a progress bar while loading")
    info.set_defaults(func=_info)
