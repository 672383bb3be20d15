"""Representations (MoDi quaternion, GANimator 6D), contact labels and normalisation."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from modi.core.contacts import foot_contacts, foot_speed
from modi.data.normalization import Normalizer
from modi.data.representation import (
    MotionRepresentation,
    continuous_quats,
    ganimator_representation,
    modi_representation,
)
from modi.core.skeleton import Skeleton

D = torch.float64


def _small_skeleton() -> Skeleton:
    names = ["Hips", "LeftUpLeg", "LeftFoot", "RightUpLeg", "RightFoot", "Spine", "Head"]
    parents = [-1, 0, 1, 0, 3, 0, 5]
    offsets = [[0, 0, 0], [10, -5, 0], [0, -40, 0], [-10, -5, 0], [0, -40, 0], [0, 15, 0], [0, 30, 0]]
    return Skeleton(names, parents, np.array(offsets, dtype=float))


def _random_quats(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    q = torch.from_numpy(Rotation.random(int(np.prod(shape)), random_state=seed).as_quat())  # x y z w
    return q[:, [3, 0, 1, 2]].reshape(*shape, 4).to(D)


def _matrices(q: torch.Tensor) -> np.ndarray:
    flat = q.reshape(-1, 4).numpy()
    return Rotation.from_quat(flat[:, [1, 2, 3, 0]]).as_matrix().reshape(*q.shape[:-1], 3, 3)


# ---------------------------------------------------------------------------------------------------------------


def test_continuous_quats_same_rotations_smooth_signs():
    q = _random_quats((3, 40, 5))
    q = q * torch.where(torch.rand(3, 40, 5, 1, dtype=D) < 0.5, -1.0, 1.0)
    c = continuous_quats(q, dim=-3)
    np.testing.assert_allclose(_matrices(c), _matrices(q), atol=1e-12)
    assert torch.all((c[:, 1:] * c[:, :-1]).sum(-1) >= 0)
    assert torch.all(c[:, 0, :, 0] >= 0)


@pytest.mark.parametrize("rotation, K", [("quat", 4), ("6d", 6)])
@pytest.mark.parametrize("root", ["velocity", "position"])
def test_parts_round_trip_and_layout(rotation, K, root):
    sk = _small_skeleton()
    rep = MotionRepresentation(sk, [2, 4], rotation=rotation, root=root)
    B, T, J = 3, 17, sk.n_joints
    q = _random_quats((B, T, J), seed=1)
    rp = torch.randn(B, T, 3, dtype=D) * 50
    c = (torch.rand(B, T, 2) > 0.5).to(D)
    x = rep.encode_parts(q, rp, c)
    assert x.shape == (B, K, J + 3, T)
    # padding is zero; contacts sit in channel 0; the root entity's channel 1 is the height
    assert torch.all(x[:, 3:, J] == 0) and torch.all(x[:, 1:, J + 1:] == 0)
    torch.testing.assert_close(x[:, 0, J + 1:], c.transpose(1, 2))
    torch.testing.assert_close(x[:, 1, J], rp[..., 1])
    q2, rp2, c2 = rep.decode_parts(x)
    np.testing.assert_allclose(_matrices(q2), _matrices(q), atol=1e-10)
    torch.testing.assert_close(rp2, rp, atol=1e-9, rtol=0)
    torch.testing.assert_close(c2, c)


@pytest.mark.parametrize("rotation", ["quat", "6d"])
def test_dropped_leaf_rotations_keep_positions(rotation):
    """leaf_rotations="drop": leaves (not the root) hold the identity, every joint position is unchanged, and the
    leaf channels of a model's output are ignored; a random tree, not only the humanoid."""
    rng = np.random.default_rng(3)
    J = 12
    parents = [-1] + [int(rng.integers(0, j)) for j in range(1, J)]
    sk = Skeleton([f"j{j}" for j in range(J)], parents, rng.normal(size=(J, 3)) * 10)
    leaves = [j for j in range(1, J) if j not in parents]
    keep = MotionRepresentation(sk, [], rotation=rotation)
    drop = MotionRepresentation(sk, [], rotation=rotation, leaf_rotations="drop")
    assert drop.dropped_rotations == leaves and keep.dropped_rotations == []
    q = _random_quats((2, 9, J), seed=4)
    rp = torch.randn(2, 9, 3, dtype=D) * 20
    xk, xd = keep.encode_parts(q, rp), drop.encode_parts(q, rp)
    assert not torch.equal(xk[:, :, leaves], xd[:, :, leaves])
    torch.testing.assert_close(xd[:, :, [j for j in range(J) if j not in leaves]],
                               xk[:, :, [j for j in range(J) if j not in leaves]])
    torch.testing.assert_close(drop.positions(xd), keep.positions(xk), atol=1e-9, rtol=0)
    noisy = xd.clone()
    noisy[:, :, leaves] = torch.randn_like(noisy[:, :, leaves])
    q2 = drop.decode_parts(noisy)[0]
    assert torch.equal(q2[..., leaves, :], torch.tensor([1.0, 0, 0, 0], dtype=D).expand_as(q2[..., leaves, :]))
    assert MotionRepresentation.from_dict(drop.to_dict()).dropped_rotations == leaves
    with pytest.raises(ValueError, match="leaf_rotations"):
        MotionRepresentation(sk, [], leaf_rotations="none")


