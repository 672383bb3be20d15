"""Plausibility metrics (modi.evaluation.plausibility): known answers in physical units."""
from __future__ import annotations

import numpy as np
import pytest

from modi.evaluation.plausibility import aggregate, guess_feet, planted_heights, plausibility_metrics

FPS = 30.0
# A stick figure, Y up, centimetres: root, head, two ankles (8 cm up when planted), two toes (on the ground).
NAMES = ["Hips", "Head", "LeftFoot", "RightFoot", "LeftToe", "RightToe"]
REST = np.array([[0, 95, 0], [0, 170, 0], [10, 8, 0], [-10, 8, 0], [10, 0, 12], [-10, 0, 12]], dtype=float)
FEET = [2, 3, 4, 5]


def _still(frames: int = 60) -> np.ndarray:
    return np.repeat(REST[None], frames, axis=0).copy()


def test_feet_found_by_name():
    assert guess_feet(NAMES) == FEET
    with pytest.raises(ValueError, match="no foot joints"):
        guess_feet(["Hips", "Head"])


def test_standing_still_is_perfectly_plausible():
    m = plausibility_metrics(_still(), FPS, FEET)
    assert m["foot_skating"] == 0.0 and m["skating_ratio"] == 0.0
    assert m["floating"] == 0.0 and m["penetration"] == 0.0
    assert m["jitter"] == 0.0 and m["acceleration"] == 0.0
    assert m["contact_fraction"] == 1.0


def test_sliding_feet_skate_at_their_speed_in_units_per_second():
    p = _still()
    speed = 60.0  # cm/s along x: the whole body glides over the floor
    p[..., 0] += speed * np.arange(60)[:, None] / FPS
    m = plausibility_metrics(p, FPS, FEET)
    assert m["foot_skating"] == pytest.approx(speed, rel=1e-9)
    assert m["skating_ratio"] == 1.0  # 60 cm/s > 0.25 body heights/s (~42 cm/s)
    slow = _still()
    slow[..., 0] += 10.0 * np.arange(60)[:, None] / FPS
    assert plausibility_metrics(slow, FPS, FEET)["skating_ratio"] == 0.0


def test_floating_and_penetration_are_distances_to_the_ground():
    up = _still()
    up[..., 1] += 5.0
    m = plausibility_metrics(up, FPS, FEET)
    assert m["floating"] == pytest.approx(5.0) and m["penetration"] == 0.0
    down = _still()
    down[..., 1] -= 3.0
    m = plausibility_metrics(down, FPS, FEET)
    assert m["penetration"] == pytest.approx(3.0) and m["max_penetration"] == pytest.approx(3.0)
    assert m["floating"] == 0.0
    # a custom ground plane
    assert plausibility_metrics(up, FPS, FEET, ground=5.0)["floating"] == pytest.approx(0.0)


def test_jitter_is_the_third_derivative_in_units_per_second_cubed():
    p = _still(40)
    t = np.arange(40) / FPS
    a = 7.0
    p[..., 2] += a * t[:, None] ** 3  # jerk = 6a everywhere
    m = plausibility_metrics(p, FPS, FEET)
    assert m["jitter"] == pytest.approx(6 * a, rel=1e-6)
    noisy = p + np.random.default_rng(0).normal(scale=0.5, size=p.shape)
    assert plausibility_metrics(noisy, FPS, FEET)["jitter"] > 100 * m["jitter"]


def test_metrics_follow_the_unit_and_ratios_do_not():
    p = _still()
    p[..., 0] += 60.0 * np.arange(60)[:, None] / FPS
    p[:, 1, 1] += np.sin(np.arange(60))  # some head jitter
    cm = plausibility_metrics(p, FPS, FEET)
    m = plausibility_metrics(p / 100.0, FPS, FEET)  # the same motion in metres
    for key in ("foot_skating", "jitter", "acceleration", "floating", "body_height"):
        assert m[key] == pytest.approx(cm[key] / 100.0, rel=1e-9, abs=1e-12), key
    assert m["skating_ratio"] == cm["skating_ratio"] and m["contact_fraction"] == cm["contact_fraction"]


