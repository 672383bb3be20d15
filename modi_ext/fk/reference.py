"""The one forward kinematics and quaternion product in Python: what ``modi`` and the tests use.

There is no other FK in the repository's Python.  ``modi.core.kinematics.forward_kinematics`` and
``modi.core.rotations``'s ``quat_mul`` / ``quat_apply`` are these functions (modi imports them: modi_ext is the
lower layer and never imports modi); the C++ kernel (``torch.ops.modi_ext.fk``, ``modi_ext.fk.ops``) is tested against ``fk_reference`` and falls
back to it where a device has no kernel.

Conventions: quaternions are ``(w, x, y, z)``, unit, in the parent's frame, and every function broadcasts over
leading dimensions.  Joint 0's global position *is* ``root_positions`` (its offset is not added); for ``j > 0`` with
``p = parents[j]``: ``Q[j] = Q[p] * q[j]`` and ``P[j] = P[p] + rotate(Q[p], offsets[j])``, where
``rotate(Q, v) = v + 2w (u x v) + 2 u x (u x v)`` for ``Q = (w, u)`` (the kernel evaluates the same expression, so
the two agree for non-unit input too; nothing is normalised).

* ``fk_reference``: the loop itself, no argument checks (the fk op checks first); offsets ``(J, 3)`` or
  ``(..., J, 3)``, ``root_positions`` with the batch shape of ``local_quats``.
* ``forward_kinematics``: the same loop for modi's callers: checks with messages naming the argument, offsets and
  roots converted to the quaternions' dtype and device (a numpy array is fine), every batch shape broadcast
  (per-frame offsets such as BVH position channels), and it always returns ``(positions, rotations)``.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

if TYPE_CHECKING:  # numpy is optional for modi_ext: only named in a signature
    import numpy as np

__all__ = ["quat_mul", "quat_apply", "fk_reference", "forward_kinematics"]


def _check_last(x: Tensor, n: int, name: str, what: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"{name}: expected {what} with last dimension {n}, got shape {tuple(x.shape)}")


def _hamilton(a: Tensor, b: Tensor) -> Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def _rotate(q: Tensor, v: Tensor) -> Tensor:
    """``rotate(q, v)`` for ``v`` of ``q``'s dtype whose batch shape expands to ``q``'s."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v.expand_as(u))
    return v + w * t + torch.linalg.cross(u, t)


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``); broadcasts."""
    _check_last(a, 4, "quat_mul(a)", "quaternions")
    _check_last(b, 4, "quat_mul(b)", "quaternions")
    return _hamilton(a, b)


def quat_apply(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``; broadcasts (dtypes promote)."""
    _check_last(q, 4, "quat_apply(q)", "quaternions")
    _check_last(v, 3, "quat_apply(v)", "vectors")
    if q.dtype != v.dtype:
        dtype = torch.promote_types(q.dtype, v.dtype)
        q, v = q.to(dtype), v.to(dtype)
    batch = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    return _rotate(q.expand(batch + (4,)), v.expand(batch + (3,)))


def fk_reference(
    local_quats: Tensor,
    offsets: Tensor,
    parents: Sequence[int],
    root_positions: Tensor,
    return_rotations: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Global joint positions ``(..., J, 3)`` [and global rotations ``(..., J, 4)``]: one Python step per joint.

    local_quats (..., J, 4), offsets (J, 3) or (..., J, 3), root_positions (..., 3) with local_quats' batch shape;
    no checks.  Differentiable through plain torch ops, to any order.
    """
    J = local_quats.shape[-2]
    rots: list[Tensor] = [local_quats[..., 0, :]]
    pos: list[Tensor] = [root_positions]
    for j in range(1, J):
        p = parents[j]
        rots.append(_hamilton(rots[p], local_quats[..., j, :]))
        pos.append(pos[p] + _rotate(rots[p], offsets[..., j, :]))
    positions = torch.stack(pos, dim=-2)
    if return_rotations:
        return positions, torch.stack(rots, dim=-2)
    return positions


def _check_parents(parents: Sequence[int], n: int) -> list[int]:
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
    local_quats: Tensor, offsets: Tensor | np.ndarray, parents: Sequence[int], root_positions: Tensor
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
    return fk_reference(local_quats.expand(batch + (n, 4)), offsets.expand(batch + (n, 3)), parents,
                        root_positions.expand(batch + (3,)), return_rotations=True)