def test_root_velocity_channels_by_hand():
    sk = _small_skeleton()
    rep = modi_representation(sk, feet=[2, 4])
    T = 5
    t = torch.arange(T, dtype=D)
    rp = torch.stack([2 * t + 5, 90 + t, -3 * t + 1], dim=-1)
    x = rep.encode_parts(_random_quats((T, sk.n_joints)), rp)
    J = sk.n_joints
    assert x[0, J].tolist() == [5, 2, 2, 2, 2]  # first frame: displacement from the origin
    assert x[2, J].tolist() == [1, -3, -3, -3, -3]
    assert x[1, J].tolist() == [90, 91, 92, 93, 94]


def test_decode_ignores_scale_of_network_quats():
    rep = modi_representation(_small_skeleton(), feet=[2, 4])
    q = _random_quats((9, 7), seed=3)
    x = rep.encode_parts(q, torch.zeros(9, 3, dtype=D))
    x[:, :7] *= 3.0  # a network output need not be unit length
    np.testing.assert_allclose(_matrices(rep.decode_parts(x)[0]), _matrices(q), atol=1e-10)


def test_ganimator_flat_view_and_wiring():
    sk = _small_skeleton()
    rep = ganimator_representation(sk, feet=[2, 4])
    assert rep.K == 6 and rep.contacts_to_root_motion
    nb = rep.layout.neighbors(1)
    for c in rep.contacts:
        assert rep.root_motion in nb[c]
    x = torch.randn(2, 6, rep.n_entities, 11, dtype=D)
    flat = rep.to_flat(x)
    assert flat.shape == (2, 6 * rep.n_entities, 11)
    torch.testing.assert_close(flat[:, 6 * 3:6 * 4], x[:, :, 3])  # entity-major: entity 3 = rows 18..23
    torch.testing.assert_close(rep.from_flat(flat), x)


def test_representation_errors_and_dict():
    sk = _small_skeleton()
    with pytest.raises(ValueError, match="rotation"):
        MotionRepresentation(sk, [2], rotation="euler")
    rep = modi_representation(sk, feet=[2, 4])
    with pytest.raises(ValueError, match="rotations"):
        rep.encode_parts(torch.zeros(5, 3, 4), torch.zeros(5, 3))
    with pytest.raises(ValueError, match="decode"):
        rep.decode_parts(torch.zeros(4, 5, 8))
    rep2 = MotionRepresentation.from_dict(rep.to_dict())
    assert rep2.to_dict() == rep.to_dict()


# ---------------------------------------------------------------------------------------------------------------
# contacts


def _foot_track(T: int, fps: float, moving_from: int, lifted: bool) -> torch.Tensor:
    """One 'foot' joint: still until moving_from, then 2 units/s sideways; optionally held in the air."""
    pos = torch.zeros(T, 1, 3, dtype=D)
    t = torch.arange(T, dtype=D) / fps
    pos[:, 0, 0] = torch.clamp(t - moving_from / fps, min=0) * 2.0
    if lifted:
        pos[:, 0, 1] = 0.5
        pos[0, 0, 1] = 0.0  # the clip's lowest point is elsewhere
    return pos


def test_contacts_velocity_and_height():
    fps, T, h = 30.0, 60, 1.0
    pos = _foot_track(T, fps, 30, lifted=False)
    c = foot_contacts(pos, [0], h, fps)
    assert c[:29, 0].tolist() == [1.0] * 29 and c[31:, 0].tolist() == [0.0] * 29
    high = _foot_track(T, fps, 30, lifted=True)
    assert foot_contacts(high, [0], h, fps)[5:29, 0].sum() == 0  # still but 0.5 x height above its floor
    assert foot_contacts(high, [0], h, fps, height_factor=None)[5:29, 0].sum() == 24


def test_contacts_scale_and_fps_invariant():
    fps, T = 30.0, 60
    pos = _foot_track(T, fps, 30, lifted=False)
    base = foot_contacts(pos, [0], 1.0, fps)
    torch.testing.assert_close(foot_contacts(pos * 100, [0], 100.0, fps), base)
    fine = _foot_track(2 * T, 2 * fps, 60, lifted=False)
    torch.testing.assert_close(foot_contacts(fine, [0], 1.0, 2 * fps)[::2], base)
    speed = foot_speed(pos, [0], fps)
    assert abs(float(speed[-1, 0]) - 2.0) < 1e-9


def test_contacts_errors():
    with pytest.raises(ValueError, match="height"):
        foot_contacts(torch.zeros(4, 2, 3), [0], 0.0, 30.0)
    with pytest.raises(ValueError, match="foot joint"):
        foot_contacts(torch.zeros(4, 2, 3), [5], 1.0, 30.0)


# ---------------------------------------------------------------------------------------------------------------
# normalisation


