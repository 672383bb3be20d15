"""MoDi's encoder into W+ as one object: projections of motions onto the generator's manifold (G(I(m))) and the
``modi apply`` tasks, returning :class:`modi.Motion`."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, Sequence, Union

import torch
from torch import Tensor

from modi.data.motion import Motion
from modi.errors import UserError
from modi.faults import atomic_write, refuse_overwrite
from modi.models.modi.encoder import applications as A
from modi.models.modi.checkpoint import load_checkpoint
from modi.models.modi.encoder.metrics import evaluate_encoder, format_table5
from modi.models.modi.encoder.training import (EncoderBundle, EncoderTrainConfig, EncoderTrainer,
                                               EncoderTrainingInterrupted, EncoderTrainResult, hold_output,
                                               load_encoder, load_encoder_data, resumed_train_options)
from modi.models.modi.latent.space import load_model
from modi.api._util import check_device, existing_file, set_threads
from modi.api.generator import ModiGenerator

MotionLike = Union[Motion, str, os.PathLike, Tensor]
TASKS = ("invert", "prefix", "fuse", "denoise", "edit")


class Encoder:
    """A trained encoder I (``modi encoder train``) with the generator G it inverts into (:attr:`generator`).

    Inputs are Motions or BVH paths on the generator's skeleton (joints matched by name, resampled to its rate; a
    window of the model's length is cut at ``start``), or normalised model windows ``(K, E, T)``."""

    def __init__(self, bundle: EncoderBundle, *, path: str | None = None) -> None:
        self.bundle = bundle
        self.generator = ModiGenerator(bundle.g, bundle.codec, bundle.gcfg, step=bundle.meta.get("step"))
        self.path = path

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike | dict, *, device: str | torch.device = "cpu") -> "Encoder":
        """Read an encoder checkpoint (it holds its generator); ``CheckpointError`` for anything else."""
        return cls(load_encoder(path, device=device), path=None if isinstance(path, dict) else str(path))

    @property
    def prefix_frames(self) -> int | None:
        """The frames a prefix-trained encoder sees (None: whole motions)."""
        return self.bundle.prefix_frames

    @property
    def data_source(self) -> str | None:
        """The data folder the encoder was trained on, as recorded in its checkpoint."""
        src = self.bundle.meta.get("data_source")
        return None if not src or src == "tensor" else str(src)

    def __repr__(self) -> str:
        pre = f", prefix {self.prefix_frames} frames" if self.prefix_frames else ""
        return f"Encoder(into W+ {self.generator.n_latent}x{self.generator.latent_dim}{pre}; {self.generator!r})"

    # ------------------------------------------------------------------------------------------- windows
    def window(self, motion: MotionLike, *, start: int = 0) -> Tensor:
        """One normalised model window ``(K, E, T)`` of a motion (a tensor is checked and passed through)."""
        if isinstance(motion, Tensor):
            k, e, t = self.bundle.g.output_shape
            if tuple(motion.shape[-3:]) != (k, e, t):
                raise UserError(f"a model window is ({k}, {e}, {t}), got {tuple(motion.shape)}")
            return motion.reshape(k, e, t).float().cpu()
        if isinstance(motion, (str, os.PathLike)):
            existing_file(motion, option="INPUT")
        return self.generator.encode_motion(motion, start=start)

    def test_windows(self, data: str | os.PathLike | None = None, split: str = "test") -> Tensor:
        """The windows of the encoder's data split (``test``: the 20% neither network saw), ``(N, K, E, T)``."""
        source = data or self.data_source
        if not source:
            raise UserError("give the data folder: this encoder does not record one")
        d = load_encoder_data(self.bundle.codec, self.bundle.gcfg, source)
        return d.test if split == "test" else d.train

    # ------------------------------------------------------------------------------------------- projections
    def encode(self, motion: MotionLike, *, start: int = 0) -> Tensor:
        """I(m): the W+ latent ``(L, D)`` of a motion (one encoder pass)."""
        w, _ = self.bundle.project(self.window(motion, start=start).unsqueeze(0), self.prefix_frames)
        return w[0]

    def reconstruct(self, motion: MotionLike, *, start: int = 0) -> Motion:
        """G(I(m)): the motion projected onto the generator's manifold (inversion in one pass; a prefix encoder
        completes the motion from its first :attr:`prefix_frames` frames)."""
        _, rec = self.bundle.project(self.window(motion, start=start).unsqueeze(0), self.prefix_frames)
        return self.generator.decode(rec)[0]

    def fuse(self, a: MotionLike, b: MotionLike, *, frame: int | None = None, start: int = 0) -> Motion:
        """Frames before ``frame`` (default: the middle) from ``a`` and after it from ``b``, the seam smoothed by
        G∘I."""
        xa, xb = self.window(a, start=start), self.window(b, start=start)
        t = xa.shape[-1] // 2 if frame is None else int(frame)
        _, rec = A.fuse(self.bundle, xa.unsqueeze(0), xb.unsqueeze(0), t)
        return self.generator.decode(rec)[0]

    def denoise(self, motion: MotionLike, *, sigma: float = 0.0, seed: int = 0, start: int = 0) -> Motion:
        """G(I(m)) of a noisy motion (``sigma`` > 0 first adds that much Gaussian noise to the joint rotations, in
        normalised units, as ``modi apply denoise``)."""
        x = self.window(motion, start=start).unsqueeze(0)
        noisy = A.add_noise(self.bundle.codec, x, sigma, seed) if sigma else x
        return self.generator.decode(self.bundle.project(noisy)[1])[0]

    # ------------------------------------------------------------------------------------------- files
    def apply(self, task: str, inputs: Sequence[MotionLike | str], out: str | os.PathLike, *, start: int = 0,
              data: str | os.PathLike | None = None, optim_steps: int = 200, frame: int | None = None,
              sigma: float = 0.5, smooth: float = 2.0, given_noisy: bool = False, seed: int = 0,
              angle: float = 90.0, from_frame: int | None = None, joint: str | None = None) -> list[dict[str, Any]]:
        """``modi apply TASK``: for each input write ``NAME_input``, ``NAME_naive``, ``NAME_encoder`` motion files
        and ``NAME.gif`` into ``out``, plus ``results.json``; returns the per-input results. ``inputs``: Motions,
        BVH paths or ``test:I`` (window I of the encoder's test split; ``data`` points elsewhere)."""
        if task not in TASKS:
            raise UserError(f"unknown task {task!r}; choose from {', '.join(TASKS)}")
        x, names = self._inputs(inputs, start, data)
        b = self.bundle
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        if task == "invert":
            if optim_steps < 0:
                raise UserError("--optim-steps must be >= 0")
            res = A.invert_motions(b, x, out, names, optim_steps=optim_steps)
        elif task == "prefix":
            res = A.complete_prefix(b, x, out, names)
        elif task == "fuse":
            if len(x) != 2:
                raise UserError(f"fuse takes two inputs, got {len(x)}")
            t = x.shape[-1] // 2 if frame is None else frame
            res = [A.fuse_motions(b, x[:1], x[1:2], t, out, name=f"{names[0]}+{names[1]}")]
        elif task == "denoise":
            res = A.denoise_motions(b, x, out, names, sigma=0.0 if given_noisy else sigma, smooth=smooth, seed=seed)
        else:
            j = None
            if joint is not None:
                try:
                    j = b.codec.skeleton.index(joint)
                except (KeyError, ValueError):
                    raise UserError(f"--joint {joint!r} is not a joint of the model's skeleton") from None
            res = A.edit_motions(b, x, out, names, angle=angle, start=from_frame, joint=j)
        atomic_write(out / "results.json", json.dumps(res, indent=1))
        return res

    def _inputs(self, inputs: Sequence[Any], start: int, data: str | os.PathLike | None) -> tuple[Tensor, list[str]]:
        xs, names, test = [], [], None
        for i, spec in enumerate(inputs):
            if isinstance(spec, str) and spec.startswith("test:"):
                if test is None:
                    source = data or self.data_source
                    if not source:
                        raise UserError("test:I inputs need --data (this encoder records no data folder)")
                    test = self.test_windows(source)
                try:
                    k = int(spec[5:])
                except ValueError:
                    raise UserError(f"bad input {spec!r}: expected test:I with an integer I") from None
                if not 0 <= k < test.shape[0]:
                    raise UserError(f"{spec}: the test split has windows 0..{test.shape[0] - 1}")
                xs.append(test[k])
                names.append(f"test{k:04d}")
            else:
                xs.append(self.window(spec, start=start))
                names.append(Path(spec).stem if isinstance(spec, (str, os.PathLike)) else f"motion{i:03d}")
        if not xs:
            raise UserError("no inputs")
        return torch.stack(xs), names

    def evaluate(self, data: str | os.PathLike | None = None, *, split: str = "test", units: str = "auto"
                 ) -> dict[str, Any]:
        """The Table 5 reconstruction metrics of ``modi encoder eval`` on a split of the data (default: the folder
        the encoder was trained on): L2/L1 on the representation, root / local / global position errors (mm and the
        released code's definition), with the mean-motion and data-mean baselines."""
        source = data or self.data_source
        if not source:
            raise UserError("give DATA: this encoder does not record a data folder")
        x = self.test_windows(source, split)
        res = evaluate_encoder(self.bundle.encoder, self.bundle.g, self.bundle.codec, x, units=units)
        res["source"] = str(source)
        return res


