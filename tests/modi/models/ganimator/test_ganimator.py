"""GANimator: shapes on arbitrary trees, learning, lengths, streaming exactness, checkpoints, real-data loading."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from modi.errors import CheckpointError, UserError
from modi.models.ganimator import config as gconfig
from modi.models.ganimator.data import (RawClip, features_to_motion, pyramid_lengths, read_clip, resample,
                                 sequence_from_clip, sequence_pyramid)
from modi.models.ganimator.networks import GanimatorModel, ganimator_neighbors, synthesize
from modi.models.ganimator.training import Trainer, load_model, read_checkpoint, train
from modi.core.skeleton import Skeleton

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


def random_tree(n: int, rng: random.Random) -> list[int]:
    return [-1] + [rng.randrange(j) for j in range(1, n)]


def synthetic_clip(parents: list[int], T: int, seed: int = 0, walk: float = 0.02) -> RawClip:
    """A smooth periodic motion on any tree (no files needed), legs pointing down so feet touch the ground."""
    from modi.core.rotations import axis_angle_to_quat

    g = torch.Generator().manual_seed(seed)
    J = len(parents)
    offsets = np.zeros((J, 3))
    for j in range(1, J):
        d = torch.randn(3, generator=g).numpy()
        d[1] = -abs(d[1]) - 0.5
        offsets[j] = 0.15 * d / np.linalg.norm(d)
    t = torch.arange(T, dtype=torch.float64)[:, None, None]
    freq = 0.5 + torch.rand(1, J, 3, generator=g, dtype=torch.float64)
    phase = 6.28 * torch.rand(1, J, 3, generator=g, dtype=torch.float64)
    aa = 0.4 * torch.sin(2 * math.pi * freq * t / 30.0 + phase)
    rot = axis_angle_to_quat(aa)
    root = torch.zeros(T, 3, dtype=torch.float64)
    root[:, 0] = walk * torch.arange(T, dtype=torch.float64)
    root[:, 1] = 0.6
    skel = Skeleton([f"j{j}" for j in range(J)], parents, offsets, rotation_orders=["ZXY"] * J)
    return RawClip(skel, rot, root, 30.0)


def tiny_cfg(**kw) -> gconfig.GanimatorConfig:
    base = dict(iterations=2, d_steps=1, base_channels=16, fake_pool=4, checkpoint_every=1e9, seed=0)
    base.update(kw)
    return gconfig.preset("tiny", **base)


def clip_seq(parents, T=60, seed=0, cfg=None, **kw):
    cfg = cfg or tiny_cfg()
    return sequence_from_clip(synthetic_clip(parents, T, seed, **kw), f"clip{seed}", cfg)


def untrained_model(seqs, cfg) -> GanimatorModel:
    lengths, _ = sequence_pyramid(seqs, cfg)
    E = seqs[0].n_entities
    amps = [[0.1] * len(l) for l in lengths]
    z = [torch.randn(1, 6, E, l[0]) for l in lengths]
    return GanimatorModel(cfg, seqs, lengths, amps, z)


# ------------------------------------------------------------------------------------------- topology / shapes


def test_neighbors_wire_contacts_to_foot_and_root_motion():
    parents = [-1, 0, 1, 2, 0, 4, 5, 0, 7]
    feet = [3, 6]
    nb = ganimator_neighbors(parents, feet, distance=2)
    J, rm = len(parents), len(parents)
    c0, c1 = J + 1, J + 2
    assert len(nb) == J + 1 + 2
    for j, n in enumerate(nb):
        assert j in n and n == sorted(n)
    assert 3 in nb[c0] and c0 in nb[3] and rm in nb[c0] and c0 in nb[rm]
    assert 6 in nb[c1] and c1 in nb[6] and rm in nb[c1]
    assert 0 in nb[rm] and rm in nb[0]
    # joint neighbourhoods are plain tree distance <= 2 (siblings through their parent count as 2)
    assert sorted(set(nb[1]) - {rm}) == [0, 1, 2, 3, 4, 7]
    assert 3 not in nb[0] and 2 in nb[0]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_all_levels_shapes_on_random_trees(seed):
    rng = random.Random(seed)
    parents = random_tree(rng.randint(3, 14), rng)
    cfg = tiny_cfg()
    seq = clip_seq(parents, T=rng.randint(40, 90), seed=seed)
    model = untrained_model([seq], cfg)
    J, E = len(parents), seq.n_entities
    assert E == J + 1 + len(seq.feet)
    lengths = model.lengths[0]
    assert lengths[-1] == seq.n_frames and lengths == sorted(lengths) and len(lengths) >= 5
    noises = model.random_noises(lengths, batch=2, fine_noise=True)
    outs = synthesize(model.gens, model.rates[0], lengths, noises, E, batch=2)
    assert [tuple(o.shape) for o in outs] == [(2, 6, E, L) for L in lengths]
    for l, o in enumerate(outs):
        assert torch.isfinite(o).all()
        assert tuple(model.discs[l](o).shape) == (2, lengths[l])


def test_pyramid_follows_published_rule():
    assert pyramid_lengths(648) == [129, 172, 229, 305, 406, 541, 648]
    assert pyramid_lengths(201) == [40, 53, 70, 93, 124, 165, 201]


def test_fixed_grid_resample_matches_interpolate_and_is_prefix_stable():
    x = torch.randn(2, 6, 3, 37)
    ref = torch.nn.functional.interpolate(x.reshape(2, 18, 37), size=50, mode="linear", align_corners=False)
    assert torch.allclose(resample(x, 50, 37 / 50).reshape(2, 18, 50), ref, atol=5e-5)  # torch rounds the scale to fp32
    a = resample(x, 40, 0.5)
    b = resample(torch.cat([x, torch.randn(2, 6, 3, 10)], -1), 60, 0.5)
    assert torch.allclose(a[..., :30], b[..., :30])


def test_resample_grids_are_kept_per_length_ratio_dtype():
    """The cached grids serve each (length, ratio, input length, dtype) its own: a float64 call after a float32 one
    of the same shape stays float64 and exact, and the cached tensors are not changed by use."""
    x32 = torch.randn(1, 6, 2, 11)
    a = resample(x32, 15, 11 / 15)
    x64 = x32.double()
    b = resample(x64, 15, 11 / 15)
    assert a.dtype == torch.float32 and b.dtype == torch.float64
    ref = torch.nn.functional.interpolate(x64.reshape(1, 12, 11), size=15, mode="linear", align_corners=False)
    torch.testing.assert_close(b.reshape(1, 12, 15), ref, rtol=1e-12, atol=1e-12)
    b.add_(1.0)  # the result is the caller's: the next call computes afresh
    torch.testing.assert_close(resample(x64, 15, 11 / 15).reshape(1, 12, 15), ref, rtol=1e-12, atol=1e-12)
    assert resample(x32, 7, 11 / 7).shape[-1] == 7  # another length, another grid
    with torch.inference_mode():  # a grid first built while sampling ...
        resample(x32, 9, 11 / 9)
    y = x32.clone().requires_grad_(True)
    resample(y, 9, 11 / 9).sum().backward()  # ... serves a backward later (its tensors are saved for it)
    assert y.grad is not None and y.grad.abs().sum() > 0


# ------------------------------------------------------------------------------------------- features


def test_features_round_trip_rotations_and_root():
    clip = synthetic_clip([-1, 0, 1, 0, 3], 50, seed=4, walk=0.03)
    seq = sequence_from_clip(clip, "rt", tiny_cfg())
    quats, root, _ = features_to_motion(seq.features, seq.n_joints, seq.root_start)
    dots = (quats.double() * clip.rotations).sum(-1).abs()
    assert torch.allclose(dots, torch.ones_like(dots), atol=1e-5)
    assert torch.allclose(root.double(), clip.root_positions * seq.scale, atol=1e-5)


# ------------------------------------------------------------------------------------------- learning


def test_reconstruction_from_zstar_improves_with_training(tmp_path):
    torch.manual_seed(0)
    cfg = tiny_cfg(iterations=25, max_levels=2, coarse_ratio=0.5, lr=2e-3, d_steps=1)
    seq = clip_seq([-1, 0, 1, 0, 3], T=48, seed=5)
    trainer = Trainer([seq], cfg, tmp_path / "run")
    real = trainer.reals[0][-1]
    with torch.no_grad():
        before = (trainer.model.reconstruct(0) - real).abs().mean().item()
    model = trainer.run(progress=False, log=None)
    with torch.no_grad():
        after = (model.reconstruct(0) - real).abs().mean().item()
    assert after < 0.5 * before, (before, after)


def test_generated_length_is_as_requested():
    cfg = tiny_cfg()
    seq = clip_seq([-1, 0, 1, 2, 0, 4], T=64, seed=6)
    model = untrained_model([seq], cfg)
    for n in (17, 64, 101, 250):
        out = model.sample(n, 2)
        assert tuple(out.shape) == (2, 6, seq.n_entities, n)
        quats, root, contacts = features_to_motion(out[0], seq.n_joints)
        assert quats.shape == (n, seq.n_joints, 4) and root.shape == (n, 3)


# ------------------------------------------------------------------------------------------- streaming


def test_streaming_appends_never_change_emitted_frames():
    from modi.models.ganimator.generate import TrajectoryStream

    cfg = tiny_cfg(conditional=True)
    seq = clip_seq([-1, 0, 1, 0, 3, 0], T=80, seed=7)
    model = untrained_model([seq], cfg).eval()
    for g in model.gens:  # make every level matter
        for p in g.parameters():
            p.data.add_(0.05 * torch.randn_like(p))
    traj = torch.randn(1, 6, 2, 230) * 0.1
    stream = TrajectoryStream(model, seed=3, fine_noise=True)
    parts, seen = [], 0
    for cut in (40, 55, 30, 70, 35):
        had_output = stream.emitted > 0
        part = stream.extend(traj[..., seen:seen + cut])
        seen += cut
        parts.append(part)
        emitted = torch.cat(parts, -1)
        if emitted.shape[-1]:
            # a full recomputation on everything received so far agrees on every emitted frame
            full = stream.offline(traj[..., :seen])
            assert torch.allclose(emitted, full[..., : emitted.shape[-1]], atol=1e-4)
            if had_output:  # only the tail of the finest level was recomputed
                assert stream.windows[-1] < seen
    parts.append(stream.finish())
    streamed = torch.cat(parts, -1)
    assert streamed.shape[-1] == 230
    assert torch.allclose(streamed, stream.offline(traj), atol=1e-4)
    # the emitted frames honour the trajectory exactly (concatenation trick)
    assert torch.allclose(streamed[:, :, model.cond_entities], traj, atol=1e-5)


# ------------------------------------------------------------------------------------------- checkpoints


def test_progress_file_follows_the_schedule(tmp_path):
    """RUN/progress.json is what front ends (the Blender add-on) poll: paused mid-block it says where the run is,
    finished it says done with every iteration counted."""
    import json

    cfg = tiny_cfg(iterations=3, max_levels=3, coarse_ratio=0.4)
    seq = clip_seq([-1, 0, 1, 0, 3], T=40, seed=8)
    trainer = Trainer([seq], cfg, tmp_path / "r")
    trainer.run(progress=False, log=None, max_seconds=0.0)
    p = json.loads((tmp_path / "r" / "progress.json").read_text())
    total = sum(cfg.block_budgets(len(trainer.blocks)))
    assert (p["state"], p["block"], p["iteration"], p["done_iterations"]) == ("paused", 1, 1, 1)
    assert p["total_iterations"] == total and p["blocks"] == len(trainer.blocks) and p["eta_s"] > 0
    Trainer([seq], cfg, tmp_path / "r").run(progress=False, log=None)
    p = json.loads((tmp_path / "r" / "progress.json").read_text())
    assert p["state"] == "done" and p["done_iterations"] == p["total_iterations"] == total and p["eta_s"] is None



def test_checkpoint_round_trip_and_exact_resume(tmp_path):
    cfg = tiny_cfg(iterations=3, max_levels=3, coarse_ratio=0.4)
    seq = clip_seq([-1, 0, 1, 0, 3], T=40, seed=8)
    full = train([seq], cfg, tmp_path / "a", progress=False, log=None)
    # interrupted after the first iteration, then resumed by a new trainer on the same directory
    Trainer([seq], cfg, tmp_path / "b").run(progress=False, log=None, max_seconds=0.0)
    assert read_checkpoint(tmp_path / "b")["state"]["iteration"] == 1
    resumed = Trainer([seq], cfg, tmp_path / "b").run(progress=False, log=None)
    for ga, gb in zip(full.gens, resumed.gens):
        for pa, pb in zip(ga.state_dict().values(), gb.state_dict().values()):
            assert torch.equal(pa, pb)
    loaded = load_model(tmp_path / "a")
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    assert torch.equal(full.sample(55, 2, generator=g1), loaded.sample(55, 2, generator=g2))
    assert torch.equal(full.reconstruct(0), loaded.reconstruct(0))
    # a different clip in the same run directory is refused, not silently mixed
    other = clip_seq([-1, 0, 1, 0, 3], T=44, seed=9)
    with pytest.raises(CheckpointError):
        Trainer([other], cfg, tmp_path / "a").run(progress=False, log=None)
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        load_model(tmp_path / "junk.ckpt")


def test_cli_generate_writes_requested_frames(tmp_path):
    from modi.cli import main

    cfg = tiny_cfg(iterations=1, max_levels=2, coarse_ratio=0.5)
    seq = clip_seq([-1, 0, 1, 0, 3], T=40, seed=10)
    train([seq], cfg, tmp_path / "run", progress=False, log=None)
    assert main(["ganimator", "generate", str(tmp_path / "run"), "--frames", "73", "--n", "2",
                 "--out", str(tmp_path / "gen"), "--no-gif"]) == 0
    for i in range(2):
        clip = read_clip(tmp_path / "gen" / f"sample_{i:03d}.bvh")
        assert clip.rotations.shape == (73, 5, 4)
    assert main(["ganimator", "generate", str(tmp_path / "nope"), "--out", str(tmp_path / "g2")]) == 2
    assert main(["ganimator", "train", str(tmp_path / "missing.bvh"), "--out", str(tmp_path / "r2")]) == 2


# ------------------------------------------------------------------------------------------- real data


def test_real_skeletons_reduce_and_find_feet(shared_data):
    from modi.models.ganimator.data import load_sequence, load_sequences

    root = shared_data / "bvh" / "ganimator"
    cfg = gconfig.preset("fast")
    salsa = load_sequence(root / "Joe" / "Salsa-Dancing-6.bvh", cfg)
    assert salsa.n_joints == 24 and salsa.fps == pytest.approx(30.0, abs=0.01) and salsa.n_frames == 648
    assert sorted(salsa.skeleton.names[f] for f in salsa.feet) == [
        "LeftToeBase", "LeftToe_End", "RightToeBase", "RightToe_End"]
    crab = load_sequence(root / "Crabnew" / "Crab-dance-long.bvh", cfg)
    assert crab.n_joints == 56 and len(crab.feet) == 6
    assert all(crab.skeleton.names[f].endswith("_end") for f in crab.feet)
    eles = load_sequences([root / "Elephant" / "idle1.bvh", root / "Elephant" / "idle2.bvh"], cfg)
    assert eles[0].skeleton.names == eles[1].skeleton.names and eles[0].feet == eles[1].feet
    assert len(eles[0].feet) == 6
    # the authors' reduced key-frame file maps onto the reduced Joe skeleton by name
    keys = load_sequence(root / "Joe" / "Baseball-Milling-Idle-edited-keyframes.bvh", cfg, like=salsa)
    assert keys.n_frames == 21 and keys.skeleton.names == salsa.skeleton.names
    with pytest.raises(UserError):
        load_sequence(root / "Crabnew" / "Crab-dance-long.bvh", cfg, like=salsa)


def test_bandai_pelvis_motion_reaches_the_root_track(shared_data):
    """Bandai files animate Hips' translation under a static joint_Root: read_clip must keep that motion (it
    moves into the root track), so GANimator learns the pelvis moving, not a pelvis nailed at its rest offset."""
    from modi.io import bvh as bvh_io
    from modi.core.kinematics import forward_kinematics

    path = shared_data / "bvh" / "bandai-namco-1" / "data" / "dataset-1_byebye_angry_001.bvh"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    b = bvh_io.load(str(path))
    clip = read_clip(path)
    exact, _ = forward_kinematics(clip.rotations, torch.from_numpy(b.local_translations()), b.parents,
                                  torch.from_numpy(b.local_translations()[:, 0].copy()))
    ours, _ = forward_kinematics(clip.rotations, clip.skeleton.offsets, b.parents, clip.root_positions)
    height = float(exact[0, :, 1].max() - exact[0, :, 1].min())
    assert float((exact[:, 1:] - ours[:, 1:]).abs().max()) < 1e-4 * height  # every joint but the dummy root
    hips = exact[:, 1]
    assert float((hips - hips.mean(0)).abs().max()) > 0.01 * height  # the pelvis really moves in this clip


def test_iterations_help_names_the_coarse_multiplier_and_min_frames_is_the_shortest():
    import argparse

    from modi.cli.commands import ganimator as cmd
    from modi.models.ganimator.data import min_training_frames

    parser = argparse.ArgumentParser()
    cmd.register(parser.add_subparsers())
    train = parser._subparsers._group_actions[0].choices["ganimator"]._subparsers._group_actions[0].choices["train"]
    help_ = next(a.help for a in train._actions if "--iterations" in a.option_strings)
    assert "× --coarse-multiplier" in help_ and "fast preset multiplies it by 3" in help_
    assert gconfig.preset("fast").block_budgets(2) == [900, 300]
    for ratio in (0.2, 0.5):
        cfg = gconfig.preset("paper", coarse_ratio=ratio)
        n = min_training_frames(cfg)
        need = cfg.kernel_size // 2 + 1
        coarsest = lambda m: pyramid_lengths(m, cfg.coarse_ratio, cfg.scale_factor)[0]  # noqa: E731
        assert coarsest(n) >= need and all(coarsest(m) < need for m in range(2, n))


# ------------------------------------------------------------------------------------------- D / G building blocks


@pytest.mark.parametrize("padding_mode", ["reflect", "replicate", "zeros"])
@pytest.mark.parametrize("U", [1, 3, 5])
def test_score_head_is_the_conv1d_it_replaces(padding_mode, U):
    """The matmul form of D's one-output temporal conv: same values and gradients of every order as nn.Conv1d."""
    from modi.models.ganimator.networks import score_head

    g = torch.Generator().manual_seed(U)
    conv = torch.nn.Conv1d(12, 1, U, padding=U // 2, padding_mode=padding_mode).double()
    h = torch.randn(3, 12, 9, dtype=torch.float64, generator=g, requires_grad=True)
    torch.testing.assert_close(score_head(conv, h), conv(h).squeeze(1), rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradgradcheck(lambda h, w, b: score_head(_with(conv, w, b), h),
                                        (h, conv.weight, conv.bias), eps=1e-6, atol=1e-6)


def _with(conv, w, b):
    """A copy of ``conv`` whose parameters are the given tensors (for gradcheck w.r.t. them)."""
    c = torch.nn.Conv1d(conv.in_channels, 1, conv.kernel_size[0], padding=conv.padding[0],
                        padding_mode=conv.padding_mode).double()
    del c.weight, c.bias
    c.weight, c.bias = w, b
    return c


def test_score_head_falls_back_for_other_convs():
    from modi.models.ganimator.networks import score_head

    conv = torch.nn.Conv1d(6, 1, 3, padding=0)
    h = torch.randn(2, 6, 10)
    torch.testing.assert_close(score_head(conv, h), conv(h).squeeze(1))


def test_folded_scale_gives_the_plain_weight_to_the_op():
    from modi_ext.layers import SkeletalConv

    nb = ganimator_neighbors([-1, 0, 1, 0, 3], [2, 4], 2)
    torch.manual_seed(0)
    a = SkeletalConv(3, 4, nb, kernel_size=5, padding_mode="reflect", bias=False)
    b = SkeletalConv(3, 4, nb, kernel_size=5, padding_mode="reflect", bias=False)
    b.load_state_dict(a.state_dict())
    expected = a.effective_weight().detach() * 0.5
    b.fold_weight_scale(0.5)
    assert b.effective_weight() is b.weight and torch.equal(b.weight_scale, torch.ones_like(b.weight_scale))
    torch.testing.assert_close(b.weight.detach(), expected, rtol=0, atol=0)
    x = torch.randn(2, 3, len(nb), 11)
    torch.testing.assert_close(b(x), 0.5 * a(x), rtol=1e-5, atol=1e-6)
    # a model built the same way and loaded from a state_dict runs the loaded weight as it is
    c = SkeletalConv(3, 4, nb, kernel_size=5, padding_mode="reflect", bias=False)
    c.fold_weight_scale(0.5)
    c.load_state_dict(b.state_dict())
    torch.testing.assert_close(c(x), b(x), rtol=0, atol=0)


def test_discriminator_scores_each_sample_of_a_batch_alone():
    """The D step scores fake and real in one batch: D must couple no samples (on the kernels and the reference)."""
    cfg = tiny_cfg()
    seq = clip_seq(random_tree(7, random.Random(4)), T=50, seed=4)
    model = untrained_model([seq], cfg)
    d = model.discs[-1]
    L = model.lengths[0][-1]
    a, b = torch.randn(1, 6, seq.n_entities, L), torch.randn(1, 6, seq.n_entities, L)
    both = d(torch.cat([a, b]))
    torch.testing.assert_close(both, torch.cat([d(a), d(b)]), rtol=1e-5, atol=1e-5)


def test_gradient_penalty_is_the_per_frame_norm_formula():
    """WGAN-GP as the released code writes it (norm over channels x entities of each frame), zero gradients included."""
    from modi.models.ganimator.training import gradient_penalty

    class D(torch.nn.Module):
        def __init__(self, scale):
            super().__init__()
            self.w = torch.nn.Parameter(scale * torch.randn(6, 5, dtype=torch.float64))

        def forward(self, x):
            return torch.einsum("bcet,ce->bt", x.tanh(), self.w)

    real, fake = torch.randn(2, 1, 6, 5, 7, dtype=torch.float64)
    for scale in (1.0, 0.0):
        d = D(scale)
        torch.manual_seed(0)
        gp = gradient_penalty(d, real, fake)
        torch.manual_seed(0)
        alpha = torch.rand((1,))
        interp = (alpha * real + (1 - alpha) * fake).requires_grad_(True)
        (g,) = torch.autograd.grad(d(interp).sum(), interp, create_graph=True)
        expected = ((g.flatten(1, 2).norm(dim=1) - 1.0) ** 2).mean()
        torch.testing.assert_close(gp, expected, rtol=1e-12, atol=1e-12)
        (got_w,) = torch.autograd.grad(gp, d.w)
        (want_w,) = torch.autograd.grad(expected, d.w)
        assert torch.isfinite(got_w).all()
        torch.testing.assert_close(got_w, want_w, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------------------- divergence (issue 32)


def _nan_after(monkeypatch, calls: int) -> None:
    """The gradient penalty turns NaN after ``calls`` calls (one per level of the block per D step)."""
    import modi.models.ganimator.training as gt

    real_gp, count = gt.gradient_penalty, [0]

    def gp(*a, **k):
        count[0] += 1
        out = real_gp(*a, **k)
        return out * float("nan") if count[0] > calls else out

    monkeypatch.setattr(gt, "gradient_penalty", gp)


def test_an_iteration_asks_nothing_of_the_device(tmp_path, monkeypatch):
    """Outside log iterations an iteration reads no value from the device and uploads nothing: the losses stay
    tensors, the non-finite guard skips a step on the device, the feet are a device index. The fake pool's coin
    (``FakePool.query``) is a draw from the CPU generator, as the authors' pool draws, so on CUDA it waits for
    nothing; its reads are counted apart, and every one of them is of a CPU tensor."""
    from benchmarks.step_ops import OpCounter

    from modi.models.ganimator import training as gt

    cfg = tiny_cfg(iterations=6, max_levels=2, coarse_ratio=0.5, d_steps=2)
    seq = clip_seq([-1, 0, 1, 0, 3], T=40, seed=8, cfg=cfg)
    trainer = Trainer([seq], cfg, tmp_path / "r")
    counter, in_pool, pool_reads = OpCounter(), [False], []

    class Watch(torch.utils._python_dispatch.TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if in_pool[0] and func is torch.ops.aten._local_scalar_dense.default:
                pool_reads.append(args[0].device.type)
            return func(*args, **(kwargs or {}))

    query = gt.FakePool.query

    def watched_query(self, fake):
        in_pool[0] = True
        try:
            return query(self, fake)
        finally:
            in_pool[0] = False

    monkeypatch.setattr(gt.FakePool, "query", watched_query)
    iteration = trainer._iteration

    def counted(*a, **k):
        counter.mark(pool_reads=len(pool_reads))
        with counter, Watch():
            return iteration(*a, **k)

    monkeypatch.setattr(trainer, "_iteration", counted)
    trainer.run(progress=False, log=None)
    steps = counter.steps[1:6]  # the first iteration also makes what is made once (checks, self-test)
    assert len(steps) == 5 and pool_reads and set(pool_reads) == {"cpu"}
    marks = [s["pool_reads"] for s in counter.steps[1:7]]
    for s, before, after in zip(steps, marks, marks[1:]):
        assert s["syncs"] == after - before, s["syncs"]  # the pool's coin, nothing else
        assert s["h2d"] == 0


@pytest.mark.parametrize("fused", [True, False], ids=["skipped-on-the-device", "host-check"])
def test_a_non_finite_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch, fused):
    """Fused Adam skips the step on the device and the save reads the guard; an optimiser off the fused kernel (a
    checkpoint saved without it) checks on the host before its step. Either way: the same message and checkpoint."""
    from modi.models.ganimator import training as gt
    from modi.models.ganimator.training import NonFiniteLossError

    if not fused:
        monkeypatch.setattr(gt, "fused_adam", lambda params, lr, betas: torch.optim.Adam(params, lr=lr, betas=betas))

    cfg = tiny_cfg(iterations=4, max_levels=2, coarse_ratio=0.5)
    seq = clip_seq([-1, 0, 1, 0, 3], T=40, seed=8)
    # the oracle: the same schedule stopped cleanly after 2 iterations
    Trainer([seq], cfg, tmp_path / "clean").run(progress=False, log=None, max_seconds=0.0)
    Trainer([seq], cfg, tmp_path / "clean").run(progress=False, log=None, max_seconds=0.0)
    clean = read_checkpoint(tmp_path / "clean")
    assert clean["state"]["iteration"] == 2
    _nan_after(monkeypatch, calls=2 * 2)  # the block has 2 levels: iteration 3's penalty is NaN
    with pytest.raises(NonFiniteLossError) as info:
        train([seq], cfg.replace(checkpoint_every=0.0), tmp_path / "bad", progress=False, log=None)
    msg = str(info.value)
    assert "\n" not in msg and "non-finite loss (discriminator" in msg and "iteration 3" in msg, msg
    assert str(tmp_path / "bad" / "ganimator.ckpt") in msg and "iteration 2" in msg, msg
    kept = read_checkpoint(tmp_path / "bad")
    assert kept["state"]["iteration"] == 2
    for g_kept, g_clean in zip(kept["model"]["gens"], clean["model"]["gens"]):
        for k in g_clean:
            assert torch.isfinite(g_kept[k]).all() and torch.equal(g_kept[k], g_clean[k]), k


def test_non_finite_weights_are_never_saved(tmp_path):
    from modi.models.ganimator.training import NonFiniteLossError

    cfg = tiny_cfg(iterations=2, max_levels=2, coarse_ratio=0.5)
    seq = clip_seq([-1, 0, 1, 0, 3], T=40, seed=8)
    trainer = Trainer([seq], cfg, tmp_path / "r")
    trainer.run(progress=False, log=None, max_seconds=0.0)
    before = (tmp_path / "r" / "ganimator.ckpt").read_bytes()
    with torch.no_grad():
        next(trainer.model.discs[1].parameters())[0] = float("inf")
    with pytest.raises(NonFiniteLossError, match="non-finite weights \\(discriminator 1\\)"):
        trainer.save()
    assert (tmp_path / "r" / "ganimator.ckpt").read_bytes() == before


def test_cli_train_on_a_diverging_run_is_one_line_exit_2(tmp_path, monkeypatch, capsys):
    from modi.cli import main
    from modi.data.procedural import write_dataset

    (clip, *_) = write_dataset(tmp_path / "d", n_clips=1, frames=40, seed=0)
    _nan_after(monkeypatch, calls=0)
    capsys.readouterr()
    rc = main(["ganimator", "train", str(clip), "--out", str(tmp_path / "run"), "--preset", "tiny",
               "--iterations", "2", "--quiet"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert rc == 2 and len(err) == 1 and "non-finite loss" in err[0] and "nothing was saved" in err[0], err
    assert not (tmp_path / "run" / "ganimator.ckpt").exists()
