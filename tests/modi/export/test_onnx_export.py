"""ONNX export: onnxruntime equals modi on the same inputs, the NumPy-only runner writes modi's own sample, and the
sidecar's contract refuses bad inputs (``modi.export.onnx``, ``modi.export.onnx_runner``)."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

for _pkg in ("onnx", "onnxscript", "onnxruntime"):
    pytest.importorskip(_pkg, reason=f"{_pkg} is not installed (pip install 'modi[onnx]')")

from modi.cli import main as modi_main  # noqa: E402
from modi.core.kinematics import bvh_positions  # noqa: E402
from modi.core.rotations import axis_angle_to_quat  # noqa: E402
from modi.core.skeleton import Skeleton  # noqa: E402
from modi.errors import UserError  # noqa: E402
from modi.export import onnx as mx  # noqa: E402
from modi.export import onnx_runner as rx  # noqa: E402
from modi.io import bvh  # noqa: E402
from modi.models.ganimator import config as gconfig  # noqa: E402
from modi.models.ganimator.data import RawClip, sequence_from_clip  # noqa: E402
from modi.models.ganimator.generate import decode, to_bvh, trajectory_conditions  # noqa: E402
from modi.models.ganimator.training import load_model, train  # noqa: E402
from modi.models.modi.sampling import generate_tensors, latents_and_noise, load_generator  # noqa: E402

pytestmark = [pytest.mark.filterwarnings("ignore::RuntimeWarning"), pytest.mark.filterwarnings("ignore::UserWarning"),
              pytest.mark.filterwarnings("ignore::FutureWarning"), pytest.mark.usefixtures("one_torch_thread")]

RUNNER = Path(rx.__file__)
NAMES = ["Hips", "Spine", "Head", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToe",
         "RightUpLeg", "RightLeg", "RightFoot", "RightToe"]
PARENTS = [-1, 0, 1, 0, 3, 4, 5, 0, 7, 8, 9]


def walking_clip(T: int = 48) -> RawClip:
    """A small biped in centimetres swinging its legs while it walks forward (no files needed)."""
    offsets = np.array([[0, 0, 0], [0, 20, 0], [0, 25, 0], [9, -4, 0], [0, -42, 0], [0, -40, 0], [0, -6, 12],
                        [-9, -4, 0], [0, -42, 0], [0, -40, 0], [0, -6, 12]], dtype=np.float64)
    t = torch.arange(T, dtype=torch.float64)
    phase = 2 * math.pi * t / 24
    aa = torch.zeros(T, len(NAMES), 3, dtype=torch.float64)
    aa[:, 3, 0], aa[:, 7, 0] = 0.5 * torch.sin(phase), -0.5 * torch.sin(phase)
    aa[:, 4, 0], aa[:, 8, 0] = 0.4 * (1 + torch.sin(phase)), 0.4 * (1 - torch.sin(phase))
    aa[:, 1, 1] = 0.2 * torch.sin(phase)
    root = torch.stack([0.3 * torch.sin(phase), 92 + 2 * torch.cos(2 * phase), 2.5 * t], -1)
    sk = Skeleton(NAMES, PARENTS, offsets, end_sites={2: np.array([0, 10.0, 0])}, rotation_orders=["ZXY"] * 11)
    return RawClip(sk, axis_angle_to_quat(aa), root, 30.0)


def tiny_cfg(**kw) -> gconfig.GanimatorConfig:
    base = dict(iterations=2, d_steps=1, base_channels=16, fake_pool=4, checkpoint_every=1e9, seed=0, coarse_ratio=0.5,
                feet=["LeftToe", "RightToe"])
    base.update(kw)
    return gconfig.preset("tiny", **base)


def close(out: np.ndarray, ref: np.ndarray) -> float:
    """max |out - ref| over the output's scale (its largest magnitude, at least 1e-6)."""
    assert out.shape == ref.shape
    return float(np.abs(out - ref).max() / max(np.abs(ref).max(), 1e-6)) if ref.size else 0.0