def open_encoder(enc: str | os.PathLike, *, device: str = "cpu", threads: int | None = None) -> Encoder:
    """An encoder checkpoint opened as ``modi apply`` and ``modi encoder eval`` open it: torch's CPU ``threads``
    set (None: torch's choice), ``device`` checked, the file checked, then read (well under a second)."""
    set_threads(threads)
    check_device(device)
    existing_file(enc, "encoder checkpoint file")
    return Encoder.from_checkpoint(enc, device=device)


def evaluate_encoder_file(enc: str | os.PathLike, data: str | os.PathLike | None = None, *, split: str = "test",
                          units: str = "auto", json_path: str | os.PathLike | None = None, device: str = "cpu",
                          threads: int | None = None) -> tuple[dict[str, Any], Encoder]:
    """``modi encoder eval``: :meth:`Encoder.evaluate` of an encoder checkpoint, also written as JSON to
    ``json_path`` (never over the checkpoint). Returns the metrics and the encoder."""
    set_threads(threads)
    check_device(device)
    existing_file(enc, "encoder checkpoint file")
    if json_path:
        refuse_overwrite(json_path, [enc], "--json")
    encoder = Encoder.from_checkpoint(enc, device=device)
    res = encoder.evaluate(data, split=split, units=units)
    if json_path:
        Path(json_path).write_text(json.dumps({k: v for k, v in res.items() if k != "source"}, indent=1))
    return res, encoder


