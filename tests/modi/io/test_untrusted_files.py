"""Files from others are data, never code: every command that reads a file someone may have shared refuses one
whose unpickling would run code, before anything runs, with one line and exit 2 (issue 32).

The planted files call ``os.system("touch MARKER")`` when unpickled the ordinary way (the first test proves the
payload is live); each case then runs a command in-process on such a file and checks the marker never appears.
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch

from modi.cli import main
from modi.errors import CheckpointError
from modi.io.safe_load import UnsafeFileError, load_data

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class _Payload:
    """Unpickling this runs a shell command that creates ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(str(self.marker))}",))


def _plant(path: Path, marker: Path, form: str = "zip", outer: dict | None = None) -> Path:
    """A file shaped like a checkpoint (``outer``) whose one value is the payload, in one of the pickle forms."""
    obj = {**(outer or {"format": "modi-checkpoint", "version": 1, "step": 0}), "G_ema": _Payload(marker)}
    path.parent.mkdir(parents=True, exist_ok=True)
    if form == "zip":
        torch.save(obj, path)
    elif form == "legacy":
        torch.save(obj, path, _use_new_zipfile_serialization=False)
    elif form == "protocol4":
        torch.save(obj, path, pickle_protocol=4)
    elif form == "pickle":
        path.write_bytes(pickle.dumps(obj, protocol=2))
    return path