def test_normalizer_zero_variance_and_round_trip(tmp_path):
    x = torch.randn(20, 4, 6, 16, dtype=D) * 3 + 7
    x[:, 3] = 0.0  # zero padding channel
    x[:, :, 2] = 5.0  # a joint that never moves
    norm = Normalizer.fit(x, skip_entities=[5])
    y = norm.normalize(x)
    assert torch.isfinite(y).all()
    assert torch.all(y[:, 3] == 0) and torch.all(y[:, :, 2] == 0)
    torch.testing.assert_close(y[:, :3, :2].mean(dim=(0, 3)), torch.zeros(3, 2, dtype=D), atol=1e-9, rtol=0)
    torch.testing.assert_close(y[:, :3, :2].std(dim=(0, 3), unbiased=False), torch.ones(3, 2, dtype=D))
    torch.testing.assert_close(y[:, :, 5], x[:, :, 5])  # skipped entity untouched
    torch.testing.assert_close(norm.denormalize(y), x)
    norm.save(tmp_path / "n.pt")
    back = Normalizer.load(tmp_path / "n.pt")
    torch.testing.assert_close(back.mean, norm.mean) and torch.testing.assert_close(back.std, norm.std)
    with pytest.raises(ValueError, match="does not match"):
        norm.normalize(torch.zeros(2, 4, 7, 3))
    with pytest.raises(ValueError, match="N, K, E, T"):
        Normalizer.fit(torch.zeros(4, 6, 16))


# ---------------------------------------------------------------------------------------------------------------
# real data: BVH -> Motion -> tensor -> Motion -> positions (and -> BVH file) reproduce the file's joints

REAL = [
    "bandai-namco-1/data/dataset-1_walk_normal_001.bvh",
    "bandai-namco-1/data/dataset-1_dash_normal_001.bvh",  # the anchor root moves too
    "ganimator/Joe/Walk-In-Circle.bvh",
    "ganimator/Crabnew/Crab-dance-long.bvh",
    "ganimator/Elephant/idle1.bvh",
    "ganimator/Xia/normal.bvh",
]


def _file_positions_and_motion(path):
    """(bvh, Motion, reference positions, joints expected exact). Bandai's ``joint_Root`` anchor rides on Hips in
    the Motion (its own position is meaningless); the Elephant's stretchy bones are made rigid by Motion, so
    there the reference is the Motion's own FK."""
    from modi.io import bvh
    from modi.data.dataset import motion_from_bvh
    from modi.core.kinematics import bvh_positions

    b = bvh.load(path)
    b.motion = b.motion[:240]  # keep the suite fast; every rig and channel layout is still exercised
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        motion = motion_from_bvh(b)
    rigid = not any("rigid" in str(w.message) for w in caught)
    ref = torch.from_numpy(bvh_positions(b)) if rigid else motion.positions().detach().clone()
    exact = list(range(1 if b.names[0] == "joint_Root" else 0, b.n_joints))
    return b, motion, ref, exact


@pytest.mark.parametrize("rel", REAL)
@pytest.mark.parametrize("rotation", ["quat", "6d"])
def test_real_round_trip_positions(shared_data, rel, rotation):
    b, motion, ref, exact = _file_positions_and_motion(shared_data / "bvh" / rel)
    sk = motion.skeleton
    rep = MotionRepresentation(sk, sk.detect_feet(), rotation=rotation)
    x = rep.encode(motion)
    assert x.shape == (rep.K, sk.n_joints + 1 + len(rep.feet), motion.n_frames)
    back = rep.decode(x, motion.fps)
    tol = 1e-4 * sk.height()
    assert float((back.positions() - ref)[:, exact].abs().max()) < tol
    assert float((rep.positions(x) - ref)[:, exact].abs().max()) < tol


def test_real_round_trip_through_bvh_file_with_reduction(shared_data, tmp_path):
    """Mixamo 65 joints -> default reduction (24) -> tensor -> BVH on disk -> positions of the kept joints."""
    from modi.io import bvh
    from modi.core.kinematics import bvh_positions

    b, motion, ref, _ = _file_positions_and_motion(shared_data / "bvh" / "ganimator/Joe/Salsa-Dancing-6.bvh")
    red, kept = motion.skeleton.reduce()
    assert red.n_joints == 24
    sub = motion.subset(kept)
    rep = modi_representation(red)
    x = rep.encode(sub)
    out = tmp_path / "round.bvh"
    bvh.save(rep.decode(x.float().double(), sub.fps).to_bvh(), out)
    back = torch.from_numpy(bvh_positions(bvh.load(out)))
    assert float((back - ref[:, kept]).abs().max()) < 1e-4 * red.height()


def test_real_walk_contacts_plausible(shared_data):
    _, motion, _, _ = _file_positions_and_motion(shared_data / "bvh" / REAL[0])
    rep = modi_representation(motion.skeleton)
    c = rep.contacts_of(motion)
    frac = c.mean(dim=0)
    assert c.shape == (motion.n_frames, 2)
    assert torch.all(frac > 0.2) and torch.all(frac < 0.85), frac  # each foot planted part of a walk cycle
    assert float((c.sum(dim=1) > 0).to(D).mean()) > 0.8  # walking: almost always some foot on the ground
