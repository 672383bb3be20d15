"""``modi ganimator train|generate|evaluate``: single-sequence GANimator from the command line."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

from modi.cli import types as ct
from modi.errors import UserError
from modi.io.formats import add_format_options
from modi.viz import add_view_option

_FMT = argparse.ArgumentDefaultsHelpFormatter


def register(subparsers) -> None:
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
    t.add_argument("--preset", default="paper", choices=["paper", "fast", "tiny"],
                   help="paper: published schedule (15k iterations per block); fast: CPU schedule (300 per block, "
                        "900 on the coarsest); tiny: smoke test. All take 5 discriminator steps per generator step")
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
    t.add_argument("--threads", type=ct.threads_int, default=None, help="torch CPU threads (default: torch's choice)")
    t.add_argument("--max-minutes", type=ct.minutes_float, default=None,
                   help="stop (checkpointed) after this many minutes; run again to continue")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=_train)

    g = sub.add_parser("generate", help="sample motions from a trained run", formatter_class=_FMT,
                       description="Generate BVH (+ GIF previews) from a trained run: random motions of any "
                                   "length, style transfer (--content), key-frame editing (--keyframes), "
                                   "trajectory control (--trajectory).")
    g.add_argument("run", help="run directory (or .ckpt file)")
    g.add_argument("--frames", type=ct.frames_int, default=None, help="frames per motion (default: the training clip's)")
    g.add_argument("--n", type=ct.int_range(1, 1000), default=1, help="number of motions (a crowd when > 1)")
    g.add_argument("--out", required=True, type=ct.output_dir, help="output directory")
    g.add_argument("--seed", type=ct.seed_int, default=0, help="random seed")
    g.add_argument("--content", default=None, help="style transfer: BVH whose coarse motion replaces level 0")
    g.add_argument("--keyframes", default=None, help="key-frame editing: BVH of coarse-level poses")
    g.add_argument("--trajectory", default=None,
                   help="root trajectory BVH (conditional runs); without it a conditional run samples one")
    g.add_argument("--stream", type=ct.int_range(0, ct.MAX_FRAMES), default=0,
                   help="with --trajectory: feed the trajectory in segments of this many frames (streaming API)")
    g.add_argument("--ik", action="store_true", help="fix foot sliding with IK where contacts are predicted")
    g.add_argument("--fine-noise", action="store_true", help="random noise at every level (default: coarsest only)")
    g.add_argument("--crowd-spacing", type=ct.nonneg_finite_float, default=None,
                   help="grid spacing of a crowd (default: 1.5 x body size; 0: every motion at its own start)")
    g.add_argument("--no-gif", action="store_true", help="do not render GIF previews")
    g.add_argument("--evaluate", action="store_true", help="print coverage / diversity of each motion vs the sources")
    add_format_options(g)
    g.set_defaults(func=_generate)
    add_view_option(g)

    e = sub.add_parser("evaluate", help="coverage and diversity of random samples of a run", formatter_class=_FMT,
                       description="Sample motions and report coverage (30-frame windows, threshold 2.0), global "
                                   "(patched nearest neighbour) and local diversity against every training clip. "
                                   "--protocol ours (default): rotations decoded from the samples, as any BVH "
                                   "output is scored. --protocol paper: the authors' released evaluate.py (200 "
                                   "samples of 2x the total source length, the generator's raw 6D + contact "
                                   "channels, per-clip figures and the script's running average over clips).")
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


def _coarsest_needed(cfg) -> int:
    """Frames the coarsest pyramid level needs: its convolutions reflect-pad ``kernel_size // 2`` frames on each
    side, and reflect padding of p frames needs more than p frames."""
    return cfg.kernel_size // 2 + 1 if cfg.padding_mode == "reflect" else 1


def _min_frames(cfg, coarsest_length: Callable[[int], int]) -> int:
    """The shortest sequence (training clip or output) whose coarsest pyramid level, ``coarsest_length(n)`` frames
    for ``n`` frames, is long enough for the convolutions of ``cfg``."""
    need = _coarsest_needed(cfg)
    for n in range(2, ct.MAX_FRAMES):
        if coarsest_length(n) >= need:
            return n
    return ct.MAX_FRAMES


def _min_training_frames(cfg) -> int:
    from modi.models.ganimator.data import pyramid_lengths

    return _min_frames(cfg, lambda n: pyramid_lengths(n, cfg.coarse_ratio, cfg.scale_factor)[0])


def _check_training_length(clips, cfg) -> None:
    need = _coarsest_needed(cfg)
    n_min = _min_training_frames(cfg)
    for c in clips:
        if c.n_frames < n_min:
            raise UserError(
                f"{c.name}: {c.n_frames} frames at {c.fps:g} fps (after resampling) is too short for GANimator: "
                f"it needs at least {n_min} frames, because the coarsest pyramid level (--coarse-ratio "
                f"{cfg.coarse_ratio:g} of the clip) must have {need} frames or more for the {cfg.kernel_size}-frame "
                f"convolutions' reflect padding of {need - 1} frames")


def _min_output_frames(model) -> int:
    """Shortest output length whose coarsest level is long enough for the model's convolutions."""
    return _min_frames(model.cfg, lambda n: model.level_lengths(n)[0])


