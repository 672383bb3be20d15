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

``progress`` is called after every iteration with a :class:`Progress`.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch

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
from modi.models.modi.config import MoDiConfig, make_config
from modi.models.modi.training import NonFiniteLossError, Trainer, prepare_data
from modi.data.normalization import Normalizer


@dataclass(frozen=True)
class Progress:
    """One finished training iteration: ``step`` of ``total`` (GANimator: within block ``block`` of
    ``n_blocks``), the iteration's ``losses`` and the ``seconds`` since the call started."""

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

    def train_step(self) -> dict[str, float]:
        out = super().train_step()
        if self._progress_fn is not None:
            self._progress_fn(Progress("modi", self.step, int(self.cfg.train.iters), dict(out),
                                       time.time() - self._t0))
        return out


_MODI_SHORTCUTS = {"iters": "train.iters", "batch": "train.batch", "seed": "train.seed", "lr": "train.lr",
                   "frames": "data.n_frames", "fps": "data.fps", "feet": "data.feet"}
_RESUMABLE = {"train.iters", "train.log_every", "train.sample_every", "train.ckpt_every"}


def modi_config(preset: str = "small", ablations: Sequence[str] = (), config: Mapping[str, Any] | None = None,
                **shortcuts: Any) -> MoDiConfig:
    """A MoDi config: a preset (``small``, ``paper``), named ablations, dotted overrides (``{"train.iters": 100}``)
    and the shortcuts ``iters``, ``batch``, ``seed``, ``lr``, ``frames``, ``fps``, ``feet`` (``UserError`` for an
    unknown name or a bad value)."""
    overrides = dict(config or {})
    for k, v in shortcuts.items():
        if k not in _MODI_SHORTCUTS:
            raise UserError(f"unknown option {k!r}; give config={{'section.key': value}} or one of "
                            f"{', '.join(_MODI_SHORTCUTS)}")
        if v is not None:
            overrides[_MODI_SHORTCUTS[k]] = v
    feet = overrides.get("data.feet")
    if feet:
        unique_names("--feet", feet)
    try:
        return make_config(preset, list(ablations), **overrides)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def train_modi(data: str | os.PathLike, out: str | os.PathLike, *, preset: str = "small",
               ablations: Sequence[str] = (), config: Mapping[str, Any] | None = None, iters: int | None = None,
               batch: int | None = None, seed: int | None = None, resume: bool | str | os.PathLike = False,
               device: str | torch.device = "cpu", threads: int | None = None,
               progress: ProgressCallback | None = None, bar: bool = False, tensorboard: bool = False,
               cache: bool = True, log: Callable[[str], Any] | None = None) -> ModiGenerator:
    """Train MoDi on every BVH under ``data`` (or the word ``procedural``: the built-in clips) into the run folder
    ``out`` (``checkpoint.pt``, ``log.jsonl``, ``config.json``, sample previews); returns the trained generator.

    The config is ``preset`` + ``ablations`` + ``config`` (dotted keys) + the shortcuts ``iters``, ``batch``,
    ``seed``. ``resume=True`` continues ``out/checkpoint.pt`` (``resume=PATH``: that file) with its config (``iters``
    may extend it). ``bar`` shows tqdm's bar; ``log`` receives the summary lines (e.g. ``print``). Cost: the data
    preparation (cached in ``out``), then ``iters`` steps (about 0.1 s each for the small preset on a CPU core).
    See the module for the guarantees (lock, no overwrite, signals)."""
    set_threads(threads)
    dev = check_device(device)
    run_dir = Path(out)
    with faults.hold_run_folder(run_dir):  # a second run into the folder is refused before any work
        ckpt = run_dir / "checkpoint.pt"
        state = None
        if resume:
            if batch is not None or seed is not None or ablations or preset != "small":
                raise UserError("a resumed run keeps its checkpoint's config: give only iters (and config "
                                f"keys {', '.join(sorted(_RESUMABLE))}) with resume")
            path = ckpt if resume is True else Path(resume)
            existing_file(path, "checkpoint to resume", "--resume")
            state = load_checkpoint(path)
            cfg = MoDiConfig.from_dict(state["config"])
            given = {**dict(config or {}), **({"train.iters": iters} if iters is not None else {})}
            for key, value in given.items():
                if key not in _RESUMABLE:
                    raise UserError(f"{key}: a resumed run keeps its checkpoint's config (only "
                                    f"{', '.join(sorted(_RESUMABLE))} may change)")
                section, _, attr = key.partition(".")
                setattr(getattr(cfg, section), attr, value)
            cfg.validate()
        else:
            cfg = modi_config(preset, ablations, config, iters=iters, batch=batch, seed=seed)
            if ckpt.exists():
                raise UserError(f"{ckpt} exists: pass resume=True to continue it, or choose a new out")
        normalizer = Normalizer.from_state_dict(state["codec"]["normalizer"]) if state is not None else None
        td = prepare_data(data, cfg, work_dir=run_dir, cache=cache, progress=bar, normalizer=normalizer)
        faults.atomic_write(run_dir / "config.json", json.dumps(cfg.to_dict(), indent=1) + "\n")
        s = td.summary
        _say(log, f"modi train: {td.windows.shape[0]} training windows {tuple(td.windows.shape[1:])} from "
                  f"{s.get('train_clips', '?')} clips; hierarchy {td.hierarchy.entity_counts}; preset {cfg.preset}; "
                  f"1 process(es) on {dev}; {cfg.train.iters} iterations")
        trainer = _ModiTrainer(cfg, td, run_dir, device=dev, resume=state, progress=bar, tensorboard=tensorboard,
                               log=log or (lambda _m: None), progress_fn=progress)
        try:
            result = trainer.train()
        except NonFiniteLossError as exc:
            raise UserError(str(exc)) from None
    if result.interrupted:
        raise TrainingInterrupted(result.checkpoint, result.signum)
    return ModiGenerator.from_checkpoint(result.checkpoint, device=dev)


