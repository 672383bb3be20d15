"""Forward kinematics of BVH files. The FK itself is :func:`modi_ext.fk.reference.forward_kinematics`, the one
Python FK (modi and the ``fk`` kernel's tests use it), re-exported here.

Convention: joint 0's global position *is* ``root_positions`` (its offset is not added); for
``j > 0``: ``pos[j] = pos[p] + R_global[p] @ offsets[j]`` and ``R_global[j] = R_global[p] @ R_local[j]``.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from modi.core.rotations import euler_to_quat
from modi_ext.fk.reference import forward_kinematics

__all__ = ["forward_kinematics", "bvh_positions", "bvh_global_quats", "bvh_global_quats_and_positions"]


def bvh_global_quats_and_positions(bvh, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """(positions (F,J,3), global quats (F,J,4)) of a :class:`modi.io.bvh.Bvh`, honouring every position channel."""
    euler = torch.from_numpy(bvh.euler_degrees()).to(dtype)  # (F, J, 3) each joint in its own order
    orders = bvh.rotation_orders
    quats = torch.empty(euler.shape[:-1] + (4,), dtype=dtype)
    for order in set(orders):
        idx = [j for j, o in enumerate(orders) if o == order]
        quats[:, idx] = euler_to_quat(euler[:, idx], order)
    trans = torch.from_numpy(bvh.local_translations()).to(dtype)  # (F, J, 3)
    pos, gq = forward_kinematics(quats, trans, bvh.parents, trans[:, 0])
    return pos, gq


def bvh_positions(bvh) -> np.ndarray:
    """``(F, J, 3)`` float64 global joint positions exactly as the file means them (file units, file joint order):
    the root at its position channels (or OFFSET), every joint translated by its own position channels
    where it has them, else by its OFFSET."""
    pos, _ = bvh_global_quats_and_positions(bvh)
    return pos.numpy()


def bvh_global_quats(bvh) -> np.ndarray:
    """``(F, J, 4)`` global rotations of every joint of a BVH."""
    _, gq = bvh_global_quats_and_positions(bvh)
    return gq.numpy()
