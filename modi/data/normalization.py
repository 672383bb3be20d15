"""Per-entity, per-channel normalisation statistics for (N, K, E, T) motion tensors.

Statistics are taken over samples and frames, one mean/std per (channel, entity). Constant channels (the zero
padding, a joint that never moves) would have std 0: a floor ``min_std`` keeps them finite, and since
``(x - mean) / std`` is then exactly 0 for them, denormalising restores the constant exactly. Entities listed in
``skip_entities`` (by default nothing; the dataset skips the contact labels so they stay 0/1 for BCE and
sigmoid losses) keep mean 0 and std 1. Stats are plain tensors; ``state_dict`` is a dict of tensors.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from modi.errors import CheckpointError
from modi.faults import atomic_torch_save
from modi.io.safe_load import load_data


@dataclass
class Normalizer:
    """``mean`` and ``std`` are (K, E); tensors to normalise are (..., K, E, T)."""

    mean: Tensor
    std: Tensor
    # (device, dtype) -> the statistics there, as (K, E, 1), with the tensors and versions they were made from:
    # made once per device (on CUDA a copy from the host, which would otherwise come with every decode)
    _placed: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.mean = torch.as_tensor(self.mean)
        self.std = torch.as_tensor(self.std)
        if self.mean.ndim != 2 or self.mean.shape != self.std.shape:
            raise ValueError(f"normalizer: mean {tuple(self.mean.shape)} and std {tuple(self.std.shape)} must be equal (K, E)")
        if not torch.all(self.std > 0):
            raise ValueError("normalizer: std must be positive everywhere")

    @classmethod
    def fit(cls, x: Tensor, min_std: float = 1e-3, skip_entities: Sequence[int] = ()) -> "Normalizer":
        """Stats of ``x`` (N, K, E, T) over N and T (float64 accumulation)."""
        if x.ndim != 4:
            raise ValueError(f"normalizer.fit: expected (N, K, E, T), got {tuple(x.shape)}")
        if x.shape[0] * x.shape[3] == 0:
            raise ValueError("normalizer.fit: no samples")
        if min_std <= 0:
            raise ValueError(f"normalizer.fit: min_std must be positive, got {min_std}")
        xd = x.detach().to(torch.float64)
        mean = xd.mean(dim=(0, 3))
        std = xd.var(dim=(0, 3), unbiased=False).sqrt().clamp_min(min_std)
        for e in skip_entities:
            if not 0 <= e < x.shape[2]:
                raise ValueError(f"normalizer.fit: skip entity {e} out of range for {x.shape[2]} entities")
            mean[:, e] = 0.0
            std[:, e] = 1.0
        return cls(mean.to(x.dtype), std.to(x.dtype))

    @classmethod
    def identity(cls, K: int, E: int, dtype: torch.dtype = torch.float32) -> "Normalizer":
        return cls(torch.zeros(K, E, dtype=dtype), torch.ones(K, E, dtype=dtype))

    def _stats(self, x: Tensor) -> tuple[Tensor, Tensor]:
        if x.ndim < 3 or tuple(x.shape[-3:-1]) != tuple(self.mean.shape):
            raise ValueError(f"normalizer: tensor {tuple(x.shape)} does not match stats (K, E) = {tuple(self.mean.shape)}")
        key = (x.device, x.dtype)
        placed = self.__dict__.setdefault("_placed", {})  # (an object unpickled from before the cache has none)
        made = placed.get(key)
        source = (self.mean, self.std, self.mean._version, self.std._version)
        if made is None or made[0] is not source[0] or made[1] is not source[1] or made[2:4] != source[2:]:
            stats = (self.mean.to(x.device, x.dtype)[..., None], self.std.to(x.device, x.dtype)[..., None])
            made = (*source, stats)
            placed[key] = made
        return made[4]

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_placed"}

    def normalize(self, x: Tensor) -> Tensor:
        mean, std = self._stats(x)
        return (x - mean) / std

    def denormalize(self, x: Tensor) -> Tensor:
        mean, std = self._stats(x)
        return x * std + mean

    def state_dict(self) -> dict[str, Tensor]:
        return {"mean": self.mean.clone(), "std": self.std.clone()}

    @classmethod
    def from_state_dict(cls, d: dict) -> "Normalizer":
        try:
            return cls(torch.as_tensor(d["mean"]), torch.as_tensor(d["std"]))
        except KeyError as exc:
            raise ValueError(f"normalizer state is missing {exc}") from None

    def save(self, path: str | os.PathLike) -> None:
        atomic_torch_save(self.state_dict(), path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Normalizer":

        st = load_data(path, "normaliser file")  # as data only: code in the file is refused unrun
        if not isinstance(st, dict) or not {"mean", "std"} <= set(st):
            raise CheckpointError(f"{path}: not a normaliser file (no 'mean' and 'std' tensors)")
        return cls.from_state_dict(st)
