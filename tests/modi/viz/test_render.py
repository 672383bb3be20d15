"""Stick-figure previews: GIF frame counts and sizes, layouts, contact highlighting, camera follow, CLI errors."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from modi.viz import render as render_mod
from modi.cli import main
from modi.errors import UserError
from modi.core.kinematics import forward_kinematics
from modi.data.procedural import builtin_skeleton, generate_clip, write_dataset
from modi.viz.render import foot_contacts, render_bvh, render_frames, render_positions

CONTACT_RGB = (225, 40, 40)


def _stick(n_frames: int, speed: float = 0.0) -> np.ndarray:
    """A 4-joint 'person' 170 units tall standing on y = 0, sliding along +x at ``speed`` units per frame."""
    base = np.array([[0, 90, 0], [0, 170, 0], [10, 0, 0], [-10, 0, 0]], dtype=float)
    pos = np.repeat(base[None], n_frames, axis=0)
    pos[:, :, 0] += speed * np.arange(n_frames)[:, None]
    pos[:, 1, 2] += 5 * np.sin(np.arange(n_frames))   # keep consecutive frames distinct
    return pos


STICK_PARENTS = [-1, 0, 0, 0]


def _gif(path):
    im = Image.open(path)
    assert im.format == "GIF"
    return im


def _rgb_frames(path) -> list[np.ndarray]:
    im = Image.open(path)
    out = []
    for i in range(im.n_frames):
        im.seek(i)
        out.append(np.asarray(im.convert("RGB")))
    return out


def test_single_gif_has_one_frame_per_pose_and_the_asked_size(tmp_path):
    out = render_positions([_stick(12)], STICK_PARENTS, tmp_path / "a.gif", fps=25, size=(96, 80))
    im = _gif(out)
    assert im.size == (96, 80) and im.n_frames == 12
    assert im.info.get("duration") == 40   # 1000 / 25 ms
    first = _rgb_frames(out)[0]
    assert (first != first[0, 0]).any(axis=-1).mean() > 0.01, "nothing drawn"


def test_grid_puts_motions_side_by_side_and_holds_short_ones(tmp_path):
    motions = [_stick(10), _stick(6), _stick(8)]
    out = render_positions(motions, STICK_PARENTS, tmp_path / "g.gif", size=(64, 48), titles=["a", "b", "c"])
    im = _gif(out)
    assert im.size == (128, 96) and im.n_frames == 10      # 2x2 grid, longest motion wins
    two = render_positions(motions[:2], STICK_PARENTS, tmp_path / "two.gif", size=(64, 48))
    assert _gif(two).size == (128, 48)


def test_grid_panels_do_not_draw_into_each_other():
    right = _stick(6)
    a = render_frames([_stick(6), right], STICK_PARENTS, size=(90, 70))
    lying = _stick(6)[:, [0, 2, 1, 3]] * np.array([3.0, 0.2, 3.0])   # a very different, wide figure on the left
    b = render_frames([lying, right], STICK_PARENTS, size=(90, 70))
    for fa, fb in zip(a, b):
        la, lb = np.asarray(fa), np.asarray(fb)
        assert np.array_equal(la[:, 90:], lb[:, 90:])
    assert not all(np.array_equal(np.asarray(fa)[:, :90], np.asarray(fb)[:, :90]) for fa, fb in zip(a, b))


def test_scene_layout_draws_every_character_in_one_image(tmp_path):
    a, b = _stick(5), _stick(5)
    b[..., 0] += 400
    frames = render_frames([a, b], STICK_PARENTS, size=(200, 150), layout="scene", azimuth=0.0, elevation=5.0)
    assert len(frames) == 5 and frames[0].size == (200, 150)
    rgb = np.asarray(frames[0].convert("RGB")).astype(int)
    cols = np.nonzero((np.ptp(rgb, axis=-1) > 40).any(0))[0]   # columns with coloured (not grey) pixels
    # two figures 400 units apart appear as two separate clusters of columns, left and right of the middle
    assert cols.min() < 100 < cols.max() and (np.diff(cols) > 10).any()


def test_camera_follows_the_root(tmp_path):
    pos = _stick(30, speed=60.0)   # walks ten body heights away
    frames = render_frames([pos], STICK_PARENTS, size=(120, 120), azimuth=0.0, elevation=10.0)
    for f in (frames[0], frames[-1]):
        rgb = np.asarray(f.convert("RGB")).astype(int)
        xs = np.nonzero(np.ptp(rgb, axis=-1) > 40)[1]   # coloured (character) pixels; the grid is grey
        assert len(xs) > 0 and 30 < xs.mean() < 90, "figure left the middle of the view"


def test_contacts_are_highlighted_only_when_given(tmp_path):
    pos = _stick(4)
    con = np.zeros((4, 4), bool)
    con[:, 2] = True
    with_c = render_positions([pos], STICK_PARENTS, tmp_path / "c.gif", size=(100, 100), contacts=[con])
    without = render_positions([pos], STICK_PARENTS, tmp_path / "n.gif", size=(100, 100))
    has = lambda f: bool((np.abs(f.astype(int) - CONTACT_RGB).sum(-1) < 10).any())   # noqa: E731
    assert all(has(f) for f in _rgb_frames(with_c))
    assert not any(has(f) for f in _rgb_frames(without))


def test_foot_contacts_from_height_and_speed():
    t = np.arange(20, dtype=float)
    pos = np.zeros((20, 3, 3))
    pos[:, 1, 1] = 170.0                       # head
    pos[:, 2, 0] = np.where(t < 10, 0.0, 40.0 * (t - 9))   # planted, then moving fast
    con = foot_contacts(pos, [0, 2], fps=30.0)
    assert con.shape == (20, 3)
    assert con[:, 0].all() and not con[:, 1].any()
    assert con[:9, 2].all() and not con[11:, 2].any()


def test_bad_outputs_and_inputs_are_user_errors(tmp_path, monkeypatch):
    with pytest.raises(UserError, match="gif or .mp4"):
        render_positions([_stick(3)], STICK_PARENTS, tmp_path / "x.png")
    monkeypatch.setattr(render_mod.shutil, "which", lambda name: None)
    with pytest.raises(UserError, match="ffmpeg"):
        render_positions([_stick(3)], STICK_PARENTS, tmp_path / "x.mp4")
    with pytest.raises(ValueError, match="parents"):
        render_positions([_stick(3)], [-1, 0], tmp_path / "x.gif")
    with pytest.raises(UserError, match="no such file"):
        render_bvh([tmp_path / "missing.bvh"], tmp_path / "x.gif")


def test_render_bvh_plays_in_real_time(tmp_path):
    (path,) = write_dataset(tmp_path, n_clips=1, frames=31, seed=1)   # 31 frames at 30 fps = 1 s
    assert _gif(render_bvh([path], tmp_path / "a.gif", fps=15, size=(64, 64))).n_frames == 16
    assert _gif(render_bvh([path], tmp_path / "b.gif", fps=30, size=(64, 64), max_frames=7)).n_frames == 7


def test_humanoid_preview_colours_limbs_and_marks_planted_feet(tmp_path):
    sk = builtin_skeleton()
    m = generate_clip("walk", 16, 30.0, 0)
    pos, _ = forward_kinematics(m.rotations.double(), torch.as_tensor(sk.offsets), sk.parents,
                                m.root_positions.double())
    pos = pos.numpy()
    feet = [sk.index(n) for n in ("LeftFoot", "LeftToe", "RightFoot", "RightToe")]
    con = foot_contacts(pos, feet, 30.0)
    assert con[:, feet].any() and not con[:, [sk.index("Head")]].any()
    frames = render_frames([pos], sk.parents, size=(160, 160), names=sk.names, contacts=[con])
    rgb = np.asarray(frames[0].convert("RGB")).astype(int)
    left, right = render_mod._CHAR_COLORS[0][1], render_mod._CHAR_COLORS[0][2]
    for colour in (left, right):
        assert (np.abs(rgb - colour).sum(-1) < 10).sum() > 5


def test_render_positions_writes_the_viewer_beside(tmp_path):
    motions = [_stick(12), _stick(8)]
    render_positions(motions, STICK_PARENTS, tmp_path / "a.gif", size=(64, 48), titles=["x", "y"], view="view.html")
    page = (tmp_path / "view.html").read_text(encoding="utf-8")
    assert '"title":"x"' in page and '"title":"y"' in page and '"frames":8' in page
    render_positions(motions, STICK_PARENTS, tmp_path / "sub.gif", size=(64, 48))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif", "sub.gif", "view.html"]


def test_cli_render_and_synth(tmp_path, capsys):
    out_dir = tmp_path / "synth"
    assert main(["synth", str(out_dir), "--n", "3", "--frames", "20", "--seed", "2", "--kinds", "walk,squat"]) == 0
    files = sorted(out_dir.glob("*.bvh"))
    assert [f.name for f in files] == ["0000_walk.bvh", "0001_squat.bvh", "0002_walk.bvh"]
    assert json.loads((out_dir / "labels.json").read_text())["0001_squat.bvh"] == "squat"

    gif = tmp_path / "two.gif"
    assert main(["render", str(files[0]), str(files[1]), str(gif), "--size", "64x48", "--max-frames", "9",
                 "--contacts"]) == 0
    im = _gif(gif)
    assert im.size == (128, 48) and im.n_frames == 9
    page = (tmp_path / "two.html").read_text(encoding="utf-8")  # the 3D viewer beside the GIF, full clips
    assert page.startswith("<!DOCTYPE html>") and '"title":"0001_squat"' in page and '"frames":20' in page
    assert main(["render", str(files[0]), str(tmp_path / "s.gif"), "--layout", "scene", "--size", "80x60",
                 "--no-view"]) == 0
    assert _gif(tmp_path / "s.gif").size == (80, 60) and not (tmp_path / "s.html").exists()

    capsys.readouterr()
    assert main(["render", str(tmp_path / "nope.bvh"), str(tmp_path / "x.gif")]) == 2
    assert "nope.bvh" in capsys.readouterr().err
    assert main(["render", str(files[0]), str(tmp_path / "x.avi")]) == 2
    assert main(["render", str(files[0])]) == 2
    assert main(["synth", str(tmp_path / "bad"), "--kinds", "walk,dance"]) == 2
    assert "dance" in capsys.readouterr().err
    assert main(["render", str(files[0]), str(gif), "--size", "big"]) == 2  # argparse's error, as one line
    assert "argument --size" in capsys.readouterr().err


def test_real_file_renders(shared_data, tmp_path):
    path = next(iter(sorted((shared_data / "bvh").rglob("*.bvh"))))
    out = render_bvh([path], tmp_path / "real.gif", size=(64, 64), max_frames=5, contacts=True)
    assert _gif(out).n_frames == 5