def reference_ganimator(model, noise: np.ndarray, frames: int, traj: torch.Tensor | None = None) -> dict:
    """modi's own rotations / root (file units) / contacts for the same level-0 noise."""
    B, L0 = noise.shape
    z = torch.from_numpy(noise).view(B, 1, 1, L0) * model.amps[0][0]
    conds = trajectory_conditions(model, traj, frames) if traj is not None else None
    feats = model.sample(frames, B, noises=[z] + [None] * (model.n_levels - 1), conds=conds)
    parts = [decode(model, feats[b]) for b in range(B)]
    inv = 1.0 / model.seqs[0].scale
    return {"rotations": np.stack([p[0].numpy() for p in parts]),
            "root_position": np.stack([(p[1] * inv).numpy() for p in parts]),
            "contacts": np.stack([p[2].numpy() for p in parts])}


def run_without_torch(*args: str) -> subprocess.CompletedProcess:
    """The runner as a standalone script in a process where importing torch fails."""
    code = ("import sys, runpy; sys.modules['torch'] = None; "
            f"sys.argv = ['onnx_runner.py'] + {list(map(str, args))!r}; "
            f"runpy.run_path({str(RUNNER)!r}, run_name='__main__')")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


def positions(path: Path, tmp: Path) -> np.ndarray:
    """What ``modi export positions`` reads back from a BVH."""
    out = tmp / (path.stem + "_pos.npy")
    assert modi_main(["export", "positions", str(path), str(out)]) == 0
    return np.load(out)


# ------------------------------------------------------------------------------------------- GANimator


@pytest.fixture(scope="module")
def gan(tmp_path_factory):
    """A GANimator run trained for 2 iterations per level on a short clip, exported with ``modi export onnx``."""
    tmp = tmp_path_factory.mktemp("gan")
    torch.manual_seed(0)
    cfg = tiny_cfg()
    seq = sequence_from_clip(walking_clip(), "walk", cfg)
    train([seq], cfg, tmp / "run", progress=False, log=None)
    assert modi_main(["export", "onnx", str(tmp / "run"), str(tmp / "gan.onnx")]) == 0
    return tmp, load_model(tmp / "run")


def test_ganimator_onnx_equals_modi_for_several_lengths(gan):
    tmp, model = gan
    run = rx.Runner(tmp / "gan.onnx")
    side = run.sidecar
    n_min = side["dims"]["frames"]["min"]
    T = model.seqs[0].n_frames
    assert model.seqs[0].feet and side["feet"] == ["LeftToe", "RightToe"]
    rng = np.random.default_rng(0)
    worst: dict[str, float] = {}
    for frames in (n_min, 37, T, 2 * T + 5):
        L0 = model.level_lengths(frames)[0]
        noise = rng.standard_normal((2, L0)).astype(np.float32)
        out = run(noise=noise, frames=np.array([frames]))
        ref = reference_ganimator(model, noise, frames)
        for k in ("rotations", "root_position", "contacts"):
            assert out[k].shape[:2] == (2, frames)
            assert close(out[k], ref[k]) < 1e-4, (frames, k, close(out[k], ref[k]))
            worst[k] = max(worst.get(k, 0.0), close(out[k], ref[k]))
    print(f"\nGANimator, frames {n_min}, 37, {T}, {2 * T + 5}: max |onnx - modi| / scale {worst}")


def test_ganimator_sidecar_describes_the_rig(gan):
    tmp, model = gan
    side = rx.read_sidecar(tmp / "gan.onnx")
    b = to_bvh(model.seqs[0], *decode(model, model.seqs[0].features)[:2])
    sk = side["skeleton"]
    assert side["kind"] == "ganimator" and side["fps"] == 30.0
    assert sk["names"] == b.names and sk["parents"] == b.parents and sk["rotation_orders"] == ["ZXY"] * 11
    np.testing.assert_allclose(sk["offsets"], b.offsets, atol=1e-6)
    assert sk["unit"] == "centimetres" and sk["end_sites"] == {"Head": [0.0, 10.0, 0.0]}
    assert [i["name"] for i in side["inputs"]] == ["noise", "frames"]
    assert [o["name"] for o in side["outputs"]] == ["rotations", "root_position", "contacts"]
    assert side["dims"]["coarse_frames"]["denominator"] == model.seqs[0].n_frames


