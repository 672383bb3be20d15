"""modi.core.ik.fix_foot_contact: pinned feet stay put (within 1 mm), everything else is left alone."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from modi.core.ik import _runs, contact_targets, fix_foot_contact, leg_chain
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import axis_angle_to_quat, matrix_to_quat, quat_mul, quat_normalize
from modi.core.skeleton import Skeleton

MM_IN_CM = 0.1  # the procedural and Bandai rigs are in centimetres


def _fk(skeleton, rotations, root):
    pos, _ = forward_kinematics(rotations.double(), torch.from_numpy(skeleton.offsets), skeleton.parents, root.double())
    return pos


def _max_pin_drift(positions, feet, contacts):
    """Largest distance of a foot from its position averaged over the contact run, over all runs."""
    worst = 0.0
    for i, f in enumerate(feet):
        for s, e in _runs(np.asarray(contacts[:, i], dtype=bool)):
            seg = positions[s:e, f]
            worst = max(worst, float((seg - seg.mean(dim=0)).norm(dim=-1).max()))
    return worst


def _sliding_walk(seed=3, frames=90):
    """A procedural walk (feet planted) whose legs get smooth angle noise, so the planted feet slide."""
    from modi.core.contacts import foot_contacts
    from modi.data.procedural import builtin_skeleton, clip_arrays

    sk = builtin_skeleton()
    local, root = clip_arrays("walk", frames, 30.0, seed)
    q = quat_normalize(matrix_to_quat(torch.from_numpy(local)))
    r = torch.from_numpy(root)
    feet = [sk.index(n) for n in ("LeftFoot", "LeftToe", "RightFoot", "RightToe")]
    contacts = foot_contacts(_fk(sk, q, r), feet, sk.height(), 30.0).bool()
    t = torch.linspace(0, 1, frames, dtype=torch.float64)
    noisy = q.clone()
    for j in (sk.index(n) for n in ("LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot")):
        aa = torch.stack([0.08 * torch.sin(2 * math.pi * (k + 1.3 * j) * t + j) for k in range(3)], dim=-1)
        noisy[:, j] = quat_mul(axis_angle_to_quat(aa), q[:, j])
    return sk, noisy, r, feet, contacts


def test_leg_chain_stops_at_the_branch():
    # 0 root -> 1 hips -> {2 spine -> 3, 4 thigh -> 5 shin -> 6 ankle -> 7 toe}
    parents = [-1, 0, 1, 2, 1, 4, 5, 6]
    assert leg_chain(parents, 7) == [6, 5, 4]
    assert leg_chain(parents, 6) == [5, 4]
    assert leg_chain([-1, 0, 1], 2) == [1]
    assert leg_chain([-1, 0], 1) == []


def test_contact_targets_pin_is_run_mean_and_blends_out():
    T = 12
    pos = torch.zeros(T, 1, 3, dtype=torch.float64)
    pos[:, 0, 0] = torch.arange(T, dtype=torch.float64)  # sliding along x by 1 per frame
    contacts = np.zeros((T, 1), dtype=bool)
    contacts[4:7] = True  # x = 4, 5, 6 -> pin at x = 5
    tgt, w = contact_targets(pos, contacts, blend_frames=2)
    assert torch.all(w[4:7] == 1) and torch.all(tgt[4:7, 0, 0] == 5.0)
    assert torch.all(w[:2] == 0) and torch.all(w[9:] == 0) and torch.all(tgt[9:, 0, 0] == pos[9:, 0, 0])
    assert 0 < w[3, 0] < 1 and 0 < w[8, 0] < 1 and w[2, 0] < w[3, 0]
    # rigid pair: a child foot overlapping its parent foot's run is moved onto the sphere of the bone length
    pos2 = torch.zeros(T, 2, 3, dtype=torch.float64)
    pos2[:, 1, 1] = 2.0
    pos2[:6, 1, 1] = 3.0  # child sits 3 from the parent for half the run, 2 for the other half: mean 2.5
    both = np.ones((T, 2), dtype=bool)
    tgt2, _ = contact_targets(pos2, both, 0, rigid_pairs=[(0, 1, 2.0)])
    torch.testing.assert_close(tgt2[0, 1], torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64))


def test_pins_sliding_feet_of_procedural_walk():
    sk, q, r, feet, contacts = _sliding_walk()
    before = _max_pin_drift(_fk(sk, q, r), feet, contacts)
    assert before > 2.0, "the test motion should slide by centimetres"
    q2, r2 = fix_foot_contact(q, r, sk, feet, contacts)
    pos2 = _fk(sk, q2, r2)
    assert _max_pin_drift(pos2, feet, contacts) < MM_IN_CM
    # rotations stay unit; joints off the leg chains are bit-identical
    torch.testing.assert_close(q2.norm(dim=-1), torch.ones(q2.shape[:2], dtype=q2.dtype))
    legs = {j for f in feet for j in leg_chain(sk.parents, f)}
    others = [j for j in range(sk.n_joints) if j not in legs]
    assert torch.equal(q2[:, others], q[:, others])
    # the root moves only a little and smoothly (it takes up only what the legs cannot reach)
    dr = r2 - r
    assert float(dr.norm(dim=-1).max()) < 5.0
    assert float((dr[1:] - dr[:-1]).norm(dim=-1).max()) < 0.5


def test_frames_far_from_contacts_are_untouched_and_dtype_kept():
    sk, q, r, feet, contacts = _sliding_walk(frames=60)
    c = torch.zeros_like(contacts)
    c[20:30, 0] = True
    q32, r32 = q.float(), r.float()
    q2, r2 = fix_foot_contact(q32, r32, sk, feet, c, blend_frames=3)
    assert q2.dtype == torch.float32 and r2.dtype == torch.float32
    # rotations change only on the run and its 3 blend frames each side; the root's smoothing reaches further
    assert torch.equal(q2[:17], q32[:17]) and torch.equal(q2[33:], q32[33:])
    assert torch.equal(r2[:4], r32[:4]) and torch.equal(r2[46:], r32[46:])
    assert _max_pin_drift(_fk(sk, q2, r2), feet, c.numpy()) < MM_IN_CM
    before = _max_pin_drift(_fk(sk, q, r), feet, c.numpy())
    # with the root held, a leg that is out of reach gets as close as it can, and the root stays bit-identical
    q3, r3 = fix_foot_contact(q, r, sk, feet, c, blend_frames=3, adjust_root=False)
    assert torch.equal(r3, r)
    assert _max_pin_drift(_fk(sk, q3, r3), feet, c.numpy()) < 0.5 * before


def test_no_contacts_returns_copy():
    sk, q, r, feet, contacts = _sliding_walk(frames=20)
    q2, r2 = fix_foot_contact(q, r, sk, feet, torch.zeros_like(contacts))
    assert torch.equal(q2, q) and torch.equal(r2, r) and q2 is not q


def test_hexapod_any_skeleton():
    # body with six 3-joint legs (like the crab): every leg hangs off the root
    parents, offsets = [-1], [[0.0, 30.0, 0.0]]
    tips = []
    for k in range(6):
        ang = 2 * math.pi * k / 6
        d = np.array([math.cos(ang), 0.0, math.sin(ang)])
        base = len(parents)
        parents += [0, base, base + 1]
        offsets += [list(8 * d), list(12 * d + [0, 5, 0]), list(6 * d + [0, -30, 0])]
        tips.append(base + 2)
    sk = Skeleton([f"j{i}" for i in range(len(parents))], parents, np.array(offsets))
    T = 40
    g = torch.Generator().manual_seed(0)
    aa = torch.randn(T, len(parents), 3, generator=g, dtype=torch.float64).cumsum(0) * 0.01
    q = axis_angle_to_quat(aa)
    r = torch.zeros(T, 3, dtype=torch.float64)
    r[:, 0] = torch.linspace(0, 10, T)
    contacts = torch.zeros(T, 6, dtype=torch.bool)
    for k in range(6):
        contacts[(k * 3) % 10 : (k * 3) % 10 + 15, k] = True
    before = _max_pin_drift(_fk(sk, q, r), tips, contacts)
    q2, r2 = fix_foot_contact(q, r, sk, tips, contacts)
    assert before > 1.0
    assert _max_pin_drift(_fk(sk, q2, r2), tips, contacts) < 1e-3 * sk.height()


@pytest.mark.parametrize(
    "change,match",
    [
        (dict(motion_rotations=torch.zeros(10, 22, 3)), "motion_rotations must be a \\(T, J, 4\\)"),
        (dict(root_positions=torch.zeros(9, 3)), "root_positions must be a \\(10, 3\\)"),
        (dict(foot_joints=[0]), "foot joint 0 out of range"),
        (dict(foot_joints=[3, 3]), "duplicates"),
        (dict(contacts=np.zeros((10, 3), dtype=bool)), "contacts must have shape \\(T, F\\) = \\(10, 2\\)"),
        (dict(contacts=np.full((10, 2), 0.5)), "contacts must be boolean"),
        (dict(blend_frames=-1), "blend_frames"),
    ],
)
def test_bad_input(change, match):
    from modi.data.procedural import builtin_skeleton

    sk = builtin_skeleton()
    J = sk.n_joints
    args = dict(motion_rotations=torch.tensor([1.0, 0, 0, 0]).repeat(10, J, 1), root_positions=torch.zeros(10, 3),
                skeleton=sk, foot_joints=[3, 7], contacts=np.zeros((10, 2), dtype=bool))
    args.update(change)
    with pytest.raises(ValueError, match=match):
        fix_foot_contact(**args)


def test_real_bandai_walk(shared_data):
    motion_mod = pytest.importorskip("modi.data.motion")
    from modi.core.contacts import foot_contacts

    files = sorted((shared_data / "bvh").rglob("*walk*.bvh"))
    files = [f for f in files if "bandai" in str(f)]
    if not files:
        pytest.skip("no Bandai walk clip in the shared data")
    m = motion_mod.Motion.from_bvh(files[0])
    sk = m.skeleton
    q, r = m.rotations[:120].double(), m.root_positions[:120].double()
    feet = sk.detect_feet(per_side=2)
    contacts = foot_contacts(_fk(sk, q, r), feet, sk.height(), m.fps).bool()
    assert contacts.any()
    assert _max_pin_drift(_fk(sk, q, r), feet, contacts) > 1.0  # mocap feet drift during labelled contact
    q2, r2 = fix_foot_contact(q, r, sk, feet, contacts)
    assert _max_pin_drift(_fk(sk, q2, r2), feet, contacts) < MM_IN_CM