def _check_generation_length(args) -> None:
    """Refuse --frames / --content / --keyframes too short for the run's pyramid, before anything is written."""
    from modi.models.ganimator.data import load_sequence
    from modi.models.ganimator.training import load_model

    if not Path(args.run).exists():
        raise UserError(f"{args.run}: no such GANimator run folder or checkpoint file")
    model = load_model(args.run)
    need, n_min = _coarsest_needed(model.cfg), _min_output_frames(model)
    why = (f"the coarsest pyramid level ({model.rates[0][0]:.3g} of the length) must have {need} frames or more for "
           f"the convolutions' reflect padding of {need - 1} frames")
    if args.frames is not None and args.frames < n_min:
        raise UserError(f"--frames {args.frames} is too short for this run: at least {n_min} frames, because {why}")
    for opt, path in (("--content", args.content), ("--keyframes", args.keyframes), ("--trajectory", args.trajectory)):
        if path is None:
            continue
        if not Path(path).is_file():
            raise UserError(f"{opt} {path}: no such BVH file")
        clip = load_sequence(path, model.cfg, like=model.seqs[0])
        if opt == "--keyframes":
            if clip.n_frames < 2:
                raise UserError(f"--keyframes {path}: {clip.n_frames} frame at {clip.fps:g} fps (after resampling); "
                                "key-frame editing needs at least 2 key-frames (the root motion is their difference)")
        elif clip.n_frames < n_min:
            raise UserError(f"{opt} {path}: {clip.n_frames} frames at {clip.fps:g} fps (after resampling) is too short "
                            f"for this run: at least {n_min} frames, because {why}")


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
    from modi import faults

    with faults.hold_run_folder(Path(args.out)):  # a second run into the folder is refused before any work
        return _train_locked(args)


