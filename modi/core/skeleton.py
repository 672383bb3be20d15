"""The skeleton: joint names, parents and rest offsets — one place for the tree itself.

Topology derived from it (neighbour lists, entity layouts, pooling hierarchies) lives in
``modi.core.skeleton_graph``; this module only holds the tree and operations that change the tree.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np


def strip_namespace(name: str) -> str:
    """``mixamorig7:LeftArm`` -> ``LeftArm``: exporters keep or drop the namespace prefix; the joint is the same."""
    return name.rsplit(":", 1)[-1]

# Default humanoid reduction: (joint pattern, ancestor pattern). A joint is dropped when its name matches the
# first and one of its ancestors matches the second -- so a crab's eye stalks (under the pelvis) survive while a
# Mixamo character's eyes (under the head) go. All case-insensitive ``re.search``.
DEFAULT_DROP_RULES: tuple[tuple[str, str], ...] = (
    (r"thumb|index|middle|ring|pinky|finger|carpal", r"hand|wrist"),
    (r"eye(?!brow)|jaw|tongue|teeth|lip|headtop|head_?top|head_?end", r"head"),
)

_TOE = re.compile(r"toe|ball", re.I)
_ANKLE = re.compile(r"foot|ankle", re.I)
_HEEL = re.compile(r"heel", re.I)
_END = re.compile(r"end$|_end|nub$|site$", re.I)
_HEAD = re.compile(r"head", re.I)


def _side(name: str) -> str | None:
    """'L', 'R' or None from a joint name: LeftFoot, Foot_L, Bip01_L_Foot, LHipJoint, mixamorig:RightToeBase."""
    base = name.split(":")[-1]
    low = base.lower()
    if "left" in low:
        return "L"
    if "right" in low:
        return "R"
    tokens = [t for t in re.split(r"[^a-z0-9]+", low) if t]
    if "l" in tokens:
        return "L"
    if "r" in tokens:
        return "R"
    m = re.match(r"([LR])(?=[A-Z])", base)
    return m.group(1) if m else None


@dataclass(eq=False, repr=False)
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

    def __eq__(self, other: object) -> bool:
        """Exactly the same tree: names, parents, offsets, End Sites and Euler orders."""
        if not isinstance(other, Skeleton):
            return NotImplemented
        return (self.names == other.names and self.parents == other.parents
                and self.rotation_orders == other.rotation_orders and np.array_equal(self.offsets, other.offsets)
                and self.end_sites.keys() == other.end_sites.keys()
                and all(np.array_equal(np.asarray(v), np.asarray(other.end_sites[k])) for k, v in self.end_sites.items()))

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by value

    def __repr__(self) -> str:
        shown = ", ".join(self.names[:6]) + (", ..." if self.n_joints > 6 else "")
        return f"Skeleton({self.n_joints} joints: {shown})"

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

    # ----------------------------------------------------------------------------------------------------------
    # Tree queries

    def descendants(self, j: int) -> list[int]:
        """All joints below ``j`` (not ``j`` itself), in index order."""
        below = {j}
        for c in range(j + 1, self.n_joints):
            if self.parents[c] in below:
                below.add(c)
        below.discard(j)
        return sorted(below)

    def ancestors(self, j: int) -> list[int]:
        """Joints above ``j``, nearest first."""
        out = []
        p = self.parents[j]
        while p >= 0:
            out.append(p)
            p = self.parents[p]
        return out

    def leaves(self) -> list[int]:
        has_child = set(p for p in self.parents if p >= 0)
        return [j for j in range(self.n_joints) if j not in has_child]

    def rest_positions(self) -> np.ndarray:
        """Global joint positions (J,3) of the rest pose (all rotations identity, root at its offset)."""
        pos = np.zeros((self.n_joints, 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos

    def bone_lengths(self) -> np.ndarray:
        """Length of each joint's offset (J,); the root's is its offset from the origin."""
        return np.linalg.norm(self.offsets, axis=1)

    # ----------------------------------------------------------------------------------------------------------
    # Subsets

    def _resolve(self, items: Sequence[int | str], what: str) -> list[int]:
        out = []
        for it in items:
            if isinstance(it, str):
                out.append(self.index(it))
            else:
                j = int(it)
                if not 0 <= j < self.n_joints:
                    raise ValueError(f"{what}: joint index {j} out of range for {self.n_joints} joints")
                out.append(j)
        return out

    def subset(self, keep: Sequence[int | str]) -> tuple["Skeleton", list[int]]:
        """Keep only the given joints (indices or names); returns ``(skeleton, kept_indices)`` (sorted).

        A kept joint is re-parented to its nearest kept ancestor and its offset becomes the sum of the offsets
        along the dropped chain -- exact for the rest pose, where every rotation is identity. The motion side
        (composing the dropped joints' rotations) is ``Motion.subset``. A kept joint that loses all its children
        gets an End Site at its first dropped child's offset, so exports still show the bone's direction.
        """
        kept = sorted(set(self._resolve(keep, "subset")))
        if not kept or kept[0] != 0:
            raise ValueError(f"subset: the root joint ({self.names[0]}) must be kept")
        new_index = {old: new for new, old in enumerate(kept)}
        parents: list[int] = []
        offsets = np.zeros((len(kept), 3))
        for new, old in enumerate(kept):
            off = self.offsets[old].copy()
            p = self.parents[old]
            while p >= 0 and p not in new_index:
                off += self.offsets[p]
                p = self.parents[p]
            parents.append(-1 if p < 0 else new_index[p])
            offsets[new] = off
        end_sites: dict[int, np.ndarray] = {}
        for new, old in enumerate(kept):
            if old in self.end_sites:
                end_sites[new] = np.asarray(self.end_sites[old], dtype=np.float64).copy()
            elif new not in parents:
                kids = self.children(old)
                if kids:
                    end_sites[new] = self.offsets[kids[0]].copy()
        orders = None if self.rotation_orders is None else [self.rotation_orders[j] for j in kept]
        sk = Skeleton([self.names[j] for j in kept], parents, offsets, end_sites, orders)
        return sk, kept

    def reduce(
        self, drop_patterns: Sequence[str] | None = None, keep: Sequence[str] | None = None
    ) -> tuple["Skeleton", list[int]]:
        """Drop joints whose names match any of ``drop_patterns`` (case-insensitive regex search); joints named in
        ``keep`` always stay. Only the matching joints go: their kept descendants are re-parented (``subset``).

        ``drop_patterns=None`` applies ``DEFAULT_DROP_RULES``: fingers below a hand and eyes/jaw/head-top below a
        head. That turns Mixamo's 65/67-joint rigs into GANimator's 24 joints and leaves Bandai (22), the crab
        and the elephant untouched.
        """
        keep_idx = set(self._resolve(list(keep or []), "reduce keep"))
        drop: set[int] = set()
        if drop_patterns is None:
            for pattern, ancestor_pattern in DEFAULT_DROP_RULES:
                pat, anc = re.compile(pattern, re.I), re.compile(ancestor_pattern, re.I)
                for j, name in enumerate(self.names):
                    if pat.search(name) and any(anc.search(self.names[a]) for a in self.ancestors(j)):
                        drop.add(j)
        else:
            try:
                pats = [re.compile(p, re.I) for p in drop_patterns]
            except re.error as exc:
                raise ValueError(f"reduce: bad drop pattern: {exc}") from None
            for j, name in enumerate(self.names):
                if any(p.search(name) for p in pats):
                    drop.add(j)
        drop -= keep_idx
        if 0 in drop:
            raise ValueError(f"reduce: the patterns would drop the root joint {self.names[0]!r}")
        return self.subset([j for j in range(self.n_joints) if j not in drop])

    def default_reduction(self) -> tuple["Skeleton", list[int]]:
        """The dataset default: ``reduce()`` with ``DEFAULT_DROP_RULES``."""
        return self.reduce()

    # ----------------------------------------------------------------------------------------------------------
    # Feet and scale

    def _named_feet(self, per_side: int) -> dict[str, list[int]]:
        """Per side ('L', 'R'): ankle-like and toe-like joints found by name, best first."""
        found: dict[str, list[int]] = {}
        for side in ("L", "R"):
            ankles = [j for j, n in enumerate(self.names) if _side(n) == side and _ANKLE.search(n) and not _END.search(n)]
            toes = [j for j, n in enumerate(self.names) if _side(n) == side and _TOE.search(n) and not _END.search(n)]
            heels = [j for j, n in enumerate(self.names) if _side(n) == side and _HEEL.search(n)]
            toe_ends = [j for j, n in enumerate(self.names) if _side(n) == side and _TOE.search(n) and _END.search(n)]
            ankles = [j for j in ankles if j not in toes]  # "LeftFootToe" is a toe, not an ankle
            ankle = ankles[0] if ankles else (heels[0] if heels else None)
            toe = toes[0] if toes else (toe_ends[0] if toe_ends else None)
            picks = [x for x in ((ankle, toe) if per_side >= 2 else (toe if toe is not None else ankle,)) if x is not None]
            if picks:
                found[side] = picks
        return found

    def _low_leaves(self, tolerance: float = 0.15) -> list[int]:
        """Leaf joints within ``tolerance`` x (vertical extent) of the lowest joint of the rest pose."""
        pos = self.rest_positions()
        y = pos[:, 1]
        extent = float(y.max() - y.min())
        leaves = self.leaves()
        if extent <= 0:
            return leaves
        return [j for j in leaves if y[j] <= y.min() + tolerance * extent]

    def _is_multi_legged(self, named: dict[str, list[int]]) -> bool:
        """True when an upright rest pose shows more low limbs than the named feet (a quadruped rigged as a biped:
        its 'hands' stand on the ground)."""
        pos = self.rest_positions()
        y = pos[:, 1]
        extent = float(y.max() - y.min())
        heads = [j for j, n in enumerate(self.names) if _HEAD.search(n) and not _END.search(n)]
        feet = [f for picks in named.values() for f in picks]
        if extent <= 0 or not heads or not feet:
            return False
        if y[heads[0]] - max(y[f] for f in feet) < 0.4 * extent:
            return False  # rest pose not upright (e.g. Bandai's bones all along x): no evidence either way
        foot_tree = set(feet)
        for f in feet:
            foot_tree.update(self.descendants(f))
        others = [j for j in self._low_leaves() if j not in foot_tree]
        return len(others) > 0

    def detect_feet(self, names: Sequence[str] | None = None, per_side: int = 1) -> list[int]:
        """Joints that get foot-contact labels.

        ``names`` overrides detection (exact joint names, in the order given). Otherwise, for a biped found by
        name (foot/ankle/heel and toe/ball joints with a left/right marker such as ``Left``, ``_L``, ``L_``):
        ``per_side=1`` gives the toe/ball joint (``LeftToeBase``, ``Toes_L``; the ankle if there is none) for left
        then right -- the ball of the foot stays planted through heel-off, so a walk keeps a foot in contact
        nearly all the time, which the ankle does not; ``per_side=2`` gives ankle and toe per side
        ``[L ankle, L toe, R ankle, R toe]`` (GANimator-style).
        Anything else -- no named feet, or an upright rest pose whose other limbs also reach the ground (the
        elephant's front "hands") -- falls back to the leaf joints lying lowest in the rest pose (within 15% of
        its vertical extent), in joint order: the crab's six leg tips, the elephant's four toes/hands.
        """
        if names is not None:
            return self._resolve(list(names), "detect_feet")
        if per_side not in (1, 2):
            raise ValueError(f"detect_feet: per_side must be 1 or 2, got {per_side}")
        named = self._named_feet(per_side)
        if "L" in named and "R" in named and not self._is_multi_legged(named):
            return named["L"] + named["R"]
        return self._low_leaves()

    def height(self) -> float:
        """A characteristic body size in skeleton units, for scale-free thresholds and tolerances.

        For a named biped (see ``detect_feet``): the bone length from a foot's tip (deepest descendant, End Site
        included) to the head's tip through their lowest common ancestor -- independent of the rest pose, which is meaningless for rigs
        such as Bandai's. Otherwise the vertical extent of the rest pose (or its largest extent, or 1.0).
        """
        named = self._named_feet(1)
        heads = [j for j, n in enumerate(self.names) if _HEAD.search(n) and not _END.search(n)]
        lengths = self.bone_lengths()
        best = 0.0
        biped = "L" in named and "R" in named and not self._is_multi_legged(named)
        if biped and heads:
            head = heads[0]
            for picks in named.values():
                foot = picks[0]
                foot_chain = [foot] + self.ancestors(foot)
                head_chain = set([head] + self.ancestors(head))
                lca = next((x for x in foot_chain if x in head_chain), 0)
                total = 0.0
                for tip in (foot, head):
                    total += self._tip_length(tip, lengths)
                    x = tip
                    while x != lca:
                        total += lengths[x]
                        x = self.parents[x]
                best = max(best, total)
        if best > 0:
            return float(best)
        pts = [self.rest_positions()] + [
            (self.rest_positions()[j] + np.asarray(e))[None] for j, e in self.end_sites.items()
        ]
        pts = np.concatenate(pts, axis=0)
        ext = pts.max(0) - pts.min(0)
        if ext[1] > 1e-9:
            return float(ext[1])
        if ext.max() > 1e-9:
            return float(ext.max())
        return 1.0

    def _tip_length(self, j: int, lengths: np.ndarray) -> float:
        """Longest bone path from ``j`` down to a leaf, End Sites included."""
        best = float(np.linalg.norm(self.end_sites[j])) if j in self.end_sites else 0.0
        for c in self.children(j):
            best = max(best, float(lengths[c]) + self._tip_length(c, lengths))
        return best

    # ----------------------------------------------------------------------------------------------------------
    # Plain-data round trip (checkpoints, caches)

    def to_dict(self) -> dict[str, Any]:
        """Plain lists only, so it survives ``torch.save(weights_only=True)`` and JSON."""
        return {
            "names": list(self.names),
            "parents": list(self.parents),
            "offsets": self.offsets.tolist(),
            "end_sites": {int(k): np.asarray(v, dtype=np.float64).tolist() for k, v in self.end_sites.items()},
            "rotation_orders": list(self.rotation_orders) if self.rotation_orders is not None else None,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Skeleton":
        return cls(
            names=list(d["names"]),
            parents=list(d["parents"]),
            offsets=np.asarray(d["offsets"], dtype=np.float64),
            end_sites={int(k): np.asarray(v, dtype=np.float64) for k, v in d.get("end_sites", {}).items()},
            rotation_orders=d.get("rotation_orders"),
        )

    def same_as(self, other: "Skeleton", atol: float = 1e-6) -> bool:
        """Same names, parents and offsets (within ``atol``): the test for 'one dataset skeleton'."""
        return (
            self.names == other.names
            and self.parents == other.parents
            and self.offsets.shape == other.offsets.shape
            and bool(np.allclose(self.offsets, other.offsets, atol=atol))
        )
