"""``modi export positions``: global joint positions of a BVH as a NumPy array (for other tools, FK cross-checks;
``modi export-positions`` is its old spelling); ``modi export gltf``: a BVH as glTF 2.0 (``.glb``/``.gltf``) for Blender, game engines and web viewers;
``modi export onnx``: a GANimator run or a MoDi generator as an ONNX graph and its JSON sidecar
(``modi.export.onnx``)."""
from __future__ import annotations

import argparse

from modi.cli import types as ct


def register(subparsers) -> None:
    e = subparsers.add_parser("export", help="convert a BVH (gltf, positions) or a model (onnx) for other tools",
                              description="Convert motion files and trained models for other tools.",
                              formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    esub = e.add_subparsers(dest="export_format", metavar="FORMAT")
    e.set_defaults(func=lambda args: (e.print_help(), 2)[1])
    _positions_options(esub.add_parser("positions", help=POSITIONS_HELP, description=POSITIONS_DESCRIPTION,
                                       formatter_class=argparse.ArgumentDefaultsHelpFormatter))
    ct.renamed_command(subparsers, "export-positions", "export positions", _positions_options,
                       description=POSITIONS_DESCRIPTION, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    g = esub.add_parser(
        "gltf", help="write a BVH as glTF 2.0 (.glb or .gltf)", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Write IN.bvh as glTF 2.0: one node per joint (names kept), a skin (Blender: an armature), "
                    "one animation at the clip's frame rate and the foot contacts as extras. glTF is Y-up in metres: "
                    "the BVH is read as Y-up (--up z turns a Z-up file) and its lengths are scaled to metres (the unit "
                    "is guessed from the body size and printed with the standing height; --scale overrides). "
                    "OUT.glb is binary; OUT.gltf is JSON with the buffer embedded (or beside it as OUT.bin with "
                    "--side-buffer). Debian's Blender 3.4 imports the file with its default options; set the scene's "
                    "frame rate to the clip's before importing (Blender resamples keys at the scene rate, 24 fps by "
                    "default). Contacts: " + _contact_rule() + ".")
    g.add_argument("input", metavar="IN.bvh", help="input BVH file")
    g.add_argument("output", metavar="OUT.glb", type=ct.output_file, help="output .glb or .gltf file")
    g.add_argument("--scale", type=ct.positive_finite_float, default=None,
                   help="multiply lengths by this to get metres (default: guessed from the body size)")
    g.add_argument("--up", choices=("y", "z"), default="y", help="the BVH file's up axis")
    g.add_argument("--mesh", action="store_true",
                   help="also write a box-per-bone body for viewers that draw no skeleton (Debian's Blender 3.4 "
                        "then needs Import Shading: Flat or Smooth, its default fails on any mesh)")
    g.add_argument("--no-contacts", action="store_true", help="do not store foot-contact labels")
    g.add_argument("--side-buffer", action="store_true", help=".gltf only: write the binary buffer as OUT.bin")
    g.set_defaults(func=run_gltf)

    o = esub.add_parser(
        "onnx", help="write a GANimator run or a MoDi generator as an ONNX model (+ JSON sidecar)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Write the generator of SOURCE (a GANimator run folder or .ckpt, or a MoDi checkpoint) as "
                    "OUT.onnx, with OUT.json beside it: the rig (joint names, parents, offsets, Euler orders, fps, "
                    "unit), the inputs' shapes and value ranges, the outputs' meaning. Inputs: GANimator: noise "
                    "(batch, coarse_frames) and frames (or, for a trajectory-conditioned run, the trajectory); "
                    "MoDi: z (or w with --input w), psi, and noise when the model injects it. Outputs: rotations "
                    "(batch, frames, joints, 4) local quaternions w,x,y,z in the rig's joint order, root_position "
                    "(batch, frames, 3), contacts (batch, frames, feet). Exported with torch.onnx.export(dynamo=True) "
                    "on modi_ext's plain-torch path; needs pip install 'modi[onnx]'. Run it without torch: "
                    "python -m modi.export.onnx_runner OUT.onnx OUT.bvh (see docs/onnx.md).")
    o.add_argument("source", metavar="SOURCE", help="GANimator run folder / .ckpt, or MoDi checkpoint.pt")
    o.add_argument("output", metavar="OUT.onnx", type=ct.output_file, help="output .onnx file (OUT.json beside it)")
    o.add_argument("--frames", type=ct.int_range(1, None), default=None,
                   help="GANimator: fix the output length (static shapes; default: any length, an input)")
    o.add_argument("--input", dest="input_kind", choices=("z", "w"), default="z",
                   help="MoDi: take the latent z (mapped by the graph) or a style w")
    o.add_argument("--raw-weights", action="store_true", help="MoDi: the raw generator instead of its EMA")
    o.add_argument("--opset", type=ct.int_range(18, None), default=18, help="ONNX opset of the graph")
    o.set_defaults(func=run_onnx)


POSITIONS_HELP = "write a BVH's global joint positions to a .npy array (T, J, 3)"
POSITIONS_DESCRIPTION = ("Run forward kinematics on a BVH exactly as the file means it (every position channel "
                         "honoured) and save the global joint positions as a float32 array of shape (frames, joints, "
                         "3), in the file's units and joint order (the order of ROOT/JOINT in the file; End Sites "
                         "excluded).")


def _positions_options(p: argparse.ArgumentParser) -> None:
    """``modi export positions``'s arguments (also on its old spelling, ``modi export-positions``)."""
    p.add_argument("input", metavar="IN.bvh", help="input BVH file")
    p.add_argument("output", metavar="OUT.npy", type=ct.output_file, help="output .npy file (written as named)")
    p.add_argument("--names", metavar="FILE", default=None, type=ct.output_file,
                   help="also write the joint names, one per line, to this text file")
    p.set_defaults(func=run)


def _contact_rule() -> str:
    from modi.api.options import PREVIEW_RULE  # lazy: torch (read when the parser is built)

    return PREVIEW_RULE


def run_gltf(args: argparse.Namespace) -> int:
    from modi.api.conversion import export_gltf  # lazy: torch

    res = export_gltf(args.input, args.output, scale=args.scale, up=args.up, mesh=args.mesh,
                      contacts=not args.no_contacts, side_buffer=args.side_buffer)
    b = res.bvh
    print(f"{args.output}: {b.n_joints} joints, {b.n_frames} frames at {b.fps:g} fps; {res.unit.describe()}")
    return 0


def run_onnx(args: argparse.Namespace) -> int:
    from modi.api.conversion import export_onnx, sidecar_path  # lazy: torch

    side = export_onnx(args.source, args.output, frames=args.frames, input_kind=args.input_kind,
                       ema=not args.raw_weights, opset=args.opset)
    ins = ", ".join(f"{i['name']} {tuple(i['shape'])}" for i in side["inputs"])
    outs = ", ".join(f"{o['name']} {tuple(o['shape'])}" for o in side["outputs"])
    fr = side["dims"]["frames"]
    length = f"{fr['fixed']} frames" if "fixed" in fr else f"frames >= {fr['min']}"
    print(f"{args.output}: {side['kind']} model, {len(side['skeleton']['names'])} joints at {side['fps']:g} fps, "
          f"{length}; inputs {ins}; outputs {outs}; sidecar {sidecar_path(args.output)}")
    return 0


def run(args: argparse.Namespace) -> int:
    from modi.api.conversion import export_positions  # lazy: torch

    pos, b = export_positions(args.input, args.output, names=args.names)
    print(f"{args.output}: {pos.shape[0]} frames x {pos.shape[1]} joints x 3 (float32, {b.fps:g} fps)")
    return 0