def _train_locked(args) -> int:
    import torch

    from modi.models.ganimator.config import preset
    from modi.models.ganimator.data import load_sequences
    from modi.models.ganimator.training import TrainingInterrupted, load_model, train

    if args.threads:
        torch.set_num_threads(args.threads)
    ct.unique_names("--feet", _csv(args.feet))
    cfg = preset(args.preset, iterations=args.iterations, d_steps=args.d_steps, base_channels=args.base_channels,
                 coarse_ratio=args.coarse_ratio, keep_joints=_csv(args.keep_joints), feet=_csv(args.feet),
                 fps=args.fps, device=args.device, seed=args.seed,
                 block_iterations=_int_csv(args.block_iters, "--block-iters"),
                 coarse_multiplier=args.coarse_multiplier, contact_rescale=args.contact_rescale,
                 contact_first_frame=args.contact_first_frame, bias_init=args.bias_init, sixd=args.sixd)
    if args.no_joint_reduction:
        cfg = cfg.replace(joint_reduction=False)
    if args.no_contacts:
        cfg = cfg.replace(contacts=False)
    cond_source = None
    if args.conditional_from:
        if not Path(args.conditional_from).exists():
            raise UserError(f"--conditional-from {args.conditional_from}: no such GANimator run folder or checkpoint file")
        cond_source = load_model(args.conditional_from, device=cfg.device)
        cfg = cfg.replace(conditional=True)
        if cond_source.cfg.sixd != cfg.sixd:
            raise UserError(f"--conditional-from: that run uses {cond_source.cfg.sixd} 6D; pass --sixd "
                            f"{cond_source.cfg.sixd} to train a model that can read its trajectories")
    for b in args.bvh:
        ct.input_file(b)
    clips = load_sequences(args.bvh, cfg)
    if cond_source is not None and [c.name for c in cond_source.seqs] != [c.name for c in clips]:
        raise UserError("--conditional-from must be a run trained on the same BVH file(s)")
    _check_training_length(clips, cfg)
    c = clips[0]
    if 0 in c.feet:
        raise UserError(f"--feet: the root joint {c.skeleton.names[0]} cannot be a foot (contacts pin feet relative "
                        "to the root)")
    print(f"{len(clips)} clip(s), {c.n_joints} joints, feet {[c.skeleton.names[f] for f in c.feet]}, "
          f"{', '.join(str(x.n_frames) for x in clips)} frames at {c.fps:.1f} fps")
    from modi.models.ganimator.data import sequence_pyramid
    from modi.models.ganimator.training import blocks_of

    n_blocks = len(blocks_of(len(sequence_pyramid(clips, cfg)[0][0]), cfg.group_size))
    print(f"{n_blocks} blocks of {cfg.group_size} levels, iterations {cfg.block_budgets(n_blocks)} "
          f"({cfg.d_steps} D : {cfg.g_steps} G : 1 reconstruction steps each)")
    try:
        train(clips, cfg, args.out, progress=not args.quiet,
              max_seconds=args.max_minutes * 60 if args.max_minutes else None, cond_source=cond_source)
    except TrainingInterrupted as exc:
        print(f"modi ganimator train: interrupted; checkpoint saved to {exc.checkpoint} "
              "(run the same command again to continue)", file=sys.stderr)
        return exc.exit_code
    print(f"checkpoint: {Path(args.out) / 'ganimator.ckpt'}")
    return 0


def _generate(args) -> int:
    from modi.models.ganimator.generate import generate_command

    _check_generation_length(args)
    result = generate_command(args)
    if args.evaluate and result.get("metrics"):
        print(json.dumps(result["metrics"], indent=2))
    return 0


def _evaluate(args) -> int:
    from modi.models.ganimator.evaluate_paper import N_SAMPLES, evaluate_paper, format_figures
    from modi.models.ganimator.generate import evaluate_run

    if args.n is not None and args.n < 1:
        raise UserError("--n must be at least 1")
    if args.frames is not None and args.frames < 30:
        raise UserError("--frames must be at least 30 (the coverage window)")
    if args.json and args.json != "-":
        from modi.models.ganimator.training import checkpoint_path

        ct.refuse_overwrite(args.json, [checkpoint_path(args.run)], "--json")
    if args.protocol == "paper":
        figures = evaluate_paper(args.run, n=args.n or N_SAMPLES, n_frames=args.frames, seed=args.seed)
    else:
        figures = evaluate_run(args.run, n=args.n or 10, n_frames=args.frames, seed=args.seed)
    text = json.dumps(figures, indent=2)
    print(text if args.json == "-" else format_figures(figures))
    if args.json and args.json != "-":
        from modi.faults import atomic_write

        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.json, text + "\n")
    return 0
