"""Known-answer tests for GANimator's single-sequence metrics (modi.evaluation.single)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from modi.evaluation.single import (
    coverage,
    local_diversity,
    patched_nearest_neighbour,
    rotation_features,
    single_sequence_metrics,
    window_distances,
)


def _source(n: int = 240, joints: int = 6, seed: int = 0) -> torch.Tensor:
    """A smooth, non-repeating 'motion': per-joint rotations from random-walk rotation vectors -> (n, 9J)."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(scale=0.15, size=(n, joints, 3))  # ~ a brisk motion at 30 fps
    rotvec = np.cumsum(steps, axis=0)
    mats = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(n, joints, 3, 3)
    return rotation_features(torch.from_numpy(mats), "matrix")


def _brute_windows(g: np.ndarray, s: np.ndarray, T: int) -> np.ndarray:
    c = np.linalg.norm(g[:, None] - s[None], axis=-1)
    L, N = c.shape
    out = np.empty((L - T + 1, N - T + 1))
    for i in range(L - T + 1):
        for k in range(N - T + 1):
            out[i, k] = np.mean([c[i + t, k + t] for t in range(T)])
    return out


def _brute_pnn(g: np.ndarray, s: np.ndarray, tmin: int) -> float:
    """Appendix B's recursion written as the plain triple loop over (segment start, end, source start)."""
    c = np.linalg.norm(g[:, None] - s[None], axis=-1)
    L, N = c.shape
    G = np.full(L + 1, np.inf)
    G[0] = 0.0
    for i in range(tmin, L + 1):
        for l in range(0, i - tmin + 1):
            for k in range(0, N - (i - l) + 1):
                G[i] = min(G[i], G[l] + sum(c[l + t, k + t] for t in range(i - l)))
    return G[L] / L


def test_frame_distance_is_the_frobenius_norm_of_rotation_differences():
    theta = 0.7
    ident = np.broadcast_to(np.eye(3), (1, 2, 3, 3)).copy()
    rx = ident.copy()
    rx[0, 1] = Rotation.from_rotvec([theta, 0, 0]).as_matrix()
    full = window_distances(rotation_features(torch.from_numpy(ident), "matrix"),
                            rotation_features(torch.from_numpy(rx), "matrix"), 1)
    # |R - I|_F^2 = 4 (1 - cos theta) for any axis
    assert full.item() == pytest.approx(np.sqrt(4 * (1 - np.cos(theta))), rel=1e-12)
    # first two rows only (authors' 6-D): rotation about x leaves row 0 unchanged -> 2 (1 - cos theta)
    six = window_distances(rotation_features(torch.from_numpy(ident), "6d"),
                           rotation_features(torch.from_numpy(rx), "6d"), 1)
    assert six.item() == pytest.approx(np.sqrt(2 * (1 - np.cos(theta))), rel=1e-12)


def test_quaternion_input_matches_matrices():
    r = Rotation.random(30, random_state=2)
    q_xyzw = r.as_quat().reshape(10, 3, 4)
    q = torch.from_numpy(np.concatenate([q_xyzw[..., 3:], q_xyzw[..., :3]], axis=-1))  # (w, x, y, z)
    m = torch.from_numpy(r.as_matrix().reshape(10, 3, 3, 3))
    assert torch.allclose(rotation_features(q), rotation_features(m), atol=1e-12)


def test_window_table_and_pnn_match_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(3):
        L, N = int(rng.integers(14, 22)), int(rng.integers(9, 16))
        g, s = rng.normal(size=(L, 5)), rng.normal(size=(N, 5))
        assert np.allclose(window_distances(g, s, 4).numpy(), _brute_windows(g, s, 4), atol=1e-12)
        assert patched_nearest_neighbour(g, s, 4) == pytest.approx(_brute_pnn(g, s, 4), rel=1e-12)


def test_source_against_itself_full_coverage_zero_diversity():
    src = _source()
    res = single_sequence_metrics([src], src)
    assert res["coverage"] == 1.0
    assert res["global_diversity"] == pytest.approx(0.0, abs=1e-6)
    assert res["local_diversity"] == pytest.approx(0.0, abs=1e-6)


