"""``modi ganimator train|generate|eval``: single-sequence GANimator from the command line."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from modi.cli import types as ct
from modi.errors import UserError
from modi.io.formats import add_format_options
from modi.viz import add_view_option

_FMT = argparse.ArgumentDefaultsHelpFormatter


def register(subparsers) -> None:
    # lazy: torch (read when the parser is built)
    from modi.api.options import GANIMATOR_PRESETS, ganimator_preset_help
    from modi.api.options import PRECISIONS  # lazy: torch (read when the parser is built)

    p = subparsers.add_parser("ganimator", help="GANimator: learn from one (or a few) BVH clips of any skeleton",
                              description="GANimator (Li et al. 2022): a coarse-to-fine pyramid of small GANs "
                                          "trained on a single short motion of any skeleton.",
                              formatter_class=_FMT)
    sub = p.add_subparsers(dest="ganimator_command", metavar="SUBCOMMAND")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    t = sub.add_parser("train", help="train (or resume) a model on BVH clips", formatter_class=_FMT,
                       description="Train a GANimator pyramid on one BVH, or several of one character (mixing). "
                                   "Re-running on the same --out resumes from its checkpoint. Ctrl-C (exit 130) "
                                   "and SIGTERM (exit 143) finish the iteration and save; a run folder in use by "
                                   "another run is refused.")
    t.add_argument("bvh", nargs="+", help="training BVH file(s); several = motion mixing (same skeleton)")
    t.add_argument("--out", required=True, type=ct.output_dir, help="run directory (checkpoint ganimator.ckpt, TensorBoard logs)")
    t.add_argument("--preset", default="paper", choices=GANIMATOR_PRESETS, help=ganimator_preset_help())
    t.add_argument("--iterations", type=ct.iters_int, default=None,
                   help="iterations per block of levels (preset's if omitted); the coarsest block trains ITERATIONS "
                        "× --coarse-multiplier (the fast preset multiplies it by 3)")
    t.add_argument("--d-steps", type=ct.int_range(0, 100), default=None, help="discriminator steps per iteration (preset's if omitted)")
    t.add_argument("--block-iters", default=None,
                   help="iterations per block of levels, coarsest first, e.g. 2000,800,800,800 (the last value "
                        "repeats for further blocks); overrides --iterations and --coarse-multiplier")
    t.add_argument("--coarse-multiplier", type=ct.float_range(0.0, 1000.0, lo_inclusive=False), default=None,
                   help="the coarsest block trains ITERATIONS x this (preset's if omitted: paper 1, fast 3, tiny 1)")
    t.add_argument("--contact-rescale", action="store_true", default=None,
                   help="contact consistency on per-source-frame velocities at every level (our earlier form; "
                        "default: per level frame, as the authors' code)")
    t.add_argument("--contact-first-frame", choices=["zero", "copy"], default=None,
                   help="first frame's contact label: zero (authors' code, the default) or a copy of the second's")
    t.add_argument("--bias-init", choices=["uniform", "zeros"], default=None,
                   help="convolution biases: uniform +-1/sqrt(fan-in) (authors' code, the default) or zeros")
    t.add_argument("--sixd", choices=["rows", "columns"], default=None,
                   help="6D rotation: first two rows (authors' code, the default) or columns of the matrix")
    t.add_argument("--base-channels", type=ct.int_range(1, 8192), default=None, help="total hidden width (preset's if omitted)")
    t.add_argument("--coarse-ratio", type=ct.float_range(0.0, 1.0, lo_inclusive=False), default=None, help="coarsest level / sequence length (0.2)")
    t.add_argument("--keep-joints", default=None, help="comma-separated joint names to keep (default: automatic)")
    t.add_argument("--no-joint-reduction", action="store_true", help="keep every joint of the file")
    t.add_argument("--feet", default=None, help="comma-separated contact joints (default: detected)")
    t.add_argument("--no-contacts", action="store_true", help="no contact labels / consistency loss")
    t.add_argument("--fps", type=ct.fps_float, default=None, help="target frame rate by integer striding (30)")
    t.add_argument("--conditional-from", default=None,
                   help="train a trajectory-conditioned model; trajectories are sampled from this trained run")
    t.add_argument("--device", default=None, type=ct.device, help="torch device (cpu, cuda)")
    t.add_argument("--seed", type=ct.seed_int, default=None, help="random seed")
    t.add_argument("--precision", choices=PRECISIONS, default=None,
                   help="forward passes in fp32, or under bf16 autocast (weights, optimiser states and checkpoints "
                        "stay fp32; see docs/precision.md); omitted: a resumed run's, else fp32; given on a resume, "
                        "the run switches to it")
    t.add_argument("--threads", type=ct.threads_int, default=None, help="torch CPU threads (default: torch's choice)")
    t.add_argument("--max-minutes", type=ct.minutes_float, default=None,
                   help="stop (checkpointed) after this many minutes; run again to continue")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=_train)

    g = sub.add_parser("generate", help="sample motions from a trained run", formatter_class=_FMT,
                       description="Generate BVH (+ GIF previews) from a trained run: random motions of any "
                                   "length, style transfer and harmonisation (--content [--content-level]), "
                                   "key-frame editing (--keyframes), trajectory control (--trajectory), loops "
                                   "(--loop), in-betweens (--inbetween), expansion (--expand) and body-part "
                                   "editing (--edit --keep). Given frames and kept joints are exact in the output "
                                   "(before --ik).")
    g.add_argument("run", help="run directory (or .ckpt file)")
    g.add_argument("--frames", type=ct.frames_int, default=None,
                   help="frames per motion (default: the training clip's); with --inbetween: the frames generated "
                        "between START and END; with --expand: the expanded length")
    g.add_argument("--n", type=ct.int_range(1, 1000), default=1, help="number of motions (a crowd when > 1)")
    g.add_argument("--out", required=True, type=ct.output_dir, help="output directory")
    g.add_argument("--seed", type=ct.seed_int, default=0, help="random seed")
    g.add_argument("--content", default=None, help="style transfer: BVH whose coarse motion replaces level 0")
    g.add_argument("--content-level", type=ct.int_range(0, 64), default=0,
                   help="with --content: the pyramid level the content enters at; 0 is style transfer, a finer level "
                        "is harmonisation (a clip pasted together by hand keeps its poses, the finer levels blend "
                        "it into the run's style)")
    g.add_argument("--keyframes", default=None, help="key-frame editing: BVH of coarse-level poses")
    g.add_argument("--loop", action="store_true",
                   help="a loop of --frames frames: the last frame flows into the first (pose and velocity)")
    g.add_argument("--loop-root", choices=["travel", "return"], default="travel",
                   help="with --loop: the root moves on each repetition (travel) or returns to its start (return)")
    g.add_argument("--inbetween", nargs=2, metavar=("START", "END"), default=None,
                   help="in-betweening: START, then --frames generated frames, then END, both kept exactly where "
                        "they are; each a BVH on the run's rig, or BVH@F for its frame F as a pose (@-1: the last)")
    g.add_argument("--expand", default=None, metavar="CLIP",
                   help="expansion: a --frames-long motion that holds CLIP unchanged from frame --at")
    g.add_argument("--at", type=ct.int_range(0, ct.MAX_FRAMES), default=None,
                   help="with --expand: the output frame where CLIP starts (default: centred)")
    g.add_argument("--edit", default=None, metavar="CLIP",
                   help="body-part editing: CLIP's --keep joints unchanged, the other joints generated to go with them")
    g.add_argument("--keep", default=None,
                   help="with --edit: comma-separated joint names to keep, or upper / lower (found from a humanoid's "
                        "tree)")
    g.add_argument("--trajectory", default=None,
                   help="root trajectory BVH (conditional runs); without it a conditional run samples one")
    g.add_argument("--stream", type=ct.int_range(0, ct.MAX_FRAMES), default=0,
                   help="with --trajectory: feed the trajectory in segments of this many frames (streaming API)")
    g.add_argument("--ik", action="store_true",
                   help="fix foot sliding with IK where contacts are predicted (moves the root and the leg joints "
                        "above each foot, also kept or given ones: docs/single_clip.md)")
    g.add_argument("--fine-noise", action="store_true", help="random noise at every level (default: coarsest only)")
    g.add_argument("--crowd-spacing", type=ct.nonneg_finite_float, default=None,
                   help="grid spacing of a crowd (default: 1.5 x body size, and 0 with --inbetween, --expand, "
                        "--edit, whose given clips keep their places; 0: every motion at its own start)")
    g.add_argument("--no-gif", action="store_true", help="do not render GIF previews")
    g.add_argument("--eval", dest="evaluate", action="store_true",
                   help="print coverage / diversity of each motion vs the sources")
    ct.renamed_option(g, "--evaluate", "--eval", "evaluate", flag=True)
    add_format_options(g)
    g.set_defaults(func=_generate)
    add_view_option(g)

    eval_description = ("Sample motions and report coverage (30-frame windows, threshold 2.0), global (patched nearest "
                        "neighbour) and local diversity against every training clip. --protocol ours (default): "
                        "rotations decoded from the samples, as any BVH output is scored. --protocol paper: the "
                        "authors' released evaluate.py (200 samples of 2x the total source length, the generator's raw "
                        "6D + contact channels, per-clip figures and the script's running average over clips).")
    _eval_options(sub.add_parser("eval", help="coverage and diversity of random samples of a run",
                                 formatter_class=_FMT, description=eval_description))
    ct.renamed_command(sub, "evaluate", "eval", _eval_options, formatter_class=_FMT, description=eval_description)


def _eval_options(e: argparse.ArgumentParser) -> None:
    """``modi ganimator eval``'s options (also on its old spelling, ``evaluate``)."""
    e.add_argument("run", help="run directory (or .ckpt file)")
    e.add_argument("--protocol", choices=["ours", "paper"], default="ours",
                   help="ours: rotation-only features decoded as from BVH; paper: the released evaluate.py")
    e.add_argument("--n", type=ct.int_range(1, 1000), default=None, help="number of samples (default: ours 10, paper 200)")
    e.add_argument("--frames", type=ct.frames_int, default=None,
                   help="frames per sample (default: ours the first training clip's, paper 2x all clips' total)")
    e.add_argument("--seed", type=ct.seed_int, default=0, help="random seed")
    e.add_argument("--json", default=None, type=ct.output_file, help="also write the figures to this JSON file ('-': print the JSON "
                                               "instead of the table)")
    e.set_defaults(func=_evaluate)


