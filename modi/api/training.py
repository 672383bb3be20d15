"""Training MoDi and GANimator from Python with the CLI's guarantees.

* **No silent overwrite**: a run folder that already holds a checkpoint is refused unless ``resume=True``
  (``UserError``: "... exists: pass resume=True ...").
* **Resume is one argument**: ``resume=True`` continues the checkpoint in the run folder (MoDi: its config and
  normaliser come from the checkpoint; ``resume=PATH`` continues another checkpoint file).
* **The run lock**: the run folder is locked for the whole call; a second run into it (another process) is refused
  at once with one line (``RunFolderBusy``, a ``UserError``).
* **Signals**: Ctrl-C or SIGTERM finishes the iteration, saves a resumable checkpoint and raises
  :class:`TrainingInterrupted` (a ``KeyboardInterrupt`` carrying ``.checkpoint`` and ``.exit_code``).
* **One-line errors**: every mistake of the caller's is a :class:`modi.errors.UserError` whose message is the line
  the CLI prints.
* **Precision**: ``precision="bf16"`` runs the forward passes under bf16 autocast (weights, optimiser states and
  checkpoints stay fp32; docs/precision.md). A resumed run keeps its checkpoint's precision unless one is given,
  which it then switches to (and logs); None means that, or fp32 for a new run.
* **CUDA graphs** (MoDi): ``cuda_graphs="auto"|"on"|"off"`` replays each kind of training step as one CUDA graph
  (``modi.models.modi.graphs``; docs/training.md). ``auto`` is eager until a GPU has shown graphed training equal to
  eager; ``on`` on a CPU is one warning and eager.

``progress`` is called after every iteration with a :class:`Progress`.
"""
from __future__ import annotations

import json
import os
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
import torch.distributed as dist

from modi import faults
from modi.faults import unique_names
from modi.api._util import check_device, existing_file, set_threads
from modi.api.ganimator import GanimatorRun
from modi.api.generator import ModiGenerator
from modi.errors import UserError
from modi.models.ganimator.config import PRESETS as GANIMATOR_PRESETS
from modi.models.ganimator.config import GanimatorConfig, preset
from modi.models.ganimator.data import check_training_length, load_sequences, sequence_pyramid
from modi.models.ganimator.training import Trainer as GanimatorTrainer
from modi.models.ganimator.training import TrainingInterrupted, blocks_of, checkpoint_path, load_model
from modi.models.modi.checkpoint import load_checkpoint
from modi.models.modi import distributed as mdist
from modi.models.modi.config import ABLATIONS, MoDiConfig, make_config
from modi.models.modi.graphs import GRAPH_MODES, GraphFallbackWarning, check_graph_mode
from modi.models.precision import PRECISIONS, check_precision
from modi.models.modi.training import Trainer, TrainResult, newest_checkpoint, prepare_data
from modi.data.normalization import Normalizer


@dataclass(frozen=True)
class Progress:
    """One finished training iteration: ``step`` of ``total`` (GANimator: within block ``block`` of
    ``n_blocks``), the iteration's ``losses`` and the ``seconds`` since the call started. ``losses`` are given at
    the log steps (MoDi: every ``train.log_every`` and the last; GANimator: every ``LOG_EVERY`` = 10 iterations
    and a block's last) and are empty between them, so that an iteration asks nothing of the device."""

    model: str
    step: int
    total: int
    losses: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    block: int | None = None
    n_blocks: int | None = None


ProgressCallback = Callable[[Progress], Any]


def _say(log: Callable[[str], Any] | None, text: str) -> None:
    if log is not None:
        log(text)


