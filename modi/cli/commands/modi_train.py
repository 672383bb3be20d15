"""``modi train``: train MoDi on a folder of BVH files (or the built-in procedural clips)."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from modi.cli import types as ct
from modi.errors import UserError


LATEST = "\0latest"  # bare --resume: the run's newest checkpoint, which must exist
OVERRIDABLE = ("iters", "log_every", "sample_every", "ckpt_every")  # may change on a resume


def register(subparsers) -> None:
    from modi.models.modi.config import ABLATIONS, PRESETS

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
    p.add_argument("--resume", nargs="?", const=LATEST, default=None, metavar="CKPT",
                   help="continue from CKPT (default: the run's newest checkpoint, RUN_DIR/checkpoint.pt); 'auto': "
                        "continue the run's newest checkpoint when there is one, else start (what a torchrun "
                        "restart does by itself). The config comes from the checkpoint: an option given that "
                        "differs from it is refused, except --iters, --log-every, --sample-every, --ckpt-every")
    p.add_argument("--dist-timeout", type=ct.positive_finite_float, default=argparse.SUPPRESS, metavar="SECONDS",
                   help="under torchrun: seconds a process waits for the others before the run stops as a lost peer "
                        "(exit 75) (default: $MODI_DIST_TIMEOUT or 300)")
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


_OPTIONS = (("iters", "train.iters"), ("batch", "train.batch"), ("lr", "train.lr"),
            ("mixing", "train.mixing"), ("frames", "data.n_frames"), ("fps", "data.fps"),
            ("stride", "data.stride"), ("feet", "data.feet"), ("seed", "train.seed"),
            ("drop", "data.drop_patterns"), ("keep", "data.keep_joints"),
            ("log_every", "train.log_every"), ("sample_every", "train.sample_every"),
            ("ckpt_every", "train.ckpt_every"), ("noise_injection", "model.noise_injection"),
            ("contact_loss", "train.contact_loss"), ("neighbors", "model.neighbors"),
            ("pooling", "model.pooling"))


def _overrides(args: argparse.Namespace) -> dict:
    """The config keys the command line sets explicitly (unset options are absent from ``args``)."""
    overrides = {}
    for flag, key in _OPTIONS:
        value = getattr(args, flag, None)
        if value is not None:
            overrides[key] = value
    if getattr(args, "representation", None) is not None:
        released = args.representation == "released"
        overrides["data.drop_root_anchor"] = released
        overrides["data.leaf_rotations"] = "drop" if released else "keep"
    return overrides


def build_config(args: argparse.Namespace):
    from modi.models.modi.config import make_config

    ct.unique_names("--feet", getattr(args, "feet", None))
    try:
        return make_config(getattr(args, "preset", "paper"), args.ablation, **_overrides(args))
    except ValueError as exc:
        raise UserError(str(exc)) from None


def config_differences(cfg, args: argparse.Namespace) -> list[str]:
    """The options given on the command line that disagree with ``cfg`` (a checkpoint's config), each as
    ``--flag value (the checkpoint has value)``; --iters, --log-every, --sample-every and --ckpt-every may change."""
    from modi.models.modi.config import ABLATIONS

    def show(v) -> str:
        return " ".join(map(str, v)) if isinstance(v, (list, tuple)) else str(v)

    def norm(v):
        return list(v) if isinstance(v, (list, tuple)) else v

    out = []
    if getattr(args, "preset", None) is not None and args.preset != cfg.preset:
        out.append(f"--preset {args.preset} (the checkpoint has {cfg.preset})")
    flags = {key: "--" + flag.replace("_", "-") for flag, key in _OPTIONS}
    wanted: dict[str, tuple[str, object]] = {}  # config key -> (the option as given, the value it sets)
    for name in args.ablation:
        for key, value in ABLATIONS[name].items():
            wanted[key] = (f"--ablation {name}", value)
    for key, value in _overrides(args).items():
        if key.split(".")[1] in OVERRIDABLE:
            continue
        given = (f"{flags[key]} {show(value)}" if key in flags and value is not True else flags.get(key)) \
            or f"--representation {args.representation}"
        wanted[key] = (given, value)
    for key, (given, value) in wanted.items():
        section, attr = key.split(".")
        have = getattr(getattr(cfg, section), attr)
        if norm(have) != norm(value) and not any(o.startswith(given + " (") for o in out):
            out.append(f"{given} ({key} is {show(have)} in the checkpoint)")
    return out


def run(args: argparse.Namespace) -> int:
    from modi.models.modi import distributed as mdist

    device = _device(args.device)
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    state: dict = {"trainer": None, "resumed": None}  # what a lost peer's line reports
    if world > 1:  # the process group is never torn down: see leave_without_teardown
        from modi.cli import leave_without_teardown

        leave_without_teardown(state)
    try:
        rank, world = mdist.init_distributed_from_env(device, getattr(args, "dist_timeout", None))
        with _run_folder_lock(Path(args.out), rank, world, device):
            return _run(args, device, rank, world, state)
    except Exception as exc:
        if world > 1 and mdist.is_peer_failure(exc):
            mdist.leave_quietly_on_signals()
            raise _peer_lost(exc, Path(args.out), state) from None
        raise


def _peer_lost(exc: Exception, run_dir: Path, state: dict) -> UserError:
    """The one line for a lost peer: the step this rank was at and the newest checkpoint it knows of."""
    from modi.models.modi import distributed as mdist

    trainer, resumed = state["trainer"], state["resumed"]
    step = trainer.step if trainer is not None else None
    saved = trainer.saved_step if trainer is not None else None
    where = run_dir / "checkpoint.pt" if saved is not None else None
    if saved is None and resumed is not None:
        where, saved = resumed
    if where is None and (run_dir / "checkpoint.pt").is_file():
        where = run_dir / "checkpoint.pt"
    return mdist.peer_lost_error(exc, step=step, checkpoint=where, checkpoint_step=saved)


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


def _resume_state(args: argparse.Namespace, run_dir: Path, rank: int, world: int):
    """``(path, state)`` of the checkpoint this start continues, or None to start afresh; rank 0 decides and
    reads it, and hands it to the other ranks, so every rank loads the same step (and a run folder on one machine
    serves them all).

    * ``--resume CKPT``: that file -- or, on a torchrun restart, the run's own newest checkpoint once there is one;
    * bare ``--resume``: the run's newest checkpoint, which must exist;
    * ``--resume auto``, or a torchrun restart (``TORCHELASTIC_RESTART_COUNT`` > 0) without ``--resume``: the run's
      newest checkpoint when there is one, else a fresh start.
    """
    import torch.distributed as dist

    from modi.models.modi import distributed as mdist
    from modi.models.modi.sampling import load_checkpoint
    from modi.models.modi.training import newest_checkpoint

    def decide():
        restart = mdist.torchrun_restart() > 0
        mode = args.resume
        if mode is None and restart:
            mode = "auto"
        if mode is None:
            if (run_dir / "checkpoint.pt").exists():
                raise UserError(f"{run_dir / 'checkpoint.pt'} exists: pass --resume to continue it (--resume auto "
                                f"under torchrun), or choose a new --out")
            return None
        if mode in ("auto", LATEST) or restart:
            found = newest_checkpoint(run_dir, warn=lambda msg: print(f"modi: {msg}", file=sys.stderr, flush=True))
            if found is None and (run_dir / "checkpoint.pt").exists():
                raise UserError(f"{run_dir / 'checkpoint.pt'} cannot be read and no snapshot can: move it away to "
                                f"start the run afresh, or choose a new --out")
            if found is not None or mode == "auto":
                return found
            if mode == LATEST:
                raise UserError(f"{run_dir / 'checkpoint.pt'}: no checkpoint to resume in {run_dir} (--resume auto "
                                f"starts a new run when there is none)")
        path = Path(mode)
        ct.input_file(path, "checkpoint to resume", "--resume")
        return path, load_checkpoint(path)

    found, error = None, None
    if rank == 0:
        try:
            found = decide()
        except Exception as exc:  # noqa: BLE001 - told to the other ranks (not left waiting), then raised here
            error = exc
    if world > 1:
        box = [(found, None if error is None else str(error))]
        dist.broadcast_object_list(box, 0)
        found, message = box[0]
        if message is not None and error is None:
            error = UserError(f"rank 0 could not resume the run (see its message: {message})")
    if error is not None:
        raise error
    return found


def _run(args: argparse.Namespace, device, rank: int, world: int, state: dict) -> int:
    import torch

    from modi import faults
    from modi.models.modi.config import MoDiConfig
    from modi.models.modi.training import NonFiniteLossError, Trainer, prepare_data

    if getattr(args, "threads", None) is not None:
        if args.threads < 1:
            raise UserError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    run_dir = Path(args.out)
    found = _resume_state(args, run_dir, rank, world)
    resume_state = None
    if found is not None:
        ckpt_path, resume_state = found
        cfg = MoDiConfig.from_dict(resume_state["config"])
        diffs = config_differences(cfg, args)
        if diffs:
            raise UserError(f"{ckpt_path} was trained with another config: {'; '.join(diffs)}. Drop these options "
                            f"to continue it, or choose a new --out")
        for flag, section, attr in (("iters", "train", "iters"), ("log_every", "train", "log_every"),
                                    ("sample_every", "train", "sample_every"), ("ckpt_every", "train", "ckpt_every")):
            if getattr(args, flag, None) is not None:
                setattr(getattr(cfg, section), attr, getattr(args, flag))
        cfg.validate()
        state["resumed"] = (ckpt_path, int(resume_state["step"]))
        if rank == 0:
            print(f"modi train: continuing {ckpt_path} from step {int(resume_state['step'])}", flush=True)
    else:
        cfg = build_config(args)
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
    state["trainer"] = trainer
    try:
        result = trainer.train()
    except NonFiniteLossError as exc:
        raise UserError(str(exc)) from None
    if rank == 0:
        losses = ", ".join(f"{k} {v:.4f}" for k, v in result.last_losses.items() if k in ("d", "g", "r1", "path",
                                                                                        "touch", "contact"))
        print(f"modi train: step {result.step} in {result.seconds:.1f} s; checkpoint {result.checkpoint}; {losses}")
    return result.exit_code
