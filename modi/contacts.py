"""Foot-contact labels from joint positions.

A foot joint is in contact when it is both slow and low: its speed is below ``velocity_factor x height`` per
second and it is within ``height_factor x height`` of the lowest point that foot reaches in the clip. Thresholds
scale with the skeleton's height (``Skeleton.height()``) and speeds are per second, so the same defaults work
for centimetre and metre rigs and for any frame rate. Velocity-only labelling (``height_factor=None``) is what
MoDi and GANimator use; the height test removes false contacts on a foot held still in the air.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

DEFAULT_VELOCITY_FACTOR = 0.25  # x height per second (~0.44 m/s for a 1.75 m person)
DEFAULT_HEIGHT_FACTOR = 0.1  # x height above that foot's lowest point in the clip


def foot_speed(positions: Tensor, feet: Sequence[int], fps: float) -> Tensor:
    """Speed of each foot joint, (..., T, F), per second; central differences inside, one-sided at the ends."""
    if positions.ndim < 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be (..., T, J, 3), got {tuple(positions.shape)}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    p = positions[..., list(feet), :]
    T = p.shape[-3]
    if T < 2:
        return torch.zeros(p.shape[:-1], dtype=p.dtype, device=p.device)
    v = torch.empty_like(p)
    v[..., 1:-1, :, :] = (p[..., 2:, :, :] - p[..., :-2, :, :]) * 0.5
    v[..., :1, :, :] = p[..., 1:2, :, :] - p[..., :1, :, :]
    v[..., -1:, :, :] = p[..., -1:, :, :] - p[..., -2:-1, :, :]
    return v.norm(dim=-1) * fps


def foot_contacts(
    positions: Tensor,
    feet: Sequence[int],
    height: float,
    fps: float,
    velocity_factor: float = DEFAULT_VELOCITY_FACTOR,
    height_factor: float | None = DEFAULT_HEIGHT_FACTOR,
    up_axis: int = 1,
) -> Tensor:
    """Binary contact labels (..., T, F) (dtype of ``positions``) for the joints ``feet`` of global
    ``positions`` (..., T, J, 3)."""
    if height <= 0:
        raise ValueError(f"height must be positive, got {height}")
    feet = [int(f) for f in feet]
    J = positions.shape[-2] if positions.ndim >= 2 else 0
    for f in feet:
        if not 0 <= f < J:
            raise ValueError(f"foot joint {f} out of range for positions with {J} joints")
    if not feet:
        return positions.new_zeros((*positions.shape[:-2], 0))
    speed = foot_speed(positions, feet, fps)
    contact = speed < velocity_factor * height
    if height_factor is not None:
        y = positions[..., feet, up_axis]  # (..., T, F)
        floor = y.min(dim=-2, keepdim=True).values
        contact = contact & (y - floor < height_factor * height)
    return contact.to(positions.dtype)