# ============================================================================================== MoDi
class _ModiTrainer(Trainer):
    """The MoDi trainer, calling ``progress`` after every step."""

    def __init__(self, *args: Any, progress_fn: ProgressCallback | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._progress_fn = progress_fn
        self._t0 = time.time()

    def _after_step(self, losses: dict[str, float] | None) -> None:
        if self._progress_fn is not None:  # the losses of log steps only: reading them is a device->host sync
            self._progress_fn(Progress("modi", self.step, int(self.cfg.train.iters), dict(losses or {}),
                                       time.time() - self._t0))


_MODI_SHORTCUTS = {"iters": "train.iters", "batch": "train.batch", "seed": "train.seed", "lr": "train.lr",
                   "frames": "data.n_frames", "fps": "data.fps", "feet": "data.feet"}
_RESUMABLE = ("train.iters", "train.log_every", "train.sample_every", "train.ckpt_every")  # may change on a resume
LATEST = "latest"  # resume: the run's newest checkpoint, which must exist

# How a message names what the caller gave: Python's spelling here; the CLI passes its flags (``spelling=``).
PYTHON_SPELLING = {"resume": "resume=True", "resume_auto": "resume='auto'", "resume_path": "resume", "out": "out",
                   "preset": "preset", "ablation": "ablations"}


def modi_config(preset: str = "small", ablations: Sequence[str] = (), config: Mapping[str, Any] | None = None,
                **shortcuts: Any) -> MoDiConfig:
    """A MoDi config: a preset (``small``, ``paper``), named ablations, dotted overrides (``{"train.iters": 100}``)
    and the shortcuts ``iters``, ``batch``, ``seed``, ``lr``, ``frames``, ``fps``, ``feet`` (``UserError`` for an
    unknown name or a bad value)."""
    overrides = _dotted(config, shortcuts)
    feet = overrides.get("data.feet")
    if feet:
        unique_names("--feet", feet)
    try:
        return make_config(preset, list(ablations), **overrides)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def _dotted(config: Mapping[str, Any] | None, shortcuts: Mapping[str, Any]) -> dict[str, Any]:
    overrides = dict(config or {})
    for k, v in shortcuts.items():
        if k not in _MODI_SHORTCUTS:
            raise UserError(f"unknown option {k!r}; give config={{'section.key': value}} or one of "
                            f"{', '.join(_MODI_SHORTCUTS)}")
        if v is not None:
            overrides[_MODI_SHORTCUTS[k]] = v
    return overrides


def config_differences(cfg: MoDiConfig, preset: str | None, ablations: Sequence[str], overrides: Mapping[str, Any],
                       spelling: Mapping[str, str] = PYTHON_SPELLING) -> list[str]:
    """What was asked for that disagrees with ``cfg`` (a checkpoint's config), one entry per option, named as the
    caller gave it (``spelling[key]``, e.g. ``--lr 0.001``; else ``key=value``); the keys of ``_RESUMABLE`` may
    change and are not compared."""

    def show(v) -> str:
        return " ".join(map(str, v)) if isinstance(v, (list, tuple)) else str(v)

    def norm(v):
        return list(v) if isinstance(v, (list, tuple)) else v

    out = []
    if preset is not None and preset != cfg.preset:
        out.append(f"{spelling.get('preset', 'preset')} {preset} (the checkpoint has {cfg.preset})")
    wanted: dict[str, tuple[str, object]] = {}  # config key -> (the option as given, the value it sets)
    for name in ablations:
        if name not in ABLATIONS:
            raise UserError(f"unknown ablation {name!r}; choose from {', '.join(sorted(ABLATIONS))}")
        for key, value in ABLATIONS[name].items():
            wanted[key] = (f"{spelling.get('ablation', 'ablation')} {name}", value)
    for key, value in overrides.items():
        if key in _RESUMABLE:
            continue
        wanted[key] = (spelling.get(key, f"{key}={show(value)}"), value)
    for key, (given, value) in wanted.items():
        section, _, attr = key.partition(".")
        try:
            have = getattr(getattr(cfg, section), attr)
        except AttributeError:
            raise UserError(f"unknown config key {key!r}") from None
        if norm(have) != norm(value) and not any(o.startswith(given + " (") for o in out):
            out.append(f"{given} ({key} is {show(have)} in the checkpoint)")
    return out


def launched_by_torchrun() -> bool:
    """Whether this process is one of several that torchrun started (``WORLD_SIZE`` > 1)."""
    return mdist.world_size_from_env() > 1


def modi_device(device: str | torch.device = "auto") -> torch.device:
    """``check_device``, plus ``auto`` (CUDA when there is one, else the CPU) and, under torchrun, ``cuda`` without
    an index meaning this process's GPU (``LOCAL_RANK``)."""
    local = torch.device("cuda", mdist.local_rank())
    if str(device) == "auto":
        return local if torch.cuda.is_available() else torch.device("cpu")
    dev = check_device(device)
    return local if dev.type == "cuda" and dev.index is None else dev


def run_modi_training(data: str | os.PathLike, out: str | os.PathLike, *, preset: str | None = None,
                      default_preset: str = "small", ablations: Sequence[str] = (),
                      config: Mapping[str, Any] | None = None, resume: bool | str | os.PathLike | None = None,
                      device: str | torch.device = "auto", threads: int | None = None,
                      dist_timeout: float | None = None, tensorboard: bool = True, cache: bool = True,
                      bar: bool = True, log: Callable[[str], Any] | None = None,
                      progress: ProgressCallback | None = None, spelling: Mapping[str, str] = PYTHON_SPELLING,
                      hold: list | None = None, precision: str | None = None,
                      cuda_graphs: str = "auto") -> TrainResult:
    """One MoDi training run into the run folder ``out``, in this process or as one rank of a torchrun launch
    (``modi train`` is this call); returns the trainer's result (``exit_code`` 130 / 143 after Ctrl-C / SIGTERM,
    with a resumable checkpoint saved).

    * config: ``preset`` (else ``default_preset``) + ``ablations`` + ``config`` (dotted keys) for a new run; a
      resumed run keeps its checkpoint's, and an option that differs from it is refused, except ``_RESUMABLE``;
    * ``resume``: None/False -- a new run (an existing ``checkpoint.pt`` is refused); True or ``"latest"`` -- the
      run's newest checkpoint, which must exist; ``"auto"`` -- that checkpoint when there is one, else a new run
      (what a torchrun restart does unasked); a path -- that checkpoint file;
    * under torchrun: rank 0 takes the run-folder lock, decides what to resume and reads it, and tells the others;
      a lost peer is one ``PeerLostError`` line (exit 75). ``hold`` gets the run's state (its trainer) appended,
      for a caller that must keep the process group alive until it exits (``modi.cli.leave_without_teardown``);
    * ``log`` gets rank 0's summary lines; ``bar`` shows progress bars on rank 0; ``progress`` is called after
      every step; messages name the options as ``spelling`` says (the CLI's flags, or Python's arguments);
    * ``precision``: ``fp32`` or ``bf16``; None keeps a resumed checkpoint's (fp32 for a new run);
    * ``cuda_graphs``: ``auto``, ``on`` or ``off`` (see the module); the summary line says what ran."""
    if precision is not None:
        check_precision(precision)
    check_graph_mode(cuda_graphs)
    set_threads(threads)
    dev = modi_device(device)
    state: dict = {"trainer": None, "resumed": None}  # what a lost peer's line reports
    if hold is not None:
        hold.append(state)
    distributed = launched_by_torchrun()
    run_dir = Path(out)
    try:
        rank, world = mdist.init_distributed_from_env(dev, dist_timeout)
        with _run_folder_lock(run_dir, rank, world, dev):
            return _train(data, run_dir, preset, default_preset, ablations, dict(config or {}), resume, dev, rank,
                          world, state, tensorboard, cache, bar, log, progress, spelling, precision, cuda_graphs)
    except (Exception, faults.Terminated) as exc:
        # a peer's failure; or torchrun's SIGTERM, sent to every worker once one has died, which can reach this
        # rank before its own next collective fails: either way the lost peer is what to report
        lost = None
        if distributed:
            lost = mdist.stopped_for_a_lost_peer() if isinstance(exc, faults.Terminated) else \
                exc if mdist.is_peer_failure(exc) else None
        if lost is None:
            raise
        mdist.leave_quietly_on_signals()
        raise _peer_lost(lost, run_dir, state) from None


def _peer_lost(exc: Exception, run_dir: Path, state: dict) -> UserError:
    """The one line for a lost peer: the step this rank was at and the newest checkpoint it knows of."""
    trainer, resumed = state["trainer"], state["resumed"]
    step = trainer.step if trainer is not None else None
    saved = trainer.saved_step if trainer is not None else None
    where = run_dir / "checkpoint.pt" if saved is not None else None
    if saved is None and resumed is not None:
        where, saved = resumed
    if where is None and (run_dir / "checkpoint.pt").is_file():
        where = run_dir / "checkpoint.pt"
    return mdist.peer_lost_error(exc, step=step, checkpoint=where, checkpoint_step=saved)


def _run_folder_lock(run_dir: Path, rank: int, world: int, device: torch.device) -> ExitStack:
    """Rank 0 takes the run folder's lock before anything else (a second run is refused at once, before any data is
    read); under torchrun every rank learns the outcome, so all of them stop together."""
    stack, refusal = ExitStack(), None
    if rank == 0:
        try:
            stack.enter_context(faults.hold_run_folder(run_dir))
        except UserError as exc:
            refusal = exc
    if world > 1:
        flag = torch.tensor([int(refusal is not None)], device=device if device.type == "cuda" else "cpu")
        dist.broadcast(flag, 0)
        if int(flag.item()) and refusal is None:
            refusal = UserError(f"{run_dir}: rank 0 could not take the run folder (see its message)")
    if refusal is not None:
        stack.close()
        raise refusal
    return stack


def _resume_state(resume: bool | str | os.PathLike | None, run_dir: Path, rank: int, world: int,
                  spelling: Mapping[str, str], log: Callable[[str], Any] | None) -> tuple[Path, dict] | None:
    """``(path, state)`` of the checkpoint this start continues, or None to start afresh (see
    ``run_modi_training``'s ``resume``; a torchrun restart without one is ``"auto"``, and with a path continues
    the run's own newest checkpoint once there is one). Rank 0 decides and reads it and hands it to the other
    ranks, so every rank loads the same step."""
    ckpt = run_dir / "checkpoint.pt"
    again, auto, out_name = spelling["resume"], spelling["resume_auto"], spelling["out"]

    def decide():
        restart = mdist.torchrun_restart() > 0
        mode = LATEST if resume is True else (None if resume is False else resume)
        if mode is None and restart:
            mode = "auto"
        if mode is None:
            if ckpt.exists():
                raise UserError(f"{ckpt} exists: pass {again} to continue it ({auto} under torchrun), or choose a "
                                f"new {out_name}")
            return None
        if mode in ("auto", LATEST) or restart:
            found = newest_checkpoint(run_dir, warn=lambda msg: _say(log, f"modi: {msg}"))
            if found is None and ckpt.exists():
                raise UserError(f"{ckpt} cannot be read and no snapshot can: move it away to start the run afresh, "
                                f"or choose a new {out_name}")
            if found is not None or mode == "auto":
                return found
            if mode == LATEST:
                raise UserError(f"{ckpt}: no checkpoint to resume in {run_dir} ({auto} starts a new run when there "
                                f"is none)")
        path = existing_file(mode, "checkpoint to resume", spelling["resume_path"])
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


def _train(data, run_dir: Path, preset, default_preset, ablations, overrides: dict, resume, dev: torch.device,
           rank: int, world: int, state: dict, tensorboard: bool, cache: bool, bar: bool, log, progress,
           spelling: Mapping[str, str], precision: str | None, cuda_graphs: str = "auto") -> TrainResult:
    say = log if rank == 0 else None
    found = _resume_state(resume, run_dir, rank, world, spelling, say)
    resume_state = None
    if found is not None:
        ckpt_path, resume_state = found
        cfg = MoDiConfig.from_dict(resume_state["config"])
        diffs = config_differences(cfg, preset, ablations, overrides, spelling)
        if diffs:
            raise UserError(f"{ckpt_path} was trained with another config: {'; '.join(diffs)}. A resumed run keeps "
                            f"its checkpoint's config: drop these options to continue it, or choose a new "
                            f"{spelling['out']}")
        for key in _RESUMABLE:
            if key in overrides:
                section, _, attr = key.partition(".")
                setattr(getattr(cfg, section), attr, overrides[key])
        try:
            cfg.validate()
        except ValueError as exc:
            raise UserError(str(exc)) from None
        state["resumed"] = (ckpt_path, int(resume_state["step"]))
        _say(say, f"modi train: continuing {ckpt_path} from step {int(resume_state['step'])}")
    else:
        cfg = modi_config(preset or default_preset, ablations, overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    normalizer = (Normalizer.from_state_dict(resume_state["codec"]["normalizer"]) if resume_state is not None
                  else None)
    td = prepare_data(data, cfg, work_dir=run_dir, cache=cache, progress=bar and rank == 0, normalizer=normalizer)
    if rank == 0:
        faults.atomic_write(run_dir / "config.json", json.dumps(cfg.to_dict(), indent=1) + "\n")
    trainer = _ModiTrainer(cfg, td, run_dir, device=dev, resume=resume_state, progress=bar, tensorboard=tensorboard,
                           log=log or (lambda _m: None), progress_fn=progress, precision=precision,
                           cuda_graphs=cuda_graphs)
    state["trainer"] = trainer
    s = td.summary
    _say(say, f"modi train: {td.windows.shape[0]} training windows {tuple(td.windows.shape[1:])} from "
              f"{s.get('train_clips', '?')} clips; hierarchy {td.hierarchy.entity_counts}; preset {cfg.preset}; "
              f"{world} process(es) on {dev}; {cfg.train.iters} iterations; precision {trainer.precision}; "
              f"{trainer.graphs_summary()}")
    result = trainer.train()  # a NaN/inf loss: NonFiniteLossError, a UserError (one line, exit 2)
    losses = ", ".join(f"{k} {v:.4f}" for k, v in result.last_losses.items()
                       if k in ("d", "g", "r1", "path", "touch", "contact"))
    _say(say, f"modi train: step {result.step} in {result.seconds:.1f} s; checkpoint {result.checkpoint}; {losses}")
    return result


def train_modi(data: str | os.PathLike, out: str | os.PathLike, *, preset: str | None = None,
               ablations: Sequence[str] = (), config: Mapping[str, Any] | None = None, iters: int | None = None,
               batch: int | None = None, seed: int | None = None, resume: bool | str | os.PathLike = False,
               device: str | torch.device = "cpu", threads: int | None = None,
               progress: ProgressCallback | None = None, bar: bool = False, tensorboard: bool = False,
               cache: bool = True, log: Callable[[str], Any] | None = None,
               precision: str | None = None, cuda_graphs: str = "auto") -> ModiGenerator:
    """Train MoDi on every BVH under ``data`` (or the word ``procedural``: the built-in clips) into the run folder
    ``out`` (``checkpoint.pt``, ``log.jsonl``, ``config.json``, sample previews); returns the trained generator.

    The config is ``preset`` (default ``small``) + ``ablations`` + ``config`` (dotted keys) + the shortcuts
    ``iters``, ``batch``, ``seed``. ``resume=True`` continues the run's newest checkpoint (``resume="auto"``: when
    there is one, else a new run; ``resume=PATH``: that file) with its config: ``iters`` may extend it, an option
    that differs from it is refused. ``precision``: ``fp32`` or ``bf16`` (bf16 autocast for the forward passes;
    None: a resumed checkpoint's, else fp32; given on a resume, the run switches to it). ``cuda_graphs``: ``auto``
    (eager until graphs are proven on a GPU), ``on`` (one CUDA graph per kind of step; on a CPU one warning, eager)
    or ``off``; a capture that fails is one warning and the run goes on eagerly. ``bar`` shows tqdm's bar;
    ``log`` receives the summary lines (e.g. ``print``).
    Cost: the data preparation (cached in ``out``), then ``iters`` steps (about 0.1 s each for the small preset on a
    CPU core). Under torchrun every rank makes this call. See the module for the guarantees (lock, no overwrite,
    signals); ``run_modi_training`` is the same run, returning the trainer's result instead."""
    overrides = _dotted(config, {"iters": iters, "batch": batch, "seed": seed})
    result = run_modi_training(data, out, preset=preset, ablations=ablations, config=overrides, resume=resume,
                               device=device, threads=threads, tensorboard=tensorboard, cache=cache, bar=bar,
                               log=log, progress=progress, precision=precision, cuda_graphs=cuda_graphs)
    if result.interrupted:
        raise TrainingInterrupted(result.checkpoint, result.signum)
    return ModiGenerator.from_checkpoint(result.checkpoint, device=modi_device(device))


# ============================================================================================== GANimator
class _GanimatorTrainer(GanimatorTrainer):
    """The GANimator trainer, calling ``progress`` after every iteration."""

    def __init__(self, *args: Any, progress_fn: ProgressCallback | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._progress_fn = progress_fn
        self._t0 = time.time()

    def _progress(self, state: str, block_rate: float | None = None, force: bool = False) -> None:
        super()._progress(state, block_rate, force)
        if self._progress_fn is not None and state == "training" and block_rate is not None:
            b = self.state["block"]
            self._progress_fn(Progress("ganimator", int(self.state["iteration"]), self.cfg.block_budget(b),
                                       dict(self.losses_read), time.time() - self._t0,
                                       b, len(self.blocks)))


def ganimator_config(preset_name: str = "fast", **options: Any) -> GanimatorConfig:
    """A GANimator config: one of :data:`GANIMATOR_PRESETS` (``paper``, ``fast``, ``tiny``) with any
    :class:`~modi.models.ganimator.config.GanimatorConfig` field overridden (None keeps the preset's)."""
    if preset_name not in GANIMATOR_PRESETS:
        raise UserError(f"unknown preset {preset_name!r}; choose one of {', '.join(GANIMATOR_PRESETS)}")
    if options.get("feet"):
        unique_names("--feet", options["feet"])
    try:
        return preset(preset_name, **options)
    except TypeError as exc:
        raise UserError(f"unknown GANimator option: {exc}") from None


def train_ganimator(bvh: str | os.PathLike | Sequence[str | os.PathLike], out: str | os.PathLike, *,
                    preset: str = "fast", resume: bool = False, conditional_from: str | os.PathLike | None = None,
                    max_minutes: float | None = None, threads: int | None = None,
                    progress: ProgressCallback | None = None, bar: bool = False,
                    log: Callable[[str], Any] | None = None, precision: str | None = None,
                    **config: Any) -> GanimatorRun:
    """Train GANimator on one BVH clip, or several of one character (motion mixing), into the run folder ``out``
    (``ganimator.ckpt``, ``log.jsonl``, ``progress.json``); returns the trained run.

    ``config``: any GANimator config field over the preset's (``iterations``, ``d_steps``, ``base_channels``,
    ``max_levels``, ``coarse_ratio``, ``feet``, ``keep_joints``, ``joint_reduction``, ``contacts``, ``fps``,
    ``device``, ``seed``, ...). ``resume=True`` continues ``out``'s checkpoint when there is one (without it an
    existing checkpoint is refused); ``conditional_from`` trains a trajectory-conditioned model against a trained
    run; ``max_minutes`` stops (checkpointed) after that long. ``precision``: ``fp32`` or ``bf16`` (bf16 autocast for
    the forward passes; None: a resumed checkpoint's, else fp32; given on a resume, the run switches to it). Cost: the
    preset's schedule (``tiny``: seconds, ``fast``: minutes per level on a CPU, ``paper``: hours)."""
    if precision is not None:
        check_precision(precision)
    set_threads(threads)
    paths = [bvh] if isinstance(bvh, (str, os.PathLike)) else list(bvh)
    if not paths:
        raise UserError("no BVH files given")
    run_dir = Path(out)
    with faults.hold_run_folder(run_dir):  # a second run into the folder is refused before any work
        ckpt = checkpoint_path(run_dir)
        if ckpt.is_file() and not resume:
            raise UserError(f"{ckpt} exists: pass resume=True to continue it, or choose a new out")
        cfg = ganimator_config(preset, **config)
        cond_source = None
        if conditional_from is not None:
            if not Path(conditional_from).exists():
                raise UserError(f"--conditional-from {conditional_from}: no such GANimator run folder or checkpoint "
                                "file")
            cond_source = load_model(conditional_from, device=cfg.device)
            cfg = cfg.replace(conditional=True)
            if cond_source.cfg.sixd != cfg.sixd:
                raise UserError(f"--conditional-from: that run uses {cond_source.cfg.sixd} 6D; pass --sixd "
                                f"{cond_source.cfg.sixd} to train a model that can read its trajectories")
        for p in paths:
            existing_file(p)
        clips = load_sequences(paths, cfg)
        if cond_source is not None and [c.name for c in cond_source.seqs] != [c.name for c in clips]:
            raise UserError("--conditional-from must be a run trained on the same BVH file(s)")
        check_training_length(clips, cfg)
        c = clips[0]
        if 0 in c.feet:
            raise UserError(f"--feet: the root joint {c.skeleton.names[0]} cannot be a foot (contacts pin feet "
                            "relative to the root)")
        _say(log, f"{len(clips)} clip(s), {c.n_joints} joints, feet {[c.skeleton.names[f] for f in c.feet]}, "
                  f"{', '.join(str(x.n_frames) for x in clips)} frames at {c.fps:.1f} fps")
        n_blocks = len(blocks_of(len(sequence_pyramid(clips, cfg)[0][0]), cfg.group_size))
        _say(log, f"{n_blocks} blocks of {cfg.group_size} levels, iterations {cfg.block_budgets(n_blocks)} "
                  f"({cfg.d_steps} D : {cfg.g_steps} G : 1 reconstruction steps each)")
        trainer = _GanimatorTrainer(clips, cfg, run_dir, cond_source=cond_source, progress_fn=progress,
                                    precision=precision)
        model = trainer.run(progress=bar, log=log, max_seconds=max_minutes * 60 if max_minutes else None)
    model.eval()
    return GanimatorRun(load_model(run_dir, device=cfg.device) if ckpt.is_file() else model, path=str(run_dir))


__all__ = ["Progress", "ProgressCallback", "train_modi", "run_modi_training", "train_ganimator", "modi_config",
           "ganimator_config", "config_differences", "launched_by_torchrun", "modi_device", "TrainingInterrupted",
           "GANIMATOR_PRESETS", "PRECISIONS", "GRAPH_MODES", "GraphFallbackWarning"]
