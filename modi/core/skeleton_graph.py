"""Skeleton topology as plain data: neighbour lists, the MoDi entity layout and skeletal pooling hierarchies.

Everything here is derived from a parent array and returned as Python lists, so it can be saved in a
checkpoint and handed to the ``modi_ext`` ops unchanged.

Conventions
-----------
* **Edges.** Joint ``j`` owns the edge that points to it (from ``parents[j]``); the root owns an abstract edge
  from the origin. So there are exactly ``J`` edges, indexed like the joints, and the edge tree has the same
  parent array as the joint tree.
* **Adjacency** follows the skeleton-aware convolutions of Aberman et al. (used by MoDi and GANimator): two edges
  are adjacent when they *share a joint* -- a parent edge and its child edge, and also two sibling edges leaving
  the same joint (left hip, right hip and spine all meet at the pelvis). ``neighbors(..., siblings=False)``
  gives the plain tree distance instead.
* **Entities** (MoDi): the ``J`` edges, then one root-motion entity (index ``J``), then one contact entity per
  foot joint. The root-motion entity is wired like a copy of the root edge (adjacent to the root edge and to the
  root edge's neighbours); a contact entity is adjacent to the edge of its foot joint (and, optionally, to the
  root-motion entity, as GANimator's virtual contact joints are).
* **Pooling** (MoDi's rule, generalised so that *any* tree reaches one entity): in every chain of edges joined
  by degree-2 joints, consecutive pairs are merged (an odd chain keeps its first, root-side edge alone); branch
  points are never pooled across. When no chain has two edges left (every inner node branches), each leaf is
  merged into its parent instead. The root-motion and contact entities ride along unchanged and merge with
  everything else in the last step, so the coarsest level holds exactly one entity. A 20-edge humanoid
  (3 spine, 2 neck/head, 3 per arm, 4 per leg) gives MoDi's 20 -> 12 -> 7 -> 2 -> 1 edge entities.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Sequence

ROOT_MOTION_NAME = "<root_motion>"
POOLINGS = ("merge", "released")
CONTACT_PREFIX = "<contact>"


def _check_parents(parents: Sequence[int]) -> list[int]:
    parents = [int(p) for p in parents]
    if not parents:
        raise ValueError("parents: empty parent array")
    if parents[0] != -1:
        raise ValueError(f"parents: entry 0 must be -1 (the root), got {parents[0]}")
    for j, p in enumerate(parents[1:], start=1):
        if not 0 <= p < j:
            raise ValueError(f"parents: entry {j} is {p}; every parent must precede its child (0 <= p < j)")
    return parents


def edge_adjacency(parents: Sequence[int], siblings: bool = True) -> list[list[int]]:
    """Direct neighbours of each edge (excluding itself): edges sharing a joint.

    With ``siblings=False`` only parent/child edges are adjacent (plain tree distance).
    """
    parents = _check_parents(parents)
    n = len(parents)
    adj: list[set[int]] = [set() for _ in range(n)]
    children: list[list[int]] = [[] for _ in range(n)]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].add(p)
            adj[p].add(j)
            children[p].append(j)
    if siblings:
        for kids in children:
            for a in kids:
                adj[a].update(k for k in kids if k != a)
    return [sorted(a) for a in adj]


def neighbors_from_adjacency(adjacency: Sequence[Sequence[int]], distance: int) -> list[list[int]]:
    """All nodes within ``distance`` hops of each node (breadth first), including the node; sorted lists."""
    if int(distance) != distance or distance < 0:
        raise ValueError(f"distance must be a non-negative integer, got {distance!r}")
    n = len(adjacency)
    out: list[list[int]] = []
    for start in range(n):
        seen = {start: 0}
        queue = deque([start])
        while queue:
            node = queue.popleft()
            if seen[node] == distance:
                continue
            for nb in adjacency[node]:
                if nb not in seen:
                    seen[nb] = seen[node] + 1
                    queue.append(nb)
        out.append(sorted(seen))
    return out


def neighbors(parents: Sequence[int], distance: int, siblings: bool = True) -> list[list[int]]:
    """Neighbour list of every edge (= joint index) at graph distance ``<= distance``, self included, sorted.

    Distance is counted in the edge graph where edges sharing a joint are adjacent (see module docstring).
    """
    return neighbors_from_adjacency(edge_adjacency(parents, siblings=siblings), distance)


def _check_feet(foot_joints: Sequence[int], n_joints: int) -> list[int]:
    feet = [int(f) for f in foot_joints]
    for f in feet:
        if not 0 <= f < n_joints:
            raise ValueError(f"foot joint index {f} out of range for a skeleton of {n_joints} joints")
    if len(set(feet)) != len(feet):
        raise ValueError(f"foot joints contain duplicates: {feet}")
    return feet


@dataclass
class EntityLayout:
    """MoDi's entity axis: ``J`` edges, one root-motion entity, one contact entity per foot joint.

    ``contacts_to_root_motion`` also links every contact entity to the root-motion entity (GANimator wires its
    virtual contact joints to both the foot and the root-motion joint).
    """

    parents: list[int]
    foot_joints: list[int] = field(default_factory=list)
    contacts_to_root_motion: bool = False
    siblings: bool = True

    def __post_init__(self) -> None:
        self.parents = _check_parents(self.parents)
        self.foot_joints = _check_feet(self.foot_joints, len(self.parents))

    @classmethod
    def from_skeleton(cls, skeleton: Any, feet: Sequence[int] | None = None, **kwargs: Any) -> "EntityLayout":
        """Layout of a ``Skeleton``; ``feet=None`` asks ``skeleton.detect_feet()``."""
        if feet is None:
            feet = skeleton.detect_feet()
        return cls(list(skeleton.parents), list(feet), **kwargs)

    @property
    def n_edges(self) -> int:
        return len(self.parents)

    @property
    def root_motion(self) -> int:
        return self.n_edges

    @property
    def contacts(self) -> list[int]:
        return [self.n_edges + 1 + i for i in range(len(self.foot_joints))]

    @property
    def n_entities(self) -> int:
        return self.n_edges + 1 + len(self.foot_joints)

    def entity_parents(self) -> list[int]:
        """A tree over all entities: edges as in the skeleton, root motion under the root edge, contacts under
        their foot edge."""
        return list(self.parents) + [0] + list(self.foot_joints)

    def entity_names(self, joint_names: Sequence[str]) -> list[str]:
        if len(joint_names) != self.n_edges:
            raise ValueError(f"entity_names: got {len(joint_names)} joint names for {self.n_edges} edges")
        return list(joint_names) + [ROOT_MOTION_NAME] + [f"{CONTACT_PREFIX}{joint_names[f]}" for f in self.foot_joints]

    def adjacency(self) -> list[list[int]]:
        """Direct neighbours of each entity (excluding itself)."""
        edge_groups = [[e] for e in range(self.n_edges)]
        return _level_adjacency(
            edge_groups, edge_adjacency(self.parents, self.siblings), 0, self.foot_joints, self.contacts_to_root_motion
        )

    def neighbors(self, distance: int = 1) -> list[list[int]]:
        """Neighbour list of every entity within ``distance`` hops, self included, sorted."""
        return neighbors_from_adjacency(self.adjacency(), distance)


def _level_adjacency(
    edge_groups: Sequence[Sequence[int]],
    edge_adj0: Sequence[Sequence[int]],
    root_edge: int,
    foot_edges: Sequence[int],
    contacts_to_root_motion: bool,
) -> list[list[int]]:
    """Adjacency of a level whose first entities are groups of finest edges, followed by the root-motion entity
    and the contact entities. Two groups are adjacent when any of their edges are."""
    owner: dict[int, int] = {}
    for g, members in enumerate(edge_groups):
        for e in members:
            owner[e] = g
    n_groups = len(edge_groups)
    n = n_groups + 1 + len(foot_edges)
    adj: list[set[int]] = [set() for _ in range(n)]
    for g, members in enumerate(edge_groups):
        for e in members:
            for nb in edge_adj0[e]:
                h = owner[nb]
                if h != g:
                    adj[g].add(h)
    rm = n_groups
    root_group = owner[root_edge]
    for g in [root_group, *adj[root_group]]:
        if g < n_groups:
            adj[rm].add(g)
            adj[g].add(rm)
    for i, f in enumerate(foot_edges):
        c = n_groups + 1 + i
        g = owner[f]
        adj[c].add(g)
        adj[g].add(c)
        if contacts_to_root_motion:
            adj[c].add(rm)
            adj[rm].add(c)
    return [sorted(a) for a in adj]


@dataclass
class Level:
    """One level of a pooling hierarchy.

    ``groups[k]`` lists the finest-level entities merged into entity ``k``; ``adjacency`` the direct neighbours
    (excluding self) from which ``neighbors`` was computed at the hierarchy's distance. ``parents`` is a tree over
    the entities (root motion hangs under the root edge's entity, contacts under their foot's entity).
    ``root_motion``/``contacts`` are the special entities' indices (``None``/``[]`` on the merged coarsest level).
    """

    n_entities: int
    neighbors: list[list[int]]
    parents: list[int] | None
    names: list[str]
    groups: list[list[int]] = field(default_factory=list)
    adjacency: list[list[int]] = field(default_factory=list)
    root_motion: int | None = None
    contacts: list[int] = field(default_factory=list)

    @property
    def n_edge_entities(self) -> int:
        """Entities made of skeleton edges only (all but root motion and contacts)."""
        return self.n_entities - (0 if self.root_motion is None else 1) - len(self.contacts)


@dataclass
class PoolingHierarchy:
    """Levels from FINEST (index 0) to COARSEST (last; exactly one entity).

    ``pooling[i][k]`` lists the entities of level ``i`` merged into entity ``k`` of level ``i + 1``; the lists
    partition level ``i``. This is the coarse->fine map ``SkeletalDownsample``/``SkeletalUpsample`` take.
    """

    levels: list[Level]
    pooling: list[list[list[int]]]
    neighbor_distance: int = 1

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    @property
    def entity_counts(self) -> list[int]:
        return [lv.n_entities for lv in self.levels]

    @property
    def edge_counts(self) -> list[int]:
        return [lv.n_edge_entities for lv in self.levels]

    def neighbors(self, level: int, distance: int) -> list[list[int]]:
        """Neighbour lists of ``level`` at another distance than the one the hierarchy was built with."""
        return neighbors_from_adjacency(self.levels[level].adjacency, distance)

    def describe(self) -> str:
        """One line per level: entity count and members, for humans."""
        lines = []
        for i, lv in enumerate(self.levels):
            lines.append(f"level {i}: {lv.n_entities} entities ({lv.n_edge_entities} edge): " + ", ".join(lv.names))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Plain lists/ints only: safe for ``torch.save(weights_only=True)`` and JSON."""
        return {
            "neighbor_distance": self.neighbor_distance,
            "pooling": [[list(m) for m in p] for p in self.pooling],
            "levels": [
                {
                    "n_entities": lv.n_entities,
                    "neighbors": lv.neighbors,
                    "parents": lv.parents,
                    "names": lv.names,
                    "groups": lv.groups,
                    "adjacency": lv.adjacency,
                    "root_motion": lv.root_motion,
                    "contacts": lv.contacts,
                }
                for lv in self.levels
            ],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "PoolingHierarchy":
        return cls(
            levels=[Level(**lv) for lv in d["levels"]],
            pooling=[[list(m) for m in p] for p in d["pooling"]],
            neighbor_distance=int(d.get("neighbor_distance", 1)),
        )


def _pool_edges_once(parents: list[int]) -> list[list[int]]:
    """One pooling step on an edge tree; returns groups (lists of entity indices of this level), sorted so that
    the coarse tree stays topologically ordered. Always merges something when there are >= 2 entities."""
    n = len(parents)
    children: list[list[int]] = [[] for _ in range(n)]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    chains: list[list[int]] = []
    for start in range(n):
        p = parents[start]
        if p >= 0 and len(children[p]) == 1:
            continue  # inside a chain, not its first edge
        chain = [start]
        while len(children[chain[-1]]) == 1:
            chain.append(children[chain[-1]][0])
        chains.append(chain)
    groups: list[list[int]]
    if any(len(c) >= 2 for c in chains):
        groups = []
        for chain in chains:
            if len(chain) % 2 == 1:
                groups.append([chain[0]])
                chain = chain[1:]
            groups.extend([chain[i], chain[i + 1]] for i in range(0, len(chain), 2))
    else:
        # Every inner entity branches: fold each leaf into its parent.
        leaf = [not children[j] for j in range(n)]
        merged: dict[int, list[int]] = {}
        for j in range(n):
            if leaf[j] and parents[j] >= 0:
                merged.setdefault(parents[j], [parents[j]]).append(j)
            elif j not in merged:
                merged[j] = [j]
        groups = list(merged.values())
    groups.sort(key=lambda g: g[0])
    return groups


def _pool_edges_keep_root(parents: list[int]) -> list[list[int]]:
    """One released-style pooling step: the root edge (0) stays alone; the rest of the tree (a forest under the
    root) pools by ``_pool_edges_once``'s rule; when that merges nothing, the root's subtrees merge into one
    entity. Progresses whenever there are >= 3 entities."""
    n = len(parents)
    if n <= 2:
        return [[j] for j in range(n)]
    sub_parents = [-1 if parents[j] == 0 else parents[j] - 1 for j in range(1, n)]
    sub_groups = _pool_edges_once(sub_parents)
    groups = [[0]] + [[m + 1 for m in g] for g in sub_groups]
    if len(groups) == n:  # nothing merged below the root: fold everything under it into one entity
        groups = [[0], list(range(1, n))]
    groups.sort(key=lambda g: g[0])
    return groups


def _group_name(names: Sequence[str]) -> str:
    if len(names) == 1:
        return names[0]
    text = "+".join(names)
    if len(text) > 60:
        text = f"{names[0]}+{len(names) - 1} more"
    return text


def build_hierarchy(
    skeleton: Any,
    feet: Sequence[int] | None = None,
    neighbor_distance: int = 1,
    contacts_to_root_motion: bool = False,
    siblings: bool = True,
    pooling: str = "merge",
) -> PoolingHierarchy:
    """Automatic skeletal pooling hierarchy for any tree (see the module docstring).

    ``skeleton`` is a ``Skeleton`` (or anything with ``parents`` and ``names``); ``feet`` lists the joints that
    get contact entities (``None``: ``skeleton.detect_feet()``; ``[]``: no contacts). ``siblings=False`` makes
    neighbours self + parent + children (the released MoDi's ``Edge`` neighbourhoods) instead of every edge sharing
    a joint. ``pooling``: ``"merge"`` (default) pools down to one entity, the specials merging in the last step;
    ``"released"`` is the released MoDi's style -- the root edge is never merged with another edge, pooling stops
    at <= 2 edge entities, and the root-motion and contact entities stay separate down to the coarsest level (the
    released code's own loop does not terminate on every skeleton, so the steps here are ours:
    ``_pool_edges_keep_root``).
    """
    if pooling not in POOLINGS:
        raise ValueError(f"pooling must be one of {', '.join(POOLINGS)}, not {pooling!r}")
    parents = _check_parents(skeleton.parents)
    joint_names = list(getattr(skeleton, "names", [f"joint{j}" for j in range(len(parents))]))
    if feet is None:
        feet = skeleton.detect_feet()
    feet = _check_feet(feet, len(parents))
    if int(neighbor_distance) != neighbor_distance or neighbor_distance < 0:
        raise ValueError(f"neighbor_distance must be a non-negative integer, got {neighbor_distance!r}")
    n_special = 1 + len(feet)
    adj0 = edge_adjacency(parents, siblings=siblings)

    # Edge-only pooling sequence: each entry maps coarse edge entity -> fine edge entities.
    edge_levels_parents = [parents]
    edge_levels_groups = [[[e] for e in range(len(parents))]]  # in finest edges
    edge_levels_names = [joint_names]
    edge_pooling: list[list[list[int]]] = []
    stop_at = 2 if pooling == "released" else 1
    while len(edge_levels_parents[-1]) > stop_at:
        cur_parents = edge_levels_parents[-1]
        cur_groups = edge_levels_groups[-1]
        cur_names = edge_levels_names[-1]
        groups = _pool_edges_keep_root(cur_parents) if pooling == "released" else _pool_edges_once(cur_parents)
        owner = {m: k for k, g in enumerate(groups) for m in g}
        new_parents = [-1 if cur_parents[g[0]] < 0 else owner[cur_parents[g[0]]] for g in groups]
        edge_pooling.append(groups)
        edge_levels_parents.append(new_parents)
        edge_levels_groups.append([sorted(e for m in g for e in cur_groups[m]) for g in groups])
        edge_levels_names.append([_group_name([cur_names[m] for m in g]) for g in groups])

    special_names = [ROOT_MOTION_NAME] + [f"{CONTACT_PREFIX}{joint_names[f]}" for f in feet]
    levels: list[Level] = []
    pooling_maps: list[list[list[int]]] = []
    n_edge_levels = len(edge_levels_parents)
    # Specials ride along on every edge level but the coarsest; there everything is one entity ("merge"). With
    # "released" pooling they ride along on every level and there is no merged level.
    if pooling == "released":
        n_full = n_edge_levels
    else:
        n_full = n_edge_levels - 1 if n_edge_levels > 1 else 1
    for i in range(n_full):
        groups = edge_levels_groups[i]
        ng = len(groups)
        owner0 = {e: k for k, g in enumerate(groups) for e in g}
        adjacency = _level_adjacency(groups, adj0, 0, feet, contacts_to_root_motion)
        lv_parents = list(edge_levels_parents[i]) + [owner0[0]] + [owner0[f] for f in feet]
        full_groups = [list(g) for g in groups] + [[len(parents) + s] for s in range(n_special)]
        levels.append(
            Level(
                n_entities=ng + n_special,
                neighbors=neighbors_from_adjacency(adjacency, neighbor_distance),
                parents=lv_parents,
                names=list(edge_levels_names[i]) + special_names,
                groups=full_groups,
                adjacency=adjacency,
                root_motion=ng,
                contacts=[ng + 1 + k for k in range(len(feet))],
            )
        )
        if i + 1 < n_full:
            nxt = edge_pooling[i]
            pooling_maps.append([list(g) for g in nxt] + [[ng + s] for s in range(n_special)])
    if pooling == "released":
        return PoolingHierarchy(levels=levels, pooling=pooling_maps, neighbor_distance=int(neighbor_distance))
    last = levels[-1]
    levels.append(
        Level(
            n_entities=1,
            neighbors=[[0]],
            parents=[-1],
            names=["<all>"],
            groups=[sorted(e for g in last.groups for e in g)],
            adjacency=[[]],
            root_motion=None,
            contacts=[],
        )
    )
    pooling_maps.append([list(range(last.n_entities))])
    return PoolingHierarchy(levels=levels, pooling=pooling_maps, neighbor_distance=int(neighbor_distance))