def test_the_payload_runs_when_unpickled_normally(tmp_path):
    """The control: read the ordinary way, the planted file does run its command, so its absence below means
    the code was refused, not that the payload was a dud."""
    marker = tmp_path / "MARKER"
    _plant(tmp_path / "f.pt", marker)
    torch.load(tmp_path / "f.pt", weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("form", ["zip", "legacy", "protocol4", "pickle"])
def test_load_data_refuses_every_pickle_form_unrun(form, tmp_path):
    marker = tmp_path / "MARKER"
    f = _plant(tmp_path / "f.pt", marker, form)
    with pytest.raises(CheckpointError) as info:
        load_data(f, "MoDi checkpoint")
    msg = str(info.value)
    assert not marker.exists()
    assert "\n" not in msg and str(f) in msg and "weights_only=False" not in msg, msg
    if form in ("zip", "legacy", "pickle"):  # protocol 2: the refused global is named
        assert isinstance(info.value, UnsafeFileError) and "posix.system" in msg, msg


def test_an_allow_list_admits_exactly_the_named_classes(tmp_path):
    """Others read the authors' checkpoints (an ``argparse.Namespace`` inside) through the same function."""
    f = tmp_path / "released.pt"
    torch.save({"args": argparse.Namespace(lr=0.1), "w": torch.ones(2)}, f)
    with pytest.raises(UnsafeFileError, match="argparse.Namespace"):
        load_data(f)
    st = load_data(f, allowed=[argparse.Namespace])
    assert st["args"].lr == 0.1 and torch.equal(st["w"], torch.ones(2))
    marker = tmp_path / "MARKER"
    _plant(tmp_path / "evil.pt", marker, outer={"args": argparse.Namespace(lr=0.1)})
    with pytest.raises(UnsafeFileError, match="posix.system"):
        load_data(tmp_path / "evil.pt", allowed=[argparse.Namespace])
    assert not marker.exists()


def test_earlier_drafts_data_classes_load_but_object_arrays_do_not(tmp_path):
    """numpy arrays and scalars and TorchVersion are data (files of earlier drafts may hold them); an object array
    (pickled Python objects) is not."""
    from torch.torch_version import TorchVersion

    from modi.io.safe_load import earlier_modi_globals

    f = tmp_path / "old.pt"
    torch.save({"a": np.arange(3.0), "n": np.int64(7), "torch_version": TorchVersion("2.1.0")}, f)
    st = load_data(f, allowed=earlier_modi_globals())
    assert np.array_equal(st["a"], np.arange(3.0)) and st["n"] == 7 and st["torch_version"] == "2.1.0"
    marker = tmp_path / "MARKER"
    torch.save({"a": np.array([_Payload(marker)], dtype=object)}, tmp_path / "obj.pt")
    with pytest.raises(UnsafeFileError):
        load_data(tmp_path / "obj.pt", allowed=earlier_modi_globals())
    assert not marker.exists()


# ------------------------------------------------------------------------------------------- every reading command


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> dict[str, str]:
    """A procedural BVH folder and a tiny MoDi generator (for the cases where the planted file is the second
    input), and a marker path shared by the planted files."""
    from modi.data.procedural import write_dataset
    from test_cli_errors import _tiny_generator_checkpoint

    w = tmp_path_factory.mktemp("untrusted")
    d = w / "d"
    write_dataset(d, n_clips=3, frames=40, seed=0)
    _tiny_generator_checkpoint(w / "tiny.pt")
    return {"d": str(d), "clip": str(d / "0000_walk.bvh"), "clip2": str(d / "0001_run.bvh"),
            "tiny": str(w / "tiny.pt")}


# (command line: {evil} a planted .pt, {run} a run folder whose ganimator.ckpt is planted, {npy} a .npy holding a
# pickled object array)
COMMANDS = [
    "generate {evil} --out {out}",
    "latent mean {evil} --out {out}",
    "latent truncate {evil} --out {out}",
    "latent interpolate {evil} --out {out}",
    "latent cluster {evil} --out {out}",
    "latent edit {evil} --out {out}",
    "latent crowd {evil} --out {out}",
    "latent invert {evil} {clip} --out {out}",
    "latent truncate {tiny} --latent {npy} --out {out}",
    "latent interpolate {tiny} --from {npy} --out {out}",
    "latent crowd {tiny} --latent {npy} --out {out}",
    "apply invert {evil} {clip} --out {out}",
    "apply prefix {evil} {clip} --out {out}",
    "apply fuse {evil} {clip} {clip2} --out {out}",
    "apply denoise {evil} {clip} --out {out}",
    "apply edit {evil} {clip} --out {out}",
    "encoder eval {evil} {d}",
    "encoder train {evil} {d} --out {out}.pt --iters 1",
    "encoder train {tiny} {d} --out {evil} --iters 1 --resume",
    "eval gen --ckpt {evil} --features {evil} --data {d}",
    "eval gen --ckpt {tiny} --features {evil} --data {d}",
    "eval real --features {evil} {d}",
    "train {d} --out {out} --resume {evil}",
    "ganimator generate {run} --frames 60 --n 1 --out {out}",
    "ganimator generate {run}/ganimator.ckpt --out {out}",
    "ganimator eval {run}",
    "ganimator eval {run} --protocol paper",
    "ganimator train {clip} --out {run} --preset tiny --iterations 1 --quiet",
    "ganimator train {clip} --out {out} --preset tiny --conditional-from {run}",
    "info {evil}",
    "info {run}",
]


def _one_error_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "%|" not in line]
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("line", COMMANDS, ids=[c.split(" --")[0].replace(" ", "_") for c in COMMANDS])
def test_a_planted_file_is_refused_unrun_by_every_reading_command(line, work, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MODI_CACHE", str(tmp_path / "cache"))
    marker = tmp_path / "MARKER"
    evil = _plant(tmp_path / "shared" / "model.pt", marker)
    run = tmp_path / "shared" / "run"
    _plant(run / "ganimator.ckpt", marker, outer={"format": "modi.ganimator/1"})
    npy = tmp_path / "shared" / "w.npy"
    np.save(npy, np.array([_Payload(marker)], dtype=object), allow_pickle=True)
    argv = shlex.split(line.format(evil=evil, run=run, npy=npy, out=tmp_path / "out", **work))
    capsys.readouterr()
    rc = main(argv)
    err = _one_error_line(capsys)
    assert not marker.exists(), f"{line}: the planted file ran its code"
    assert rc == 2, (line, rc, err)
    assert "objects other than data" in err and str(tmp_path / "shared") in err, err


@pytest.mark.parametrize("line", ["import modi-released {evil} --data {d} --out {out}",
                                  "import encoder-released {evil} --generator {evil} --data {d} --out {out}"])
def test_a_planted_released_checkpoint_is_refused_unrun(line, work, tmp_path, capsys):
    """``modi import`` reads the authors' files with their classes allowed (issue 30); code is still refused."""
    marker = tmp_path / "MARKER"
    evil = _plant(tmp_path / "shared" / "released.pt", marker, outer={"args": argparse.Namespace(lr=0.1)})
    capsys.readouterr()
    rc = main(shlex.split(line.format(evil=evil, out=tmp_path / "out", **work)))
    err = _one_error_line(capsys)
    assert not marker.exists() and rc == 2 and str(evil) in err, (rc, err)


def test_a_planted_dataset_cache_is_refused_unrun(work, tmp_path, capsys):
    cache = tmp_path / "cache"
    assert main(["data", "info", work["d"], "--window", "16", "--cache-dir", str(cache)]) == 0
    (cached,) = cache.glob("dataset-*.pt")
    marker = tmp_path / "MARKER"
    _plant(cached, marker, outer={"v": 1})
    capsys.readouterr()
    rc = main(["data", "info", work["d"], "--window", "16", "--cache-dir", str(cache)])
    err = _one_error_line(capsys)
    assert not marker.exists() and rc == 2
    assert "objects other than data" in err and str(cached) in err and "--no-cache" in err, err
    # a merely corrupt cache (a write cut short) is still rebuilt, as before
    cached.write_bytes(cached.read_bytes()[:100])
    with pytest.warns(UserWarning, match="ignoring unreadable dataset cache"):
        assert main(["data", "info", work["d"], "--window", "16", "--cache-dir", str(cache)]) == 0


def test_a_planted_normaliser_file_is_refused_unrun(tmp_path):
    from modi.data.normalization import Normalizer

    marker = tmp_path / "MARKER"
    f = _plant(tmp_path / "norm.pt", marker, outer={"mean": torch.zeros(3)})
    with pytest.raises(UnsafeFileError, match="posix.system"):
        Normalizer.load(f)
    assert not marker.exists()
    good = Normalizer(torch.zeros(2, 1), torch.ones(2, 1))
    good.save(tmp_path / "good.pt")
    assert torch.equal(Normalizer.load(tmp_path / "good.pt").std, torch.ones(2, 1))


# ------------------------------------------------------------------------------------------- modi info


def _bvh_joints(path: str) -> list[str]:
    """Joint names straight from the BVH text (the oracle for the skeleton ``info`` reports)."""
    return [line.split()[1] for line in Path(path).read_text().splitlines() if line.split()[:1] in (["ROOT"], ["JOINT"])]


@pytest.fixture(scope="module")
def trained(work, tmp_path_factory) -> dict[str, str]:
    w = tmp_path_factory.mktemp("trained")
    assert main(["ganimator", "train", work["clip"], "--out", str(w / "gan"), "--preset", "tiny", "--iterations", "1",
                 "--no-joint-reduction", "--quiet"]) == 0
    assert main(["encoder", "train", work["tiny"], work["d"], "--out", str(w / "enc.pt"), "--iters", "1",
                 "--batch", "2", "--eval-every", "0", "--quiet", "--no-cache"]) == 0
    return {"gan": str(w / "gan"), "enc": str(w / "enc.pt")}


def _info(capsys, *argv: str) -> dict:
    capsys.readouterr()
    assert main(["info", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_info_describes_a_ganimator_run_from_its_data(work, trained, capsys):
    import modi

    d = _info(capsys, trained["gan"])
    joints = _bvh_joints(work["clip"])
    assert d["kind"] == "GANimator checkpoint" and d["format"] == "modi.ganimator/1" and d["version"] == 1
    assert d["skeleton"]["names"] == joints and d["skeleton"]["root"] == joints[0]
    assert d["config"]["preset"] == "tiny" and d["config"]["iterations"] == 1 and not d["config"]["joint_reduction"]
    assert d["step"].startswith("fully trained") and d["data"].startswith("0000_walk (40 frames at 30 fps")
    assert d["modi_version"] == modi.__version__
    capsys.readouterr()
    assert main(["info", trained["gan"]]) == 0
    text = capsys.readouterr().out
    assert f"written by:  modi {modi.__version__}" in text and f"{len(joints)} joints, root {joints[0]}" in text


def test_info_describes_encoder_generator_and_feature_files(work, trained, tmp_path, capsys):
    from modi.evaluation.features import STGCN, FeatureConfig, FeatureExtractor

    enc = _info(capsys, trained["enc"])
    assert enc["kind"] == "MoDi encoder checkpoint" and enc["step"] == 1 and enc["data"] == work["d"]
    assert enc["config"]["train"]["iters"] == 1 and enc["skeleton"]["joints"] == len(_bvh_joints(work["clip"]))
    gen = _info(capsys, work["tiny"])  # written by a helper that records no version: said so, not guessed
    assert gen["kind"] == "MoDi generator checkpoint" and gen["step"] == 0 and gen["modi_version"] is None
    capsys.readouterr()
    main(["info", work["tiny"]])
    assert "written by:  not recorded" in capsys.readouterr().out
    cfg = FeatureConfig(joint_names=["hips", "knee", "foot"], parents=[-1, 0, 1], class_names=["walk", "run"],
                        channels=[4], strides=[1])
    FeatureExtractor(cfg, STGCN(cfg), np.zeros(6, np.float32), np.ones(6, np.float32)).save(tmp_path / "f.pt")
    feat = _info(capsys, str(tmp_path / "f.pt"))
    assert feat["kind"].startswith("feature-extractor") and feat["skeleton"]["names"] == ["hips", "knee", "foot"]
    assert feat["config"]["class_names"] == ["walk", "run"] and feat["version"] == 1


@pytest.mark.parametrize("content, expected", [(b"", "not a readable modi file"),
                                               (None, "not a modi checkpoint, encoder or feature-extractor file")])
def test_info_on_other_files_is_one_line_exit_2(content, expected, tmp_path, capsys):
    f = tmp_path / "x.pt"
    if content is None:
        torch.save({"weights": torch.ones(2)}, f)
    else:
        f.write_bytes(content)
    capsys.readouterr()
    assert main(["info", str(f)]) == 2
    err = _one_error_line(capsys)
    assert expected in err and str(f) in err, err
