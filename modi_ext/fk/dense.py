"""FK's dense form: the torch loop of ``modi_ext.fk.reference`` (one quaternion product per joint, vectorised over
the batch).  FK has no faster torch form, so its dense path and its oracle are the same loop; this module is where
the ops find it, as for the skeletal family (``MODI_EXT_IMPL=dense``, and the path where a device has no kernel).
"""
from __future__ import annotations

from modi_ext.fk.reference import fk_reference

__all__ = ["fk"]


def fk(local_quats, offsets, parents, root_positions, return_rotations: bool = False):
    """``fk_reference``: the arguments and semantics of the fk op, after its checks."""
    return fk_reference(local_quats, offsets, parents, root_positions, return_rotations)
