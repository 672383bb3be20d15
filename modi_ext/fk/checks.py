"""The fk op's argument checks: every argument validated on the host, errors naming the argument.

``check_args`` runs before any path (kernel or torch form) sees a call of ``modi_ext.fk.ops.fk``; the
``ForwardKinematics`` layer (``modi_ext.layers``) checks its tensors with ``check_tensors`` and its skeleton once,
at construction, with ``check_parents``.  The C++ op checks its own arguments again.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["check_args", "check_parents", "check_tensors"]


def check_args(local_quats, offsets, parents, root_positions) -> tuple[int, ...]:
    """Validate every argument of ``fk``; returns the parent list as a tuple of ints."""
    check_tensors(local_quats, offsets, root_positions)
    return check_parents(parents, local_quats.shape[-2])


def check_parents(parents: Sequence[int] | torch.Tensor, n_joints: int | None = None) -> tuple[int, ...]:
    """Validate a parent list (root first, ``0 <= parents[j] < j``) and return it as a tuple of ints."""
    if isinstance(parents, torch.Tensor):
        if parents.dim() != 1 or parents.dtype.is_floating_point or parents.dtype.is_complex:
            raise ValueError(f"fk: parents must be a 1-D integer list or tensor, got {parents.dtype} {tuple(parents.shape)}")
        parents = parents.tolist()
    try:
        par = tuple(int(p) for p in parents)
    except (TypeError, ValueError):
        raise ValueError(f"fk: parents must be a sequence of ints, got {parents!r}") from None
    if any(int(p) != p for p in parents):
        raise ValueError("fk: parents must be integers")
    if not par:
        raise ValueError("fk: parents is empty (need at least the root joint)")
    if n_joints is not None and len(par) != n_joints:
        raise ValueError(f"fk: parents has {len(par)} entries but local_quats has {n_joints} joints (dim -2)")
    if par[0] != -1:
        raise ValueError(f"fk: parents[0] must be -1 (joint 0 is the root), got {par[0]}")
    for j in range(1, len(par)):
        if not 0 <= par[j] < j:
            raise ValueError(
                f"fk: parents[{j}] = {par[j]} is out of range; parents must be topologically sorted (0 <= parents[j] < j)"
            )
    return par


def check_tensors(local_quats: torch.Tensor, offsets: torch.Tensor, root_positions: torch.Tensor) -> None:
    for name, t in (("local_quats", local_quats), ("offsets", offsets), ("root_positions", root_positions)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"fk: {name} must be a torch.Tensor, got {type(t).__name__}")
    if local_quats.dim() < 2 or local_quats.shape[-1] != 4:
        raise ValueError(f"fk: local_quats must have shape (..., J, 4), got {tuple(local_quats.shape)}")
    allowed = (torch.float32, torch.float64) + ((torch.float16, torch.bfloat16) if local_quats.is_cuda else ())
    if local_quats.dtype not in allowed:
        raise ValueError(f"fk: local_quats must be float32 or float64 (or float16/bfloat16 on CUDA), got "
                         f"{local_quats.dtype} on {local_quats.device}")
    if local_quats.numel() == 0:
        raise ValueError(f"fk: local_quats is empty (shape {tuple(local_quats.shape)}): empty batch or zero frames")
    J = local_quats.shape[-2]
    for name, t in (("offsets", offsets), ("root_positions", root_positions)):
        if t.dtype != local_quats.dtype:
            raise ValueError(f"fk: {name} has dtype {t.dtype}, expected {local_quats.dtype} (same as local_quats)")
        if t.device != local_quats.device:
            raise ValueError(f"fk: {name} is on {t.device} but local_quats is on {local_quats.device}")
    if tuple(offsets.shape) != (J, 3):
        raise ValueError(f"fk: offsets must have shape (J, 3) = ({J}, 3), got {tuple(offsets.shape)}")
    if tuple(root_positions.shape) != tuple(local_quats.shape[:-2]) + (3,):
        raise ValueError(
            f"fk: root_positions must have shape {tuple(local_quats.shape[:-2]) + (3,)} (local_quats.shape[:-2] + (3,)), "
            f"got {tuple(root_positions.shape)}"
        )
    for name, t in (("local_quats", local_quats), ("offsets", offsets), ("root_positions", root_positions)):
        if not t.is_contiguous():
            raise ValueError(f"fk: {name} must be contiguous (call .contiguous() first)")
