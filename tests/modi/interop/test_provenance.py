"""What an import records about its source (``modi.interop.provenance``), and how the GANimator import settles a
contact label that float32 rounding decides, on synthetic data (the released-code tests cover real runs)."""
from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from modi.cli.commands.info import _imported_text
from modi.core.skeleton import Skeleton
from modi.interop import ganimator_released as G
from modi.interop import provenance as P
from modi.models.ganimator.data import Sequence as Clip


def _clips(frames: np.ndarray, window: int, stride: int) -> list[dict]:
    """Their split_to_fixed_length_clips' windows of one animation (only the arrays the stride is read from)."""
    out = []
    for s in range(0, frames.shape[0] - window + 1, stride):
        f = frames[s:s + window]
        out.append({"rot_edge_no_root": f[:, :8].reshape(window, 2, 4), "pos_root": f[:, 8:11]})
    return out


def test_window_and_stride_from_their_data():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(200, 11)), rng.normal(size=(100, 11))
    assert P.window_and_stride(_clips(a, 64, 32) + _clips(b, 64, 32)) == (64, 32)
    assert P.window_and_stride(_clips(a, 16, 4)) == (16, 4)
    assert P.window_and_stride(_clips(a, 64, 64)) == (64, None)  # no two windows overlap: not made up
    assert P.window_and_stride([]) == (None, None)


def test_iterations_from_name_or_optimiser(tmp_path):
    assert P.released_iterations(tmp_path / "000041.pt")[0] == 42  # written at the end of their iteration 41
    # their generator optimiser steps once per iteration and once more every g_reg_every-th (from 0)
    assert [P.iterations_from_steps(s, 4) for s in (0, 1, 2, 3, 5, 6, 7)] == [0, None, 1, 2, 4, None, 5]
    optim = {"state": {0: {"step": torch.tensor(3.0)}, 1: {"step": torch.tensor(3.0)}}, "param_groups": []}
    n, how = P.released_iterations(tmp_path / "renamed.pt", optim, 4)
    assert n == 2 and "step count" in how
    assert P.released_iterations(tmp_path / "init.pt", {"state": {}}, 4) == (None, "not recorded in the file")


def test_file_and_folder_records(tmp_path):
    (tmp_path / "a.pt").write_bytes(b"one")
    (tmp_path / "b.txt").write_bytes(b"two")
    rec = P.file_record(tmp_path / "a.pt")
    assert rec["name"] == "a.pt" and rec["bytes"] == 3 and rec["sha256"] == hashlib.sha256(b"one").hexdigest()
    folder = P.folder_record(tmp_path, [tmp_path / "b.txt", tmp_path / "a.pt"])
    assert [f["name"] for f in folder["files"]] == ["a.pt", "b.txt"]
    lines = f"a.pt {hashlib.sha256(b'one').hexdigest()}\nb.txt {hashlib.sha256(b'two').hexdigest()}\n"
    assert folder["sha256"] == hashlib.sha256(lines.encode()).hexdigest()


def test_record_is_plain_data():
    import argparse

    r = P.record("modi-released", {"name": "x"}, args=argparse.Namespace(a=np.float32(0.5), b=(1, 2), c=None),
                 seed=None)
    assert r["args"] == {"a": 0.5, "b": [1, 2], "c": None} and r["imported_by"]
    with pytest.raises(ValueError):
        P.record("other", {})


def _clip(T: int = 40, J: int = 3, C: int = 2, seed: int = 0) -> Clip:
    g = torch.Generator().manual_seed(seed)
    feats = torch.randn(6, J + 1 + C, T, generator=g)
    feats[:, J + 1:] = 0
    feats[0, J + 1:] = (torch.rand(C, T, generator=g) > 0.5).float()
    sk = Skeleton(["a", "b", "c"], [-1, 0, 1], np.ones((3, 3)))
    return Clip(name="x", skeleton=sk, feet=[1, 2], features=feats, root_start=torch.zeros(3), fps=30.0, scale=1.0,
                contact_threshold=0.018, size=1.0, kept_joints=[0, 1, 2])


def test_a_label_rounding_decides_is_settled_by_the_amplitudes():
    """Their labels (``theirs``) differ from a reading of the file in one label whose foot speed is within float32
    rounding of the threshold; the amplitudes of their pyramid pick that label back, and only labels inside the
    rounding band are ever changed."""
    ours = _clip()
    lengths = [8, 11, 15, 20, 27, 40]
    speed = np.full((39, 2), 0.05)
    speed[20, 1] = 0.018 + 2e-6           # label 21 of foot 1: within 8 ulps of a coordinate of 10
    speed[30, 0] = 0.018 - 1e-3           # clearly below: never flipped
    assert G.ambiguous_labels(speed, 0.018, 10.0) == [(21, 1)]
    theirs = G._flipped(ours, [(21, 1)])
    amps = G._amplitudes(theirs, lengths)
    assert G._amp_error(G._amplitudes(ours, lengths), amps)[0] > G.EXACT
    got, flips, err, n = G.settle_labels(ours, speed, 10.0, lengths, amps)
    assert flips == [(21, 1)] and n == 1 and err <= G.EXACT
    assert torch.equal(got.features, theirs.features)
    # a motion that no label flip explains stays as far off (the caller refuses it, naming the cause)
    _, flips, err, _ = G.settle_labels(_clip(seed=1), speed, 10.0, lengths, amps)
    assert err > G.ACCEPT


def test_info_rows_of_an_import():
    rows = _imported_text({"kind": "modi-released", "source": {"name": "000001.pt", "sha256": "ab" * 32},
                           "iterations": 2, "iterations_from": "from the file name 000001.pt",
                           "args": {"iter": 2, "path": "/d/edge.npy"}, "seed": None, "imported_by": "0.1.0",
                           "data": {"name": "edge.npy", "sha256": "cd" * 32, "clips": 4, "window": 64, "stride": 32,
                                    "fps": 30.0}})
    text = "\n".join(rows)
    assert "released MoDi checkpoint 000001.pt" in text and "2 iterations, from the file name" in text
    assert "windows of 64 frames every 32" in text and "--iter=2" in text and "none (their" in text
    old = _imported_text({"kind": None, "source": {"path": "/runs/theirs"}})  # what earlier imports kept
    assert old == ["imported:    /runs/theirs (recorded before modi kept what the file says)"]
    assert _imported_text(None) == []
