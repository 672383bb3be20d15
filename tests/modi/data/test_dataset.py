"""The windowed BVH dataset: split by file, windows, resampling, cache, normalisation, and `modi data info`."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from modi.data.dataset import DatasetConfig, build_dataset, find_bvh_files, split_files
from modi.errors import UserError


@pytest.fixture(scope="module")
def proc_dir(tmp_path_factory):
    """Six procedural clips of 100 frames at 30 fps and one of 200 frames at 60 fps."""
    from modi.data.procedural import write_dataset

    root = tmp_path_factory.mktemp("proc")
    write_dataset(root / "a", n_clips=6, frames=100, seed=1, fps=30.0)
    write_dataset(root / "b", n_clips=1, frames=200, seed=2, fps=60.0, kinds=["walk"])
    return root


def test_split_files_is_seeded_and_by_fraction():
    s = split_files(174, 0.2, seed=0)
    assert s.count("test") == 35 and s.count("train") == 139
    assert s == split_files(174, 0.2, seed=0)
    assert s != split_files(174, 0.2, seed=1)
    assert split_files(2, 0.2, 0).count("test") == 1  # at least one test file when possible
    assert split_files(1, 0.2, 0) == ["train"]
    assert split_files(10, 0.0, 0) == ["train"] * 10


def test_windows_split_and_layout(proc_dir, tmp_path):
    cfg = DatasetConfig(window=32, stride=16, test_fraction=0.3, seed=3)
    ds = build_dataset(proc_dir, cfg, cache_dir=tmp_path)
    assert not ds.from_cache
    assert len(ds.clips) == 7
    by_path = {c.path: c for c in ds.clips}
    # 100 frames at 30 fps: starts 0, 16, 32, 48, 64 -> 5 windows
    assert all(by_path[f"a/{p.name}"].n_windows == 5 for p in find_bvh_files(proc_dir / "a"))
    slow = by_path["b/0000_walk.bvh"]
    assert slow.source_fps == pytest.approx(60.0) and slow.source_frames == 200
    assert abs(slow.frames - 100) <= 1  # 3.3 s resampled to 30 fps
    J = ds.skeleton.n_joints
    E = J + 1 + len(ds.feet)
    assert ds.train.shape[1:] == (4, E, 32) and ds.test.shape[1:] == (4, E, 32)
    assert ds.train.shape[0] + ds.test.shape[0] == sum(c.n_windows for c in ds.clips)
    # no clip contributes windows to both splits, and the split agrees with the clip table
    train_clips = set(ds.clip_index_train.tolist())
    test_clips = set(ds.clip_index_test.tolist())
    assert train_clips.isdisjoint(test_clips) and test_clips
    assert all(ds.clips[i].split == "train" for i in train_clips)
    assert all(ds.clips[i].split == "test" for i in test_clips)
    # representation invariants: unit quaternions, centred start, binary contacts
    x = ds.train
    assert torch.allclose(x[:, :, :J].norm(dim=1), torch.ones(()), atol=1e-5)
    assert torch.all(x[:, 0, J, 0] == 0) and torch.all(x[:, 2, J, 0] == 0)
    cont = x[:, 0, J + 1:]
    assert torch.all((cont == 0) | (cont == 1))
    # normaliser: finite, contacts untouched
    y = ds.normalized("train")
    assert torch.isfinite(y).all()
    assert torch.equal(y[:, :, J + 1:], x[:, :, J + 1:])
    assert ds.hierarchy().levels[0].n_entities == E
    # a window decodes to the clip's own joint positions over its frames, moved to start at x = z = 0
    from modi.io import bvh
    from modi.data.dataset import motion_from_bvh

    k = int(torch.nonzero(ds.clip_index_train == ds.clip_index_train[-1])[0, 0]) + 1
    clip, start = ds.clips[int(ds.clip_index_train[k])], int(ds.window_start_train[k])
    motion = motion_from_bvh(bvh.load(proc_dir / clip.path)).resample(cfg.fps)
    ref = motion.positions()[start:start + 32]
    ref = ref - ref[:1, :1] * torch.tensor([1.0, 0.0, 1.0], dtype=ref.dtype)
    got = ds.representation.positions(ds.train[k].double())
    assert float((got - ref).abs().max()) < 1e-3 * ds.skeleton.height()


def test_cache_hit_and_invalidation(proc_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("MODI_CACHE", str(tmp_path / "envcache"))
    cfg = DatasetConfig(window=32, stride=16)
    a = build_dataset(proc_dir / "a", cfg)
    assert list((tmp_path / "envcache").glob("dataset-*.pt"))
    b = build_dataset(proc_dir / "a", cfg)
    assert b.from_cache and torch.equal(a.train, b.train) and torch.equal(a.test, b.test)
    assert b.skeleton.same_as(a.skeleton) and b.feet == a.feet
    torch.testing.assert_close(b.normalizer.std, a.normalizer.std)
    # another setting -> another key
    c = build_dataset(proc_dir / "a", DatasetConfig(window=32, stride=8))
    assert not c.from_cache and c.train.shape[0] > a.train.shape[0]
    # edited content -> rebuilt
    copy = tmp_path / "copy"
    copy.mkdir()
    for p in find_bvh_files(proc_dir / "a"):
        (copy / p.name).write_bytes(p.read_bytes())
    build_dataset(copy, cfg)
    assert build_dataset(copy, cfg).from_cache
    f = find_bvh_files(copy)[0]
    f.write_text(f.read_text().replace("Frame Time", "Frame  Time", 1))
    assert not build_dataset(copy, cfg).from_cache
    assert not build_dataset(copy, cfg, cache=False).from_cache


def test_dataset_errors(tmp_path):
    with pytest.raises(UserError, match="no .bvh"):
        build_dataset(tmp_path)
    with pytest.raises(UserError, match="no such directory"):
        build_dataset(tmp_path / "missing")
    with pytest.raises(UserError, match="window"):
        build_dataset(tmp_path, DatasetConfig(window=0))


def test_short_clips_give_no_training_windows(proc_dir, tmp_path):
    with pytest.raises(UserError, match="shorter than"):
        build_dataset(proc_dir / "a", DatasetConfig(window=500), cache=False)


def test_cli_data_info(proc_dir, tmp_path, capsys):
    from modi.cli import main

    assert main(["data", "info", str(proc_dir), "--window", "32", "--cache-dir", str(tmp_path), "-v"]) == 0
    out = capsys.readouterr().out
    assert "clips:       7" in out and "feet:        LeftToe, RightToe" in out
    assert "0000_walk.bvh" in out and "windows:" in out
    assert main(["data", "info", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such directory" in err
    with pytest.raises(SystemExit) as exc:
        main(["data", "info", "--help"])
    assert exc.value.code == 0
    assert "(default: 64)" in capsys.readouterr().out


def test_bandai_full_dataset(shared_data, tmp_path):
    root = shared_data / "bvh" / "bandai-namco-1"
    t0 = time.perf_counter()
    ds = build_dataset(root, cache_dir=tmp_path)
    elapsed = time.perf_counter() - t0
    assert len(ds.clips) == 174
    assert sum(c.split == "test" for c in ds.clips) == 35
    # all 22 joints kept; the joint_Root anchor rides on Hips, whose translation is the root trajectory
    assert ds.source_skeleton.n_joints == 22 and ds.skeleton.n_joints == 22
    assert [ds.skeleton.names[f] for f in ds.feet] == ["Toes_L", "Toes_R"]
    assert ds.train.shape[1:] == (4, 25, 64)
    assert ds.train.shape[0] > 4 * ds.test.shape[0] * 0.6
    assert torch.isfinite(ds.normalized("train")).all() and torch.isfinite(ds.normalized("test")).all()
    assert ds.hierarchy().edge_counts == [22, 11, 7, 2, 1]
    # walking covers ground: the root-motion entity's horizontal displacement is not all zero
    assert float(ds.train[:, [0, 2], 22].abs().sum()) > 0
    print(f"Bandai: {len(ds.clips)} clips, {ds.train.shape[0]}+{ds.test.shape[0]} windows in {elapsed:.1f} s")
    again = build_dataset(root, cache_dir=tmp_path)
    assert again.from_cache and torch.equal(again.train, ds.train)


def test_root_anchor_rule():
    """Only a root whose single child sits at the root is an anchor (Bandai's joint_Root once Hips' translation
    is the trajectory); a root with a real bone or with two children is not."""
    from modi.data.dataset import root_anchor
    from modi.core.skeleton import Skeleton

    def sk(parents, offsets):
        return Skeleton([f"j{i}" for i in range(len(parents))], parents, np.array(offsets, dtype=float))

    assert root_anchor(sk([-1, 0, 1], [[0, 0, 0], [0, 0, 0], [0, 5, 0]]))
    assert root_anchor(sk([-1, 0, 1], [[3, 90, 1], [0, 0, 0], [0, 5, 0]]))  # where the anchor stands is irrelevant
    assert not root_anchor(sk([-1, 0, 1], [[0, 0, 0], [0, 2, 0], [0, 5, 0]]))  # a real bone from the root
    assert not root_anchor(sk([-1, 0, 0], [[0, 0, 0], [0, 0, 0], [0, 5, 0]]))  # two children
    assert not root_anchor(sk([-1], [[0, 0, 0]]))
