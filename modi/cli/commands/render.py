"""``modi render``: stick-figure GIF/MP4 previews of BVH files, and the 3D viewer page beside them."""
from __future__ import annotations

import argparse

from modi.cli import types as ct
from modi.errors import UserError


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 320x320, got {text!r}") from None
    if w < 16 or h < 16 or w > 4096 or h > 4096:
        raise argparse.ArgumentTypeError(f"size must be between 16x16 and 4096x4096, got {text!r}")
    return w, h


def _rule() -> str:
    from modi.api.options import PREVIEW_RULE  # lazy: torch (read when the parser is built)

    return PREVIEW_RULE


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="stick-figure preview of BVH files (GIF, or MP4 with ffmpeg)",
        usage="%(prog)s [options] IN.bvh [IN.bvh ...] OUT.gif|OUT.mp4",
        description="Render one or more BVH files to a stick-figure GIF (or .mp4 when ffmpeg is on PATH); the LAST "
                    "file is the output. A ground grid, and a camera that follows the body (not a static floor "
                    "root). Each file is scaled to metres (its unit guessed from the body size, or --scale) and, "
                    "side by side (--layout grid), framed in its own panel; --layout scene puts all in one scene. "
                    "Left limbs are blue, right orange; --contacts marks feet in red: " + _rule() + ".",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("files", nargs="+", metavar="FILE", help="input .bvh files, then the output .gif/.mp4 (last)")
    p.add_argument("--fps", type=ct.fps_float, default=30.0, help="output frame rate (clips are played in real time)")
    p.add_argument("--size", type=_size, default="320x320", help="WxH pixels per panel (whole image for scene)")
    p.add_argument("--layout", choices=("grid", "scene"), default="grid",
                   help="grid: one panel per file; scene: all characters in one panel")
    p.add_argument("--contacts", action="store_true", help="highlight feet touching the ground")
    p.add_argument("--up", choices=("y", "z"), default="y", help="the files' up axis")
    p.add_argument("--scale", type=ct.positive_finite_float, default=None,
                   help="metres per file unit for every input (default: guessed per file from the body size)")
    p.add_argument("--max-frames", type=ct.int_range(1, ct.MAX_FRAMES), default=None,
                   help="stop after this many output frames (default: the whole clip)")
    p.add_argument("--azimuth", type=ct.angle_float, default=35.0, help="camera azimuth in degrees (0 = looking along -Z)")
    p.add_argument("--elevation", type=ct.float_range(-90.0, 90.0), default=18.0, help="camera elevation in degrees")
    p.add_argument("--no-view", action="store_true",
                   help="do not write the 3D viewer page OUT.html beside the preview (see 'modi view')")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from modi.api.viewing import render  # lazy: torch, Pillow

    if len(args.files) < 2:
        raise UserError("render needs at least one input .bvh and an output .gif/.mp4")
    *inputs, out = args.files
    try:
        ct.output_file(out)
    except argparse.ArgumentTypeError as exc:
        raise UserError(f"output {exc}") from None
    path, page = render(inputs, out, fps=args.fps, size=args.size, layout=args.layout, contacts=args.contacts,
                        up=args.up, scale=args.scale, max_frames=args.max_frames, azimuth=args.azimuth,
                        elevation=args.elevation, view=not args.no_view)
    print(path)
    if page is not None:
        print(page)
    return 0
