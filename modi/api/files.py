"""``modi.load``: the right object for any file modi reads."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

import numpy as np
import torch

from modi.api.encoder import Encoder
from modi.api.ganimator import GanimatorRun
from modi.api.generator import ModiGenerator
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
    """A glTF file's skeleton animation as a Motion in metres: :meth:`Motion.from_gltf`, under its earlier name."""
    return Motion.from_gltf(path)


def load(path: str | os.PathLike, *, device: str | torch.device = "cpu", raw_weights: bool = False) -> Loaded:
    """The right object for any file modi reads:

    * ``.bvh`` -> :class:`modi.Motion` (through :meth:`Motion.from_bvh`), ``.glb`` / ``.gltf`` -> :class:`Motion` in
      metres (through :meth:`Motion.from_gltf`);
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
        return Motion.from_gltf(p)
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


__all__ = ["load", "motion_from_gltf", "Loaded"]
