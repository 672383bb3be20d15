"""Known-answer tests for SinMDM's scorecard (modi.evaluation.scorecard): every expected value below is worked out by
hand from the definitions (docs/scorecard.md), not by calling the code under test."""
from __future__ import annotations

import dataclasses
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from modi.evaluation.features import FeatureConfig, FeatureExtractor, STGCN, make_windows
from modi.evaluation.scorecard import (
    HM_NORMALISERS,
    harmonic_mean,
    inter_diversity,
    intra_diversity,
    scorecard_metrics,
    sifid,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_sifid_is_the_frechet_distance_of_the_two_gaussian_fits():
    # 1-D: real {0, 2}: mean 1, variance 2 (unbiased); generated {1, 5}: mean 3, variance 8
    # d = (1 - 3)^2 + 2 + 8 - 2 sqrt(2 * 8) = 4 + 10 - 8 = 6
    assert sifid([[0.0], [2.0]], [[1.0], [5.0]]) == pytest.approx(6.0, rel=1e-12)
    # 2-D, diagonal covariances: the corners of a 2-square (mean (1, 1), variance 4/3 per axis, no correlation) and
    # the same corners scaled by 3 and shifted by 1 (mean (4, 4), variance 12): |(3, 3)|^2 + 2 (4/3 + 12 - 2 sqrt(16))
    real = np.array([[0, 0], [2, 0], [0, 2], [2, 2]], dtype=float)
    assert sifid(real, 3 * real + 1) == pytest.approx(18 + 2 * (4 / 3 + 12 - 8), rel=1e-10)
    # a motion against itself: 0
    assert sifid(real, real) == pytest.approx(0.0, abs=1e-12)


def test_inter_and_intra_diversity_are_mean_distances_over_all_pairs():
    # (0, 0), (3, 4), (6, 8): the pairs are 5, 10 and 5 apart
    assert inter_diversity([[0, 0], [3, 4], [6, 8]]) == pytest.approx(20 / 3, rel=1e-12)
    # sub-windows at 0.5, 2.5, 4.5 on a line: 2, 4, 2
    assert intra_diversity([[0.5], [2.5], [4.5]]) == pytest.approx(8 / 3, rel=1e-12)
    with pytest.raises(ValueError, match="at least 2"):
        inter_diversity([[1.0, 2.0]])
    with pytest.raises(ValueError, match="NaN"):
        intra_diversity([[0.0], [np.nan]])


def test_harmonic_mean_with_the_authors_normalisers():
    assert HM_NORMALISERS == (11.889, 1.67, 1.151)  # SinMDM issue #26
    # each score at half its normaliser: every normalised term is 0.5, and so is their harmonic mean
    assert harmonic_mean(11.889 / 2, 1.67 / 2, 1.151 / 2) == pytest.approx(0.5, rel=1e-12)
    # perfect SIFID (term 1), inter-diversity at its normaliser (1), half the allowed intra diff (0.5): 3 / (1 + 1 + 2)
    assert harmonic_mean(0.0, 1.67, 1.151 / 2) == pytest.approx(0.75, rel=1e-12)
    # SIFID 2.0, inter 2.0, diff 0.1 by the formula of issue #26
    s, v, d = (11.889 - 2.0) / 11.889, 2.0 / 1.67, (1.151 - 0.1) / 1.151
    assert harmonic_mean(2.0, 2.0, 0.1) == pytest.approx(3 / (1 / s + 1 / v + 1 / d), rel=1e-12)
    # at or past a normaliser, or no inter-diversity: 0, not a negative 'mean'
    assert harmonic_mean(11.889, 1.0, 0.1) == 0.0
    assert harmonic_mean(20.0, 1.0, 0.1) == 0.0
    assert harmonic_mean(1.0, 1.0, 2.0) == 0.0
    assert harmonic_mean(1.0, 0.0, 0.1) == 0.0
    assert harmonic_mean(1.0, 1.0, 0.5, normalisers=(2.0, 2.0, 1.0)) == pytest.approx(0.5, rel=1e-12)
    with pytest.raises(ValueError, match="three positive"):
        harmonic_mean(1.0, 1.0, 0.1, normalisers=(1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="non-negative"):
        harmonic_mean(-1.0, 1.0, 0.1)


class _StubExtractor:
    """A 'network' whose numbers can be followed by hand: a 2-frame window, the temporal feature vector of a frame is
    joint 0's x, a window's pooled feature is the mean of its frames' x."""

    config = SimpleNamespace(window=2, fps=30.0)

    def windows(self, clips, stride=None, tail=True):
        return np.concatenate([make_windows(c, 2, stride or 2, tail) for c in clips])

    def features(self, w):
        return w[:, :, 0, :1].mean(axis=1)

    def temporal_features(self, w):
        return w[:, :, 0, :1]


def _line(values) -> np.ndarray:
    clip = np.zeros((len(values), 1, 3))
    clip[:, 0, 0] = values
    return clip


def test_scorecard_windows_pooling_and_floor_by_hand():
    t = np.arange(6.0)
    src, a, b = _line(t), _line(2 * t), _line(t + 1)
    out = scorecard_metrics(_StubExtractor(), src, [a, b], sifid_stride=1, normalisers=(10.0, 3.0, 2.0))
    # SIFID samples (stride 1): source windows [0,1] [1,2] ... [4,5] -> {0,1,1,2,2,3,3,4,4,5}: mean 2.5, var 22.5/9.
    # 2t doubles them (mean 5, var 10): 2.5^2 + 2.5 + 10 - 2 sqrt(25) = 8.75; t + 1 shifts them: 1 + 2.5 + 2.5 - 5 = 1
    assert [r["sifid"] for r in out["per_sequence"]] == pytest.approx([8.75, 1.0], rel=1e-9)
    assert out["sifid"] == pytest.approx(4.875, rel=1e-9)
    # disjoint sub-windows: source 0.5 2.5 4.5 -> 8/3; 2t: 1 5 9 -> 16/3; t + 1: 1.5 3.5 5.5 -> 8/3
    assert out["intra_diversity_source"] == pytest.approx(8 / 3, rel=1e-12)
    assert [r["intra_diversity"] for r in out["per_sequence"]] == pytest.approx([16 / 3, 8 / 3], rel=1e-12)
    assert out["intra_diversity"] == pytest.approx(4.0, rel=1e-12)
    assert out["intra_diversity_diff"] == pytest.approx(4 / 3, rel=1e-12)
    # motion embeddings are the means of the sub-windows: 5 and 3.5
    assert out["inter_diversity"] == pytest.approx(1.5, rel=1e-12)
    s, v, d = (10 - 4.875) / 10, 1.5 / 3, (2 - 4 / 3) / 2
    assert out["harmonic_mean"] == pytest.approx(3 / (1 / s + 1 / v + 1 / d), rel=1e-9)
    # the source against itself: the floor, SIFID 0 and no intra difference; one file has no inter-diversity
    floor = scorecard_metrics(_StubExtractor(), src, [src], sifid_stride=1)
    assert floor["sifid"] == pytest.approx(0.0, abs=1e-12) and floor["intra_diversity_diff"] == 0.0
    assert floor["inter_diversity"] is None and floor["harmonic_mean"] is None
    with pytest.raises(ValueError, match=r"generated\[1\].*shorter than two 2-frame windows"):
        scorecard_metrics(_StubExtractor(), src, [a, _line(t[:3])])


# ------------------------------------------------------------------------------------ the command, on a tiny network


def _tiny_extractor(skeleton, path):
    cfg = FeatureConfig(joint_names=list(skeleton.names), parents=list(skeleton.parents), class_names=["a", "b"],
                        window=16, channels=[4], strides=[2], temporal_kernel=3, dropout=0.0, body_height=1.0)
    torch.manual_seed(0)
    FeatureExtractor(cfg, STGCN(cfg), np.zeros((6, 1, 1)), np.ones((6, 1, 1))).save(path)
    return cfg


def _renamed(m, prefix):
    sk = dataclasses.replace(m.skeleton, names=[prefix + n for n in m.skeleton.names])
    return dataclasses.replace(m, skeleton=sk)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from modi.data.procedural import generate_clip

    d = tmp_path_factory.mktemp("scorecard")
    src = generate_clip("wave", 90, 30.0, np.random.default_rng(0))
    src.save(d / "src.bvh")
    (d / "gen").mkdir()
    _renamed(src, "ns:").save(d / "gen" / "a_copy.bvh")  # another tool's export: namespaced joints
    rev = type(src)(src.skeleton, torch.flip(src.rotations, [0]), torch.flip(src.root_positions, [0]), src.fps)
    rev.save(d / "gen" / "b_reversed.bvh")
    _tiny_extractor(src.skeleton, d / "tiny.pt")
    return SimpleNamespace(dir=d, src=src)


def test_cli_single_adds_the_scorecard_for_a_folder_of_another_tools_files(scene, capsys):
    from modi.cli import main

    d = scene.dir
    out = d / "res.json"
    rc = main(["eval", "single", "--source", str(d / "src.bvh"), str(d / "gen"), "--features", str(d / "tiny.pt"),
               "--json", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "coverage" in printed and "SIFID" in printed and "harmonic mean" in printed
    res = json.loads(out.read_text())
    card = res["scorecard"]
    copy, rev = res["per_file"]
    assert copy["file"].endswith("a_copy.bvh") and copy["coverage"] == 1.0  # the existing figures stay
    assert copy["sifid"] == pytest.approx(0.0, abs=1e-6)  # the namespaced copy is the source itself
    assert rev["sifid"] > 1e-4 and card["inter_diversity"] > 0
    assert card["sifid"] == pytest.approx((copy["sifid"] + rev["sifid"]) / 2, rel=1e-9)
    assert card["intra_diversity_diff"] == pytest.approx(
        abs((copy["intra_diversity"] + rev["intra_diversity"]) / 2 - card["intra_diversity_source"]), abs=1e-12)
    assert card["normalisers"] == {"sifid": 11.889, "inter_diversity": 1.67, "intra_diversity_diff": 1.151}
    assert math.isfinite(card["harmonic_mean"]) and card["harmonic_mean"] >= 0


def test_positions_are_compared_in_the_sources_unit(scene):
    from modi.api.evaluation import evaluate_single

    src = scene.src
    sk = dataclasses.replace(src.skeleton, offsets=src.skeleton.offsets / 100)  # the source, in metres
    metres = type(src)(sk, src.rotations, src.root_positions / 100, src.fps, unit="metres")
    card = evaluate_single([metres], src, features=scene.dir / "tiny.pt")["scorecard"]
    assert card["sifid"] == pytest.approx(0.0, abs=1e-6) and card["intra_diversity_diff"] == pytest.approx(0, abs=1e-9)


def test_bad_input_is_one_line_and_exit_code_2(scene, tmp_path, capsys):
    from modi.cli import main
    from modi.core.skeleton import Skeleton

    d = scene.dir
    base = ["eval", "single", "--source", str(d / "src.bvh")]
    (tmp_path / "empty").mkdir()
    short = type(scene.src)(scene.src.skeleton, scene.src.rotations[:31], scene.src.root_positions[:31], 30.0)
    short.save(tmp_path / "short.bvh")
    sk = scene.src.skeleton
    other = Skeleton(["Other"] + list(sk.names[1:]), sk.parents, sk.offsets)
    _tiny_extractor(other, tmp_path / "other.pt")
    cases = [
        ([str(d / "gen"), "--features", str(tmp_path / "missing.pt")], "feature extractor not found"),
        ([str(d / "gen"), "--features", str(tmp_path / "other.pt")], "lacks 1 joint(s)"),
        ([str(tmp_path / "empty"), "--features", str(d / "tiny.pt")], "no .bvh files in the folder"),
        ([str(tmp_path / "short.bvh"), "--features", str(d / "tiny.pt")], "shorter than two 16-frame windows"),
        ([str(d / "gen"), "--features", str(d / "tiny.pt"), "--hm-norms", "1", "0", "1"], "argument --hm-norms"),
        ([str(d / "gen"), "--features", str(d / "tiny.pt"), "--sifid-stride", "0"], "argument --sifid-stride"),
    ]
    for argv, message in cases:
        assert main(base + argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, (argv, err)
