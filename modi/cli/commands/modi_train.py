"""``modi train``: train MoDi on a folder of BVH files (or the built-in procedural clips)."""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from modi.cli import types as ct
from modi.errors import UserError


def register(subparsers) -> None:
    from modi.models.modi.config import ABLATIONS, PRESETS

    p = subparsers.add_parser(
        "train", help="train a MoDi generator on BVH clips",
        description="Train MoDi (skeleton-aware StyleGAN2 for motion) on every BVH under DATA_DIR, or on the "
                    "built-in procedural clips when DATA_DIR is the word 'procedural'. Writes RUN_DIR/checkpoint.pt "
                    "(one self-contained file), TensorBoard scalars in RUN_DIR/tb, RUN_DIR/log.jsonl and sample "
                    "BVH + GIF grids in RUN_DIR/samples. Ctrl-C (exit 130) and SIGTERM (exit 143) finish the step and "
                    "save a checkpoint; --resume continues exactly. A run folder in use by another run is refused. "
                    "Multi-process: torchrun --nproc_per_node N -m modi train ... (gloo on CPU, NCCL on GPU).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", metavar="DATA_DIR", help="folder of BVH files, or 'procedural'")
    p.add_argument("--out", required=True, metavar="RUN_DIR", type=ct.output_dir, help="run folder (created if missing)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper",
                   help="model/optimiser preset: 'paper' (channels 256..32, batch 16, 80k iters) or 'small' (CPU)")
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
    p.add_argument("--resume", nargs="?", const="auto", default=None, metavar="CKPT",
                   help="continue from CKPT (default RUN_DIR/checkpoint.pt); config comes from the checkpoint")
    p.add_argument("--device", default="auto", type=ct.device_or_auto, help="cpu, cuda, cuda:N or auto")
    p.add_argument("--threads", type=ct.threads_int, default=argparse.SUPPRESS,
                   help="torch CPU threads (default: torch's choice; 1 is fastest on a busy machine)")
    p.add_argument("--no-tensorboard", action="store_true", help="do not write TensorBoard event files")
    p.add_argument("--no-cache", action="store_true", help="rebuild the dataset instead of using the cache")
    p.set_defaults(func=run)


def _device(name: str):
    import torch

    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise UserError(f"--device: unknown device {name!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda requested but torch has no CUDA device")
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return dev


def build_config(args: argparse.Namespace):
    from modi.models.modi.config import make_config

    ct.unique_names("--feet", getattr(args, "feet", None))
    overrides = {}
    for flag, key in (("iters", "train.iters"), ("batch", "train.batch"), ("lr", "train.lr"),
                      ("mixing", "train.mixing"), ("frames", "data.n_frames"), ("fps", "data.fps"),
                      ("stride", "data.stride"), ("feet", "data.feet"), ("seed", "train.seed"),
                      ("drop", "data.drop_patterns"), ("keep", "data.keep_joints"),
                      ("log_every", "train.log_every"), ("sample_every", "train.sample_every"),
                      ("ckpt_every", "train.ckpt_every"), ("noise_injection", "model.noise_injection"),
                      ("contact_loss", "train.contact_loss"), ("neighbors", "model.neighbors"),
                      ("pooling", "model.pooling")):
        value = getattr(args, flag, None)
        if value is not None:
            overrides[key] = value
    if getattr(args, "representation", None) is not None:
        released = args.representation == "released"
        overrides["data.drop_root_anchor"] = released
        overrides["data.leaf_rotations"] = "drop" if released else "keep"
    try:
        return make_config(args.preset, args.ablation, **overrides)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    from modi.models.modi.training import init_distributed_from_env

    device = _device(args.device)
    rank, world = init_distributed_from_env(device)
    with _run_folder_lock(Path(args.out), rank, world, device):
        return _run(args, device, rank, world)


def _run_folder_lock(run_dir: Path, rank: int, world: int, device):
    """Rank 0 takes RUN_DIR's lock before anything else (a second run is refused at once, before any data is
    read); under torchrun every rank learns the outcome, so all of them exit 2 together."""
    from contextlib import ExitStack

    from modi import faults

    stack, refusal = ExitStack(), None
    if rank == 0:
        try:
            stack.enter_context(faults.hold_run_folder(run_dir))
        except UserError as exc:
            refusal = exc
    if world > 1:
        import torch
        import torch.distributed as dist

        flag = torch.tensor([int(refusal is not None)], device=device if device.type == "cuda" else "cpu")
        dist.broadcast(flag, 0)
        if int(flag.item()) and refusal is None:
            refusal = UserError(f"{run_dir}: rank 0 could not take the run folder (see its message)")
    if refusal is not None:
        stack.close()
        raise refusal
    return stack


def _run(args: argparse.Namespace, device, rank: int, world: int) -> int:
    import torch

    from modi import faults
    from modi.models.modi.config import MoDiConfig
    from modi.models.modi.sampling import load_checkpoint
    from modi.models.modi.training import NonFiniteLossError, Trainer, prepare_data

    if getattr(args, "threads", None) is not None:
        if args.threads < 1:
            raise UserError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    run_dir = Path(args.out)
    resume_state = None
    if args.resume is not None:
        ckpt_path = run_dir / "checkpoint.pt" if args.resume == "auto" else Path(args.resume)
        ct.input_file(ckpt_path, "checkpoint to resume", "--resume")
        resume_state = load_checkpoint(ckpt_path)
        cfg = MoDiConfig.from_dict(resume_state["config"])
        for flag, section, attr in (("iters", "train", "iters"), ("log_every", "train", "log_every"),
                                    ("sample_every", "train", "sample_every"), ("ckpt_every", "train", "ckpt_every")):
            if getattr(args, flag, None) is not None:
                setattr(getattr(cfg, section), attr, getattr(args, flag))
        cfg.validate()
    else:
        cfg = build_config(args)
        if (run_dir / "checkpoint.pt").exists():
            raise UserError(f"{run_dir / 'checkpoint.pt'} exists: pass --resume to continue it, or choose a new --out")
    if getattr(args, "iters", 0) < 0:
        raise UserError(f"--iters must be >= 0, got {args.iters}")
    run_dir.mkdir(parents=True, exist_ok=True)
    normalizer = None
    if resume_state is not None:
        from modi.data.normalization import Normalizer

        normalizer = Normalizer.from_state_dict(resume_state["codec"]["normalizer"])
    data = prepare_data(args.data, cfg, work_dir=run_dir, cache=not args.no_cache, progress=rank == 0,
                        normalizer=normalizer)
    if rank == 0:
        faults.atomic_write(run_dir / "config.json", json.dumps(cfg.to_dict(), indent=1) + "\n")
        s = data.summary
        print(f"modi train: {data.windows.shape[0]} training windows {tuple(data.windows.shape[1:])} from "
              f"{s.get('train_clips', '?')} clips; hierarchy {data.hierarchy.entity_counts}; preset {cfg.preset}; "
              f"{world} process(es) on {device}; {cfg.train.iters} iterations", flush=True)
    trainer = Trainer(cfg, data, run_dir, device=device, resume=resume_state,
                      tensorboard=not args.no_tensorboard)
    try:
        result = trainer.train()
    except NonFiniteLossError as exc:
        raise UserError(str(exc)) from None
    if rank == 0:
        losses = ", ".join(f"{k} {v:.4f}" for k, v in result.last_losses.items() if k in ("d", "g", "r1", "path",
                                                                                        "touch", "contact"))
        print(f"modi train: step {result.step} in {result.seconds:.1f} s; checkpoint {result.checkpoint}; {losses}")
    return result.exit_code
