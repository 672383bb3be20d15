"""MoDi's hierarchy as the networks see it: one ``LevelSpec`` per level, coarse -> fine, from a pooling hierarchy.

Also the entity maps between two levels as matrices: the unpooling copy (the to-motion skip connection) and the
skeletal mean pooling of the pooling ablation.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch

from modi.models.modi.config import ModelConfig

__all__ = ["LevelSpec", "build_levels", "unpool_matrix", "pool_matrix"]


@dataclass
class LevelSpec:
    """One hierarchy level as the model sees it (coarse -> fine order).

    ``up_pooling[c]`` lists this level's entities that merge into entity ``c`` of the previous (coarser) level;
    it is ``None`` for level 0.
    """

    n_entities: int
    neighbors: list[list[int]]
    up_pooling: list[list[int]] | None
    n_frames: int
    channels: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LevelSpec":
        return cls(
            n_entities=int(d["n_entities"]),
            neighbors=[[int(n) for n in ns] for ns in d["neighbors"]],
            up_pooling=None if d["up_pooling"] is None else [[int(n) for n in ns] for ns in d["up_pooling"]],
            n_frames=int(d["n_frames"]),
            channels=int(d["channels"]),
        )


def build_levels(hierarchy: Any, cfg: ModelConfig, n_frames: int) -> list[LevelSpec]:
    """Turn a ``PoolingHierarchy`` (finest first) into coarse -> fine ``LevelSpec``s for the given frame count.

    Uses at most ``len(cfg.channels)`` of the finest hierarchy levels, and needs ``n_frames`` to halve cleanly
    once per level, because every level doubles time.
    """
    h_levels = list(hierarchy.levels)
    poolings = list(hierarchy.pooling)
    if len(poolings) != len(h_levels) - 1:
        raise ValueError(f"hierarchy has {len(h_levels)} levels but {len(poolings)} pooling maps (need levels-1)")
    n_levels = min(len(h_levels), len(cfg.channels))
    factor = 2 ** (n_levels - 1)
    if n_frames % factor != 0:
        raise ValueError(
            f"n_frames={n_frames} must be divisible by 2**(levels-1)={factor} for a {n_levels}-level hierarchy; "
            f"use a multiple of {factor} frames or fewer channel levels"
        )
    channels = [int(c) for c in cfg.channels][-n_levels:]
    specs: list[LevelSpec] = []
    for i in range(n_levels):  # i: coarse -> fine; hierarchy index = n_levels - 1 - i
        h = n_levels - 1 - i
        lv = h_levels[h]
        up = None if i == 0 else [[int(e) for e in group] for group in poolings[h]]
        specs.append(
            LevelSpec(
                n_entities=int(lv.n_entities),
                neighbors=[[int(n) for n in ns] for ns in lv.neighbors],
                up_pooling=up,
                n_frames=n_frames // 2 ** (n_levels - 1 - i),
                channels=channels[i],
            )
        )
    for i in range(1, n_levels):
        covered = sorted({e for group in specs[i].up_pooling for e in group})
        if covered != list(range(specs[i].n_entities)):
            raise ValueError(f"pooling map into level {i} does not cover each of its {specs[i].n_entities} entities")
        if len(specs[i].up_pooling) != specs[i - 1].n_entities:
            raise ValueError(f"pooling map into level {i} has {len(specs[i].up_pooling)} groups, "
                             f"expected {specs[i - 1].n_entities}")
    return specs


def unpool_matrix(pooling: list[list[int]], n_fine: int) -> torch.Tensor:
    """(E_fine, E_coarse) copy matrix: each fine entity takes its coarse entity's features (averaged if shared)."""
    m = torch.zeros(n_fine, len(pooling))
    for c, group in enumerate(pooling):
        for e in group:
            m[e, c] = 1.0
    return m / m.sum(1, keepdim=True).clamp_min(1.0)


def pool_matrix(pooling: list[list[int]], n_fine: int) -> torch.Tensor:
    """(E_coarse, E_fine) averaging matrix: skeletal mean pooling (Aberman et al.) for the pooling ablation."""
    m = torch.zeros(len(pooling), n_fine)
    for c, group in enumerate(pooling):
        for e in group:
            m[c, e] = 1.0 / len(group)
    return m
