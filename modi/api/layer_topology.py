"""Skeleton topology for layers of one's own: neighbour lists and pooling maps of a skeleton (or a BVH), joint-only
or with MoDi's root-motion and contact entities, every entity labelled.

The lists go straight into the ``modi_ext`` layers::

    topo = modi.Topology.from_bvh("walk.bvh")            # joints only
    conv = modi_ext.layers.SkeletalConv(4, 16, topo.neighbors(0))
    down = modi_ext.layers.SkeletalDownsample(16, 32, topo.pooling(0))
    # x: (B, 4, J, T) quaternions of the J joints  ->  conv(x): (B, 16, J, T)  ->  down: (B, 32, E_1, T // 2)
"""
from __future__ import annotations

import os
from typing import Any, Sequence

from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import PoolingHierarchy, build_hierarchy, neighbors_from_adjacency
from modi.data.motion import Motion
from modi.errors import UserError

ENTITIES = ("joints", "modi")


class Topology:
    """The pooling hierarchy of a skeleton, finest level first, as plain lists.

    ``entities="joints"`` (default): one entity per joint (the edge that points to it), nothing else, so a
    ``(B, C, J, T)`` tensor of per-joint features fits level 0. ``entities="modi"``: MoDi's entity axis, the J
    joints then one root-motion entity (``"<root_motion>"``) and one contact entity per foot (``"<contact>NAME"``).
    ``feet`` (joint names or indices; default: detected by name) only matters for ``"modi"``. ``distance`` is the
    neighbourhood radius in edges; ``siblings=False`` makes neighbours self + parent + children (the released
    MoDi's), ``pooling="released"`` its pooling (root edge never merged).
    """

    def __init__(self, skeleton: Skeleton, *, entities: str = "joints", feet: Sequence[int | str] | None = None,
                 distance: int = 1, siblings: bool = True, pooling: str = "merge") -> None:
        if entities not in ENTITIES:
            raise UserError(f"entities must be one of {', '.join(ENTITIES)}, got {entities!r}")
        self.skeleton = skeleton
        self.entities = entities
        self.distance = int(distance)
        if entities == "joints":
            foot_idx: list[int] = []
        elif feet is None:
            foot_idx = skeleton.detect_feet()
        else:
            foot_idx = [skeleton.index(f) if isinstance(f, str) else int(f) for f in feet]
        try:
            self.hierarchy: PoolingHierarchy = build_hierarchy(skeleton, foot_idx, neighbor_distance=self.distance,
                                                               siblings=siblings, pooling=pooling)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        self.feet = [skeleton.names[f] for f in foot_idx]
        self._keep = [self._kept(i) for i in range(self.hierarchy.n_levels)]

    @classmethod
    def from_bvh(cls, path: str | os.PathLike, **kwargs: Any) -> "Topology":
        """The topology of a BVH file's skeleton (see the class for the options)."""
        return cls(Motion.from_bvh(path).skeleton, **kwargs)

    # ------------------------------------------------------------------------------------------- levels
    def _kept(self, level: int) -> list[int]:
        """Indices (in the full level) of the entities this topology keeps."""
        lv = self.hierarchy.levels[level]
        if self.entities == "modi":
            return list(range(lv.n_entities))
        special = set(lv.contacts) | ({lv.root_motion} if lv.root_motion is not None else set())
        return [e for e in range(lv.n_entities) if e not in special]

    @property
    def n_levels(self) -> int:
        return self.hierarchy.n_levels

    @property
    def entity_counts(self) -> list[int]:
        """Entities per level, finest first."""
        return [len(k) for k in self._keep]

    def labels(self, level: int = 0) -> list[str]:
        """The name of each entity of ``level``: joint names (``A+B`` for merged groups), ``<root_motion>``,
        ``<contact>NAME``, ``<all>``."""
        names = self.hierarchy.levels[level].names
        return [names[e] for e in self._keep[level]]

    def neighbors(self, level: int = 0, distance: int | None = None) -> list[list[int]]:
        """Neighbour list of every entity of ``level`` (self included, sorted): the ``neighbors`` argument of
        ``modi_ext.layers.SkeletalConv``. ``distance`` other than the topology's recomputes it."""
        keep = self._keep[level]
        where = {e: i for i, e in enumerate(keep)}
        adj = [[where[n] for n in self.hierarchy.levels[level].adjacency[e] if n in where] for e in keep]
        return neighbors_from_adjacency(adj, self.distance if distance is None else int(distance))

    def pooling(self, level: int = 0) -> list[list[int]]:
        """The map from ``level`` to ``level + 1``: entry ``k`` lists the entities of ``level`` merged into entity
        ``k`` of the next (the ``pooling`` argument of ``SkeletalDownsample`` / ``SkeletalUpsample``)."""
        if not 0 <= level < self.n_levels - 1:
            raise UserError(f"pooling: level must be in 0..{self.n_levels - 2}, got {level}")
        fine = {e: i for i, e in enumerate(self._keep[level])}
        coarse = self._keep[level + 1]
        return [[fine[m] for m in self.hierarchy.pooling[level][c] if m in fine] for c in coarse]

    def describe(self) -> str:
        """One line per level: its entity count and labels."""
        return "\n".join(f"level {i}: {n} entities: {', '.join(self.labels(i))}"
                         for i, n in enumerate(self.entity_counts))

    def __repr__(self) -> str:
        return (f"Topology({self.skeleton.n_joints} joints, entities={self.entities!r}, levels "
                f"{'-'.join(map(str, self.entity_counts))})")


__all__ = ["Topology", "ENTITIES"]
