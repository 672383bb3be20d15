"""One notion of a body (modi.core.body, issue 31), checked against oracles outside it: joint names mirrored by string
substitution, ``modi export positions`` for heights, GIF pixels for what is drawn and how big, Pillow's reading of
the GIF for its delays, and the page / glTF / GIF contact labels against each other."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from modi.core.body import Body, side_of
from modi.cli import main
from modi.io import bvh as bvh_io
from modi.core.kinematics import bvh_positions
from modi.viz import render as R

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _mirror(name: str) -> str:
    """The other side's name, by plain string substitution (the oracle for side detection)."""
    swaps = [("Left", "Right"), ("left", "right"), ("LEFT", "RIGHT")]
    for a, b in swaps:
        if a in name:
            return name.replace(a, b)
        if b in name:
            return name.replace(b, a)
    out = re.sub(r"(?<![A-Za-z])([LlRr])(?![a-z])", lambda m: {"L": "R", "R": "L", "l": "r", "r": "l"}[m.group(1)],
                 name.rsplit(":", 1)[-1])
    return name[: len(name) - len(name.rsplit(":", 1)[-1])] + out


@pytest.mark.parametrize("name,side", [
    ("LeftArm", 1), ("mixamorig:RightHandIndex1", 2), ("left_foot", 1), ("L_Knee", 1), ("R_Knee", 2),
    ("DEF_BN_Leg_L_11", 1), ("Leg_R_01", 2), ("Hand.L", 1), ("Hand.R", 2), ("Bip01 L Thigh", 1),
    ("Bip01_R_Calf", 2), ("l_hip", 1), ("r_hip", 2), ("knee_l", 1), ("knee_r", 2), ("lHip", 1), ("LHipJoint", 1),
    ("RThumb", 2), ("ThighL", 1), ("Hips", 0), ("LowerBack", 0), ("Bip01_Pelvis", 0), ("joint_Root", 0),
    ("Spine1", 0), ("Head", 0), ("BN_Nose_01", 0), ("Larynx", 0), ("Root", 0)])
def test_side_of_common_naming_schemes(name, side):
    assert side_of(name) == side


def test_sides_of_every_rig_in_shared_data_pair_up(shared_data):
    rigs = {}
    for p in sorted((shared_data / "bvh").rglob("*.bvh")):
        names = tuple(bvh_io.load(p).names)
        rigs.setdefault(names, p)
    assert len(rigs) >= 6, "expected the Bandai, Mixamo (x2), Xia, crab and elephant rigs"
    for names, p in rigs.items():
        sides = [side_of(n) for n in names]
        left = [n for n, s in zip(names, sides) if s == 1]
        assert left and len(left) == sides.count(2), (p.name, left)
        for n in left:  # every left joint has its mirror, and the mirror is right
            m = _mirror(n)
            assert m in names and side_of(m) == 2, (p.name, n, m)
        for n, s in zip(names, sides):
            if s == 0:
                assert _mirror(n) == n or _mirror(n) not in names, (p.name, n)  # a centre joint has no mirror


def _head_top_y(npy: Path, names: list[str]) -> float:
    """The issue's standing height: the largest head-top y of ``modi export positions``."""
    pos = np.load(npy)
    heads = [j for j, n in enumerate(names) if "head" in n.lower()]
    return float(pos[:, heads, 1].max())


@pytest.mark.parametrize("rel", ["ganimator/Joe/Walk-In-Circle.bvh",
                                 "bandai-namco-1/data/dataset-1_walk_normal_001.bvh"])
def test_printed_height_is_the_standing_height(shared_data, tmp_path, capsys, rel):
    src = shared_data / "bvh" / rel
    if not src.is_file():
        pytest.skip(f"{src} absent")
    assert main(["export", "positions", str(src), str(tmp_path / "p.npy"), "--names", str(tmp_path / "n.txt")]) == 0
    names = (tmp_path / "n.txt").read_text().split()
    truth = _head_top_y(tmp_path / "p.npy", names) * 0.01        # both rigs are centimetres
    capsys.readouterr()
    assert main(["export", "gltf", str(src), str(tmp_path / "o.glb")]) == 0
    printed = float(re.search(r"standing height ([\d.]+) m", capsys.readouterr().out).group(1))
    assert abs(printed - truth) <= 0.03 * truth, (printed, truth)
    if "Joe" in rel:
        assert abs(printed - 1.74) < 0.03


