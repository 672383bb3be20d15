"""``modi.load``: the right object for any file modi reads, and :class:`FileInfo`, what ``modi info`` prints."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

import numpy as np
import torch

from modi.api.encoder import Encoder
from modi.api.ganimator import GanimatorRun
from modi.api.generator import ModiGenerator
from modi.core.rotations import matrix_to_quat, quat_mul
from modi.core.skeleton import Skeleton
from modi.data.motion import Motion
from modi.errors import UserError
from modi.evaluation.features import FeatureExtractor, load_extractor
from modi.io import gltf
from modi.io.safe_load import earlier_modi_globals, load_data

Loaded = Union[Motion, ModiGenerator, Encoder, GanimatorRun, FeatureExtractor, torch.Tensor]
_RUN_FILES = {"ganimator.ckpt": "ganimator", "checkpoint.pt": "modi"}
_FORMATS = {"modi-checkpoint": "modi", "modi-encoder": "encoder", "modi.ganimator/1": "ganimator",
            "modi-features-v1": "features"}


def motion_from_gltf(path: str | os.PathLike) -> Motion:
    """A glTF file's skeleton animation as a Motion in metres (bones rigid: a non-root joint's offset is the mean of
    its translation track; the transform above the skeleton is folded into the root)."""
    tr = gltf.read_tracks(path)
    above = np.asarray(tr.above, dtype=np.float64)
    s = float(np.linalg.norm(above[:3, 0])) or 1.0
    rot = torch.from_numpy(above[:3, :3] / s)
    q_above = matrix_to_quat(rot).to(torch.float64)
    trans = tr.translations.to(torch.float64)
    root = s * trans[:, 0] @ rot.T + torch.from_numpy(above[:3, 3])
    rotations = tr.rotations.to(torch.float64).clone()
    rotations[:, 0] = quat_mul(q_above.expand_as(rotations[:, 0]), rotations[:, 0])
    offsets = s * trans.mean(0).numpy()
    offsets[0] = root[0].numpy()
    skeleton = Skeleton(list(tr.names), list(tr.parents), offsets)
    contacts = None
    if tr.contacts is not None and tr.contacts.any():
        contacts = {tr.names[j]: tr.contacts[:, j] for j in range(len(tr.names)) if tr.contacts[:, j].any()}
    return Motion(skeleton, rotations, root, tr.fps, "metres", contacts=contacts)


def load(path: str | os.PathLike, *, device: str | torch.device = "cpu", raw_weights: bool = False) -> Loaded:
    """The right object for any file modi reads:

    * ``.bvh`` -> :class:`modi.Motion` (through :meth:`Motion.from_bvh`), ``.glb`` / ``.gltf`` -> :class:`Motion` in
      metres;
    * a MoDi checkpoint (``modi train``, or a released one imported with ``modi import``) or its run folder ->
      :class:`ModiGenerator` (EMA weights; ``raw_weights`` for the raw generator);
    * an encoder checkpoint -> :class:`Encoder`; a GANimator run folder or ``ganimator.ckpt`` ->
      :class:`GanimatorRun`; a feature-extractor file -> its ``FeatureExtractor``;
    * a ``.npy`` latent -> a tensor.

    Checkpoints are read as data only: a file that names code is refused unrun. Anything else is one
    :class:`modi.errors.UserError` line. Cost: reading the file (and building the network, well under a second)."""
    p = Path(path)
    if p.is_dir():
        for name, kind in _RUN_FILES.items():
            if (p / name).is_file():
                return GanimatorRun.from_checkpoint(p, device=device) if kind == "ganimator" else \
                    ModiGenerator.from_checkpoint(p / name, device=device, ema=not raw_weights)
        raise UserError(f"{p}: a folder without a modi checkpoint ({' or '.join(_RUN_FILES)})")
    if not p.is_file():
        raise UserError(f"{p}: no such file")
    suffix = p.suffix.lower()
    if suffix == ".bvh":
        return Motion.from_bvh(p)
    if suffix in gltf.SUFFIXES:
        return motion_from_gltf(p)
    if suffix == ".npy":
        try:
            return torch.from_numpy(np.load(p, allow_pickle=False).astype(np.float32))
        except ValueError as exc:  # numbers only: a pickled object array could run code
            raise UserError(f"{p}: not a .npy array of numbers ({exc})") from None
    st = load_data(p, "modi file", allowed=earlier_modi_globals())
    fmt = st.get("format") if isinstance(st, dict) else None
    kind = _FORMATS.get(fmt)
    if kind == "modi":
        gen = ModiGenerator.from_checkpoint(st, device=device, ema=not raw_weights)
        gen.path = str(p)
        return gen
    if kind == "encoder":
        enc = Encoder.from_checkpoint(st, device=device)
        enc.path = str(p)
        return enc
    if kind == "ganimator":
        return GanimatorRun.from_checkpoint(p, device=device)
    if kind == "features":
        return load_extractor(p)
    raise UserError(f"{p}: not a file modi reads (a BVH or glTF motion, a MoDi, encoder or GANimator checkpoint, a "
                    "feature-extractor file or a .npy latent)"
                    + (f"; format tag {fmt!r}" if fmt is not None else ""))


@dataclass
class FileInfo:
    """What ``modi info FILE`` prints, as an object: ``kind``, ``format`` and ``version``, training ``step``, the
    ``skeleton`` (joints, root, names, parents), the ``config``, the ``data`` it was trained on and the modi and
    torch versions that wrote it. ``str()`` is the text ``modi info`` prints; :meth:`to_dict` its ``--json``."""

    file: str
    kind: str
    format: Any
    version: Any
    step: Any
    skeleton: dict[str, Any] | None
    config: Any
    data: Any
    modi_version: str | None = None
    torch_version: str | None = None
    text: str = field(default="", repr=False, compare=False)

    @classmethod
    def from_dict(cls, d: dict[str, Any], text: str = "") -> "FileInfo":
        return cls(d["file"], d["kind"], d.get("format"), d.get("version"), d.get("step"), d.get("skeleton"),
                   d.get("config"), d.get("data"), d.get("modi_version"), d.get("torch_version"), text)

    def to_dict(self) -> dict[str, Any]:
        """The ``modi info --json`` object."""
        return {"file": self.file, "kind": self.kind, "format": self.format, "version": self.version,
                "step": self.step, "skeleton": self.skeleton, "config": self.config, "data": self.data,
                "modi_version": self.modi_version, "torch_version": self.torch_version}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, default=str)

    def __str__(self) -> str:
        return self.text or self.to_json()


__all__ = ["load", "FileInfo", "motion_from_gltf", "Loaded"]
