"""Data sets from Python as ``modi synth`` and ``modi data info`` make and describe them."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from modi.data.dataset import DatasetConfig, MotionDataset, build_dataset
from modi.data.procedural import KINDS, write_dataset
from modi.errors import UserError


def write_procedural(out_dir: str | os.PathLike, *, n: int = 32, frames: int = 128, fps: float = 30.0,
                     seed: int = 0, kinds: Sequence[str] = KINDS) -> list[Path]:
    """``modi synth``: write ``n`` procedural clips (``kinds`` in turn) on the built-in humanoid as BVH, plus
    ``labels.json``; clip ``i`` depends only on ``(seed, i)``. Returns the clip paths. Cost: milliseconds a clip."""
    kinds = list(kinds)
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise UserError(f"--kinds: unknown kind(s) {', '.join(bad) or '(none given)'}; choose from {', '.join(KINDS)}")
    if n < 1:
        raise UserError(f"--n must be >= 1, got {n}")
    if frames < 2:
        raise UserError(f"--frames must be >= 2, got {frames}")
    if not fps > 0:
        raise UserError(f"--fps must be > 0, got {fps}")
    return write_dataset(out_dir, n_clips=n, frames=frames, seed=seed, fps=fps, kinds=kinds)


@dataclass
class DatasetInfo:
    """What ``modi data info`` prints: the data set and the seconds it took to build (or read from the cache)."""

    dataset: MotionDataset
    seconds: float

    @property
    def dropped(self) -> list[str]:
        """Joints of the files that the joint reduction left out."""
        kept = set(self.dataset.kept_joints)
        return [n for j, n in enumerate(self.dataset.source_skeleton.names) if j not in kept]


def dataset_info(folder: str | os.PathLike, config: DatasetConfig | None = None, *, cache: bool = True,
                 cache_dir: str | os.PathLike | None = None, progress: bool = False) -> DatasetInfo:
    """``modi data info``: build (or read from the cache) the training data set of a BVH folder. Cost: reading
    every clip the first time (seconds for a few hundred), milliseconds from the cache."""
    t0 = time.perf_counter()
    ds = build_dataset(folder, config, cache=cache, cache_dir=cache_dir, progress=progress)
    return DatasetInfo(ds, time.perf_counter() - t0)


__all__ = ["write_procedural", "dataset_info", "DatasetInfo"]