def test_bandai_floor_root_is_ground_and_other_rigs_have_none(shared_data):
    files = sorted((shared_data / "bvh" / "bandai-namco-1" / "data").glob("*.bvh"))[::25]
    others = sorted((shared_data / "bvh" / "ganimator").rglob("*.bvh"))
    if not files or not others:
        pytest.skip("Bandai or GANimator clips absent from ../shared/data")
    for p in files + others:
        b = bvh_io.load(p)
        body = Body.of(bvh_positions(b), b.parents, b.names)
        if p in files:
            assert body.ground == [0] and b.names[body.centre] == "Hips", p.name
            assert 0 not in body.bones() and 1 not in body.bones()
        else:
            assert body.ground == [] and body.centre == 0, p.name


def _floor_root_walk(T: int = 40) -> tuple[np.ndarray, list[int], list[str]]:
    """A floor root at the origin and a stick body (hips, head, two feet) walking 4 m away from it along +x."""
    x = np.linspace(0.0, 4.0, T)
    pos = np.zeros((T, 5, 3))
    pos[:, 1] = np.stack([x, np.full(T, 0.9), np.zeros(T)], -1)
    pos[:, 2] = pos[:, 1] + [0.0, 0.8, 0.0]
    pos[:, 3] = pos[:, 1] + [0.0, -0.9, 0.15]
    pos[:, 4] = pos[:, 1] + [0.0, -0.9, -0.15]
    return pos, [-1, 0, 1, 1, 1], ["Root", "Hips", "Head", "LeftFoot", "RightFoot"]


def _figure_pixels(frame: Image.Image, x0: int = 0, y0: int = 0, w: int | None = None, h: int | None = None):
    """(ys, xs) of the character-coloured pixels (bones and joints) of a palette frame, in one panel (less its
    legend line)."""
    a = np.asarray(frame)
    w = a.shape[1] if w is None else w
    h = a.shape[0] if h is None else h
    a = a[y0:y0 + h - 16, x0:x0 + w]   # not the bottom line: the side legend is written there in the same colours
    lo = len(R._BASE_COLORS)
    return np.nonzero((a >= lo) & (a < lo + 3 * len(R._CHAR_COLORS)))


def test_gif_draws_no_ground_root_bone_and_follows_the_body():
    pos, parents, names = _floor_root_walk()
    frames = R.render_frames(pos, parents, fps=30, size=(200, 200), names=names, azimuth=0.0, elevation=10.0)
    ys, xs = _figure_pixels(frames[-1])
    # the body is 4 m from the root: a root->hips line would run off the frame's left edge
    assert xs.min() > 40 and xs.max() < 160, (xs.min(), xs.max())
    assert (ys.max() - ys.min()) >= 0.4 * 200


def test_gif_panels_frame_each_figure_in_metres(shared_data, tmp_path):
    crab = shared_data / "bvh" / "ganimator" / "Crabnew" / "Crab-dance-long.bvh"   # metres
    joe = shared_data / "bvh" / "ganimator" / "Joe" / "Walk-In-Circle.bvh"          # centimetres
    if not crab.is_file() or not joe.is_file():
        pytest.skip("crab or Joe clip absent from ../shared/data")
    out = tmp_path / "two.gif"
    from modi.viz import view_pages

    with view_pages(False):
        R.render_bvh([crab, joe], out, fps=30, size=(160, 160), max_frames=4)
    im = Image.open(out)
    im.seek(2)
    frame = im.convert("P") if im.mode != "P" else im
    for k in range(2):
        ys, xs = _figure_pixels(frame, 160 * k, 0, 160, 160)
        assert len(ys) and (ys.max() - ys.min()) >= 0.4 * 160, (k, len(ys))


def test_gif_delays_keep_real_time(tmp_path):
    pos, parents, names = _floor_root_walk(30)
    out = R.render_positions(pos, parents, tmp_path / "t.gif", fps=30, size=(64, 64), names=names)
    im = Image.open(out)
    delays = []
    for k in range(im.n_frames):
        im.seek(k)
        delays.append(im.info["duration"])
    assert len(delays) == 30 and set(delays) == {30, 40}
    assert sum(delays) == 1000          # 30 frames at 30 fps: one second
    assert sorted(set(R.gif_delays(24, 24.0))) == [4, 5] and sum(R.gif_delays(24, 24.0)) == 100
    assert set(R.gif_delays(60, 60.0)) == {2}   # GIF cannot go faster than 2 cs a frame (browsers slow 0-1 cs)