def test_reordered_segments_have_zero_pnn_only_when_segments_are_long_enough():
    src = _source(240)
    swapped = torch.cat([src[120:], src[:120]])  # two 120-frame segments of the source
    assert patched_nearest_neighbour(swapped, src, 30) == pytest.approx(0.0, abs=1e-6)
    chopped = torch.cat([src[i : i + 20] for i in (200, 40, 120, 0, 160, 80, 220, 20, 180, 60, 140, 100)])
    assert patched_nearest_neighbour(chopped, src, 30) > 0.05  # 20-frame pieces cannot be copied whole
    assert patched_nearest_neighbour(chopped, src, 20) == pytest.approx(0.0, abs=1e-6)


def test_reversed_or_shuffled_source_covers_less():
    src = _source(240)
    full = coverage(src, src)
    rev = coverage(torch.flip(src, [0]), src)
    rng = np.random.default_rng(4)
    order = rng.permutation(24)
    shuffled = torch.cat([src[10 * i : 10 * i + 10] for i in order])
    shuf = coverage(shuffled, src)
    assert full == 1.0
    assert rev < 0.5 and shuf < 0.5
    assert local_diversity(shuffled, src) > local_diversity(src, src) + 0.05


def test_threshold_is_applied_to_the_per_frame_mean():
    src = _source(100, joints=1)
    # a generated copy offset by a constant rotation of angle a on the one joint: every frame is |R - QR|_F
    # = sqrt(4 (1 - cos a)) away, so coverage flips exactly where that crosses the threshold
    a = 2 * np.arcsin(1.0 / (2 * np.sqrt(2)))  # gives distance exactly 1.0
    q = Rotation.from_rotvec([0, 0, a]).as_matrix()
    mats = src.reshape(100, 1, 3, 3).numpy()
    gen = rotation_features(torch.from_numpy(q @ mats), "matrix")
    assert coverage(gen, src, threshold=1.0 + 1e-6) == 1.0
    assert coverage(gen, src, threshold=1.0 - 1e-6) < 1.0


def test_metrics_invariant_to_order_of_generated_sequences():
    src = _source(150)
    rng = np.random.default_rng(5)
    gens = [torch.cat([src[a : a + 45] for a in rng.integers(0, 105, size=3)]) + 0.01 * i for i in range(5)]
    gens.append(_source(120, seed=9))  # different length: processed in its own batch
    r1 = single_sequence_metrics(gens, src, batch_elements=2 * 135 * 150)
    perm = [4, 2, 5, 0, 3, 1]
    r2 = single_sequence_metrics([gens[i] for i in perm], src)
    for key in ("coverage", "global_diversity", "local_diversity"):
        assert r2[key] == pytest.approx(r1[key], rel=1e-12)
    for j, i in enumerate(perm):
        assert r2["per_sequence"][j] == pytest.approx(r1["per_sequence"][i], rel=1e-12)


def test_bad_input_is_rejected_clearly():
    src = _source(100)
    with pytest.raises(ValueError, match="fewer than"):
        coverage(src[:10], src)
    with pytest.raises(ValueError, match="differ in size"):
        coverage(src[:, :9], src)
    with pytest.raises(ValueError, match="quaternions or"):
        rotation_features(torch.zeros(5, 3, 5))
    with pytest.raises(ValueError, match="representation"):
        rotation_features(torch.zeros(5, 3, 3, 3), "euler")