def test_procedural_walk_is_planted_and_a_treadmill_walk_skates():
    from modi.data.procedural import builtin_skeleton, generate_clip

    sk = builtin_skeleton()
    feet = sk.detect_feet(per_side=2)
    walk = generate_clip("walk", 90, FPS, np.random.default_rng(1))
    pos = walk.positions().numpy()
    planted = plausibility_metrics(pos, walk.fps, feet)
    treadmill = pos.copy()
    treadmill[..., [0, 2]] -= pos[:, :1, [0, 2]]  # root held in place: planted feet now slide backwards
    sliding = plausibility_metrics(treadmill, walk.fps, feet)
    assert sliding["foot_skating"] > 5 * planted["foot_skating"]
    assert planted["penetration"] < 1.0 and planted["floating"] < 3.0


def test_planted_heights_calibrate_contact_per_foot():
    clips = [_still(), _still()]
    assert planted_heights(clips, FEET) == pytest.approx([8.0, 8.0, 0.0, 0.0])
    up = _still()
    up[..., 1] += 20.0  # floating 20 cm: no foot is near its planted height -> no contact at all
    m = plausibility_metrics(up, FPS, FEET, foot_heights=planted_heights(clips, FEET))
    assert m["contact_fraction"] == 0.0 and m["floating"] == pytest.approx(20.0)


def test_aggregate_and_bad_input():
    a = plausibility_metrics(_still(), FPS, FEET)
    up = _still()
    up[..., 1] += 4.0
    b = plausibility_metrics(up, FPS, FEET)
    assert aggregate([a, b])["floating"] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="frames, joints, 3"):
        plausibility_metrics(np.zeros((10, 3)), FPS, FEET)
    with pytest.raises(ValueError, match="at least 4 frames"):
        plausibility_metrics(_still(3), FPS, FEET)
    with pytest.raises(ValueError, match="fps"):
        plausibility_metrics(_still(), 0.0, FEET)
    with pytest.raises(ValueError, match="feet"):
        plausibility_metrics(_still(), FPS, [9])
    with pytest.raises(ValueError, match="NaN"):
        plausibility_metrics(_still() * np.nan, FPS, FEET)


def test_cli_feet_match_modulo_namespace_prefix(tmp_path):
    """``--feet LeftFoot`` finds ``mixamorig:LeftFoot`` (exporters keep or drop the prefix): same figures as the full
    names; a bare name that fits two joints is refused."""
    import json
    import re

    from modi.cli import main

    assert main(["synth", str(tmp_path / "clips"), "--n", "1", "--seed", "3"]) == 0
    src = next((tmp_path / "clips").glob("*.bvh")).read_text()
    feet = [n for n in re.findall(r"JOINT (\S+)", src) if "Foot" in n or "Toe" in n][:2]
    assert len(feet) == 2
    pref = tmp_path / "prefixed.bvh"
    pref.write_text(re.sub(r"(ROOT|JOINT) (\S+)", r"\1 ns:\2", src))
    assert main(["eval", "plausibility", str(pref), "--feet", *feet, "--json", str(tmp_path / "a.json")]) == 0
    assert main(["eval", "plausibility", str(pref), "--feet", *[f"ns:{f}" for f in feet],
                 "--json", str(tmp_path / "b.json")]) == 0
    a, b = (json.loads((tmp_path / f"{k}.json").read_text())["mean"] for k in "ab")
    assert a == b and a["contact_fraction"] > 0
    two = tmp_path / "two.bvh"
    two.write_text(src.replace(f"JOINT {feet[0]}", f"JOINT x:{feet[0]}", 1)
                   .replace(f"JOINT {feet[1]}", f"JOINT y:{feet[0]}", 1))
    assert main(["eval", "plausibility", str(two), "--feet", feet[0]]) == 2
