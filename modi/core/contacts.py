"""Foot-contact labels from joint positions.

A foot joint is in contact when it is both slow and low: its speed is below ``velocity_factor x height`` per
second and it is within ``height_factor x height`` of the lowest point that foot reaches in the clip. Thresholds
scale with the skeleton's height (``Skeleton.height()``) and speeds are per second, so the same defaults work
for centimetre and metre rigs and for any frame rate. Velocity-only labelling (``height_factor=None``) is what
MoDi and GANimator use; the height test removes false contacts on a foot held still in the air.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from modi.core.body import Body

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


# ---------------------------------------------------------------------------------------------- what users see
PREVIEW_HEIGHT_FRACTION = 0.07   # x standing height above the floor
PREVIEW_SPEED_FRACTION = 0.3     # x standing height per second
PREVIEW_MIN_RUN_S = 0.1          # contact runs and gaps shorter than this are removed
PREVIEW_RULE = (f"a foot joint touches the ground while it is within {PREVIEW_HEIGHT_FRACTION:g} x the standing "
                f"height above the floor (the body's lowest point in the clip) and slower than "
                f"{PREVIEW_SPEED_FRACTION:g} standing heights per second; gaps, then contacts, shorter than "
                f"{PREVIEW_MIN_RUN_S:g} s are removed")


def _drop_short_runs(mask, value: bool, min_len: int):
    """Flip runs of ``value`` shorter than ``min_len`` frames (along axis 0) that have the other value on both
    sides (runs touching the clip's ends are kept: their true length is unknown)."""
    out = mask.copy()
    T = out.shape[0]
    for f in range(out.shape[1]):
        col = out[:, f]
        t = 0
        while t < T:
            if col[t] != value:
                t += 1
                continue
            s = t
            while t < T and col[t] == value:
                t += 1
            if s > 0 and t < T and t - s < min_len:
                col[s:t] = not value
    return out


def preview_contacts(positions, feet: Sequence[int], fps: float, parents: Sequence[int] | None = None,
                     names: Sequence[str] | None = None):
    """(T, J) bool contact labels that the GIF, the viewer page and the glTF export all show (:data:`PREVIEW_RULE`).

    ``positions`` (T, J, 3) numpy, Y up, any unit: the thresholds scale with :class:`modi.core.body.Body`'s standing
    height and are measured from the body's floor (a static ground root excluded), not from each joint's own
    lowest point, so a foot that never comes down is never in contact. Label once on the clip's own frames and
    resample the labels with the positions: every output then shows the same labels.
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"positions must be (T, J, 3), got {p.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    T, J = p.shape[:2]
    out = np.zeros((T, J), dtype=bool)
    feet = [int(f) for f in feet]
    if not feet or T == 0:
        return out
    body = Body.of(p, list(parents) if parents is not None else [-1] + [0] * (J - 1), names)
    h = body.standing_height
    speed = foot_speed(torch.from_numpy(p), feet, fps).numpy()                 # (T, F)
    low = p[:, feet, 1] - body.floor < PREVIEW_HEIGHT_FRACTION * h
    lab = low & (speed < PREVIEW_SPEED_FRACTION * h)
    k = max(1, int(round(PREVIEW_MIN_RUN_S * fps)))
    lab = _drop_short_runs(_drop_short_runs(lab, False, k), True, k)
    out[:, feet] = lab
    return out


_FOOT_WORDS = ("foot", "toe", "ankle", "heel")


def foot_joints_by_name(names: Sequence[str]) -> list[int]:
    """Joints whose names say foot/toe/ankle/heel (what contact highlighting marks when no list is given)."""
    return [j for j, n in enumerate(names) if any(w in n.lower() for w in _FOOT_WORDS)]


def feet_of(b) -> list[int]:
    """Foot joints of a clip (anything with ``skeleton()`` and ``names``): the skeleton's own detection when
    available, else by name."""
    sk = b.skeleton()
    if hasattr(sk, "detect_feet"):
        try:
            feet = list(sk.detect_feet(per_side=2))
        except (ValueError, KeyError):   # detection is a convenience for previews: fall back to names
            feet = []
        if feet:
            return feet
    return foot_joints_by_name(b.names)
