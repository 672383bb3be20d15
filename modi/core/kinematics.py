"""Reference forward kinematics in torch — the one place FK is defined (the ``fk`` kernel is checked
against :func:`forward_kinematics`).

Convention: joint 0's global position *is* ``root_positions`` (its offset is not added); for
``j > 0``: ``pos[j] = pos[p] + R_global[p] @ offsets[j]`` and ``R_global[j] = R_global[p] @ R_local[j]``.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from modi.core.rotations import euler_to_quat, quat_apply, quat_mul

__all__ = ["forward_kinematics", "bvh_positions", "bvh_global_quats", "bvh_global_quats_and_positions"]


def _check_parents(parents: list[int], n: int) -> list[int]:
    parents = [int(p) for p in parents]
    if len(parents) != n:
        raise ValueError(f"forward_kinematics: parents has {len(parents)} entries, local_quats has {n} joints")
    if n == 0:
        raise ValueError("forward_kinematics: no joints")
    if parents[0] != -1:
        raise ValueError("forward_kinematics: joint 0 must be the root (parent -1)")
    for j, p in enumerate(parents[1:], start=1):
        if not 0 <= p < j:
            raise ValueError(f"forward_kinematics: parents[{j}] = {p}; parents must precede children")
    return parents


def forward_kinematics(
    local_quats: Tensor, offsets: Tensor | np.ndarray, parents: list[int], root_positions: Tensor
) -> tuple[Tensor, Tensor]:
    """Global joint positions ``(..., J, 3)`` and global rotations ``(..., J, 4)``.

    ``local_quats (..., J, 4)`` unit (w,x,y,z) in the parent's frame; ``offsets (J, 3)`` or
    ``(..., J, 3)`` (per-frame translations, e.g. BVH position channels); ``root_positions (..., 3)``.
    Differentiable in all tensor inputs; loops over joints (J is small), vectorised over the rest.
    """
    if not isinstance(local_quats, Tensor) or local_quats.ndim < 2 or local_quats.shape[-1] != 4:
        shape = tuple(local_quats.shape) if isinstance(local_quats, Tensor) else type(local_quats).__name__
        raise ValueError(f"forward_kinematics: local_quats must be (..., J, 4), got {shape}")
    n = local_quats.shape[-2]
    parents = _check_parents(parents, n)
    offsets = torch.as_tensor(offsets, dtype=local_quats.dtype, device=local_quats.device)
    if offsets.ndim < 2 or offsets.shape[-2:] != (n, 3):
        raise ValueError(f"forward_kinematics: offsets must be (J={n}, 3) or (..., J, 3), got {tuple(offsets.shape)}")
    root_positions = torch.as_tensor(root_positions, dtype=local_quats.dtype, device=local_quats.device)
    if root_positions.shape[-1:] != (3,):
        raise ValueError(f"forward_kinematics: root_positions must be (..., 3), got {tuple(root_positions.shape)}")
    batch = torch.broadcast_shapes(local_quats.shape[:-2], offsets.shape[:-2], root_positions.shape[:-1])
    quats = local_quats.expand(batch + (n, 4))
    offs = offsets.expand(batch + (n, 3))
    gq: list[Tensor] = [quats[..., 0, :]]
    gp: list[Tensor] = [root_positions.expand(batch + (3,))]
    for j in range(1, n):
        p = parents[j]
        gp.append(gp[p] + quat_apply(gq[p], offs[..., j, :]))
        gq.append(quat_mul(gq[p], quats[..., j, :]))
    return torch.stack(gp, dim=-2), torch.stack(gq, dim=-2)


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
