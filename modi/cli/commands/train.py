"""``modi train``: train MoDi on a folder of BVH files (or the built-in procedural clips)."""
from __future__ import annotations

import argparse
import sys
import warnings

from modi.cli import leave_without_teardown
from modi.cli import types as ct


def register(subparsers) -> None:
    from modi.api.options import MODI_ABLATIONS as ABLATIONS, MODI_PRESETS as PRESETS  # lazy: every command registers
    from modi.api.options import GRAPH_MODES, PRECISIONS  # lazy: every command registers

    p = subparsers.add_parser(
        "train", help="train a MoDi generator on BVH clips",
        description="Train MoDi (skeleton-aware StyleGAN2 for motion) on every BVH under DATA_DIR, or on the "
                    "built-in procedural clips when DATA_DIR is the word 'procedural'. Writes RUN_DIR/checkpoint.pt "
                    "(one self-contained file), TensorBoard scalars in RUN_DIR/tb, RUN_DIR/log.jsonl and sample "
                    "BVH + GIF grids in RUN_DIR/samples. Ctrl-C (exit 130) and SIGTERM (exit 143) finish the step and "
                    "save a checkpoint; --resume continues exactly. A run folder in use by another run is refused. "
                    "Multi-process: torchrun --nproc-per-node N -m modi train ... (gloo on CPU, NCCL on GPU); a "
                    "torchrun restart continues from the newest checkpoint, and a lost process is one line and exit "
                    "75 (see docs/distributed.md).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", metavar="DATA_DIR", help="folder of BVH files, or 'procedural'")
    p.add_argument("--out", required=True, metavar="RUN_DIR", type=ct.output_dir, help="run folder (created if missing)")
    p.add_argument("--preset", choices=sorted(PRESETS), default=argparse.SUPPRESS,
                   help="model/optimiser preset: 'paper' (channels 256..32, batch 16, 80k iters) or 'small' (CPU) "
                        "(default: paper)")
    p.add_argument("--ablation", action="append", choices=sorted(ABLATIONS), default=[],
                   help="paper ablation to apply (repeatable)")
    keep = argparse.SUPPRESS  # unset options keep the preset's value
    p.add_argument("--iters", type=ct.iters_int, default=keep, help="total iterations (default: paper 80000, small 5000)")
    p.add_argument("--batch", type=ct.batch_int, default=keep,
                   help="total batch over all processes (default: paper 16, small 8)")
    p.add_argument("--lr", type=ct.lr_float, default=keep, help="Adam learning rate for G and D (default: 0.002)")
    p.add_argument("--mixing", type=ct.probability, default=keep, help="style-mixing probability (default: 0.9)")
    p.add_argument("--frames", type=ct.multiple_of(16, 16, 4096), default=keep,
                   help="frames per training window, a multiple of 16 (default: 64)")
    p.add_argument("--fps", type=ct.fps_float, default=keep, help="resample clips to this rate (default: 30)")
    p.add_argument("--stride", type=ct.int_range(1, ct.MAX_FRAMES), default=keep, help="frames between training windows (default: 8)")
    p.add_argument("--feet", nargs="+", metavar="JOINT", default=keep, help="contact joints (default: detected)")
    p.add_argument("--drop", nargs="+", metavar="REGEX", default=keep,
                   help="drop joints whose names match (default: fingers and face joints)")
    p.add_argument("--keep", nargs="+", metavar="JOINT", default=keep, help="joints never dropped (default: none)")
    p.add_argument("--seed", type=ct.seed_int, default=keep, help="training seed (default: 0)")
    p.add_argument("--noise-injection", action="store_const", const=True, default=keep,
                   help="add StyleGAN2 per-frame noise in every styled conv (default: off, as the released MoDi)")
    p.add_argument("--contact-loss", choices=("released", "squared"), default=keep,
                   help="contact consistency: 'released' = s(c) x ankle speed per frame in data units (the authors' "
                        "code); 'squared' = s(c) x speed^2 in body heights/s on the contact joints (paper eq. 3) "
                        "(default: released)")
    p.add_argument("--neighbors", choices=("siblings", "tree"), default=keep,
                   help="skeletal-conv neighbours: 'siblings' = edges sharing a joint; 'tree' = self + parent + "
                        "children, as the released MoDi (default: siblings)")
    p.add_argument("--pooling", choices=("merge", "released"), default=keep,
                   help="pooling hierarchy: 'merge' = down to one entity; 'released' = root edge never pooled, "
                        "root-motion and contact entities kept to the coarsest level, stop at <= 2 edges "
                        "(default: merge)")
    p.add_argument("--representation", choices=("released", "joints"), default=keep,
                   help="'released' = no root anchor that only repeats its child (Bandai's joint_Root) and no "
                        "rotation for joints without children, as the released MoDi preprocessing; 'joints' = "
                        "every joint and rotation (default: joints)")
    p.add_argument("--log-every", type=ct.positive_int, default=keep, help="steps between logged scalars (default: 10)")
    p.add_argument("--sample-every", type=ct.nonneg_int, default=keep,
                   help="steps between sample grids, 0 = never (default: paper 1000, small 500)")
    p.add_argument("--ckpt-every", type=ct.nonneg_int, default=keep,
                   help="steps between checkpoint writes (default: paper 500, small 250)")
    p.add_argument("--resume", nargs="?", const=True, default=None, metavar="CKPT",
                   help="continue from CKPT (default: the run's newest checkpoint, RUN_DIR/checkpoint.pt); 'auto': "
                        "continue the run's newest checkpoint when there is one, else start (what a torchrun "
                        "restart does by itself). The config comes from the checkpoint: an option given that "
                        "differs from it is refused, except --iters, --log-every, --sample-every, --ckpt-every")
    p.add_argument("--precision", choices=PRECISIONS, default=argparse.SUPPRESS,
                   help="forward passes in fp32, or under bf16 autocast (weights, optimiser states and checkpoints "
                        "stay fp32; see docs/precision.md) (default: a resumed checkpoint's, else fp32; given on "
                        "--resume, the run switches to it)")
    p.add_argument("--cuda-graphs", choices=GRAPH_MODES, default="auto",
                   help="replay each kind of training step (plain, path length, R1, both) as one CUDA graph: far "
                        "fewer launches on a GPU. 'auto' stays eager until a GPU run has shown graphed training "
                        "equal to eager; 'on' asks for graphs (on a CPU: one warning, eager; a step that cannot be "
                        "captured: one warning, the run goes on eagerly); single process only (see "
                        "docs/cli.md#cuda-graphs)")
    p.add_argument("--dist-timeout", type=ct.positive_finite_float, default=argparse.SUPPRESS, metavar="SECONDS",
                   help="under torchrun: seconds a process waits for the others before the run stops as a lost peer "
                        "(exit 75) (default: $MODI_DIST_TIMEOUT or 300)")
    p.add_argument("--device", default="auto", type=ct.device_or_auto, help="cpu, cuda, cuda:N or auto")
    p.add_argument("--threads", type=ct.threads_int, default=argparse.SUPPRESS,
                   help="torch CPU threads (default: torch's choice; 1 is fastest on a busy machine)")
    p.add_argument("--no-tensorboard", action="store_true", help="do not write TensorBoard event files")
    p.add_argument("--no-cache", action="store_true", help="rebuild the dataset instead of using the cache")
    p.set_defaults(func=run)


