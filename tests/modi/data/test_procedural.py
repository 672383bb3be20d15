"""The procedural generator: a valid humanoid, rigid bones, planted feet, deterministic seeds, BVH round trip."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from modi.io import bvh as bvh_io
from modi.core.kinematics import bvh_positions, forward_kinematics
from modi.data.procedural import KINDS, builtin_skeleton, generate_clip, write_dataset

FPS = 30.0


def _positions(motion) -> np.ndarray:
    sk = motion.skeleton
    pos, _ = forward_kinematics(motion.rotations.double(), torch.as_tensor(sk.offsets), sk.parents,
                                motion.root_positions.double())
    return pos.numpy()


@pytest.fixture(scope="module")
def clips() -> dict[str, list[np.ndarray]]:
    """Three clips of every kind as global positions (T, J, 3)."""
    return {k: [_positions(generate_clip(k, 128, FPS, np.random.default_rng(s))) for s in range(3)] for k in KINDS}


def test_builtin_skeleton_is_a_named_humanoid():
    sk = builtin_skeleton()
    assert 20 <= sk.n_joints <= 24
    assert sk.parents[0] == -1 and all(0 <= p < j for j, p in enumerate(sk.parents) if j > 0)
    feet = [sk.names[j] for j in sk.detect_feet()]   # found by name: one foot joint per side
    assert len(feet) == 2 and feet[0] in ("LeftFoot", "LeftToe") and feet[1] in ("RightFoot", "RightToe")
    for name in ("Head", "LeftHand", "RightHand", "LeftToe", "RightToe"):
        assert sk.index(name) in sk.end_sites
    # Y up: the head is well above the hips, feet below, in centimetres.
    rest = _positions(generate_clip("idle", 2, FPS, 0))[0]
    assert rest[sk.index("Head"), 1] - rest[sk.index("LeftFoot"), 1] > 120


@pytest.mark.parametrize("kind", KINDS)
def test_bones_are_rigid_and_feet_stay_above_ground(kind, clips):
    sk = builtin_skeleton()
    rest = np.linalg.norm(sk.offsets, axis=-1)
    for pos in clips[kind]:
        assert np.isfinite(pos).all()
        for j, p in enumerate(sk.parents):
            if p >= 0:
                length = np.linalg.norm(pos[:, j] - pos[:, p], axis=-1)
                np.testing.assert_allclose(length, rest[j], atol=1e-4)
        assert pos[..., 1].min() > -0.5, "a joint goes through the floor"
        assert pos[..., 1].min() < 3.0, "the character never touches the ground"


def _planted(pos: np.ndarray, joint: int, height: float = 1.05) -> tuple[float, float]:
    """(fraction of frames the joint is below ``height`` (toes rest at 1 cm), its worst speed then, cm/s)."""
    y = pos[:, joint, 1]
    low = (y[1:] < height) & (y[:-1] < height)
    speed = np.linalg.norm(np.diff(pos[:, joint], axis=0), axis=-1) * FPS
    return float(low.mean()), float(speed[low].max()) if low.any() else 0.0


def test_walk_plants_each_foot_while_the_root_travels(clips):
    sk = builtin_skeleton()
    for pos in clips["walk"]:
        travel = np.linalg.norm(pos[-1, 0, [0, 2]] - pos[0, 0, [0, 2]])
        assert travel > 250, f"walk covered only {travel:.0f} cm in 128 frames"
        for toe in ("LeftToe", "RightToe"):
            frac, speed = _planted(pos, sk.index(toe))
            assert 0.3 < frac < 0.8, f"{toe} on the ground {frac:.0%} of a walk"
            assert speed < 5.0, f"{toe} slides at {speed:.1f} cm/s while on the ground"
        both_up = (pos[:, sk.index("LeftToe"), 1] > 2.0) & (pos[:, sk.index("RightToe"), 1] > 2.0)
        assert both_up.mean() < 0.1, "a walk has no flight phase"


def test_run_has_flight_and_planted_stance(clips):
    sk = builtin_skeleton()
    for pos in clips["run"]:
        speed = np.linalg.norm(pos[-1, 0, [0, 2]] - pos[0, 0, [0, 2]]) / (127 / FPS)
        assert speed > 200, f"run at {speed:.0f} cm/s"
        both_up = (pos[:, sk.index("LeftToe"), 1] > 2.0) & (pos[:, sk.index("RightToe"), 1] > 2.0)
        assert both_up.mean() > 0.1
        for toe in ("LeftToe", "RightToe"):
            frac, slide = _planted(pos, sk.index(toe))
            assert frac > 0.1 and slide < 5.0


def test_kinds_do_what_their_names_say(clips):
    sk = builtin_skeleton()
    head, hips = sk.index("Head"), 0
    for pos in clips["jump"]:
        assert pos[:, hips, 1].max() - np.median(pos[:, hips, 1]) > 10, "jump never leaves the ground"
        feet_y = pos[:, [sk.index("LeftToe"), sk.index("RightToe")], 1].min(1)
        assert feet_y.max() > 10
    for pos in clips["wave"]:
        hands = pos[:, [sk.index("LeftHand"), sk.index("RightHand")], 1].max(1)
        assert (hands > pos[:, head, 1]).mean() > 0.3, "the waving hand is not raised above the head"
    for pos in clips["squat"]:
        assert np.ptp(pos[:, hips, 1]) > 20
    for kind in ("squat", "idle", "wave"):
        for pos in clips[kind]:
            for toe in ("LeftToe", "RightToe"):
                frac, slide = _planted(pos, sk.index(toe))
                assert frac == 1.0 and slide < 1e-6, f"{kind}: feet move"


def test_same_seed_same_clip_other_seed_other_clip():
    a = generate_clip("walk", 40, FPS, np.random.default_rng(7))
    b = generate_clip("walk", 40, FPS, 7)
    c = generate_clip("walk", 40, FPS, 8)
    assert torch.equal(a.rotations, b.rotations) and torch.equal(a.root_positions, b.root_positions)
    assert not torch.allclose(a.root_positions, c.root_positions)
    assert a.rotations.shape == (40, builtin_skeleton().n_joints, 4)
    np.testing.assert_allclose(a.rotations.norm(dim=-1).numpy(), 1.0, atol=1e-5)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="kind"):
        generate_clip("dance", 10)
    with pytest.raises(ValueError, match="n_frames"):
        generate_clip("walk", 0)
    with pytest.raises(ValueError, match="kind"):
        write_dataset("unused", 2, kinds=["walk", "moonwalk"])


def test_write_dataset_round_trips_through_bvh_and_is_deterministic(tmp_path):
    paths = write_dataset(tmp_path / "a", n_clips=7, frames=24, seed=3)
    again = write_dataset(tmp_path / "b", n_clips=7, frames=24, seed=3)
    assert [p.name for p in paths] == [p.name for p in again]
    for p, q in zip(paths, again):
        assert p.read_bytes() == q.read_bytes()
    labels = json.loads((tmp_path / "a" / "labels.json").read_text())
    assert labels == {p.name: KINDS[i % len(KINDS)] for i, p in enumerate(paths)}
    for i, p in enumerate(paths):
        b = bvh_io.load(p)
        assert b.n_frames == 24 and abs(b.fps - 30.0) < 1e-3
        assert b.names == builtin_skeleton().names
        expected = _positions(generate_clip(labels[p.name], 24, 30.0, np.random.default_rng([3, i])))
        np.testing.assert_allclose(bvh_positions(b), expected, atol=0.05)   # 4 decimals in the file
    other = write_dataset(tmp_path / "c", n_clips=2, frames=24, seed=4)
    assert other[0].read_bytes() != paths[0].read_bytes()
