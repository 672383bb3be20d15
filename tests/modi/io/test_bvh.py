"""modi.io.bvh: parsing, writing, round trips on every shared file, malformations with line numbers, fuzzing."""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from modi.io import bvh as B
from modi.errors import BvhError
from modi.core.kinematics import bvh_positions

_DATA = Path(os.environ.get("MODI_SHARED_DATA", Path(__file__).resolve().parents[4] / "shared" / "data")) / "bvh"
ALL_FILES = sorted(str(p.relative_to(_DATA)) for p in _DATA.rglob("*.bvh")) if _DATA.is_dir() else []

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 1 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 1 0
    }
  }
  JOINT Left Leg
  {
    OFFSET 0.5 -1 0
    CHANNELS 2 Yrotation Xposition
  }
}
MOTION
Frames: 2
Frame Time: 0.04
0 0 0 0 0 0 0 0 0 0 0
1 2 3 4 5 6 7 8 9 10 11
"""
# 1-based line numbers of SMALL, used by the malformation tests
L_ROOT, L_SPINE, L_SPINE_OFFSET, L_SPINE_CHANNELS, L_SPINE_CLOSE = 2, 6, 8, 9, 14
L_LEG_CHANNELS, L_ROOT_CLOSE, L_MOTION, L_FRAMES, L_FTIME, L_F1, L_F2 = 18, 20, 21, 22, 23, 24, 25


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@lru_cache(maxsize=None)
def _load(rel: str) -> B.Bvh:
    return B.load(_DATA / rel)


@lru_cache(maxsize=None)
def _positions(rel: str) -> np.ndarray:
    return bvh_positions(_load(rel))


def _set_line(text: str, lineno: int, new: str) -> str:
    lines = text.split("\n")
    lines[lineno - 1] = new
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------- synthetic


def test_small_file_fields():
    b = B.loads(SMALL)
    assert b.names == ["Hips", "Spine", "Left Leg"]
    assert b.parents == [-1, 0, 0]
    assert b.channels[2] == ["Yrotation", "Xposition"]
    assert b.n_frames == 2 and b.n_channels == 11 and b.motion.shape == (2, 11)
    assert b.frame_time == pytest.approx(0.04) and b.fps == pytest.approx(25.0)
    np.testing.assert_array_equal(b.offsets, [[0, 0, 0], [0, 1, 0], [0.5, -1, 0]])
    assert set(b.end_sites) == {1}
    np.testing.assert_array_equal(b.end_sites[1], [0, 1, 0])
    # a partial rotation set gets the missing axes appended in XYZ order
    assert b.rotation_orders == ["ZXY", "ZXY", "YXZ"]
    eul = b.euler_degrees()
    np.testing.assert_array_equal(eul[1], [[4, 5, 6], [7, 8, 9], [10, 0, 0]])
    tr = b.local_translations()
    # root: its position channels; Spine: OFFSET; Left Leg: X from its channel, Y/Z from OFFSET
    np.testing.assert_array_equal(tr[1], [[1, 2, 3], [0, 1, 0], [11, -1, 0]])
    sk = b.skeleton()
    assert sk.names == b.names and sk.parents == b.parents and sk.rotation_orders == b.rotation_orders


def test_layout_variants_parse_identically(tmp_path):
    ref = B.loads(SMALL)
    variants = {
        "crlf": SMALL.replace("\n", "\r\n"),
        "cr": SMALL.replace("\n", "\r"),
        "tabs": SMALL.replace("  ", "\t"),
        "spaces": SMALL.replace("  ", "     ").replace("0 0 0 0", "0   0 0\t0"),
        "braces_inline": SMALL.replace("ROOT Hips\n{", "ROOT Hips {").replace("Spine\n  {", "Spine {"),
        "colon_split": SMALL.replace("Frames: 2", "Frames : 2").replace("Frame Time: 0.04", "Frame Time :  0.04"),
        "case": SMALL.replace("HIERARCHY", "hierarchy").replace("End Site", "end site"),
        "blank_lines": SMALL.replace("MOTION\n", "\nMOTION\n\n").replace("11\n", "11\n\n\n"),
        "bom": "\ufeff" + SMALL,
    }
    for name, text in variants.items():
        b = B.loads(text)
        assert b.names == ref.names, name
        np.testing.assert_array_equal(b.motion, ref.motion, err_msg=name)
        np.testing.assert_array_equal(b.offsets, ref.offsets, err_msg=name)
    p = tmp_path / "x.bvh"
    p.write_bytes(variants["crlf"].encode())
    for src in (p, str(p), p.read_bytes()):
        np.testing.assert_array_equal(B.load(src).motion, ref.motion)


# what other exporters add to the header: MoDi's released files name end effectors after "End Site"
ANNOTATED = {
    "modi_end_site": SMALL.replace("    End Site\n", "    End Site #name: Head\n"),
    "end_site_name": SMALL.replace("    End Site\n", "    End Site Spine_end\n"),
    "end_site_name_brace": SMALL.replace("    End Site\n    {", "    End Site Spine_end {"),
    "comments": SMALL.replace("ROOT Hips", "ROOT Hips # pelvis").replace("OFFSET 0 1 0", "OFFSET 0 1 0 #cm")
    .replace("Yrotation\n  JOINT", "Yrotation  # root channels\n  JOINT")
    .replace("  {\n    OFFSET 0.5", "  { # leg\n    OFFSET 0.5").replace("HIERARCHY\n", "HIERARCHY\n# by some tool\n")
    .replace("Frame Time: 0.04", "Frame Time: 0.04 # 25 fps"),
    "hash_inside_name": SMALL.replace("JOINT Left Leg", "JOINT Left#Leg"),
}


def test_exporter_annotations_parse_like_the_plain_file():
    ref = B.loads(SMALL)
    for name, text in ANNOTATED.items():
        b = B.loads(text)
        assert b.names == (["Hips", "Spine", "Left#Leg"] if name == "hash_inside_name" else ref.names), name
        assert b.parents == ref.parents and b.channels == ref.channels, name
        np.testing.assert_array_equal(b.offsets, ref.offsets, err_msg=name)
        np.testing.assert_array_equal(b.end_sites[1], ref.end_sites[1], err_msg=name)
        np.testing.assert_array_equal(b.motion, ref.motion, err_msg=name)
        assert b.frame_time == ref.frame_time, name


def test_frame_time_check_can_be_left_to_the_caller():
    text = _set_line(SMALL, L_FTIME, "Frame Time: 0")
    with pytest.raises(BvhError, match="positive"):
        B.loads(text)
    assert B.loads(text, check_frame_time=False).frame_time == 0.0
    with pytest.raises(BvhError, match="expected a number"):  # it must still be a number
        B.loads(_set_line(SMALL, L_FTIME, "Frame Time: x"), check_frame_time=False)


def test_save_load_round_trip_small(tmp_path):
    b = B.loads(SMALL)
    b.motion = b.motion + np.array([0.1234567] * 11)
    p = tmp_path / "out.bvh"
    B.save(b, p)
    r = B.load(p)
    assert r.names == b.names and r.parents == b.parents and r.channels == b.channels
    np.testing.assert_allclose(r.motion, b.motion, atol=1e-6)
    assert r.frame_time == pytest.approx(b.frame_time)
    np.testing.assert_array_equal(r.end_sites[1], b.end_sites[1])
    assert not list(tmp_path.glob("*.tmp*"))


def test_save_reorders_non_depth_first_joints():
    # topological but breadth-first order: root, A, B, A1 (child of A) -> written as root, A, A1, B
    b = B.Bvh(["r", "A", "B", "A1"], [-1, 0, 0, 1], np.eye(4, 3), [["Zrotation"], ["Xrotation"], ["Yrotation"],
              ["Zrotation"]], {}, 0.1, np.array([[1.0, 2.0, 3.0, 4.0]]))
    r = B.loads(B.dumps(b))
    assert r.names == ["r", "A", "A1", "B"]
    assert r.parents == [-1, 0, 1, 0]
    np.testing.assert_allclose(r.motion, [[1.0, 2.0, 4.0, 3.0]])
    np.testing.assert_allclose(bvh_positions(r)[:, [0, 1, 3, 2]], bvh_positions(b), atol=1e-9)


def test_save_rejects_bad_bvh(tmp_path):
    b = B.loads(SMALL)
    b.motion[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        B.save(b, tmp_path / "x.bvh")
    with pytest.raises(ValueError, match="motion must be"):
        B.Bvh(b.names, b.parents, b.offsets, b.channels, {}, 0.1, np.zeros((3, 5)))


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        B.load(tmp_path / "nope.bvh")


# ------------------------------------------------------------------------------------------- malformations

MALFORMED = {
    # name: (text, expected line, message fragment)
    "truncated_motion": ("\n".join(SMALL.split("\n")[:L_F1]) + "\n", L_F1 + 1, "truncated"),
    "too_few_values": (_set_line(SMALL, L_F2, "1 2 3 4 5 6 7 8 9 10"), L_F2, "10 values"),
    "too_many_values": (_set_line(SMALL, L_F1, "0 " * 12), L_F1, "12 values"),
    "extra_frame": (SMALL + "1 2 3 4 5 6 7 8 9 10 11\n", L_F2 + 1, "more frame lines"),
    "non_numeric": (_set_line(SMALL, L_F2, "1 2 3 4 five 6 7 8 9 10 11"), L_F2, "non-numeric"),
    "non_finite": (_set_line(SMALL, L_F1, "0 0 nan 0 0 0 0 0 0 0 0"), L_F1, "non-finite"),
    "zero_frames": (_set_line(SMALL, L_FRAMES, "Frames: 0"), L_FRAMES, "at least one frame"),
    "bad_frame_count": (_set_line(SMALL, L_FRAMES, "Frames: two"), L_FRAMES, "integer"),
    "bad_frame_time": (_set_line(SMALL, L_FTIME, "Frame Time: -1"), L_FTIME, "positive"),
    "missing_close_brace": (_set_line(SMALL, L_ROOT_CLOSE, ""), L_MOTION, "unbalanced braces"),
    "extra_close_brace": (_set_line(SMALL, L_ROOT_CLOSE, "}\n}"), L_ROOT_CLOSE + 1, "unbalanced braces"),
    "stray_open_brace": (_set_line(SMALL, L_SPINE_OFFSET, "    OFFSET 0 1 0 {"), L_SPINE_OFFSET, "unexpected '{'"),
    "unknown_channel": (_set_line(SMALL, L_SPINE_CHANNELS, "CHANNELS 3 Zrotation Wrotation Yrotation"),
                        L_SPINE_CHANNELS, "unknown channel name 'Wrotation'"),
    "repeated_channel": (_set_line(SMALL, L_SPINE_CHANNELS, "CHANNELS 3 Zrotation Zrotation Yrotation"),
                         L_SPINE_CHANNELS, "repeated"),
    "channel_count_mismatch": (_set_line(SMALL, L_SPINE_CHANNELS, "CHANNELS 3 Zrotation Xrotation"),
                               L_SPINE_CHANNELS, "lists only 2"),
    "channel_count_garbage": (_set_line(SMALL, L_SPINE_CHANNELS, "CHANNELS x Zrotation"), L_SPINE_CHANNELS, "integer"),
    "duplicate_joint": (_set_line(SMALL, L_SPINE, "  JOINT Hips"), L_SPINE, "duplicate joint name 'Hips'"),
    "missing_hierarchy": (_set_line(SMALL, 1, "HIERARCHYY"), 1, "expected HIERARCHY"),
    "missing_root": (_set_line(SMALL, L_ROOT, "JOINT Hips"), L_ROOT, "expected ROOT"),
    "missing_motion": (_set_line(SMALL, L_MOTION, "MOTON"), L_MOTION, "expected MOTION"),
    "no_motion_at_all": ("\n".join(SMALL.split("\n")[:L_ROOT_CLOSE]), L_ROOT_CLOSE, "end of file"),
    "short_offset": (_set_line(SMALL, L_SPINE_OFFSET, "OFFSET 0 1"), L_SPINE_OFFSET, "OFFSET of Spine"),
    "bad_offset": (_set_line(SMALL, L_SPINE_OFFSET, "OFFSET 0 one 0"), L_SPINE_OFFSET, "expected a number"),
    "inf_offset": (_set_line(SMALL, L_SPINE_OFFSET, "OFFSET 0 inf 0"), L_SPINE_OFFSET, "not finite"),
    "missing_offset": (_set_line(SMALL, L_SPINE_OFFSET, ""), L_SPINE, "no OFFSET"),
    "second_root": (_set_line(SMALL, L_ROOT_CLOSE, "}\nROOT B"), L_ROOT_CLOSE + 1, "more than one ROOT"),
    "nameless_joint": (_set_line(SMALL, L_SPINE, "  JOINT"), L_SPINE, "without a name"),
    "bad_end_site": (_set_line(SMALL, 10, "    End Sight"), 10, "End Site"),
    "end_site_name_no_brace": (_set_line(SMALL, 11, "OFFSET 0 1 0").replace("End Site\n", "End Site #name: Head\n"),
                               11, "expected '{' after End Site"),
    "end_site_closed_at_once": (_set_line(SMALL, 10, "    End Site Head }"), 10, "got '}'"),
    "comment_eats_offset": (_set_line(SMALL, L_SPINE_OFFSET, "OFFSET 0 1 #0"), L_SPINE_OFFSET, "OFFSET of Spine"),
    "comment_eats_channels": (_set_line(SMALL, L_SPINE_CHANNELS, "CHANNELS 3 Zrotation # Xrotation Yrotation"),
                              L_SPINE_CHANNELS, "lists only 1"),
    "comment_only_joint_name": (_set_line(SMALL, L_SPINE, "  JOINT # Spine"), L_SPINE, "without a name"),
    "offset_trailing_junk": (_set_line(SMALL, L_SPINE_OFFSET, "OFFSET 0 1 0 cm"), L_SPINE_OFFSET, "unexpected 'cm'"),
    "empty": ("", 1, "empty"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_raises_bvh_error_with_line(case):
    text, line, fragment = MALFORMED[case]
    with pytest.raises(BvhError) as info:
        B.loads(text)
    assert info.value.line == line, str(info.value)
    assert fragment in str(info.value)
    assert isinstance(info.value, ValueError)  # BvhError is also a ValueError for library callers


def test_error_names_the_file(tmp_path):
    p = tmp_path / "bad.bvh"
    p.write_text(MALFORMED["non_numeric"][0])
    with pytest.raises(BvhError) as info:
        B.load(p)
    assert info.value.path == str(p)
    assert str(info.value).startswith(f"{p}:{L_F2}:")


def test_crlf_error_lines_match_lf():
    text, line, _ = MALFORMED["unknown_channel"]
    with pytest.raises(BvhError) as info:
        B.loads(text.replace("\n", "\r\n"))
    assert info.value.line == line


# ------------------------------------------------------------------------------------------- fuzzing

_GARBAGE = st.one_of(
    st.sampled_from(["nan", "inf", "-", "1e999", "{", "}", "x", "", "JOINT", "End", "Site", "MOTION", "CHANNELS",
                     "OFFSET", "0", "-1", "1.5", "Frames:", "Frame", "Time:", "99999999999", "Xrotation",
                     "Wrotation", "\t", "ROOT", "HIERARCHY", "1_0", "0x10", "\x00", "é", "#", "#name:", "a#b"]),
    st.text(max_size=6),
)
_OPS = st.one_of(
    st.tuples(st.just("delete"), st.integers(0, 10**6)),
    st.tuples(st.just("duplicate"), st.integers(0, 10**6)),
    st.tuples(st.just("swap"), st.integers(0, 10**6), st.integers(0, 10**6)),
    st.tuples(st.just("token"), st.integers(0, 10**6), st.integers(0, 50), _GARBAGE),
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("brace"), st.integers(0, 10**6), st.sampled_from(["{", "}", "{ }", "} {"])),
    st.tuples(st.just("channel"), st.integers(0, 10**6), st.sampled_from(["Xrotation", "Wrotation", "xposition",
                                                                            "Zrotation Zrotation", "", "7"])),
    st.tuples(st.just("crlf")),
)


def _mutate(text: str, ops) -> str:
    for op in ops:
        lines = text.split("\n")
        n = len(lines)
        kind = op[0]
        if kind == "delete" and n:
            del lines[op[1] % n]
        elif kind == "duplicate" and n:
            i = op[1] % n
            lines.insert(i, lines[i])
        elif kind == "swap" and n:
            i, j = op[1] % n, op[2] % n
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "token" and n:
            i = op[1] % n
            toks = lines[i].split()
            if toks:
                toks[op[2] % len(toks)] = op[3]
            else:
                toks = [op[3]]
            lines[i] = " ".join(toks)
        elif kind == "truncate":
            text = text[: int(len(text) * op[1])]
            continue
        elif kind == "brace" and n:
            lines.insert(op[1] % n, op[2])
        elif kind == "channel":
            idx = [k for k, ln in enumerate(lines) if "CHANNELS" in ln]
            if idx:
                i = idx[op[1] % len(idx)]
                toks = lines[i].split()
                if len(toks) > 2:
                    toks[-1] = op[2]
                lines[i] = " ".join(toks)
        elif kind == "crlf":
            text = text.replace("\n", "\r\n")
            continue
        text = "\n".join(lines)
    return text


def _check_load_never_crashes(text: str) -> None:
    try:
        b = B.loads(text)
    except BvhError as exc:
        assert exc.line is None or exc.line >= 1
        return
    # whatever load accepts, save must write and load must read back the same
    assert b.motion.shape == (b.n_frames, b.n_channels)
    again = B.loads(B.dumps(b))
    assert again.names == b.names and again.parents == b.parents and again.channels == b.channels
    np.testing.assert_allclose(again.motion, b.motion, rtol=1e-9, atol=1e-6)


@settings(max_examples=200, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(_OPS, min_size=1, max_size=4))
def test_fuzz_synthetic_bvh_only_raises_bvh_error(ops):
    _check_load_never_crashes(_mutate(SMALL, ops))


@settings(max_examples=200, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.sampled_from(sorted(ANNOTATED)), ops=st.lists(_OPS, min_size=1, max_size=4))
def test_fuzz_annotated_bvh_only_raises_bvh_error(seed, ops):
    _check_load_never_crashes(_mutate(ANNOTATED[seed], ops))


@pytest.fixture(scope="module")
def small_real_text(shared_data) -> str:
    return (shared_data / "bvh" / "ganimator" / "Joe" / "Baseball-Milling-Idle-edited-keyframes.bvh").read_text()


@settings(max_examples=200, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(ops=st.lists(_OPS, min_size=1, max_size=4))
def test_fuzz_real_bvh_only_raises_bvh_error(small_real_text, ops):
    _check_load_never_crashes(_mutate(small_real_text, ops))


# ------------------------------------------------------------------------------------------- every shared file


def _height(pos: np.ndarray) -> float:
    return float(np.ptp(pos[0], axis=0).max())


@pytest.mark.parametrize("rel", ALL_FILES)
def test_shared_file_round_trip(shared_data, rel):
    b = _load(rel)
    assert b.n_frames > 0 and b.motion.shape == (b.n_frames, b.n_channels)
    r = B.loads(B.dumps(b))
    assert r.names == b.names and r.parents == b.parents and r.channels == b.channels
    assert abs(r.frame_time - b.frame_time) < 1e-8
    assert np.abs(r.motion - b.motion).max() < 1e-4
    np.testing.assert_allclose(r.offsets, b.offsets, atol=1e-6)
    p0, p1 = _positions(rel), bvh_positions(r)
    assert np.abs(p0 - p1).max() < 1e-4 * _height(p0)


@pytest.mark.parametrize("rel", ALL_FILES)
def test_shared_file_bone_lengths(shared_data, rel):
    """Bones whose translation is fixed keep their length in every frame, equal to the declared OFFSET's norm.

    (Some rigs animate bone translations — Bandai's Hips, a few stretchy Elephant bones — those are excluded.)
    """
    b = _load(rel)
    pos = _positions(rel)
    trans = b.local_translations()
    scale = _height(pos)
    fixed = np.ptp(trans, axis=0).max(axis=1) < 1e-6 * scale  # (J,) joints not translated over time
    fixed[0] = False
    assert fixed.sum() >= 0.75 * (b.n_joints - 1)
    j = np.nonzero(fixed)[0]
    p = np.array(b.parents)[j]
    lengths = np.linalg.norm(pos[:, j] - pos[:, p], axis=-1)  # (F, J')
    declared = np.linalg.norm(b.offsets[j], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(declared, lengths.shape), atol=1e-4 * scale)
    assert np.ptp(lengths, axis=0).max() < 1e-6 * scale


def test_bandai_files_share_one_skeleton(shared_data):
    rels = [r for r in ALL_FILES if r.startswith("bandai")]
    if not rels:
        pytest.skip("no Bandai clips")
    first = _load(rels[0])
    assert first.n_joints == 22 and first.names[:2] == ["joint_Root", "Hips"]
    assert all(c == ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]
               for c in first.channels)
    for r in rels[1:]:
        b = _load(r)
        assert b.names == first.names and b.parents == first.parents
        assert b.fps == pytest.approx(30.0, rel=1e-3)