def test_cli_single_writes_means_and_per_file_values(tmp_path, capsys):
    import json

    from modi.cli import main
    from modi.data.procedural import generate_clip

    src = generate_clip("wave", 120, 30.0, np.random.default_rng(0))
    src.save(tmp_path / "src.bvh")
    src.save(tmp_path / "copy.bvh")
    rev = type(src)(src.skeleton, torch.flip(src.rotations, [0]), torch.flip(src.root_positions, [0]), src.fps)
    rev.save(tmp_path / "rev.bvh")
    out = tmp_path / "single.json"
    rc = main(["eval", "single", "--source", str(tmp_path / "src.bvh"), str(tmp_path / "copy.bvh"),
               str(tmp_path / "rev.bvh"), "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    assert set(res) >= {"coverage", "global_diversity", "local_diversity", "per_file"}
    copy, reverse = res["per_file"]
    assert copy["coverage"] == 1.0 and copy["global_diversity"] == pytest.approx(0.0, abs=1e-3)
    assert reverse["global_diversity"] > copy["global_diversity"]
    assert res["coverage"] == pytest.approx((copy["coverage"] + reverse["coverage"]) / 2)
    assert "coverage" in capsys.readouterr().out
    # a generated file shorter than the window is one clear error, not a traceback
    short = type(src)(src.skeleton, src.rotations[:20], src.root_positions[:20], src.fps)
    short.save(tmp_path / "short.bvh")
    assert main(["eval", "single", "--source", str(tmp_path / "src.bvh"), str(tmp_path / "short.bvh")]) == 2
    assert "fewer than the 30-frame window" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------- files from other tools
# A Mixamo-like rig with fingers and a head-top (dropped by GANimator's joint reduction) and a namespace prefix,
# and copies of it as other tools write them: prefix dropped, siblings reordered, a wrong Frame Time.

_RIG = [("Hips", -1), ("Spine", 0), ("Neck", 1), ("Head", 2), ("HeadTop_End", 3), ("LeftArm", 1), ("LeftHand", 5),
        ("LeftHandIndex1", 6), ("LeftHandIndex2", 7), ("RightArm", 1), ("RightHand", 9), ("RightHandThumb1", 10),
        ("LeftUpLeg", 0), ("LeftLeg", 12), ("LeftFoot", 13), ("RightUpLeg", 0), ("RightLeg", 15), ("RightFoot", 16)]
_REDUCED = [n for n, _ in _RIG if n not in ("HeadTop_End", "LeftHandIndex1", "LeftHandIndex2", "RightHandThumb1")]


def _rig_bvh(frames: int = 240, fps: float = 60.0, seed: int = 0):
    """Smooth, non-periodic Euler curves on every joint (root also translates), namespaced 'mixamorig:'."""
    from modi.io.bvh import Bvh

    rng = np.random.default_rng(seed)
    J = len(_RIG)
    t = np.arange(frames)[:, None] / fps
    freq, phase = rng.uniform(0.2, 1.5, size=(1, 3 * J)), rng.uniform(0, 2 * np.pi, size=(1, 3 * J))
    rot = 40.0 * np.sin(2 * np.pi * freq * t + phase) + 15.0 * np.sin(2 * np.pi * 1.7 * freq * t + 2 * phase)
    root = np.concatenate([np.cumsum(rng.normal(size=(frames, 1)), 0), 90 + 3 * np.sin(3 * t),
                           np.cumsum(rng.normal(size=(frames, 1)), 0)], axis=1)
    offsets = rng.uniform(-10, 10, size=(J, 3))
    offsets[0] = [0, 90, 0]
    channels = [["Xposition", "Yposition", "Zposition"] if j == 0 else [] for j in range(J)]
    channels = [c + ["Zrotation", "Xrotation", "Yrotation"] for c in channels]
    return Bvh([f"mixamorig:{n}" for n, _ in _RIG], [p for _, p in _RIG], offsets, channels, {},
               1.0 / fps, np.concatenate([root, rot], axis=1))


def _as_other_tool_writes_it(b, prefix: str = "", drop: tuple[str, ...] = ()):
    """The same motion with the namespace prefix replaced, the legs listed before the spine (sibling order) and
    the joints in ``drop`` (leaves) removed."""
    from modi.io.bvh import Bvh
    from modi.evaluation.single import bare_name

    names = [bare_name(n) for n in b.names]
    legs = [j for j, n in enumerate(names) if "Leg" in n or "Foot" in n]
    order = [0] + legs + [j for j in range(1, len(names)) if j not in legs and names[j] not in drop]
    starts = b.channel_starts
    cols = [starts[j] + k for j in order for k in range(len(b.channels[j]))]
    return Bvh([prefix + names[j] for j in order], [-1 if j == 0 else order.index(b.parents[j]) for j in order],
               b.offsets[order], [b.channels[j] for j in order], {}, b.frame_time, b.motion[:, cols])


def _run_single(capsys, *argv):
    from modi.cli import main

    rc = main(["eval", "single", *map(str, argv)])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_bare_name_drops_any_namespace_prefix():
    from modi.evaluation.single import bare_name

    assert bare_name("mixamorig:Hips") == bare_name("mixamorig7:Hips") == bare_name("Hips") == "Hips"


_OPTIONS = [[], ["--joints", "all"], ["--fps", "60"], ["--fps", "24"], ["--representation", "matrix"],
            ["--gen-fps", "60"], ["--joints", "all", "--fps", "60", "--representation", "matrix"]]


@pytest.mark.parametrize("options", _OPTIONS, ids=lambda o: " ".join(o) or "defaults")
def test_source_against_itself_under_every_option(tmp_path, capsys, options):
    import json

    from modi.io.bvh import save

    save(_rig_bvh(), tmp_path / "src.bvh")
    rc, out, err = _run_single(capsys, tmp_path / "src.bvh", "--source", tmp_path / "src.bvh",
                               "--json", tmp_path / "r.json", *options)
    assert rc == 0, err
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["coverage"] == 1.0
    assert res["global_diversity"] == pytest.approx(0.0, abs=1e-6)
    assert res["local_diversity"] == pytest.approx(0.0, abs=1e-6)
    joints = [n for n, _ in _RIG] if "all" in options else _REDUCED
    fps = float(options[options.index("--fps") + 1]) if "--fps" in options else 30.0
    p = res["protocol"]
    assert p["joint_names"] == joints and p["n_joints"] == len(joints)
    assert p["joints"] == ("all" if "all" in options else "reduced") and p["fps"] == fps
    assert p["n_samples"] == 1 and p["sample_frames"] == p["source_frames"] == int(239 * fps / 60) + 1
    assert f"scoring {len(joints)} joints" in out and " ".join(joints) in out


@pytest.mark.parametrize("prefix,drop", [("", ()), ("mixamorig7:", ()),
                                         ("", ("HeadTop_End", "LeftHandIndex2", "LeftHandIndex1", "RightHandThumb1"))])
@pytest.mark.parametrize("joints", ["reduced", "all"])
def test_renamed_reordered_wrong_rate_copy_scores_exactly_like_the_source(tmp_path, capsys, prefix, drop, joints):
    import json

    from modi.io.bvh import dumps, save

    src = _rig_bvh()
    save(src, tmp_path / "src.bvh")
    text = dumps(_as_other_tool_writes_it(src, prefix, drop))
    (tmp_path / "copy.bvh").write_text(text.replace("Frame Time: 0.01666667", "Frame Time: 1.00000000"))
    # a second, different generated file so the means are not trivially 1 / 0
    other = _rig_bvh(seed=1)
    other.names = src.names
    save(other, tmp_path / "other.bvh")
    results = {}
    # a copy without fingers shares only the reduced joints, whatever --joints says: the reference is then the
    # source scored on those
    for gen, option in (("src", "reduced" if drop else joints), ("copy", joints)):
        rc, out, err = _run_single(capsys, tmp_path / f"{gen}.bvh", tmp_path / "other.bvh", "--source",
                                 tmp_path / "src.bvh", "--gen-fps", "60", "--joints", option,
                                 "--json", tmp_path / f"{gen}.json")
        assert rc == 0, err
        results[gen] = json.loads((tmp_path / f"{gen}.json").read_text())
    assert ("not scored: HeadTop_End LeftHandIndex1" in out) == (bool(drop) and joints == "all")
    a, b = results["src"], results["copy"]
    for key in ("coverage", "global_diversity", "local_diversity"):
        assert a[key] == b[key]
        assert a["per_file"][0][key] == b["per_file"][0][key]
    assert a["per_file"][0]["coverage"] == 1.0
    expected = _REDUCED if (joints == "reduced" or drop) else [n for n, _ in _RIG]
    assert b["protocol"]["joint_names"] == expected


@pytest.mark.parametrize("frame_time", ["1.00000000", "0.5", "0", "-0.03"])
def test_implausible_frame_time_names_the_option(tmp_path, capsys, frame_time):
    from modi.io.bvh import dumps, save

    src = _rig_bvh(120)
    save(src, tmp_path / "src.bvh")
    text = dumps(_as_other_tool_writes_it(src)).replace("Frame Time: 0.01666667", f"Frame Time: {frame_time}")
    (tmp_path / "gen.bvh").write_text(text)
    rc, _, err = _run_single(capsys, tmp_path / "gen.bvh", "--source", tmp_path / "src.bvh")
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("modi: error:") and "--gen-fps" in lines[0], err
    assert "Traceback" not in err
    assert _run_single(capsys, tmp_path / "gen.bvh", "--source", tmp_path / "src.bvh", "--gen-fps", "60")[0] == 0
    for bad in ("0", "1", "nan", "inf"):
        rc, _, err = _run_single(capsys, tmp_path / "gen.bvh", "--source", tmp_path / "src.bvh", "--gen-fps", bad)
        assert rc == 2 and "--gen-fps" in err and len(err.strip().splitlines()) == 1, err



def test_reports_never_overwrite_an_input_and_numbers_are_checked_while_parsing(tmp_path, capsys):
    from modi.io.bvh import save

    save(_rig_bvh(120), tmp_path / "src.bvh")
    save(_rig_bvh(120, seed=1), tmp_path / "gen.bvh")
    before = {n: (tmp_path / n).read_bytes() for n in ("src.bvh", "gen.bvh")}
    for opt, target in (("--json", "src.bvh"), ("--md", "gen.bvh"), ("--json", "gen.bvh")):
        rc, _, err = _run_single(capsys, tmp_path / "gen.bvh", "--source", tmp_path / "src.bvh", opt, tmp_path / target)
        lines = err.strip().splitlines()
        assert rc == 2 and len(lines) == 1 and f"{opt} {tmp_path / target} is the input file" in lines[0], err
    assert {n: (tmp_path / n).read_bytes() for n in before} == before
    for opt, bad, says in (("--fps", "5000", "in (2, 1000]"), ("--fps", "2", "in (2, 1000]"),
                           ("--gen-fps", "1e9", "in (2, 1000]"), ("--window", "0", "between 1 and"),
                           ("--min-segment", "-3", "between 1 and"), ("--local-window", "1.5", "integer"),
                           ("--json", str(tmp_path), "is a folder")):
        rc, _, err = _run_single(capsys, tmp_path / "gen.bvh", "--source", tmp_path / "src.bvh", opt, bad)
        assert rc == 2 and f"argument {opt}" in err and says in err and len(err.strip().splitlines()) == 1, err


def test_a_different_rig_is_rejected_by_joint_parent(tmp_path, capsys):
    from modi.io.bvh import save

    src = _rig_bvh(120)
    save(src, tmp_path / "src.bvh")
    moved = _rig_bvh(120)
    moved.parents[[n for n, _ in _RIG].index("LeftArm")] = 2  # under Neck, not Spine: same names, another rig
    save(moved, tmp_path / "gen.bvh")
    rc, _, err = _run_single(capsys, tmp_path / "gen.bvh", "--source", tmp_path / "src.bvh")
    assert rc == 2 and "'LeftArm' hangs from 'Neck'" in err and "Traceback" not in err


def test_the_output_of_ganimator_generate_scores_against_its_source(tmp_path, capsys, shared_data):
    """``modi ganimator generate`` writes the reduced, 30 fps rig without the ``mixamorig7:`` prefix: reproduce its
    writer on the source itself, which must then cover the source with (almost) no diversity."""
    import json

    from modi.models.ganimator.config import GanimatorConfig
    from modi.models.ganimator.data import features_to_motion, load_sequence
    from modi.models.ganimator.generate import write_bvh

    source = shared_data / "bvh" / "ganimator" / "Joe" / "Salsa-Dancing-6.bvh"
    seq = load_sequence(source, GanimatorConfig())
    quats, root, _ = features_to_motion(seq.features, seq.n_joints, seq.root_start, sixd=seq.sixd)
    write_bvh(seq, quats, root, tmp_path / "gen.bvh")
    assert not any(":" in n for n in seq.skeleton.names)
    rc, out, err = _run_single(capsys, tmp_path / "gen.bvh", "--source", source, "--json", tmp_path / "r.json")
    assert rc == 0, err
    assert "scoring 24 joints (reduced; of the source's 65) at 30 fps" in out
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["coverage"] == 1.0 and res["global_diversity"] < 1e-3, res
