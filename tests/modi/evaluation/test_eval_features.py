"""The ST-GCN feature extractor: input pipeline known answers, a tiny learnable problem, save/load, CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from modi.errors import CheckpointError, UserError
from modi.evaluation.features import (
    FeatureConfig,
    STGCN,
    canonicalize,
    load_extractor,
    lr_pairs,
    make_windows,
    spatial_partitions,
    train_feature_extractor,
)

# A 6-joint toy body: root, spine, head, two arms hanging from the spine, one hip pair for the facing.
NAMES = ["Root", "Spine", "Head", "Arm_L", "Arm_R", "Hip_L", "Hip_R"]
PARENTS = [-1, 0, 1, 1, 1, 0, 0]
REST = np.array([[0, 100, 0], [0, 130, 0], [0, 160, 0], [20, 140, 0], [-20, 140, 0], [10, 95, 0], [-10, 95, 0]],
                dtype=np.float64)


def _clip(label: int, rng: np.random.Generator, frames: int = 48) -> np.ndarray:
    """Class 0 waves the left arm, class 1 bobs the whole body (a squat); random heading, place, speed, noise."""
    t = np.arange(frames) / 30.0
    pos = np.repeat(REST[None], frames, axis=0).copy()
    wave = 25 * np.sin(2 * np.pi * rng.uniform(1.0, 2.0) * t + rng.uniform(0, 6.3))
    if label == 0:
        pos[:, 3, 1] += wave
    else:
        pos[:, :5, 1] += 0.6 * wave[:, None]
    pos += rng.normal(scale=0.5, size=pos.shape)
    yaw = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return pos @ rot.T + np.array([rng.uniform(-300, 300), 0, rng.uniform(-300, 300)])


def _config(**kw) -> FeatureConfig:
    base = dict(joint_names=NAMES, parents=PARENTS, class_names=["wave", "squat"], window=32,
                body_height=160.0, pairs=lr_pairs(NAMES, PARENTS), channels=[8, 16], strides=[2, 2],
                temporal_kernel=5, dropout=0.0)
    base.update(kw)
    return FeatureConfig(**base)


def _windows(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    labels = np.arange(n) % 2
    return np.stack([make_windows(_clip(int(y), rng), 32, 100)[0] for y in labels]), labels


def test_lr_pairs_pick_the_pair_nearest_the_root():
    assert lr_pairs(NAMES, PARENTS) == [(5, 6)]
    mixamo = ["Hips", "LeftUpLeg", "LeftLeg", "RightUpLeg", "RightLeg", "Spine", "LeftArm", "RightArm"]
    assert lr_pairs(mixamo, [-1, 0, 1, 0, 3, 0, 5, 5]) == [(1, 3)]
    cmu = ["Hips", "LHipJoint", "RHipJoint", "LeftUpLeg", "RightUpLeg"]
    assert lr_pairs(cmu, [-1, 0, 0, 1, 2]) == [(1, 2)]
    assert lr_pairs(["Root", "A", "B"], [-1, 0, 0]) == []


def test_canonical_frame_removes_heading_and_position():
    rng = np.random.default_rng(0)
    w = np.stack([make_windows(_clip(0, rng), 32, 100)[0]])
    pairs = lr_pairs(NAMES, PARENTS)
    ref = canonicalize(w, 1, pairs, 160.0)
    yaw = 1.234
    c, s = np.cos(yaw), np.sin(yaw)
    moved = w @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + np.array([50.0, 0.0, -70.0])
    assert np.allclose(canonicalize(moved, 1, pairs, 160.0), ref, atol=1e-9)
    # the left hip ends up on +X (facing +Z), the root's mean ground point at the origin, unit = body height
    assert (ref[0, :, 5, 0] > ref[0, :, 6, 0]).all()
    assert np.allclose(ref[0, :, 0, [0, 2]].mean(axis=1), 0.0, atol=1e-9)
    assert ref[0, :, 2, 1].mean() == pytest.approx(160.0 / 160.0, abs=0.01)
    # Z-up data gives the same canonical windows as the Y-up original
    zup = w[..., [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    assert np.allclose(canonicalize(zup, 2, pairs, 160.0), ref, atol=1e-9)


def test_make_windows_covers_the_tail_and_pads_short_clips():
    clip = np.arange(10 * 2 * 3, dtype=float).reshape(10, 2, 3)
    w = make_windows(clip, 4, 4)  # starts 0, 4 and the tail-aligned 6 (frame value = 6 * start)
    assert [int(x[0, 0, 0]) for x in w] == [0, 24, 36]
    short = make_windows(clip[:3], 5, 1)
    assert short.shape == (1, 5, 2, 3) and np.array_equal(short[0, 3], clip[2]) and np.array_equal(short[0, 4], clip[2])


def test_partitions_are_normalised_neighbourhoods():
    A = spatial_partitions(PARENTS)
    assert A.shape == (3, 7, 7)
    assert torch.allclose(A.sum(dim=(0, 1)), torch.ones(7))
    assert A[1, 1, 3] > 0 and A[2, 3, 1] > 0 and A[1, 3, 1] == 0  # spine -> arm is "from nearer the root"


def test_extractor_learns_a_two_class_problem_and_survives_save_load(tmp_path: Path, one_torch_thread):
    torch.manual_seed(0)
    wtr, ltr = _windows(96, seed=1)
    wte, lte = _windows(40, seed=2)
    ext, hist = train_feature_extractor(wtr, ltr, _config(), wte, lte, epochs=6, batch_size=16, lr=1e-2,
                                        progress=False, seed=0)
    assert hist["val_top1"] >= 0.9, hist
    feats = ext.features(wte)
    assert feats.shape == (40, 16) and np.isfinite(feats).all()
    # the classes are separated in feature space too: nearest class mean classifies the held-out windows
    mu = np.stack([ext.features(wtr)[ltr == c].mean(0) for c in (0, 1)])
    nearest = np.linalg.norm(feats[:, None] - mu[None], axis=-1).argmin(1)
    assert (nearest == lte).mean() >= 0.9
    path = tmp_path / "f.pt"
    ext.save(path)
    again = load_extractor(path)
    assert again.config == ext.config
    assert np.allclose(again.features(wte), feats, atol=1e-6)
    assert again.info["val_top1"] == hist["val_top1"]


def test_features_ignore_joint_order_and_extra_joints_but_not_missing_ones():
    ext_model = STGCN(_config())
    from modi.evaluation.features import FeatureExtractor

    ext = FeatureExtractor(_config(), ext_model, np.zeros((6, 1, 7)), np.ones((6, 1, 7)))
    rng = np.random.default_rng(3)
    clip = _clip(0, rng)
    names = NAMES + ["Extra"]
    with_extra = np.concatenate([clip, clip[:, :1] + 5], axis=1)
    perm = [7, 2, 0, 1, 6, 5, 4, 3]
    a = ext.clip_positions(with_extra, names, 30.0)
    b = ext.clip_positions(with_extra[:, perm], [names[i] for i in perm], 30.0)
    assert np.array_equal(a, b)
    with pytest.raises(UserError, match="Arm_R"):
        ext.clip_positions(clip[:, :4], NAMES[:4], 30.0)
    half = ext.clip_positions(with_extra, names, 60.0)  # 48 frames at 60 fps -> 24 frames at 30 fps
    assert half.shape[0] == 24 and np.allclose(half[1], clip[2])


def test_load_rejects_foreign_files(tmp_path: Path):
    bad = tmp_path / "x.pt"
    torch.save({"hello": 1}, bad)
    with pytest.raises(CheckpointError, match="not a modi feature-extractor"):
        load_extractor(bad)
    (tmp_path / "y.pt").write_text("garbage")
    with pytest.raises(CheckpointError):
        load_extractor(tmp_path / "y.pt")
    with pytest.raises(CheckpointError, match="not found"):
        load_extractor(tmp_path / "none.pt")


def _labelled_folder(root: Path) -> None:
    """Procedural walk (label 0) and wave (label 1) clips in the Bandai layout (JSON beside each BVH)."""
    from modi.io import bvh as bvh_io
    from modi.data.procedural import generate_clip

    (root / "cfg").mkdir(parents=True)
    (root / "cfg" / "content_label.txt").write_text("walk\nwave\n")
    (root / "data").mkdir()
    for i in range(8):
        kind = ("walk", "wave")[i % 2]
        m = generate_clip(kind, 72, 30.0, np.random.default_rng([7, i]))
        bvh_io.save(m.to_bvh(), root / "data" / f"{kind}_{i}.bvh", precision=4)
        (root / "data" / f"{kind}_{i}.json").write_text(json.dumps({"content": i % 2}))


def test_cli_train_features_then_real_floor(tmp_path: Path, capsys, one_torch_thread):
    from modi.cli import main

    data = tmp_path / "set"
    _labelled_folder(data)
    out = tmp_path / "f.pt"
    rc = main(["eval", "train-features", str(data), "--out", str(out), "--window", "32", "--epochs", "2",
               "--stride", "8", "--batch-size", "16", "--json", str(tmp_path / "t.json")])
    assert rc == 0 and out.is_file()
    text = capsys.readouterr().out
    assert "held-out top-1" in text
    ext = load_extractor(out)
    assert ext.config.class_names == ["walk", "wave"]
    assert len(ext.info["heldout_files"]) == 2 and len(ext.info["train_files"]) == 6
    assert not set(ext.info["heldout_files"]) & set(ext.info["train_files"])
    rc = main(["eval", "real", str(data), "--features", str(out), "--stride", "8", "--json", str(tmp_path / "r.json"),
               "--md", str(tmp_path / "r.md")])
    assert rc == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    d = rep["distribution (held-out vs train)"]
    assert d["fid"] >= 0 and 0 <= d["precision"] <= 1 and 0 <= d["recall"] <= 1 and d["diversity"] > 0
    assert "foot_skating" in rep["plausibility (held-out clips)"]
    assert "| fid |" in (tmp_path / "r.md").read_text()

    # `eval gen` with a stand-in sampler (a MoDi checkpoint needs a trained model): procedural motions
    # of the same skeleton, sampled deterministically per seed as the real sampler promises
    from modi.api.generator import ModiGenerator
    from modi.data.procedural import generate_clip

    calls = []

    class FakeGenerator:
        def __init__(self, ckpt):
            self.path = ckpt

        def generate(self, n, seed=0, psi=1.0, ik=False):
            calls.append((self.path, n, seed, psi, ik))
            return [generate_clip(("walk", "wave")[i % 2], 40, 30.0, np.random.default_rng([seed, i]))
                    for i in range(n)]

    real_from_checkpoint = ModiGenerator.__dict__["from_checkpoint"]
    ModiGenerator.from_checkpoint = classmethod(lambda cls, ckpt, **kw: FakeGenerator(str(ckpt)))
    try:
        rc = main(["eval", "gen", "--ckpt", "x.ckpt", "--features", str(out), "--data", str(data), "--n", "12",
                   "--stride", "8", "--json", str(tmp_path / "g.json"), "--md", str(tmp_path / "g.md")])
    finally:
        ModiGenerator.from_checkpoint = real_from_checkpoint
    assert rc == 0 and calls == [("x.ckpt", 12, 0, 1.0, False)]
    rep = json.loads((tmp_path / "g.json").read_text())
    d = rep["distribution (generated vs real)"]
    assert d["n_fake"] == 12 and d["n_real"] > 12 and d["fid"] >= 0
    assert rep["plausibility (generated)"]["feet"] and "jitter" in rep["plausibility (real)"]


def test_cli_errors_are_one_line(tmp_path: Path, capsys):
    from modi.cli import main

    assert main(["eval", "train-features", str(tmp_path / "nowhere"), "--out", str(tmp_path / "f.pt")]) == 2
    assert "data folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["eval", "train-features", str(tmp_path / "empty"), "--out", str(tmp_path / "f.pt")]) == 2
    assert "no labelled BVH" in capsys.readouterr().err
    assert main(["eval", "real", str(tmp_path), "--features", str(tmp_path / "none.pt")]) == 2
    assert "not found" in capsys.readouterr().err
