"""Foot-contact cleanup by inverse kinematics (MoDi and GANimator post-processing).

Generated motion predicts contact labels but its feet still slide. While a foot's label is on, the foot is
pinned at the mean of its positions over that contact run (a toe and its ankle pinned together are made
consistent with their bone length); for ``blend_frames`` frames on either side its target eases from the
original path to the pin, so the fix does not pop. The targets are met by prioritised damped least-squares IK
on the leg chains (the joints from each foot up to where the leg branches off the body), per frame for all feet
together with the geometric Jacobian, iterated to convergence: pinned feet are the primary task and end within
``tol`` (default ``1e-5 x skeleton height``, ~0.02 mm on a 1.7 m human) of their pins; blend targets are met in
the remaining freedom. A stiff root translation lets the body dip where pinned legs cannot reach; that shift
is then smoothed over time and the legs re-solved, so the root does not jerk. Joints off the leg chains keep
their rotations bit for bit, and frames with no active target keep theirs. Any skeleton and unit.
"""
from __future__ import annotations

from collections.abc import Sequence
from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor

from modi.core.rotations import axis_angle_to_quat, quat_apply, quat_conjugate, quat_mul, quat_normalize
from modi.core.skeleton import Skeleton
from modi_ext.fk import fk

__all__ = ["fix_foot_contact", "leg_chain", "contact_targets"]