def train_encoder(ckpt: str | os.PathLike, data: str | os.PathLike, out: str | os.PathLike, *, iters: int = 5000,
                  batch: int = 16, losses: str | None = None, optimizer: str | None = None, head: str | None = None,
                  lr: float | None = None, lambda_rec: float | None = None, lambda_contact: float | None = None,
                  lambda_root: float | None = None, lambda_pos: float | None = None, prefix: int | None = None,
                  channel_multiplier: float = 1.0, hidden: int | None = None, units: str = "auto", seed: int = 0,
                  eval_every: int = 500, ckpt_every: int = 250, resume: bool = False, cache: bool = True,
                  progress: bool = True, device: str = "cpu", threads: int | None = None,
                  log: Callable[[str], Any] | None = None) -> EncoderTrainResult:
    """``modi encoder train``: train the encoder I into W+ for the frozen generator of ``ckpt`` on the 80% split of
    ``data`` (a BVH folder, or ``"procedural"``) and write ``out`` (one self-contained checkpoint with the generator
    inside) and ``out.log.jsonl``; the Table 5 metrics on the test split are in the result (``format_table5``
    prints them). Options left None take ``EncoderTrainConfig``'s defaults, or with ``resume`` the checkpoint's
    (given ones must agree). ``out`` is locked for the call and never silently overwritten (``resume=True``
    continues it). Ctrl-C / SIGTERM save a resumable checkpoint and raise :class:`EncoderTrainingInterrupted`
    (with ``.step``). ``log`` gets the data line before training. Cost: ``iters`` steps (minutes to hours)."""
    with hold_output(out):  # a second run writing OUT is refused before any work
        set_threads(threads)
        check_device(device)
        out = Path(out)
        if out.exists() and not resume:
            raise UserError(f"{out} exists: pass --resume to continue it, or choose another --out")
        if resume and not out.exists():
            raise UserError(f"--resume: {out} does not exist")
        options = {"losses": losses, "optimizer": optimizer, "head": head, "lr": lr, "lambda_rec": lambda_rec,
                   "lambda_contact": lambda_contact, "lambda_root": lambda_root, "lambda_pos": lambda_pos}
        if resume:  # the checkpoint's loss form, weights, optimizer and head, unless given (then they must agree)
            options = resumed_train_options(out, options)
        else:
            options = {k: v for k, v in options.items() if v is not None}  # EncoderTrainConfig's defaults
        if hidden is not None and options.get("head", "released") == "released":
            raise UserError("--hidden is the width of the bottleneck head's hidden layer; the released head has none "
                            "(its layers are n_latent x latent_dim wide): add --head bottleneck or drop --hidden")
        st = load_checkpoint(ckpt)
        gen_state = {k: st[k] for k in ("format", "version", "config", "codec", "skeleton", "levels", "G_ema", "step")
                     if k in st}
        g, codec, gcfg = load_model(st, device=device)
        cfg = EncoderTrainConfig(iters=iters, batch=batch, **options, prefix_frames=prefix,
                                 channel_multiplier=channel_multiplier, hidden=hidden, units=units, seed=seed,
                                 eval_every=eval_every, ckpt_every=ckpt_every)
        _, _, t = g.output_shape
        if prefix is not None and not 0 < prefix < t:
            raise UserError(f"--prefix must be in 1..{t - 1} (the model makes {t} frames), got {prefix}")
        windows = load_encoder_data(codec, gcfg, data, cache=cache, progress=progress)
        if log is not None:
            log(f"modi encoder train: {windows.train.shape[0]} train / {windows.test.shape[0]} test windows "
                f"{tuple(windows.train.shape[1:])}; generator step {st['step']}; {cfg.iters} steps")
        trainer = EncoderTrainer((g, codec, gcfg), windows, out, cfg, generator_state=gen_state,
                                 resume=out if resume else None, progress=progress)
        try:
            return trainer.train()
        except EncoderTrainingInterrupted as exc:
            exc.step = trainer.step
            raise


__all__ = ["Encoder", "TASKS", "open_encoder", "evaluate_encoder_file", "train_encoder", "EncoderTrainingInterrupted",
           "format_table5"]