def _csv(s: str | None) -> list[str] | None:
    return [x.strip() for x in s.split(",") if x.strip()] if s else None


def _int_csv(s: str | None, flag: str) -> list[int] | None:
    items = _csv(s)
    if items is None:
        return None
    try:
        values = [int(x) for x in items]
    except ValueError:
        raise UserError(f"{flag}: expected comma-separated whole numbers, got {s!r}") from None
    if any(v < 0 for v in values):
        raise UserError(f"{flag}: iteration counts must be >= 0, got {s!r}")
    return values


def _train(args) -> int:
    from modi.api.training import TrainingInterrupted, train_ganimator  # lazy: torch

    try:
        train_ganimator(args.bvh, args.out, preset=args.preset, resume=True, conditional_from=args.conditional_from,
                        max_minutes=args.max_minutes, threads=args.threads, bar=not args.quiet, log=print,
                        precision=args.precision,
                        iterations=args.iterations, d_steps=args.d_steps, base_channels=args.base_channels,
                        coarse_ratio=args.coarse_ratio, keep_joints=_csv(args.keep_joints), feet=_csv(args.feet),
                        fps=args.fps, device=args.device, seed=args.seed,
                        block_iterations=_int_csv(args.block_iters, "--block-iters"),
                        coarse_multiplier=args.coarse_multiplier, contact_rescale=args.contact_rescale,
                        contact_first_frame=args.contact_first_frame, bias_init=args.bias_init, sixd=args.sixd,
                        joint_reduction=False if args.no_joint_reduction else None,
                        contacts=False if args.no_contacts else None)
    except TrainingInterrupted as exc:
        print(f"modi ganimator train: interrupted; checkpoint saved to {exc.checkpoint} "
              "(run the same command again to continue)", file=sys.stderr)
        return exc.exit_code
    print(f"checkpoint: {Path(args.out) / 'ganimator.ckpt'}")
    return 0