# ============================================================================================== GANimator
class _GanimatorTrainer(GanimatorTrainer):
    """The GANimator trainer, calling ``progress`` after every iteration."""

    def __init__(self, *args: Any, progress_fn: ProgressCallback | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._progress_fn = progress_fn
        self._t0 = time.time()
        self._losses: dict[str, float] = {}

    def _iteration(self, *args: Any, **kwargs: Any) -> dict[str, float]:
        self._losses = super()._iteration(*args, **kwargs)
        return self._losses

    def _progress(self, state: str, block_rate: float | None = None, force: bool = False) -> None:
        super()._progress(state, block_rate, force)
        if self._progress_fn is not None and state == "training" and block_rate is not None:
            b = self.state["block"]
            self._progress_fn(Progress("ganimator", int(self.state["iteration"]), self.cfg.block_budget(b),
                                       {k: float(v) for k, v in self._losses.items()}, time.time() - self._t0,
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
                    log: Callable[[str], Any] | None = None, **config: Any) -> GanimatorRun:
    """Train GANimator on one BVH clip, or several of one character (motion mixing), into the run folder ``out``
    (``ganimator.ckpt``, ``log.jsonl``, ``progress.json``); returns the trained run.

    ``config``: any GANimator config field over the preset's (``iterations``, ``d_steps``, ``base_channels``,
    ``max_levels``, ``coarse_ratio``, ``feet``, ``keep_joints``, ``joint_reduction``, ``contacts``, ``fps``,
    ``device``, ``seed``, ...). ``resume=True`` continues ``out``'s checkpoint when there is one (without it an
    existing checkpoint is refused); ``conditional_from`` trains a trajectory-conditioned model against a trained
    run; ``max_minutes`` stops (checkpointed) after that long. Cost: the preset's schedule (``tiny``: seconds,
    ``fast``: minutes per level on a CPU, ``paper``: hours)."""
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
        trainer = _GanimatorTrainer(clips, cfg, run_dir, cond_source=cond_source, progress_fn=progress)
        model = trainer.run(progress=bar, log=log, max_seconds=max_minutes * 60 if max_minutes else None)
    model.eval()
    return GanimatorRun(load_model(run_dir, device=cfg.device) if ckpt.is_file() else model, path=str(run_dir))


__all__ = ["Progress", "ProgressCallback", "train_modi", "train_ganimator", "modi_config", "ganimator_config",
           "TrainingInterrupted", "GANIMATOR_PRESETS"]