def test_numpy_runner_writes_modis_own_sample(gan):
    """``modi ganimator generate`` draws level-0 noise from a seeded torch generator; the same noise through the
    ONNX model, run by the runner in a process without torch, gives a BVH that reads back to the same positions."""
    tmp, model = gan
    frames, seed = 70, 3
    assert modi_main(["ganimator", "generate", str(tmp / "run"), "--out", str(tmp / "own"), "--seed", str(seed),
                      "--frames", str(frames), "--no-gif"]) == 0
    L0 = model.level_lengths(frames)[0]
    noise = torch.randn(1, 1, 1, L0, generator=torch.Generator().manual_seed(seed)).view(1, L0).numpy()
    np.save(tmp / "noise.npy", noise)
    r = run_without_torch(tmp / "gan.onnx", tmp / "onnx.bvh", "--noise", tmp / "noise.npy", "--frames", frames,
                          "--contacts")
    assert r.returncode == 0, r.stderr
    ours, theirs = positions(tmp / "onnx.bvh", tmp), positions(tmp / "own" / "sample.bvh", tmp)
    assert ours.shape == theirs.shape == (frames, 11, 3)
    assert close(ours, theirs) < 1e-4
    print(f"\nGANimator BVH via the runner vs modi ganimator generate: positions {close(ours, theirs):.2e} of scale")
    assert bvh.load(str(tmp / "onnx.bvh")).names == bvh.load(str(tmp / "own" / "sample.bvh")).names
    assert np.load(tmp / "onnx_contacts.npy").shape == (frames, 2)


def test_runner_draws_its_own_noise_and_writes_a_batch(gan):
    tmp, _ = gan
    r = run_without_torch(tmp / "gan.onnx", tmp / "drawn.bvh", "--batch", 2, "--frames", 40, "--seed", 1)
    assert r.returncode == 0, r.stderr
    for i in range(2):
        b = bvh.load(str(tmp / f"drawn_{i:03d}.bvh"))
        assert b.n_frames == 40 and np.isfinite(bvh_positions(b)).all()


def test_contract_refuses_bad_inputs(gan):
    tmp, model = gan
    side = rx.read_sidecar(tmp / "gan.onnx")
    n_min = side["dims"]["frames"]["min"]
    L0 = model.level_lengths(60)[0]
    good = {"noise": np.zeros((1, L0), np.float32), "frames": np.array([60])}
    rx.check_inputs(side, good)
    cases = {
        "coarse_frames must be": {**good, "noise": np.zeros((1, L0 + 1), np.float32)},
        "expected 2 dimensions": {**good, "noise": np.zeros((1, 1, L0), np.float32)},
        "NaN or infinite": {**good, "noise": np.full((1, L0), np.nan, np.float32)},
        r"frames: values must be >= \d+": {**good, "frames": np.array([n_min - 1]),
                                      "noise": np.zeros((1, model.level_lengths(n_min - 1)[0]), np.float32)},
        "missing input": {"noise": good["noise"]},
        "unknown input": {**good, "z": good["noise"]},
        "whole numbers": {**good, "frames": np.array([60.5])},
    }
    for message, feeds in cases.items():
        with pytest.raises(rx.ContractError, match=message):
            rx.check_inputs(side, feeds)
    bad = np.full((1, L0), np.nan, np.float32)
    np.save(tmp / "bad.npy", bad)
    r = run_without_torch(tmp / "gan.onnx", tmp / "bad.bvh", "--noise", tmp / "bad.npy", "--frames", 60)
    assert r.returncode == 2 and f"noise: {L0} value(s) are NaN" in r.stderr and not (tmp / "bad.bvh").exists()
    r = run_without_torch(tmp / "gan.onnx", tmp / "bad.bvh", "--noise", tmp / "noise.npy", "--frames", 60)
    assert r.returncode == 2 and f"must be {L0} for 60 output frames" in r.stderr


