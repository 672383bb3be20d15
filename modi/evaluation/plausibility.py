"""Physical plausibility of joint trajectories: foot skating, floating/penetration, jitter.

Everything is in the skeleton's own length unit (e.g. cm for Bandai-Namco, whatever the BVH uses) and in
seconds, so numbers are comparable between real and generated motion of the same skeleton. Heights are
measured along ``up_axis`` above a ground plane at ``ground`` (BVH convention: 0). Default thresholds are
fractions of the character's height, so they scale with the unit.
"""
from __future__ import annotations

import re
from typing import Any

import numpy as np
import torch

__all__ = ["plausibility_metrics", "planted_heights", "guess_feet", "aggregate"]

_FOOT = re.compile(r"(foot|toe|ankle|heel)", re.IGNORECASE)


def guess_feet(names: list[str]) -> list[int]:
    """Foot joints by name (foot/toe/ankle/heel). Raises when none match: guessing from geometry silently
    would make the skating number meaningless."""
    feet = [j for j, n in enumerate(names) if _FOOT.search(n)]
    if not feet:
        raise ValueError("no foot joints found by name (foot/toe/ankle/heel); pass foot joint indices explicitly")
    return feet


def _positions(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    p = np.asarray(x, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"positions: expected (frames, joints, 3), got shape {tuple(p.shape)}")
    if p.shape[0] < 4:
        raise ValueError(f"positions: need at least 4 frames for jerk, got {p.shape[0]}")
    if not np.isfinite(p).all():
        raise ValueError("positions: contains NaN or infinite values")
    return p


def plausibility_metrics(
    positions: Any,
    fps: float,
    feet: list[int],
    up_axis: int = 1,
    ground: float = 0.0,
    body_height: float | None = None,
    contact_height: float | None = None,
    contact_speed: float | None = None,
    foot_heights: list[float] | None = None,
) -> dict[str, float]:
    """Plausibility figures of one motion given global joint positions ``(T, J, 3)``.

    * ``foot_skating``: mean horizontal speed (units/s) of foot joints over the frames where they are in
      contact, contact meaning the joint is less than ``contact_height`` (default 2.5% of body height) above
      its planted height. A foot joint sits above the floor by the foot's thickness when planted (Bandai's
      ankles ~11 cm, toes ~4 cm), so ``foot_heights`` gives each foot's planted height above the ground —
      calibrate it on real data (see ``planted_heights``); by default each clip's own 5th percentile is used;
      ``skating_ratio``: fraction of those contact frames sliding faster than ``contact_speed``
      (default 0.25 body heights/s, i.e. roughly 45 cm/s for an adult — clearly sliding).
    * ``floating``: mean over frames of the lowest foot's clearance (height above the ground minus its
      planted height from ``foot_heights``, or minus 0 when not given), 0 when touching;
      ``penetration``: mean depth of that foot below its planted height; ``max_penetration``.
    * ``jitter``: mean norm of the third time derivative of joint positions (units/s^3);
      ``acceleration``: mean norm of the second derivative (units/s^2), to tell jitter from fast motion.
    """
    p = _positions(positions)
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if up_axis not in (0, 1, 2):
        raise ValueError(f"up_axis must be 0, 1 or 2, got {up_axis}")
    J = p.shape[1]
    if not feet or any(not 0 <= f < J for f in feet):
        raise ValueError(f"feet: need joint indices in [0, {J}), got {feet}")
    h = p[..., up_axis] - ground
    if body_height is None:
        body_height = float(np.median(h.max(axis=1) - h.min(axis=1)))
    if body_height <= 0:
        raise ValueError("body height is zero: all joints at the same height")
    c_h = 0.025 * body_height if contact_height is None else contact_height
    c_v = 0.25 * body_height if contact_speed is None else contact_speed
    horiz = [a for a in range(3) if a != up_axis]

    fp = p[:, feet]  # (T, F, 3)
    v = np.diff(fp[..., horiz], axis=0) * fps  # (T-1, F, 2)
    speed = np.linalg.norm(v, axis=-1)
    fh = fp[..., up_axis] - ground
    if foot_heights is None:
        planted = np.zeros(len(feet))
        base = np.percentile(fh, 5, axis=0)  # contact relative to the clip's own low point
    else:
        planted = base = np.asarray(foot_heights, dtype=np.float64)
        if base.shape != (len(feet),):
            raise ValueError(f"foot_heights: need one height per foot joint ({len(feet)}), got {base.shape}")
    clearance = (fh - planted).min(axis=1)  # (T,) the lowest foot relative to where it stands when planted
    fh = fh - base
    contact = (fh[1:] < c_h) & (fh[:-1] < c_h)
    n_contact = int(contact.sum())
    skating = float(speed[contact].mean()) if n_contact else 0.0
    ratio = float((speed[contact] > c_v).mean()) if n_contact else 0.0

    acc = np.diff(p, n=2, axis=0) * fps**2
    jerk = np.diff(p, n=3, axis=0) * fps**3
    return {
        "foot_skating": skating,
        "skating_ratio": ratio,
        "contact_fraction": float(n_contact / contact.size),
        "floating": float(np.clip(clearance, 0, None).mean()),
        "penetration": float(np.clip(-clearance, 0, None).mean()),
        "max_penetration": float(np.clip(-clearance, 0, None).max()),
        "jitter": float(np.linalg.norm(jerk, axis=-1).mean()),
        "acceleration": float(np.linalg.norm(acc, axis=-1).mean()),
        "body_height": float(body_height),
    }


def planted_heights(positions: list[Any], feet: list[int], up_axis: int = 1, ground: float = 0.0) -> list[float]:
    """Each foot joint's planted height above the ground: its 5th height percentile over a set of (real) clips."""
    hs = np.concatenate([_positions(p)[:, feet, up_axis] - ground for p in positions], axis=0)
    return np.percentile(hs, 5, axis=0).tolist()


def aggregate(per_motion: list[dict[str, float]]) -> dict[str, float]:
    """Mean of each figure over motions (frame-weighting is not attempted: clips count equally)."""
    if not per_motion:
        raise ValueError("no motions to aggregate")
    return {k: float(np.mean([m[k] for m in per_motion])) for k in per_motion[0]}
