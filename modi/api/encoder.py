"""MoDi's encoder into W+ as one object: projections of motions onto the generator's manifold (G(I(m))) and the
``modi apply`` tasks, returning :class:`modi.Motion`."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence, Union

import torch
from torch import Tensor

from modi.data.motion import Motion
from modi.errors import UserError
from modi.faults import atomic_write
from modi.models.modi.encoder import applications as A
from modi.models.modi.encoder.metrics import evaluate_encoder
from modi.models.modi.encoder.training import EncoderBundle, load_encoder, load_encoder_data
from modi.api._util import existing_file
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


__all__ = ["Encoder", "TASKS"]