_OPTIONS = (("iters", "train.iters"), ("batch", "train.batch"), ("lr", "train.lr"),
            ("mixing", "train.mixing"), ("frames", "data.n_frames"), ("fps", "data.fps"),
            ("stride", "data.stride"), ("feet", "data.feet"), ("seed", "train.seed"),
            ("drop", "data.drop_patterns"), ("keep", "data.keep_joints"),
            ("log_every", "train.log_every"), ("sample_every", "train.sample_every"),
            ("ckpt_every", "train.ckpt_every"), ("noise_injection", "model.noise_injection"),
            ("contact_loss", "train.contact_loss"), ("neighbors", "model.neighbors"),
            ("pooling", "model.pooling"))
SPELLING = {"resume": "--resume", "resume_auto": "--resume auto", "resume_path": "--resume", "out": "--out",
            "preset": "--preset", "ablation": "--ablation"}  # how the API's messages name the options


def _overrides(args: argparse.Namespace) -> tuple[dict, dict]:
    """The config keys the command line sets explicitly (unset options are absent from ``args``), and how each was
    given (``--lr 0.001``), for the messages that refuse one."""
    overrides, given = {}, {}
    for flag, key in _OPTIONS:
        value = getattr(args, flag, None)
        if value is not None:
            overrides[key] = value
            shown = " ".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)
            given[key] = "--" + flag.replace("_", "-") + ("" if value is True else f" {shown}")
    if getattr(args, "representation", None) is not None:
        released = args.representation == "released"
        overrides["data.drop_root_anchor"] = released
        overrides["data.leaf_rotations"] = "drop" if released else "keep"
        for key in ("data.drop_root_anchor", "data.leaf_rotations"):
            given[key] = f"--representation {args.representation}"
    return overrides, given


def build_config(args: argparse.Namespace):
    """The config of a new run from the command line."""
    from modi.api.training import modi_config  # lazy: torch

    return modi_config(getattr(args, "preset", "paper"), args.ablation, _overrides(args)[0])


def run(args: argparse.Namespace) -> int:
    from modi.api import training as api  # lazy: torch

    overrides, given = _overrides(args)
    hold: list = []
    if api.launched_by_torchrun():  # the process group is never torn down: see leave_without_teardown
        leave_without_teardown(hold)
    with warnings.catch_warnings():  # restores the hook on the way out
        warnings.showwarning = _one_line(warnings.showwarning, api.GraphFallbackWarning)
        result = api.run_modi_training(
            args.data, args.out, preset=getattr(args, "preset", None), default_preset="paper",
            ablations=args.ablation, config=overrides, resume=args.resume, device=args.device,
            threads=getattr(args, "threads", None), dist_timeout=getattr(args, "dist_timeout", None),
            tensorboard=not args.no_tensorboard, cache=not args.no_cache, log=lambda line: print(line, flush=True),
            spelling={**SPELLING, **given}, hold=hold, precision=getattr(args, "precision", None),
            cuda_graphs=args.cuda_graphs)
    return result.exit_code


def _one_line(show, category: type):
    """``warnings.showwarning`` that prints a ``category`` warning as its message alone on stderr (the CUDA-graph
    notices are one line each, not Python's two with the source), and hands any other warning to ``show``."""

    def showwarning(message, cat, filename, lineno, file=None, line=None):
        if issubclass(cat, category):
            print(str(message), file=file or sys.stderr, flush=True)
        else:
            show(message, cat, filename, lineno, file, line)
    return showwarning
