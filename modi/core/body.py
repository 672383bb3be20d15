"""One notion of a body for every preview (GIF, viewer page) and export (glTF).

Files describe more than a body: Bandai clips hang the skeleton under a static ``joint_Root`` on the floor (its
"bone" to the hips is the walk's translation, not a limb), Mixamo rigs carry 30 finger joints, End Sites mark the
tips of leaves. Outputs that each decided on their own what to draw, how tall the figure is and which side a limb
is on would disagree, so :class:`Body` decides once, from joint names and positions:

* ``ground`` -- a root that is not part of the body: a static root whose distance to one of its children changes
  by more than 10 % of the figure's size over the clip (the child is translated, not attached), or a root that
  stays on the floor with a single child held above it (Bandai clips that stand still or move the root along). It is not drawn,
  not skinned, and cameras follow ``centre`` (its child) instead.
* ``sides`` -- 0 centre, 1 left, 2 right, by name (:func:`side_of`).
* ``small`` -- finger joints (drawn small: a hand is not 15 full-size dots).
* ``standing_height`` -- the largest head-top height above the floor over the clip, the number an animator would
  measure (``modi export positions`` gives the same), not a chain length.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["Body", "side_of", "is_finger", "metres_scale", "SIDE_NAMES", "UnitGuess", "guess_unit", "unit_name", "UNIT_SCALES",
           "UNITS_MM"]

SIDE_NAMES = ("centre", "left", "right")
_FINGER = re.compile(r"thumb|index|middle|ring|pinky|pinkie|little|finger", re.I)
_HEAD = re.compile(r"head", re.I)
_TOKENS = re.compile(r"[_.\s\-]+")


def side_of(name: str) -> int:
    """0 centre, 1 left, 2 right. Schemes: ``LeftArm``/``left_arm``, ``L_Knee``, ``Leg_L_01``, ``Hand.L``,
    ``Bip01 L Thigh``/``Bip01_L_Thigh``, ``l_hip``, ``knee_l``, ``lHip``/``LHipJoint``, ``ThighL``; a namespace
    (``mixamorig:``) is ignored."""
    base = name.rsplit(":", 1)[-1]
    low = base.lower()
    if "left" in low:
        return 1
    if "right" in low:
        return 2
    tokens = [t for t in _TOKENS.split(base) if t]
    if any(t in ("L", "l") for t in tokens):
        return 1
    if any(t in ("R", "r") for t in tokens):
        return 2
    head = tokens[0] if tokens else ""
    if len(head) > 1 and head[0] in "Ll" and head[1].isupper():     # LHipJoint, lHip, LThumb
        return 1
    if len(head) > 1 and head[0] in "Rr" and head[1].isupper():
        return 2
    tail = tokens[-1] if tokens else ""
    if len(tail) > 2 and tail[-1] == "L" and tail[-2].islower():    # ThighL
        return 1
    if len(tail) > 2 and tail[-1] == "R" and tail[-2].islower():
        return 2
    return 0


def is_finger(name: str) -> bool:
    return bool(_FINGER.search(name.rsplit(":", 1)[-1]))


# ---------------------------------------------------------------------------------------------- units


@dataclass(frozen=True)
class UnitGuess:
    """What the file's lengths were taken to be: ``scale`` converts them to metres."""

    scale: float
    unit: str          # "metres", "centimetres", "inches", "millimetres" or "given"
    height: float      # body size in file units (``Skeleton.height``, a chain length: what the guess uses)
    standing: float | None = None  # standing height in file units (:class:`modi.core.body.Body`), what is printed

    def describe(self) -> str:
        shown = self.height if self.standing is None else self.standing
        what = "body size" if self.standing is None else "standing height"
        if self.unit == "given":
            return f"lengths x {self.scale:g} to metres (--scale given; {what} {shown * self.scale:.3g} m)"
        return (f"body size {self.height:.4g} file units looks like {self.unit}: lengths x {self.scale:g} to metres "
                f"({what} {shown * self.scale:.3g} m; override with --scale)")


_UNITS = (("metres", 1.0), ("inches", 0.0254), ("centimetres", 0.01), ("millimetres", 0.001))
UNIT_SCALES = dict(_UNITS)  # metres per unit, by the long name
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "dm": 100.0}  # millimetres per unit, by the short name
_UNIT_ALIASES = {"m": "metres", "meters": "metres", "meter": "metres", "metre": "metres", "cm": "centimetres",
                 "centimeters": "centimetres", "mm": "millimetres", "millimeters": "millimetres", "in": "inches",
                 "inch": "inches"}