def leg_chain(parents: Sequence[int], foot: int) -> list[int]:
    """Joints whose rotation moves ``foot`` within its limb: ancestors from the foot's parent upward, stopping
    at (and including) the joint that hangs off a branching joint or the root. Empty if the foot's parent is
    the root."""
    n_children = [0] * len(parents)
    for p in parents[1:]:
        n_children[p] += 1
    chain: list[int] = []
    k = parents[foot]
    while k > 0:
        chain.append(k)
        p = parents[k]
        if p <= 0 or n_children[p] > 1:
            break
        k = p
    return chain


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each run of True."""
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    d = np.diff(padded)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def contact_targets(
    positions: Tensor,
    contacts: np.ndarray,
    blend_frames: int,
    rigid_pairs: Sequence[tuple[int, int, float]] = (),
) -> tuple[Tensor, Tensor]:
    """Per-frame targets (T, F, 3) and weights (T, F) in [0, 1] for foot positions (T, F, 3).

    Weight 1 inside a contact run (target = the run's pin); outside, a smoothstep that falls to 0 over
    ``blend_frames`` frames, blending the target from the nearest run's pin back to the original path.
    A run's pin is its mean position, except that for ``rigid_pairs`` ``(a, d, length)`` (foot ``d`` is the
    child of foot ``a`` at a fixed bone ``length``, e.g. ankle and toe) overlapping runs must agree: taken in
    order of their start, each run's pin is moved onto the sphere of radius ``length`` around the pin of the
    partner run it overlaps, so both can be met exactly.
    """
    T, F = contacts.shape
    runs = [_runs(contacts[:, f]) for f in range(F)]
    pins = [[positions[s:e, f].mean(dim=0) for s, e in runs[f]] for f in range(F)]
    for a, d, length in rigid_pairs:
        events = sorted([(s, e, a, i) for i, (s, e) in enumerate(runs[a])] + [(s, e, d, i) for i, (s, e) in enumerate(runs[d])])
        for n, (s, e, f, i) in enumerate(events):
            # The one earlier-started run of the partner that overlaps this run (runs of one foot are disjoint).
            prev = [(f2, i2) for s2, e2, f2, i2 in events[:n] if f2 != f and e2 > s]
            if prev:
                anchor = pins[prev[-1][0]][prev[-1][1]]
                v = pins[f][i] - anchor
                pins[f][i] = anchor + length * v / v.norm().clamp_min(1e-12)
    targets = positions.clone()
    weight = torch.zeros(T, F, dtype=positions.dtype)
    t = np.arange(T)
    for f in range(F):
        if not runs[f]:
            continue
        dist = np.full(T, np.inf)
        nearest = np.zeros(T, dtype=np.int64)
        for i, (s, e) in enumerate(runs[f]):
            dd = np.where(t < s, s - t, np.where(t >= e, t - e + 1, 0)).astype(np.float64)
            closer = dd < dist
            dist[closer], nearest[closer] = dd[closer], i
        x = np.clip(1.0 - dist / (blend_frames + 1), 0.0, 1.0)
        alpha = torch.from_numpy(x * x * (3.0 - 2.0 * x)).to(positions.dtype)
        pin = torch.stack(pins[f])[torch.from_numpy(nearest)]
        weight[:, f] = alpha
        targets[:, f] = alpha[:, None] * pin + (1.0 - alpha[:, None]) * positions[:, f]
    return targets, weight


def _skew_neg(d: Tensor) -> Tensor:
    """-[d]x (..., 3, 3): the matrix with -[d]x w = w x d, the motion of a point at offset d under rotation w."""
    x, y, z = d.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((torch.stack((o, z, -y), -1), torch.stack((-z, o, x), -1), torch.stack((y, -x, o), -1)), -2)


@contextmanager
def _one_thread():
    """The solver is thousands of tiny batched ops; intra-op threads only add overhead (and stall badly on a busy
    machine), so it runs single-threaded and restores the caller's setting afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def fix_foot_contact(
    motion_rotations: Tensor,
    root_positions: Tensor,
    skeleton: Skeleton,
    foot_joints: list[int],
    contacts: Tensor | np.ndarray,
    *,
    blend_frames: int = 5,
    tol: float | None = None,
    max_iters: int = 60,
    adjust_root: bool = True,
) -> tuple[Tensor, Tensor]:
    """Pin each foot while its contact label is on; returns new ``(rotations (T,J,4), root_positions (T,3))``.

    motion_rotations: (T, J, 4) local unit quaternions (w, x, y, z); root_positions: (T, 3); foot_joints: the
    F joints the labels refer to (not the root); contacts: (T, F) bool (or 0/1). ``blend_frames``: frames over
    which a pin eases in and out; ``tol``: convergence threshold in skeleton units (default
    ``1e-5 * skeleton.height()``); ``adjust_root=False`` keeps the root path bit-identical (a pin out of the leg's
    reach is then only approached). Output has the input's dtype and device; the inputs are not modified.
    """
    if not isinstance(motion_rotations, Tensor) or motion_rotations.ndim != 3 or motion_rotations.shape[-1] != 4:
        raise ValueError(f"fix_foot_contact: motion_rotations must be a (T, J, 4) tensor, got {_shape(motion_rotations)}")
    T, J = motion_rotations.shape[:2]
    if J != skeleton.n_joints:
        raise ValueError(f"fix_foot_contact: motion_rotations has {J} joints, the skeleton has {skeleton.n_joints}")
    if T == 0:
        raise ValueError("fix_foot_contact: motion has zero frames")
    if not isinstance(root_positions, Tensor) or tuple(root_positions.shape) != (T, 3):
        raise ValueError(f"fix_foot_contact: root_positions must be a ({T}, 3) tensor, got {_shape(root_positions)}")
    feet = [int(f) for f in foot_joints]
    for f in feet:
        if not 0 < f < J:
            raise ValueError(f"fix_foot_contact: foot joint {f} out of range 1..{J - 1} (the root cannot be pinned)")
    if len(set(feet)) != len(feet):
        raise ValueError(f"fix_foot_contact: foot_joints has duplicates: {feet}")
    c = contacts.detach().cpu().numpy() if isinstance(contacts, Tensor) else np.asarray(contacts)
    if c.shape != (T, len(feet)):
        raise ValueError(f"fix_foot_contact: contacts must have shape (T, F) = ({T}, {len(feet)}), got {c.shape}")
    if c.dtype != np.bool_:
        if not np.isin(c, (0, 1)).all():
            raise ValueError("fix_foot_contact: contacts must be boolean (or 0/1)")
        c = c.astype(bool)
    if blend_frames < 0:
        raise ValueError(f"fix_foot_contact: blend_frames must be >= 0, got {blend_frames}")
    if not feet or not c.any():
        return motion_rotations.detach().clone(), root_positions.detach().clone()
    with _one_thread():
        rot, root = _fix(motion_rotations, root_positions, skeleton, feet, c, blend_frames, tol, max_iters, adjust_root)
    return rot.to(motion_rotations.device, motion_rotations.dtype), root.to(root_positions.device, root_positions.dtype)


