"""GANimator's joint reduction, in one place below both the trainer and the evaluation.

``modi.models.ganimator.data`` trains on the reduced skeleton and ``modi.evaluation.single`` compares a source with
generated clips on the same joint set; both import this module downwards instead of evaluation reaching up into
the GANimator package.
"""
from __future__ import annotations

import re
from typing import Sequence as Seq

from modi.errors import UserError
from modi.core.skeleton import Skeleton, strip_namespace

_FINGER = re.compile(r"(thumb|index|middle|ring|pinky|pinkie|finger|handtip|carpal)", re.IGNORECASE)
_HAND = re.compile(r"(hand|wrist)", re.IGNORECASE)
_HEADTOP = re.compile(r"(headtop|head_top|headend|head_end|head_tip)", re.IGNORECASE)


def reduce_joints(skeleton: Skeleton, keep: Seq[str] | None = None) -> list[int]:
    """Indices of the joints to keep (sorted, root first).

    With ``keep`` (names, with or without namespace) exactly those joints are kept. Otherwise finger joints below
    a hand/wrist and head-top end joints are dropped with everything below them — detail that a single short clip
    cannot teach and that triples the entity count of a Mixamo rig.
    """
    names = [strip_namespace(n) for n in skeleton.names]
    if keep is not None:
        wanted = {strip_namespace(k) for k in keep}
        missing = wanted - set(names)
        if missing:
            raise UserError(f"keep_joints: no joint named {', '.join(sorted(missing))} in the skeleton")
        kept = sorted(names.index(k) for k in wanted)
        if 0 not in kept:
            raise UserError("keep_joints must include the root joint " + names[0])
        return kept
    drop = [False] * skeleton.n_joints
    for j in range(1, skeleton.n_joints):
        p = skeleton.parents[j]
        if drop[p]:
            drop[j] = True
            continue
        under_hand = False
        a = p
        while a >= 0:
            if _HAND.search(names[a]):
                under_hand = True
                break
            a = skeleton.parents[a]
        if (under_hand and _FINGER.search(names[j])) or _HEADTOP.search(names[j]):
            drop[j] = True
    return [j for j in range(skeleton.n_joints) if not drop[j]]
