"""The skeleton: joint names, parents and rest offsets — one place for the tree itself.

Topology derived from it (neighbour lists, entity layouts, pooling hierarchies) lives in
``modi.topology``; this module only holds the tree and operations that change the tree.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Skeleton:
    """A joint tree. Joints are topologically sorted: ``parents[j] < j`` and ``parents[0] == -1``.

    ``offsets[j]`` is joint ``j``'s rest translation in its parent's frame (the BVH OFFSET);
    ``end_sites`` maps a joint index to the offset of its BVH End Site (kept for faithful export).
    ``rotation_orders[j]`` is the Euler order used when writing BVH (e.g. ``"ZXY"``).
    """

    names: list[str]
    parents: list[int]
    offsets: np.ndarray
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)
    rotation_orders: list[str] | None = None

    def __post_init__(self) -> None:
        self.offsets = np.asarray(self.offsets, dtype=np.float64).reshape(-1, 3)
        self.parents = [int(p) for p in self.parents]
        n = len(self.names)
        if len(self.parents) != n or self.offsets.shape[0] != n:
            raise ValueError(
                f"skeleton: names ({n}), parents ({len(self.parents)}) and offsets ({self.offsets.shape[0]}) disagree"
            )
        if n == 0:
            raise ValueError("skeleton: no joints")
        if self.parents[0] != -1:
            raise ValueError("skeleton: joint 0 must be the root (parent -1)")
        for j, p in enumerate(self.parents[1:], start=1):
            if not 0 <= p < j:
                raise ValueError(f"skeleton: joint {j} ({self.names[j]}) has parent {p}; parents must precede children")
        if len(set(self.names)) != n:
            raise ValueError("skeleton: duplicate joint names")
        if self.rotation_orders is None:
            self.rotation_orders = ["ZYX"] * n

    @property
    def n_joints(self) -> int:
        return len(self.names)

    def children(self, j: int) -> list[int]:
        return [c for c, p in enumerate(self.parents) if p == j]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r}; joints are {', '.join(self.names)}") from None
