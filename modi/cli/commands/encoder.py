"""``modi encoder train|eval`` and ``modi apply invert|prefix|fuse|denoise|edit``: MoDi's encoder into W+.

Inputs to ``modi apply`` are BVH clips on the generator's skeleton (joints matched by name; a window of the
model's length is cut at ``--start``) or ``test:I`` -- window I of the 20% test split of the data the encoder was
trained on (unseen by both networks; ``--data`` points elsewhere).
"""
from __future__ import annotations

import argparse
import sys

from modi.cli import types as ct
from modi.io.formats import add_format_options
from modi.viz import add_view_option


def _units(text: str) -> str:
    """A length unit of the mm metrics, checked while parsing (not after hours of training)."""
    from modi.api.options import LENGTH_UNITS  # lazy: torch

    if text != "auto" and text not in LENGTH_UNITS:
        raise argparse.ArgumentTypeError(f"unknown unit {text!r}; choose from auto, {', '.join(LENGTH_UNITS)}")
    return text


def _runtime(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", type=ct.device, help="cpu, cuda or cuda:N")
    p.add_argument("--threads", type=ct.threads_int, default=None, help="torch CPU threads (default: torch's choice)")


def register(subparsers) -> None:
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = subparsers.add_parser("encoder", help="train / evaluate the encoder into W+", description=__doc__,
                              formatter_class=fmt)
    sub = p.add_subparsers(dest="encoder_command", metavar="ACTION")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    q = sub.add_parser("train", help="train an encoder for a frozen generator", formatter_class=fmt,
                       description="Train the encoder I (reverse synthesis hierarchy -> W+) on the 80% split of DATA "
                                   "(split by file like the generator's data) with the generator frozen; losses: "
                                   "λ_rec rec L2 + λ_contact BCE + λ_root root L2 + λ_pos FK-position L2 (the "
                                   "released code's form and weights by default, --losses ours for ours). Writes ENC "
                                   "(one self-contained checkpoint with the generator inside) and ENC.log.jsonl, and "
                                   "prints the Table 5 metrics on the 20% test split. Ctrl-C (exit 130) and SIGTERM "
                                   "(exit 143) finish the step and save; --resume continues.")
    q.add_argument("ckpt", metavar="CKPT", help="MoDi generator checkpoint")
    q.add_argument("data", metavar="DATA", help="BVH folder the generator was trained on, or 'procedural'")
    q.add_argument("--out", required=True, metavar="ENC", type=ct.output_file, help="encoder checkpoint to write (e.g. runs/enc.pt)")
    q.add_argument("--iters", type=ct.iters_int, default=5000, help="training steps")
    q.add_argument("--batch", type=ct.batch_int, default=16, help="batch size")
    q.add_argument("--losses", choices=("released", "ours"), default=None,
                   help="loss form: 'released' (the default) = the authors' code (weights rec/contact/root/pos "
                        "10/1000/20/1, root L2 on the real root rotation, FK positions local, in data units); "
                        "'ours' = 1/100/2/0.1, root L2 on entity 0, global positions in tenths of the body size. "
                        "With --resume: the checkpoint's, like the other loss, optimizer and head options")
    q.add_argument("--optimizer", choices=("released", "ours"), default=None,
                   help="Adam defaults: 'released' (the default) lr 0.002*16/17, betas (0, 0.99^(16/17)); 'ours' lr "
                        "0.002, betas (0.9, 0.99)")
    q.add_argument("--head", choices=("released", "bottleneck"), default=None,
                   help="encoder head: 'released' (the default) = features one level before the coarsest through two "
                        "linear layers of width n_latent x latent_dim -> W+; 'bottleneck' = the earlier head "
                        "(coarsest level, one --hidden-wide layer, offset from the mean latent)")
    q.add_argument("--lr", type=ct.lr_float, default=None, help="Adam learning rate (default: from --optimizer)")
    q.add_argument("--lambda-rec", type=ct.float_range(0.0, 1e6), default=None, help="weight of the representation L2 "
                   "(default: from --losses)")
    q.add_argument("--lambda-contact", type=ct.float_range(0.0, 1e6), default=None, help="weight of the contact BCE "
                   "(default: from --losses)")
    q.add_argument("--lambda-root", type=ct.float_range(0.0, 1e6), default=None, help="weight of the root L2 (default: from --losses)")
    q.add_argument("--lambda-pos", type=ct.float_range(0.0, 1e6), default=None,
                   help="weight of the FK-position L2 (default: from --losses)")
    q.add_argument("--prefix", type=ct.positive_int, default=None, metavar="T",
                   help="train the prefix variant: the encoder sees frames [0, T) only")
    q.add_argument("--channel-multiplier", type=ct.float_range(0.0, 64.0, lo_inclusive=False), default=1.0, help="encoder width relative to the generator")
    q.add_argument("--hidden", type=ct.int_range(1, 8192), default=None,
                   help="bottleneck head only: width of its hidden layer (default: max(latent, channels))")
    q.add_argument("--units", default="auto", type=_units, help="data length unit for the mm metrics (auto, mm, cm, m, in)")
    q.add_argument("--seed", type=ct.seed_int, default=0, help="seed")
    q.add_argument("--eval-every", type=ct.nonneg_int, default=500, help="steps between test-split evaluations (0: end only)")
    q.add_argument("--ckpt-every", type=ct.nonneg_int, default=250, help="steps between checkpoint writes")
    q.add_argument("--resume", action="store_true",
                   help="continue ENC instead of starting anew, with its loss form, weights, optimizer and head")
    q.add_argument("--no-cache", action="store_true", help="rebuild the dataset instead of using the cache")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    _runtime(q)
    q.set_defaults(func=run_train)

    q = sub.add_parser("eval", help="Table 5 metrics of an encoder on a data split", formatter_class=fmt,
                       description="Reconstruction errors of G(I(m)) on the test (default) or train split: L2 and "
                                   "L1 on the whole normalised representation, global root / local / global joint "
                                   "position errors in two definitions -- ours (mean distance, mm) and the released "
                                   "code's (mean squared coordinate error in data units, the figures the paper's "
                                   "Table 5 reports) -- beside the mean-motion and data-mean baselines and the "
                                   "paper's Mixamo row.")
    q.add_argument("enc", metavar="ENC", help="encoder checkpoint")
    q.add_argument("data", metavar="DATA", nargs="?", default=None,
                   help="BVH folder (default: the data the encoder was trained on)")
    q.add_argument("--split", choices=("test", "train"), default="test", help="which split to score")
    q.add_argument("--units", default="auto", type=_units, help="data length unit (auto, mm, cm, m, in)")
    q.add_argument("--json", default=None, metavar="FILE", type=ct.output_file, help="also write the metrics as JSON")
    _runtime(q)
    q.set_defaults(func=run_eval)

    a = subparsers.add_parser("apply", help="encoder applications: invert, prefix, fuse, denoise, edit",
                              description=__doc__, formatter_class=fmt)
    asub = a.add_subparsers(dest="apply_command", metavar="TASK")
    a.set_defaults(func=lambda args: (a.print_help(), 2)[1])

    def task(name: str, help_: str, desc: str, n_inputs: str = "+") -> argparse.ArgumentParser:
        t = asub.add_parser(name, help=help_, description=desc + " Each input gives NAME_input.bvh, NAME_naive.bvh, "
                            "NAME_encoder.bvh and NAME.gif (the three side by side); results.json has the numbers.",
                            formatter_class=fmt)
        t.add_argument("enc", metavar="ENC", help="encoder checkpoint ('modi encoder train')")
        t.add_argument("inputs", metavar="INPUT", nargs=n_inputs, help="BVH file or test:I")
        t.add_argument("--out", required=True, metavar="DIR", type=ct.output_dir, help="output folder")
        t.add_argument("--start", type=ct.int_range(0, ct.MAX_FRAMES), default=0, help="first frame of the window cut from BVH inputs")
        t.add_argument("--data", default=None, help="data folder for test:I inputs (default: the encoder's)")
        _runtime(t)
        add_format_options(t)
        return t

    t = task("invert", "project unseen motions with the encoder (vs optimisation)",
             "Invert motions into W+ with one encoder pass; the naive column is optimisation-based inversion.")
    t.add_argument("--optim-steps", type=ct.int_range(0, 1_000_000), default=200, help="steps of the optimisation baseline (0: mean motion)")
    t.set_defaults(func=run_apply, task="invert")
    t = task("prefix", "complete motions from their first frames",
             "Predict a whole motion from its prefix with an encoder trained with --prefix; the naive column "
             "holds the last seen pose.")
    t.set_defaults(func=run_apply, task="prefix")
    t = task("fuse", "fuse two clips at a frame", "Frames before --frame from the first input and from the "
             "second after it: the naive column is the hard cut, the encoder smooths the seam.", n_inputs=2)
    t.add_argument("--frame", type=ct.int_range(0, ct.MAX_FRAMES), default=None, help="cut frame t (default: the middle)")
    t.set_defaults(func=run_apply, task="fuse")
    t = task("denoise", "remove noise from motions", "Add Gaussian noise to the joint rotations (normalised "
             "units), then compare temporal smoothing with G(I(noisy)). --given-noisy skips adding noise.")
    t.add_argument("--sigma", type=ct.float_range(0.0, 100.0), default=0.5, help="noise std in normalised units")
    t.add_argument("--smooth", type=ct.float_range(0.0, 1000.0), default=2.0, help="std of the smoothing kernel in frames")
    t.add_argument("--given-noisy", action="store_true", help="inputs are already noisy: add nothing")
    t.add_argument("--seed", type=ct.seed_int, default=0, help="noise seed")
    t.set_defaults(func=run_apply, task="denoise")
    t = task("edit", "turn a crude spatial edit into a natural motion", "Raise the right upper arm by --angle "
             "degrees from --from-frame on (a crude keyframe edit, the naive column) and project it with G∘I.")
    t.add_argument("--angle", type=ct.angle_float, default=90.0, help="degrees the arm is turned toward the sky")
    t.add_argument("--from-frame", type=ct.int_range(0, ct.MAX_FRAMES), default=None, help="first edited frame (default: the middle)")
    t.add_argument("--joint", default=None, help="joint to turn (default: the right shoulder found by name)")
    t.set_defaults(func=run_apply, task="edit")
    for t in asub.choices.values():  # every task writes a GIF, and the 3D viewer beside it
        add_view_option(t)


# --------------------------------------------------------------------------------------------- actions
def run_train(args: argparse.Namespace) -> int:
    from modi.api.encoder import EncoderTrainingInterrupted, format_table5, train_encoder  # lazy: torch

    try:
        res = train_encoder(args.ckpt, args.data, args.out, iters=args.iters, batch=args.batch, losses=args.losses,
                            optimizer=args.optimizer, head=args.head, lr=args.lr, lambda_rec=args.lambda_rec,
                            lambda_contact=args.lambda_contact, lambda_root=args.lambda_root,
                            lambda_pos=args.lambda_pos, prefix=args.prefix,
                            channel_multiplier=args.channel_multiplier, hidden=args.hidden, units=args.units,
                            seed=args.seed, eval_every=args.eval_every, ckpt_every=args.ckpt_every,
                            resume=args.resume, cache=not args.no_cache, progress=not args.quiet, device=args.device,
                            threads=args.threads, log=lambda line: print(line, flush=True))
    except EncoderTrainingInterrupted as exc:
        print(f"modi encoder train: interrupted at step {exc.step}; checkpoint saved to {exc.checkpoint} "
              "(add --resume to the same command to continue)", file=sys.stderr)
        return exc.exit_code
    print(f"modi encoder train: step {res.step} in {res.seconds:.0f} s; checkpoint {res.checkpoint}")
    print(f"Table 5 metrics on the {res.metrics['n_windows']} test windows:")
    print(format_table5(res.metrics))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from modi.api.encoder import evaluate_encoder_file, format_table5  # lazy: torch

    res, enc = evaluate_encoder_file(args.enc, args.data, split=args.split, units=args.units, json_path=args.json,
                                     device=args.device, threads=args.threads)
    source = res.pop("source")
    pre = f" (prefix encoder: sees frames < {enc.prefix_frames})" if enc.prefix_frames else ""
    print(f"modi encoder eval: {args.split} split of {source}, {res['n_windows']} windows, "
          f"{res['mm_per_unit']:g} mm per unit{pre}")
    print(format_table5(res))
    return 0


def run_apply(args: argparse.Namespace) -> int:
    from modi.api.encoder import open_encoder  # lazy: torch

    enc = open_encoder(args.enc, device=args.device, threads=args.threads)
    res = enc.apply(args.task, args.inputs, args.out, start=args.start, data=args.data,
                    optim_steps=getattr(args, "optim_steps", 200), frame=getattr(args, "frame", None),
                    sigma=getattr(args, "sigma", 0.5), smooth=getattr(args, "smooth", 2.0),
                    given_noisy=getattr(args, "given_noisy", False), seed=getattr(args, "seed", 0),
                    angle=getattr(args, "angle", 90.0), from_frame=getattr(args, "from_frame", None),
                    joint=getattr(args, "joint", None))
    keys = [k for k in res[0] if k not in ("bvh", "gif")]
    for r in res:
        nums = ", ".join(f"{k} {r[k]:.4g}" if isinstance(r[k], float) else f"{k} {r[k]}" for k in keys)
        print(f"modi apply {args.task}: {r['gif']}: {nums}")
    return 0