def unit_name(unit: str) -> str:
    """The long name of a length unit (``"m"`` -> ``"metres"``; also cm, mm, in and the US spellings);
    ``ValueError`` for anything else."""
    key = str(unit).strip().lower()
    key = _UNIT_ALIASES.get(key, key)
    if key not in UNIT_SCALES:
        raise ValueError(f"unknown length unit {unit!r}; use one of m, cm, mm, in (or metres, centimetres, "
                         "millimetres, inches)")
    return key


def guess_unit(height: float) -> UnitGuess:
    """The unit that makes the body closest to 1.7 m (on a log scale) among m, in, cm and mm.

    Boundaries in file units: < 10.7 metres, < 107 inches, < 537 centimetres, else millimetres. A crab of 0.45 and an
    elephant of 2 stay metres; a Mixamo or Bandai human of 150-230 is centimetres. It is a guess, so it is printed.
    """
    h = float(height) if math.isfinite(height) and height > 0 else 1.0
    unit, scale = min(_UNITS, key=lambda u: abs(math.log(h * u[1] / 1.7)))
    return UnitGuess(scale, unit, h)


def metres_scale(height: float) -> float:
    """File units to metres for a body of ``height`` file units: :func:`guess_unit`'s guess (the unit among m, in, cm
    and mm that makes it closest to 1.7 m), the one every preview and export uses."""
    return guess_unit(height).scale


def _children(parents: Sequence[int]) -> list[list[int]]:
    out: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            out[p].append(j)
    return out


@dataclass
class Body:
    """What of a skeleton is the body, for one clip of global positions (T, J, 3), Y up."""

    names: list[str]
    parents: list[int]
    ground: list[int]          # joints that are not body (a static floor root)
    centre: int                # the joint cameras follow (the root, or the ground root's child)
    sides: list[int]
    small: list[bool]
    floor: float               # lowest body point over the clip (file units)
    standing_height: float     # largest head-top height above ``floor`` (file units)

    @classmethod
    def of(cls, positions, parents: Sequence[int], names: Sequence[str] | None = None) -> "Body":
        p = np.asarray(positions, dtype=np.float64)
        if p.ndim == 2:
            p = p[None]
        if p.ndim != 3 or p.shape[-1] != 3 or p.shape[1] != len(parents):
            raise ValueError(f"positions must be (T, {len(parents)}, 3), got {p.shape}")
        parents = [int(q) for q in parents]
        names = list(names) if names is not None else [f"joint_{j}" for j in range(len(parents))]
        kids = _children(parents)
        size = float(max(np.median(np.ptp(p, axis=1).max(axis=-1)), 1e-9))
        ground: list[int] = []
        centre = next((j for j, q in enumerate(parents) if q < 0), 0)
        root = centre
        if kids[root]:
            root_still = float(np.ptp(p[:, root], axis=0).max()) <= 0.01 * size
            loose = [c for c in kids[root]
                     if np.ptp(np.linalg.norm(p[:, c] - p[:, root], axis=-1)) > 0.1 * size]
            others = [j for j in range(len(parents)) if j != root]
            on_floor = bool(others) and float(p[:, root, 1].max()) <= float(p[:, others, 1].min()) + 0.05 * size
            raised = [c for c in kids[root] if float((p[:, c, 1] - p[:, root, 1]).mean()) > 0.25 * size]
            if not (root_still and loose) and on_floor and len(kids[root]) == 1 and raised:
                loose, root_still = raised, True  # a floor root under a raised hips is a ground root all the same
            if root_still and loose:
                ground = [root]
                centre = loose[0]
        body = [j for j in range(len(parents)) if j not in ground]
        y = p[:, body, 1]
        floor = float(y.min())
        heads = [j for j in body if _HEAD.search(names[j].rsplit(":", 1)[-1])]
        if heads:
            tip = set(heads)
            for h in heads:  # the head's own descendants (HeadTop_End), not the whole tree below a "head" name
                stack = list(kids[h])
                while stack:
                    c = stack.pop()
                    tip.add(c)
                    stack.extend(kids[c])
            top = float(p[:, sorted(tip), 1].max())
        else:
            top = float(y.max())
        height = top - floor
        if not height > 0:
            height = size
        return cls(names, parents, ground, centre, [side_of(n) for n in names], [is_finger(n) for n in names],
                   floor, float(height))

    def bones(self) -> list[int]:
        """Joints whose bone to their parent is drawn/skinned (not the root, not from a ground root)."""
        g = set(self.ground)
        return [j for j, q in enumerate(self.parents) if q >= 0 and q not in g and j not in g]

    def body_joints(self) -> list[int]:
        g = set(self.ground)
        return [j for j in range(len(self.parents)) if j not in g]