def _mode(args, run) -> str:
    if args.loop:
        return f"loop ({args.loop_root})"
    if args.inbetween:
        return "in-between"
    if args.expand:
        return "expansion"
    if args.edit:
        return "body-part editing"
    if args.content:
        return "style transfer" if not args.content_level else f"harmonisation (level {args.content_level})"
    if args.keyframes:
        return "key-frame editing"
    if args.trajectory or run.conditional:
        return "trajectory" + (" (streamed)" if args.stream else "")
    return "random"


def _generate(args) -> int:
    from modi.api.ganimator import GanimatorRun  # lazy: torch

    run = GanimatorRun.from_checkpoint(args.run)
    spacing = None if args.crowd_spacing is None else args.crowd_spacing / run.scale  # the option is in GANimator's units
    if spacing is None and (args.inbetween or args.expand or args.edit):
        spacing = 0.0  # given clips stay where they are in the scene: no crowd grid unless asked for
    motions = run.generate(args.n, frames=args.frames, seed=args.seed, keyframes=args.keyframes,
                           trajectory=args.trajectory, style=args.content, style_level=args.content_level,
                           loop=args.loop, loop_root=args.loop_root, inbetween=args.inbetween, expand=args.expand,
                           at=args.at, edit=args.edit, keep=args.keep, stream=args.stream,
                           fine_noise=args.fine_noise, ik=args.ik, spacing=spacing)
    written, gif = run.write(motions, args.out, gif=not args.no_gif)
    print(f"{_mode(args, run)}: wrote {len(written)} BVH to {Path(args.out)}" + (f" and {gif}" if gif else ""))
    if args.evaluate:
        print(json.dumps(run.metrics(motions), indent=2))
    return 0


def _evaluate(args) -> int:
    from modi.api.ganimator import evaluate_ganimator, format_figures  # lazy: torch

    figures = evaluate_ganimator(args.run, n=args.n, frames=args.frames, seed=args.seed, protocol=args.protocol,
                                 json_path=args.json if args.json != "-" else None)
    print(json.dumps(figures, indent=2) if args.json == "-" else format_figures(figures))
    return 0
