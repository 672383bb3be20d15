"""modi.data.motion: BVH round trips on real skeletons, resampling, joint subsets."""
from __future__ import annotations

import warnings
from functools import lru_cache

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from modi.io import bvh as B
from modi.core.kinematics import bvh_positions
from modi.data.motion import Motion
from modi.core.rotations import quat_identity, quat_mul, quat_inverse, quat_to_matrix
from modi.core.skeleton import Skeleton

BANDAI = "bandai-namco-1/data/dataset-1_bow_active_001.bvh"
JOE = "ganimator/Joe/Walk-In-Circle.bvh"
EXACT_FILES = [JOE, "ganimator/Crabnew/Crab-dance-long.bvh", "ganimator/Xia/normal.bvh",
               "ganimator/Joe/traj-example.bvh", "ganimator/Malcolm/Gangnam-Style.bvh"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@lru_cache(maxsize=None)
def _bvh(path) -> B.Bvh:
    return B.load(path)


def _height(pos) -> float:
    pos = np.asarray(pos)
    return float(np.ptp(pos[0], axis=0).max())


def _angle_between(qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor:
    """Rotation angle (rad) of qa^-1 qb, sign-invariant."""
    d = quat_mul(quat_inverse(qa), qb)
    return 2 * torch.atan2(d[..., 1:].norm(dim=-1), d[..., 0].abs())


@pytest.mark.parametrize("rel", EXACT_FILES)
def test_bvh_round_trip_is_exact(shared_data, rel, tmp_path):
    b = _bvh(shared_data / "bvh" / rel)
    m = Motion.from_bvh(b)
    ref = bvh_positions(b)
    h = _height(ref)
    assert m.n_frames == b.n_frames and m.n_joints == b.n_joints
    assert m.skeleton.names == b.names and m.skeleton.rotation_orders == b.rotation_orders
    np.testing.assert_allclose(m.positions().numpy(), ref, atol=1e-9 * h)
    out = m.to_bvh()
    assert out.channels[0][:3] == ["Xposition", "Yposition", "Zposition"] and len(out.channels[0]) == 6
    assert all(len(c) == 3 and c[0].endswith("rotation") for c in out.channels[1:])
    np.testing.assert_allclose(bvh_positions(out), ref, atol=1e-9 * h)
    m.save(tmp_path / "m.bvh")  # through text at 6 decimals
    assert np.abs(bvh_positions(B.load(tmp_path / "m.bvh")) - ref).max() < 1e-4 * h


def test_from_path_and_fps_snapping(shared_data):
    path = shared_data / "bvh" / JOE
    m = Motion.from_bvh(path)
    assert _bvh(path).frame_time == pytest.approx(0.016667)
    assert m.fps == 60.0  # "Frame Time: 0.016667" stands for 1/60
    assert abs(m.to_bvh().frame_time - 1 / 60) < 1e-12
    assert m.rotations.dtype == torch.float64
    assert Motion.from_bvh(path, dtype=torch.float32).rotations.dtype == torch.float32


def test_rotations_are_unit_and_sign_continuous(shared_data):
    m = Motion.from_bvh(_bvh(shared_data / "bvh" / JOE))  # walks in a circle: the root turns through 180 deg
    q = m.rotations
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(q.shape[:2], dtype=q.dtype))
    assert ((q[1:] * q[:-1]).sum(-1) >= 0).all()
    assert (q[0, :, 0] >= 0).all()


def test_bandai_static_root_is_folded_into_hips(shared_data):
    b = _bvh(shared_data / "bvh" / BANDAI)
    assert np.ptp(b.local_translations()[:, 1], axis=0).max() > 1.0  # the Hips translation is animated
    m = Motion.from_bvh(b)
    ref = bvh_positions(b)
    h = _height(ref)
    got = bvh_positions(m.to_bvh())
    # the Hips' motion is the root track (zero offset) and every joint, the static joint_Root included, is exact
    np.testing.assert_array_equal(m.skeleton.offsets[1], [0.0, 0.0, 0.0])
    assert np.abs(got - ref).max() < 1e-9 * h
    np.testing.assert_allclose(m.positions().numpy(), ref, atol=1e-9 * h)
    # dropping the dummy root gives an exact Hips-rooted 21-joint motion
    sub = m.subset(range(1, 22))
    assert sub.skeleton.names[0] == "Hips" and sub.skeleton.parents[0] == -1
    np.testing.assert_allclose(sub.positions().numpy(), ref[:, 1:], atol=1e-9 * h)


def test_elephant_stretchy_bones_warn_and_stay_close(shared_data):
    b = _bvh(shared_data / "bvh" / "ganimator/Elephant/idle1.bvh")
    with pytest.warns(UserWarning, match="animated translations"):
        m = Motion.from_bvh(b)
    ref = bvh_positions(b)
    h = _height(ref)
    got = bvh_positions(m.to_bvh())
    trans = b.local_translations()
    animated = np.ptp(trans, axis=0).max(axis=1) > 1e-5 * h  # (below that: 6-decimal print jitter)
    animated[0] = False
    # joints with no animated translation on their chain are exact up to that jitter; the rest stay
    # within the size of the stretch
    affected = animated.copy()
    for j, p in enumerate(b.parents):
        if p >= 0 and affected[p]:
            affected[j] = True
    assert (~affected).sum() >= 5
    assert np.abs(got[:, ~affected] - ref[:, ~affected]).max() < 1e-5 * h
    assert np.abs(got - ref).max() < 0.1 * h


def test_no_warning_for_rigid_files(shared_data):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Motion.from_bvh(_bvh(shared_data / "bvh" / "ganimator/Xia/proud.bvh"))


# ------------------------------------------------------------------------------------------- resample


def _toy_motion(t=11, fps=30.0, seed=0) -> Motion:
    g = torch.Generator().manual_seed(seed)
    sk = Skeleton(["r", "a", "b"], [-1, 0, 1], np.array([[0.0, 0, 0], [0, 1, 0], [0, 1, 0]]),
                  rotation_orders=["ZXY", "XYZ", "YZX"])
    aa = torch.randn(t, 3, 3, generator=g, dtype=torch.float64) * 0.4
    from modi.core.rotations import axis_angle_to_quat

    return Motion(sk, axis_angle_to_quat(aa), torch.randn(t, 3, generator=g, dtype=torch.float64), fps)


def test_resample_frame_counts():
    m = _toy_motion(t=11, fps=30.0)
    assert m.resample(30.0).n_frames == 11
    assert m.resample(15.0).n_frames == 6  # floor(10 * 0.5) + 1
    assert m.resample(60.0).n_frames == 21
    assert m.resample(20.0).n_frames == 7  # floor(10 * 2/3) + 1
    assert m.resample(24.0).fps == 24.0
    with pytest.raises(ValueError, match="fps must be positive"):
        m.resample(0)


def test_resample_down_by_two_keeps_every_other_frame(shared_data):
    m = Motion.from_bvh(_bvh(shared_data / "bvh" / JOE))
    half = m.resample(30.0)
    assert half.n_frames == (m.n_frames - 1) // 2 + 1
    torch.testing.assert_close(half.root_positions, m.root_positions[::2])
    assert _angle_between(half.rotations, m.rotations[::2]).max() < 1e-7


def test_resample_up_matches_scipy_slerp_and_linear_root():
    m = _toy_motion(t=6, fps=10.0)
    up = m.resample(25.0)  # source times 0, 0.4, 0.8, ...
    assert up.n_frames == 13
    times = np.arange(13) * 0.4
    for j in range(3):
        q = m.rotations[:, j].numpy()
        ref = Slerp(np.arange(6), Rotation.from_quat(q[:, [1, 2, 3, 0]]))(times).as_matrix()
        np.testing.assert_allclose(quat_to_matrix(up.rotations[:, j]).numpy(), ref, atol=1e-10)
    ref_root = np.stack([np.interp(times, np.arange(6), m.root_positions[:, k].numpy()) for k in range(3)], -1)
    np.testing.assert_allclose(up.root_positions.numpy(), ref_root, atol=1e-12)


# ------------------------------------------------------------------------------------------- subset


def test_subset_keep_all_is_identity(shared_data):
    m = Motion.from_bvh(_bvh(shared_data / "bvh" / "ganimator/Xia/normal.bvh"))
    s = m.subset(list(range(m.n_joints)))
    assert s.skeleton.names == m.skeleton.names and s.skeleton.parents == m.skeleton.parents
    torch.testing.assert_close(s.positions(), m.positions())
    np.testing.assert_allclose(s.skeleton.offsets, m.skeleton.offsets)


def test_subset_dropping_leaves_is_exact_and_adds_end_sites(shared_data):
    m = Motion.from_bvh(_bvh(shared_data / "bvh" / JOE))
    names = m.skeleton.names
    keep = [j for j, n in enumerate(names) if "Hand" not in n or n.endswith("Hand")]  # drop the fingers
    s = m.subset(keep)
    assert s.n_joints == 65 - 40
    torch.testing.assert_close(s.positions(), m.positions()[:, keep])
    hand = s.skeleton.index("mixamorig7:LeftHand")
    first_finger = names.index("mixamorig7:LeftHandThumb1")
    np.testing.assert_allclose(s.skeleton.end_sites[hand], m.skeleton.offsets[first_finger])


def test_subset_sums_offsets_and_composes_rotations(shared_data):
    m = Motion.from_bvh(_bvh(shared_data / "bvh" / JOE))
    sk = m.skeleton
    spine, spine1, spine2 = (sk.index(f"mixamorig7:{n}") for n in ("Spine", "Spine1", "Spine2"))
    keep = [j for j in range(sk.n_joints) if j != spine1]
    s = m.subset(keep)
    new_spine2 = s.skeleton.index("mixamorig7:Spine2")
    assert s.skeleton.parents[new_spine2] == s.skeleton.index("mixamorig7:Spine")
    np.testing.assert_allclose(s.skeleton.offsets[new_spine2], sk.offsets[spine1] + sk.offsets[spine2])
    # global orientations of every kept joint are preserved exactly
    _, g_old = m.forward_kinematics()
    _, g_new = s.forward_kinematics()
    assert _angle_between(g_new, g_old[:, keep]).max() < 1e-9
    # positions: exact at and above the cut, bounded below it (Spine1 really rotates in this clip)
    old_pos, new_pos = m.positions()[:, keep], s.positions()
    torch.testing.assert_close(new_pos[:, : new_spine2], old_pos[:, : new_spine2])
    h = _height(m.positions())
    assert (new_pos - old_pos).norm(dim=-1).max() < 0.1 * h

    # ... and exact everywhere when the dropped joint does not rotate
    rot = m.rotations.clone()
    rot[:, spine1] = quat_identity((m.n_frames,), torch.float64)
    still = Motion(sk, rot, m.root_positions, m.fps)
    torch.testing.assert_close(still.subset(keep).positions(), still.positions()[:, keep])


def test_subset_errors():
    m = _toy_motion()
    with pytest.raises(ValueError, match="empty"):
        m.subset([])
    with pytest.raises(ValueError, match="0..2"):
        m.subset([0, 3])
    sk = Skeleton(["r", "a", "b"], [-1, 0, 0], np.ones((3, 3)))
    two = Motion(sk, m.rotations, m.root_positions, 30)
    with pytest.raises(ValueError, match="no common kept ancestor"):
        two.subset([1, 2])


def test_motion_validation():
    m = _toy_motion()
    with pytest.raises(ValueError, match="rotations must be"):
        Motion(m.skeleton, m.rotations[:, :2], m.root_positions, 30)
    with pytest.raises(ValueError, match="root_positions must be"):
        Motion(m.skeleton, m.rotations, m.root_positions[:3], 30)
    with pytest.raises(ValueError, match="fps"):
        Motion(m.skeleton, m.rotations, m.root_positions, -1)
    c = m.crop(2, 5)
    assert c.n_frames == 3
    torch.testing.assert_close(c.positions(), m.positions()[2:5])
    assert m.to(torch.float32).rotations.dtype == torch.float32


# ------------------------------------------------------------------------------------------- issue 40 defects


def test_bandai_write_back_keeps_the_static_root_where_the_file_has_it(shared_data, tmp_path):
    """Read a Bandai clip, save it, read the file again: every joint's pose is the file's, and joint_Root stays at
    [0, 0, 0] (it used to move to the Hips' track, [-1.71, 90.27, -407.12] in frame 0 of this clip)."""
    path = shared_data / "bvh" / "bandai-namco-1/data/dataset-1_walk_normal_001.bvh"
    b = _bvh(path)
    ref = bvh_positions(b)
    h = _height(ref)
    m = Motion.from_bvh(path)
    m.to_bvh(tmp_path / "back.bvh")
    back = B.load(tmp_path / "back.bvh")
    got = bvh_positions(back)
    np.testing.assert_allclose(got[:, 0], np.zeros_like(got[:, 0]), atol=1e-9)
    assert np.abs(got - ref).max() < 1e-5 * h
    again = Motion.from_bvh(back)  # and the written file reads back the same way
    assert again.static_root is not None
    assert float((again.positions() - m.positions()).abs().max()) < 1e-5 * h


def test_bvh_objects_compare_by_value(shared_data):
    a = B.load(shared_data / "bvh" / JOE)
    b = B.load(shared_data / "bvh" / JOE)
    assert a == b and not (a != b)  # used to raise "The truth value of an array ... is ambiguous"
    c = b.copy()
    c.motion[3, 4] += 1.0
    assert a != c
    assert a.skeleton() == b.skeleton()
    assert len(repr(a)) < 200


def test_motion_repr_is_one_short_line_and_equality_is_by_value(shared_data):
    m = Motion.from_bvh(shared_data / "bvh" / JOE)
    text = repr(m)
    assert "\n" not in text and len(text) < 200, text  # was 14,032 characters of tensors
    assert "753 frames at 60 fps" in text and "centimetres" in text
    assert m == Motion.from_bvh(shared_data / "bvh" / JOE)
    assert m != m.crop(0, 10)


def test_one_reader_one_rate_for_a_xia_clip(shared_data):
    """Xia's ``Frame Time: 0.008333`` is 120 fps: Motion.from_bvh and GANimator's reader agree (GANimator used to keep
    120.0048 / 4 = 30.0012 fps and wrote ``Frame Time: 0.03333200``)."""
    from modi.models.ganimator.config import preset
    from modi.models.ganimator.data import load_sequence, read_clip

    path = shared_data / "bvh" / "ganimator/Xia/normal.bvh"
    assert Motion.from_bvh(path).fps == 120.0
    assert read_clip(path).fps == 120.0
    assert load_sequence(path, preset("fast")).fps == 30.0


def test_positions_in_metres_and_units_always_known(shared_data):
    joe = Motion.from_bvh(shared_data / "bvh" / JOE)  # a Mixamo rig in centimetres
    assert joe.unit == "centimetres" and joe.metres_per_unit() == 0.01
    torch.testing.assert_close(joe.positions(unit="m"), joe.positions() * 0.01)
    torch.testing.assert_close(joe.positions(unit="cm"), joe.positions())
    assert joe.resample(30).unit == "centimetres" and joe.crop(0, 3).unit == "centimetres"
    given = Motion(joe.skeleton, joe.rotations, joe.root_positions, joe.fps, unit="m")
    assert given.unit == "metres"
    with pytest.raises(ValueError, match="unknown length unit"):
        joe.positions(unit="furlongs")


def test_to_gltf_writes_metres(shared_data, tmp_path):
    from modi.io.gltf import load_positions

    m = Motion.from_bvh(shared_data / "bvh" / JOE).crop(0, 20)
    out = m.to_gltf(tmp_path / "joe.glb")
    names, parents, pos, fps, _ = load_positions(out)
    assert names == m.skeleton.names and fps == pytest.approx(60.0)
    np.testing.assert_allclose(pos, m.positions(unit="m").numpy(), atol=1e-4)


def test_from_gltf_reads_back_what_to_gltf_wrote(tmp_path):
    """``Motion.from_gltf`` beside ``to_gltf``; ``modi.api.files.motion_from_gltf`` (its earlier home) is it."""
    from modi.api.files import motion_from_gltf
    from modi.data.procedural import generate_clip

    m = generate_clip("walk", 16, rng=0)
    out = m.to_gltf(tmp_path / "walk.glb")
    g = Motion.from_gltf(out)
    assert g.unit == "metres" and g.fps == m.fps and g.skeleton.names == m.skeleton.names
    torch.testing.assert_close(g.positions(), m.positions(unit="m"), atol=1e-4, rtol=0)
    assert motion_from_gltf(out) == g