def test_fixed_length_export(gan, tmp_path):
    tmp, model = gan
    assert modi_main(["export", "onnx", str(tmp / "run"), str(tmp_path / "fixed.onnx"), "--frames", "50"]) == 0
    run = rx.Runner(tmp_path / "fixed.onnx")
    assert [i["name"] for i in run.sidecar["inputs"]] == ["noise"] and run.sidecar["dims"]["frames"] == {"fixed": 50}
    noise = np.random.default_rng(1).standard_normal((2, model.level_lengths(50)[0])).astype(np.float32)
    out, ref = run(noise=noise), reference_ganimator(model, noise, 50)
    assert all(close(out[k], ref[k]) < 1e-4 for k in ref)


def test_conditional_run(gan, tmp_path):
    """A trajectory-conditioned run: the trajectory (file units) in, its frames set the length."""
    tmp, uncond = gan
    torch.manual_seed(0)
    cfg = tiny_cfg(conditional=True)
    seq = sequence_from_clip(walking_clip(), "walk", cfg)
    train([seq], cfg, tmp_path / "cond", progress=False, log=None, cond_source=uncond)
    model = load_model(tmp_path / "cond")
    side = mx.export_onnx(tmp_path / "cond", tmp_path / "cond.onnx")
    assert [i["name"] for i in side["inputs"]] == ["noise", "trajectory"]
    run = rx.Runner(tmp_path / "cond.onnx")
    scale = torch.ones(1, 6, 2, 1)
    scale[0, :3, 0] = model.seqs[0].scale
    worst: dict[str, float] = {}
    for frames in (side["dims"]["frames"]["min"], 48, 90):
        traj = uncond.sample(frames, 2, generator=torch.Generator().manual_seed(frames))[:, :, model.cond_entities]
        noise = np.random.default_rng(frames).standard_normal((2, model.level_lengths(frames)[0])).astype(np.float32)
        out = run(noise=noise, trajectory=(traj / scale).numpy())
        ref = reference_ganimator(model, noise, frames, traj)
        for k in ref:
            assert close(out[k], ref[k]) < 1e-4, (frames, k, close(out[k], ref[k]))
            worst[k] = max(worst.get(k, 0.0), close(out[k], ref[k]))
    print(f"\nGANimator conditional: max |onnx - modi| / scale {worst}")
    with pytest.raises(rx.ContractError, match="coarse_frames must be"):
        run(noise=noise, trajectory=(traj[..., :-7] / scale).numpy())


# ------------------------------------------------------------------------------------------- MoDi


@pytest.fixture(scope="module")
def modi_ckpt(tmp_path_factory):
    """A small MoDi with noise injection after 2 iterations on the built-in clips, exported."""
    tmp = tmp_path_factory.mktemp("modi")
    assert modi_main(["train", "procedural", "--preset", "small", "--iters", "2", "--batch", "4", "--noise-injection",
                      "--out", str(tmp / "run"), "--no-tensorboard", "--sample-every", "0", "--threads", "1"]) == 0
    ckpt = tmp / "run" / "checkpoint.pt"
    assert modi_main(["export", "onnx", str(ckpt), str(tmp / "modi.onnx")]) == 0
    return tmp, ckpt


def test_modi_onnx_equals_modi(modi_ckpt):
    tmp, ckpt = modi_ckpt
    run = rx.Runner(tmp / "modi.onnx")
    side = run.sidecar
    assert [i["name"] for i in side["inputs"]] == ["z", "psi", "noise"] and side["dims"]["frames"] == {"fixed": 64}
    model = load_generator(ckpt)
    g, codec, _ = model
    worst: dict[str, float] = {}
    for psi, n in ((1.0, 3), (0.6, 1)):
        z, noise = latents_and_noise(g, list(range(n)), seed=5)
        x, _ = generate_tensors(ckpt, n, seed=5, psi=psi, model=model)
        d = codec.decode(x)
        flat = torch.cat([m.flatten(1) for m in noise], 1).numpy()
        out = run(z=z.numpy(), psi=np.array([psi], np.float32), noise=flat)
        for k, ref in (("rotations", d["rotations"]), ("root_position", d["root"]), ("contacts", d["contacts"])):
            assert close(out[k], ref.numpy()) < 1e-4, (psi, k, close(out[k], ref.numpy()))
            worst[k] = max(worst.get(k, 0.0), close(out[k], ref.numpy()))
    print(f"\nMoDi (noise injection), psi 1 and 0.6: max |onnx - modi| / scale {worst}")
    S = side["inputs"][2]["shape"][1]
    with pytest.raises(rx.ContractError, match="values must be <= 2"):
        run(z=z.numpy(), psi=np.array([2.5], np.float32), noise=np.zeros((n, S), np.float32))
    with pytest.raises(rx.ContractError, match="batch"):
        run(z=np.zeros((2, 128), np.float32), psi=np.ones(1, np.float32), noise=np.zeros((3, S), np.float32))


