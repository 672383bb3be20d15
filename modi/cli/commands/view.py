"""``modi view``: one self-contained HTML page that plays BVH/glTF motions in 3D (see ``modi.viz.viewer``)."""
from __future__ import annotations

import argparse
from pathlib import Path

from modi.cli import types as ct


def _rule() -> str:
    from modi.api.options import PREVIEW_RULE  # lazy: torch (read when the parser is built)

    return PREVIEW_RULE


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="3D viewer of BVH/glTF motions as one offline HTML page",
        description="Write one HTML file (no network needed) that plays the motions in sync, by time, in 3D. "
                    "Side by side (the default): small multiples, one cell per motion with its own camera following "
                    "its figure and its label in the cell's corner; one scene: every motion where it is. Left limbs "
                    "are blue, right orange, feet in contact red (legend in the bar); contacts: " + _rule() + ". "
                    "A clip shorter than the others holds its last pose, marked 'ended'. Positions are shown in "
                    "metres: BVH units are guessed from the body size (m, in, cm or mm; printed) unless --scale is "
                    "given; glTF is metres already.",
        epilog="URL parameters (page.html?t=1.5&paused=1): t=SECONDS (every clip at that time), frame=N (frame N "
               "of the first motion; t wins), paused=1, az=DEGREES (35), el=DEGREES (18), follow=0|1 (cameras follow "
               "the bodies; on side by side), layout=grid|scene, speed=X (1). Keys and mouse: space play/pause, "
               "left/right arrow one frame back/on, drag orbit, shift-drag or right-drag pan, wheel zoom, "
               "double-click reset the camera, hover a joint for its name. (probe=M,J is a test hook: the page names "
               "the joint picked at joint J of motion M in its body's data-probe attribute.)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("inputs", nargs="+", metavar="FILE", help="input .bvh, .glb or .gltf files")
    p.add_argument("--out", default="view.html", type=ct.output_file, metavar="OUT.html", help="output page")
    p.add_argument("--layout", choices=("grid", "scene"), default="grid",
                   help="grid: small multiples, one cell per motion; scene: all in one scene at their own positions")
    p.add_argument("--scale", type=ct.float_range(0.0, 1e6, lo_inclusive=False), default=None,
                   help="metres per file unit for every input (default: guessed per BVH from the body size -- m, in, "
                        "cm or mm, as 'modi export gltf' does -- and 1 for glTF)")
    p.add_argument("--up", choices=("y", "z"), default="y", help="the BVH files' up axis")
    p.add_argument("--no-contacts", action="store_true", help="do not mark foot contacts")
    p.add_argument("--title", default=None, help="page title (default: the output's name)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from modi.api.viewing import write_page  # lazy: torch

    motions = write_page(args.inputs, args.out, scale=args.scale, up=args.up, contacts=not args.no_contacts,
                         title=args.title, layout=args.layout)
    for f, m in zip(args.inputs, motions):
        if m.unit:
            print(f"{f}: {m.unit}")
    out = Path(args.out)
    frames = max(m.positions.shape[0] for m in motions)
    print(f"{out}: {len(motions)} motion{'s' if len(motions) > 1 else ''}, up to {frames} frames, "
          f"{out.stat().st_size / 1024:.0f} KiB")
    return 0