def _fix(motion_rotations: Tensor, root_positions: Tensor, skeleton: Skeleton, feet: list[int], c: np.ndarray,
         blend_frames: int, tol: float | None, max_iters: int, adjust_root: bool) -> tuple[Tensor, Tensor]:
    """The solver behind :func:`fix_foot_contact` (arguments already checked); float64 on the CPU inside."""
    parents = list(skeleton.parents)
    tol = 1e-5 * skeleton.height() if tol is None else float(tol)
    scale = max(skeleton.height(), 1e-12)
    rot = quat_normalize(motion_rotations.detach().to("cpu", torch.float64)).contiguous()
    root = root_positions.detach().to("cpu", torch.float64).contiguous()
    offsets = torch.as_tensor(skeleton.offsets, dtype=torch.float64).contiguous()

    pos0 = fk(rot, offsets, parents, root)
    index = {f: i for i, f in enumerate(feet)}
    rigid = [(index[parents[f]], i, float(np.linalg.norm(skeleton.offsets[f])))
             for i, f in enumerate(feet) if parents[f] in index]
    targets, weight = contact_targets(pos0[:, feet], c, blend_frames, rigid)
    frames = torch.nonzero(weight.amax(dim=1) > 0).flatten()
    tgt, w = targets[frames], weight[frames]  # (A, F, 3), (A, F)
    hard = w >= 1.0
    soft = (w > 0) & ~hard

    chains = [leg_chain(parents, f) for f in feet]
    dofs = sorted({k for ch in chains for k in ch})
    F, S, A = len(feet), len(dofs), frames.numel()
    P = 3 * S + 3
    member = torch.tensor([[k in ch for k in dofs] for ch in chains], dtype=torch.float64).reshape(F, S)
    # Prioritised damped least squares in scaled coordinates: rotations in radians (their Jacobian columns scale
    # with limb length), the root translation scaled by 1e-2 so it is stiff and only takes a visible share where
    # a pinned leg cannot reach. Pinned feet are the primary task; blend-in/out targets are met in its null
    # space, so where the two disagree (a heel rising while its toe stays planted) the pinned foot wins exactly.
    root_scale = 1e-2 * scale
    lam = (1e-4 * scale) ** 2
    lam_soft = (1e-2 * scale) ** 2  # heavier: a soft target the pinned feet forbid must not cause huge steps
    eye_r = torch.eye(3 * F, dtype=torch.float64)
    hard_rows = hard.repeat_interleave(3, dim=1).to(torch.float64)[..., None]  # (A, 3F, 1)
    soft_rows = soft.repeat_interleave(3, dim=1).to(torch.float64)[..., None]
    rot_cols = torch.cat((torch.ones(3 * S), torch.zeros(P - 3 * S))).to(torch.float64)[None, None, :]
    # Root translation moves every foot one-for-one: an identity block per foot.
    jac_root = root_scale * torch.eye(3, dtype=torch.float64).repeat(F, 1).expand(A, 3 * F, 3)

    def dls(jac: Tensor, rhs: Tensor, damping: float) -> tuple[Tensor, Tensor]:
        """Damped pseudo-inverse applied to rhs, and the pseudo-inverse itself."""
        pinv = torch.linalg.solve(jac @ jac.transpose(1, 2) + damping * eye_r, jac).transpose(1, 2)  # J^T M^-1, M = M^T
        return pinv @ rhs, pinv

    dof_parents = [parents[k] for k in dofs]

    def solve(sub_rot: Tensor, sub_root: Tensor, move_root: bool) -> tuple[Tensor, Tensor, float]:
        """Iterate to convergence; returns the new rotations, root and the largest pinned-foot error."""
        hard_err, prev_soft = 0.0, float("inf")
        sub_rot, sub_root = sub_rot.clone(), sub_root.clone()
        for _ in range(max_iters):
            pos, gq = fk(sub_rot, offsets, parents, sub_root, return_rotations=True)
            err = tgt - pos[:, feet]  # (A, F, 3)
            dist = err.norm(dim=-1)
            hard_err = float(dist[hard].max()) if hard.any() else 0.0
            soft_err = float(dist[soft].max()) if soft.any() else 0.0
            if hard_err <= tol and soft_err <= tol:
                break
            cols = []
            if S:
                d = pos[:, feet, None, :] - pos[:, None, dofs, :]  # (A, F, S, 3)
                blocks = _skew_neg(d) * member[None, :, :, None, None]
                cols.append(blocks.permute(0, 1, 3, 2, 4).reshape(A, 3 * F, 3 * S))  # rows (f, xyz), cols (k, xyz)
            cols.append(jac_root if move_root else torch.zeros_like(jac_root))
            jac = torch.cat(cols, dim=2)  # (A, 3F, P)
            e = err.reshape(A, 3 * F, 1)
            j1 = hard_rows * jac
            dx, _pinv1 = dls(j1, hard_rows * e, lam)
            # Blend targets never move the root: their task acts on the rotations only, in the null space of the
            # pinned feet's Jacobian restricted to the rotations.
            j1r = j1 * rot_cols
            _unused, pinv1r = dls(j1r, hard_rows * e, lam)
            j2 = soft_rows * jac * rot_cols
            j2 = j2 - (j2 @ pinv1r) @ j1r  # J2 (I - J1r^+ J1r) without forming the P x P projector
            dx2, _unused = dls(j2, soft_rows * (e - jac @ dx), lam_soft)
            dx = dx + dx2
            step = 0.0
            if S:
                # Shorten a frame's whole step (keeping its direction, hence the priority) so that no joint turns by
                # more than 0.25 rad: far-off targets are approached gradually instead of overshot.
                ang = dx[:, : 3 * S, 0].reshape(A, S, 3).norm(dim=-1).amax(dim=1)
                dx = dx * torch.clamp(0.25 / ang.clamp_min(1e-30), max=1.0)[:, None, None]
                dw = dx[:, : 3 * S, 0].reshape(A, S, 3)
                step = float(ang.max()) * scale
                # A world-frame rotation dw about joint k is the local pre-rotation R_parent^T dw.
                local_dw = quat_apply(quat_conjugate(gq[:, dof_parents]), dw)
                sub_rot[:, dofs] = quat_normalize(quat_mul(axis_angle_to_quat(local_dw), sub_rot[:, dofs]))
            if move_root:
                droot = root_scale * dx[:, 3 * S :, 0]
                sub_root = sub_root + droot
                step = max(step, float(droot.abs().max()))
            # Done once the pins hold and the blend targets have settled (met, or as close as the pins allow).
            if hard_err <= tol and (step <= 1e-2 * tol or prev_soft - soft_err <= max(1e-2 * tol, 1e-3 * soft_err)):
                break
            prev_soft = soft_err
        return sub_rot, sub_root, hard_err

    sub_rot, sub_root, _err = solve(rot[frames], root[frames], adjust_root)
    new_root = root.clone()
    if adjust_root:
        # Where the root had to move (pinned feet out of reach), spread the shift smoothly over neighbouring
        # frames and solve again from there, so the body does not jerk in and out of the correction.
        shift = torch.zeros_like(root)
        shift[frames] = sub_root - root[frames]
        if float(shift.abs().max()) > tol:
            # The smoothed envelope is at least the shift each frame needed, so the legs can reach with the root
            # held; only if they still cannot (a locked-straight leg has no first-order way to shorten) may it move.
            new_root = root + _smooth(shift, max(2 * blend_frames, 4))
            sub_rot, sub_root, err = solve(sub_rot, new_root[frames], False)
            if err > tol:
                sub_rot, sub_root, _err = solve(sub_rot, sub_root, True)
    new_root[frames] = sub_root

    out_dtype, out_device = motion_rotations.dtype, motion_rotations.device
    rot_out = motion_rotations.detach().clone()
    if S:  # write back only the leg-chain joints: every other rotation stays bit-identical
        rows, cols = frames[:, None].to(out_device), torch.tensor(dofs, device=out_device)[None, :]
        rot_out[rows, cols] = sub_rot[:, dofs].to(out_device, out_dtype)
    return rot_out, new_root


def _smooth(x: Tensor, radius: int) -> Tensor:
    """Smooth envelope of (T, C) over time: per channel, the largest-magnitude value within ``radius`` frames
    (so a short spike keeps its full size), then a Hann-window average of that (edges replicated)."""
    T = x.shape[0]
    idx = (torch.arange(T)[:, None] + torch.arange(-radius, radius + 1)[None, :]).clamp(0, T - 1)  # (T, W)
    windows = x[idx]  # (T, W, C)
    pick = windows.abs().argmax(dim=1, keepdim=True)
    env = windows.gather(1, pick)[:, 0]  # (T, C)
    win = torch.hann_window(2 * radius + 3, periodic=False, dtype=x.dtype)[1:-1]
    win = win / win.sum()
    padded = torch.nn.functional.pad(env.T[:, None, :], (radius, radius), mode="replicate")
    return torch.nn.functional.conv1d(padded, win[None, None, :])[:, 0, :].T


def _shape(x: object) -> object:
    return tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