def test_modi_graph_with_w_input_is_the_generator(modi_ckpt):
    """``--input w``: the graph's function (in torch) is the generator called with ``input_is_w``."""
    _, ckpt = modi_ckpt
    g, codec, _ = load_generator(ckpt)
    graph = mx.ModiGraph(g, codec, "w").eval()
    z, noise = latents_and_noise(g, [0, 1], seed=2)
    w = g.mapping(z).detach()
    with torch.no_grad():
        rot, root, con = graph(w, torch.tensor([0.8]), torch.cat([m.flatten(1) for m in noise], 1))
        d = codec.decode(g(w, input_is_w=True, truncation_psi=0.8, noise=noise))
    for a, b in ((rot, d["rotations"]), (root, d["root"]), (con, d["contacts"])):
        assert close(a.numpy(), b.numpy()) < 1e-5


def test_modi_runner_writes_modis_own_sample(modi_ckpt):
    tmp, ckpt = modi_ckpt
    assert modi_main(["generate", str(ckpt), "--n", "1", "--seed", "7", "--out", str(tmp / "own"),
                      "--gif-max", "0"]) == 0
    g, _, _ = load_generator(ckpt)
    z, noise = latents_and_noise(g, [0], seed=7)
    np.save(tmp / "z.npy", z.numpy())
    np.save(tmp / "noise.npy", torch.cat([m.flatten(1) for m in noise], 1).numpy())
    r = run_without_torch(tmp / "modi.onnx", tmp / "onnx.bvh", "--input", f"z={tmp / 'z.npy'}",
                          "--input", f"noise={tmp / 'noise.npy'}")
    assert r.returncode == 0, r.stderr
    ours, theirs = positions(tmp / "onnx.bvh", tmp), positions(tmp / "own" / "motion_0000.bvh", tmp)
    assert ours.shape == theirs.shape and close(ours, theirs) < 1e-4
    print(f"\nMoDi BVH via the runner vs modi generate: positions {close(ours, theirs):.2e} of scale")


# ------------------------------------------------------------------------------------------- refusals


def test_export_refusals(modi_ckpt, tmp_path, monkeypatch, capsys):
    tmp, ckpt = modi_ckpt
    assert modi_main(["export", "onnx", str(tmp_path / "nothing"), str(tmp_path / "m.onnx")]) == 2
    assert "no such run folder or checkpoint" in capsys.readouterr().err
    assert modi_main(["export", "onnx", str(ckpt), str(tmp_path / "m.onnx"), "--frames", "40"]) == 2
    assert "--frames applies to GANimator runs" in capsys.readouterr().err
    assert modi_main(["export", "onnx", str(ckpt), str(tmp_path / "m.onx")]) == 2
    assert "must end in .onnx" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "onnxscript", None)
    with pytest.raises(UserError, match=r"pip install 'modi\[onnx\]'"):
        mx.export_onnx(ckpt, tmp_path / "m.onnx")


def test_euler_decomposition_round_trips_every_order():
    """The runner's NumPy quaternion -> Euler for BVH matches modi's Euler -> matrix, gimbal lock included."""
    from modi.core.rotations import euler_to_matrix

    rng = np.random.default_rng(0)
    q = rng.standard_normal((200, 4))
    c = np.cos(np.pi / 4)  # quarter turns about each axis: gimbal lock for the orders with that middle axis
    q = np.concatenate([q, [[1, 0, 0, 0], [c, 0, c, 0], [c, c, 0, 0], [c, 0, 0, c]]])
    m = rx.quat_to_matrix(q)
    for order in ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"):
        back = euler_to_matrix(torch.from_numpy(rx.matrix_to_euler(m, order)), order).numpy()
        np.testing.assert_allclose(back, m, atol=1e-9)
