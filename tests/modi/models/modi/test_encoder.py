"""The encoder into W+ and its applications, on a tiny in-process generator (16 frames, built-in humanoid).

A GAN cannot be trained inside a test, so the fixture makes the tiny generator a decoder of procedural motion by a
short autoencoder fit (generator + a throwaway encoder); the generator is then frozen and a fresh encoder is
trained by ``EncoderTrainer`` exactly as ``modi encoder train`` does, on an 80/20 split of the windows.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from modi.models.modi.encoder import applications as A
from modi.models.modi.encoder.metrics import PAPER_TABLE5, evaluate_encoder, format_table5, reconstruction_metrics
from modi.models.modi.encoder.model import build_encoder, encode, visible_input
from modi.models.modi.encoder.training import (EncoderTrainConfig, EncoderTrainer, encoder_losses, generator_bundle,
                                   load_encoder, split_windows)
from modi.errors import CheckpointError, UserError
from modi.models.modi.latent import space

T = 16


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def procedural_windows():
    from modi.data.normalization import Normalizer
    from modi.data.procedural import KINDS, builtin_skeleton, generate_clip
    from modi.data.representation import modi_representation

    sk = builtin_skeleton()
    rep = modi_representation(sk, sk.detect_feet())
    raw = torch.cat([rep.encode(generate_clip(KINDS[i % 6], 64, 30.0, np.random.default_rng(i)))
                     .unfold(-1, T, 4).permute(2, 0, 1, 3) for i in range(12)]).float()
    J = rep.n_joints
    raw[:, 0, J, 0] = 0.0  # windows start at x = z = 0, like the dataset's
    raw[:, 2, J, 0] = 0.0
    return rep, Normalizer.fit(raw, skip_entities=rep.contacts), raw


def decoder_generator(steps: int = 250):
    """(g, codec, normalised windows): a tiny generator fitted as the decoder of an autoencoder, then frozen."""
    from modi.models.modi.config import ModelConfig
    from modi.models.modi.levels import build_levels
    from modi.models.modi.networks import Generator
    from modi.models.modi.training import MotionCodec
    from modi.core.skeleton_graph import build_hierarchy

    torch.manual_seed(0)
    rep, norm, raw = procedural_windows()
    codec = MotionCodec(rep, norm, 30.0)
    x = norm.normalize(raw)
    cfg = ModelConfig(latent_dim=16, n_mlp=2, channels=(8, 8, 8))
    g = Generator(cfg, build_levels(build_hierarchy(rep.skeleton, rep.feet), cfg, T), rep.K)
    enc = build_encoder(g, head="bottleneck")
    opt = torch.optim.Adam(list(g.parameters()) + list(enc.parameters()), lr=0.005, betas=(0.9, 0.99))
    gen = torch.Generator().manual_seed(0)
    for _ in range(steps):
        xb = x[torch.randint(len(x), (16,), generator=gen)]
        loss = (g.synthesis(encode(enc, xb), noise_mode="const") - xb).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    g.eval()
    for p in g.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        g.w_avg.copy_(encode(enc, x).mean((0, 1)))  # the mean latent of the data's codes
    return g, codec, x


@pytest.fixture(scope="module")
def model():
    return decoder_generator()


@pytest.fixture(scope="module")
def trained(model, tmp_path_factory):
    g, codec, x = model
    data = split_windows(x, 0.2, seed=0)
    out = tmp_path_factory.mktemp("enc") / "enc.pt"
    # 300 steps left the encoder within ~2% of the mean-motion baseline, so float rounding of a different kernel
    # build could flip the comparison; 600 steps give it a margin (L2 0.92-0.95x the baseline on the ext and dense paths)
    cfg = EncoderTrainConfig(iters=600, batch=16, lr=0.005, eval_every=0, ckpt_every=0)
    res = EncoderTrainer((g, codec, None), data, out, cfg, progress=False).train()
    return res, data, load_encoder(out)


# --------------------------------------------------------------------------------------------- model
def test_encoder_shapes_and_untrained_output_is_the_mean(model):
    g, codec, x = model
    enc = build_encoder(g, head="bottleneck")
    w = enc(x[:3])
    assert w.shape == (3, g.n_latent, g.latent_dim)
    torch.testing.assert_close(enc.w_avg, g.w_avg)  # predictions are offsets from the mean latent
    with pytest.raises(ValueError, match="encoder input"):
        enc(x[:2, :, :3])


def test_prefix_encoder_ignores_the_hidden_frames(model):
    g, codec, x = model
    enc = build_encoder(g, prefix_frames=6).eval()
    a = x[:2].clone()
    b = a.clone()
    b[..., 6:] = torch.randn_like(b[..., 6:]) * 3  # a different future
    torch.testing.assert_close(encode(enc, a), encode(enc, b))
    changed = a.clone()
    changed[..., 2] += 1.0  # a visible frame matters
    assert (encode(enc, changed) - encode(enc, a)).abs().max() > 1e-6
    inp, mask = visible_input(a, 6)
    assert torch.all(inp[..., 6:] == 0) and torch.all(mask[..., :6] == 1) and torch.all(mask[..., 6:] == 0)
    with pytest.raises(ValueError, match="prefix_frames"):
        build_encoder(g, prefix_frames=T)


def test_losses_are_zero_on_a_perfect_reconstruction_and_weighted(model):
    g, codec, x = model
    cfg = EncoderTrainConfig(losses="ours")
    real = x[:4]
    same = encoder_losses(codec, real, real, cfg, space.position_scale(codec))
    assert float(same["rec"]) == 0 and float(same["root"]) == 0 and float(same["pos"]) == 0
    noisy = real + 0.1 * torch.randn_like(real)
    out = encoder_losses(codec, noisy, real, cfg, space.position_scale(codec))
    total = out["rec"] + 100 * out["contact"] + 2 * out["root"] + 0.1 * out["pos"]
    torch.testing.assert_close(out["total"], total)
    J = codec.rep.n_joints
    expected_root = ((noisy[:, :, J] - real[:, :, J]) ** 2).mean() + ((noisy[:, :, 0] - real[:, :, 0]) ** 2).mean()
    torch.testing.assert_close(out["root"], expected_root)


# --------------------------------------------------------------------------------------------- metrics
def test_metrics_measure_known_displacements_in_mm(model):
    g, codec, x = model
    real = x[:3]
    zero = reconstruction_metrics(codec, real, real)
    assert all(abs(zero[k]) < 1e-6 for k in ("l2", "l1", "root_mm", "local_mm", "global_mm"))
    # shift the whole trajectory by d units along x: the root velocity of frame 0 carries the start position
    d = 5.0
    J = codec.rep.n_joints
    shifted = real.clone()
    shifted[:, 0, J, 0] += d / codec.normalizer.std[0, J]
    m = reconstruction_metrics(codec, real, shifted)
    mm = space.mm_per_unit(codec.height)
    assert mm == 10.0  # the built-in humanoid is in centimetres
    assert m["root_mm"] == pytest.approx(d * mm, rel=1e-3)
    assert m["global_mm"] == pytest.approx(d * mm, rel=1e-3)
    assert m["local_mm"] == pytest.approx(0.0, abs=1e-3)
    assert m["l2"] == pytest.approx(float(((shifted - real) ** 2).mean()), rel=1e-5)
    # the released definitions: mean squared coordinate error in data units (x moved by d, y and z not)
    assert m["root_mse"] == pytest.approx(d * d / 3, rel=1e-3)
    assert m["global_mse"] == pytest.approx(d * d / 3, rel=1e-3)
    assert m["local_mse"] == pytest.approx(0.0, abs=1e-6)
    assert m["global_mse_cm2"] == pytest.approx(m["global_mse"], rel=1e-6)  # the humanoid is in cm
    # a rotation error changes local positions: MSE = mean over joints/frames/coords of the squared differences
    turned = real.clone()
    turned[:, 1, 0] += 0.3
    m2 = reconstruction_metrics(codec, real, turned)
    dr, dt = codec.decode(real), codec.decode(turned)
    loc = lambda d_: d_["positions"] - d_["root"][..., None, :]  # noqa: E731 - FK with root translation zeroed
    assert m2["local_mse"] == pytest.approx(float((loc(dr) - loc(dt)).pow(2).mean()), rel=1e-4)
    assert m2["local_mse"] > 0


def test_encoder_beats_the_trivial_baselines_on_the_test_split(trained, model):
    res, data, bundle = trained
    g, codec, _ = model
    m = res.metrics
    assert m["n_windows"] == data.test.shape[0]
    enc, base = m["encoder"], m["mean_motion"]
    assert enc["l2"] < base["l2"]
    assert enc["global_mm"] < 0.8 * base["global_mm"]
    assert enc["root_mm"] < 0.8 * base["root_mm"]
    # the reloaded checkpoint gives the same numbers
    again = evaluate_encoder(bundle.encoder, bundle.g, bundle.codec, data.test)
    assert again["encoder"]["l2"] == pytest.approx(enc["l2"], rel=1e-4)
    table = format_table5(m)
    assert "mean motion" in table and f"{PAPER_TABLE5['global_mm']:.1f}" in table
    assert "Local position (mm)" in table and "Local position (MSE)" in table  # both definitions
    assert "Local position (MSE)" not in format_table5(m, definitions=("ours",))


def test_checkpoint_is_self_contained_and_resume_is_exact(model, tmp_path):
    g, codec, x = model
    data = split_windows(x[:40], 0.2, seed=1)
    cfg = EncoderTrainConfig(iters=4, batch=4, eval_every=0, ckpt_every=0)
    straight = EncoderTrainer((g, codec, None), data, tmp_path / "a.pt", cfg, progress=False)
    straight.train()
    half = EncoderTrainer((g, codec, None), data, tmp_path / "b.pt", cfg, progress=False)
    half.train(2)
    resumed = EncoderTrainer((g, codec, None), data, tmp_path / "b.pt", cfg, progress=False, resume=tmp_path / "b.pt")
    assert resumed.step == 2
    resumed.train()
    for (k, a), b in zip(straight.encoder.state_dict().items(), resumed.encoder.state_dict().values()):
        torch.testing.assert_close(a, b, msg=k)
    bundle = load_encoder(tmp_path / "a.pt")
    torch.testing.assert_close(bundle.g.synthesis(space.as_wplus(bundle.g, g.w_avg[None]), noise_mode="const"),
                               space.mean_motion(g))
    with pytest.raises(CheckpointError, match="generator checkpoint"):
        torch.save(generator_bundle(g, codec), tmp_path / "gen.pt")
        load_encoder(tmp_path / "gen.pt")
    other = EncoderTrainConfig(iters=4, batch=4, eval_every=0, ckpt_every=0, prefix_frames=5)
    with pytest.raises(CheckpointError, match="built differently"):
        EncoderTrainer((g, codec, None), data, tmp_path / "c.pt", other, progress=False, resume=tmp_path / "a.pt")


# --------------------------------------------------------------------------------------------- applications
def test_fusion_keeps_prefix_and_suffix_close_to_their_sources(trained, tmp_path):
    _, data, bundle = trained
    te = data.test
    n = te.shape[0] // 2
    a, b = te[:n], te[n:2 * n]
    t = T // 2
    naive, fused = A.fuse(bundle, a, b, t)
    torch.testing.assert_close(naive[..., :t], a[..., :t])
    torch.testing.assert_close(naive[..., t:], b[..., t:])
    margin = 3
    pre, suf = slice(0, t - margin), slice(t + margin, None)

    def err(x, y, frames):
        return float((x[..., frames] - y[..., frames]).pow(2).mean())

    assert err(fused, a, pre) < err(fused, b, pre)
    assert err(fused, b, suf) < err(fused, a, suf)
    r = A.fuse_motions(bundle, a[:1], b[:1], t, tmp_path, name="ab")
    assert (tmp_path / "ab.gif").is_file() and len(r["bvh"]) == 4
    with pytest.raises(UserError, match="fusion frame"):
        A.concatenate(a, b, 0)


def test_applications_write_triplets_and_report(trained, tmp_path):
    _, data, bundle = trained
    x = data.test[:1]
    inv = A.invert_motions(bundle, x, tmp_path / "inv", ["m"], optim_steps=3, progress=False)[0]
    assert [p.rsplit("_", 1)[1] for p in inv["bvh"]] == ["input.bvh", "naive.bvh", "encoder.bvh"]
    assert (tmp_path / "inv" / "m.gif").is_file()
    den = A.denoise_motions(bundle, x, tmp_path / "den", ["m"], sigma=0.5)[0]
    assert den["l2_naive"] < den["l2_noisy"]  # smoothing removes part of white noise
    with pytest.raises(UserError, match="--prefix"):
        A.complete_prefix(bundle, x, tmp_path / "p")


def test_noise_smoothing_and_hold_helpers(model):
    g, codec, x = model
    noisy = A.add_noise(codec, x[:2], 0.3, seed=0)
    J = codec.rep.n_joints
    torch.testing.assert_close(noisy[:, :, J:], x[:2, :, J:])  # root motion and contacts untouched
    assert float((noisy[:, :, :J] - x[:2, :, :J]).std()) == pytest.approx(0.3, rel=0.1)
    const = torch.ones(1, 2, 3, 10) * 4.0
    torch.testing.assert_close(A.smooth_time(const, 2.0), const)
    held = A.hold_after(codec, x[:1], 5)
    raw = codec.normalizer.denormalize(held)
    torch.testing.assert_close(raw[..., :J, 7], raw[..., :J, 4])
    assert torch.all(raw[:, [0, 2], J, 5:] == 0)  # the root stops


def test_raise_arm_lifts_the_edited_frames_only(model):
    from modi.models.modi.latent.editing import bone_elevation, find_right_arm

    g, codec, x = model
    s, e, _ = find_right_arm(codec.skeleton)
    src = x[:2]
    edited = A.raise_arm(codec, src, angle=40.0, start=8)

    def elev(m):
        return bone_elevation(codec.decode(m)["positions"], s, e)

    before, after = elev(src), elev(edited)
    torch.testing.assert_close(after[:, :8], before[:, :8], atol=1e-3, rtol=0)
    raised = before[:, 8:] + 40.0
    expected = torch.where(raised <= 180.0, raised, 360.0 - raised)  # past vertical the bone comes down again
    torch.testing.assert_close(after[:, 8:], expected, atol=0.5, rtol=0)


def test_prefix_completion_end_to_end(model, tmp_path):
    g, codec, x = model
    data = split_windows(x, 0.2, seed=0)
    cfg = EncoderTrainConfig(iters=3, batch=4, eval_every=0, ckpt_every=0, prefix_frames=6)
    EncoderTrainer((g, codec, None), data, tmp_path / "p.pt", cfg, progress=False).train()
    bundle = load_encoder(tmp_path / "p.pt")
    r = A.complete_prefix(bundle, data.test[:1], tmp_path / "out", ["m"])[0]
    assert r["prefix_frames"] == 6 and (tmp_path / "out" / "m.gif").is_file()


def test_apply_cli_on_bvh_inputs(trained, tmp_path, capsys):
    from modi.cli import main
    from modi.data.procedural import generate_clip

    res, _, _ = trained
    clips = []
    for i, kind in enumerate(("walk", "jump")):
        p = tmp_path / f"{kind}.bvh"
        generate_clip(kind, 40, 30.0, np.random.default_rng(i)).save(p)
        clips.append(str(p))
    enc = str(res.checkpoint)
    assert main(["apply", "fuse", enc, *clips, "--out", str(tmp_path / "f"), "--frame", "8", "--start", "4"]) == 0
    out = json.loads((tmp_path / "f" / "results.json").read_text())
    assert out[0]["t"] == 8 and (tmp_path / "f" / "walk+jump.gif").is_file()
    assert main(["apply", "edit", enc, clips[0], "--out", str(tmp_path / "e"), "--angle", "60"]) == 0
    assert main(["apply", "invert", enc, clips[0], "--out", str(tmp_path / "i"), "--start", "100"]) == 2
    assert "need 116" in capsys.readouterr().err
    assert main(["apply", "prefix", enc, clips[0], "--out", str(tmp_path / "p")]) == 2


# --------------------------------------------------------------------------------------------- released vs ours
def test_released_head_reads_one_level_before_the_coarsest(model):
    """models/gan.py LatentPrediction at latent_rec_idx 4: level-1 features -> two linear layers of width
    n_latent x latent_dim -> W+ (not an offset from w̄)."""
    g, codec, x = model
    enc = build_encoder(g)
    assert enc.cfg.head == "released" and enc.final_conv is None
    lv1 = enc.levels[1]
    width = g.n_latent * g.latent_dim
    assert enc.fc.weight.shape == (width, lv1.channels * lv1.n_entities * lv1.n_frames)
    assert enc.head.weight.shape == (width, width)
    assert len(enc.blocks) == len(enc.levels) - 2  # no block into the coarsest level
    w = enc(x[:3])
    assert w.shape == (3, g.n_latent, g.latent_dim)
    feats = enc.blocks(enc.from_motion(x[:3]))
    assert feats.shape[1:] == (lv1.channels, lv1.n_entities, lv1.n_frames)
    torch.testing.assert_close(w, enc.head(enc.fc(feats.flatten(1))).view_as(w))
    old = build_encoder(g, head="bottleneck")
    assert old.final_conv is not None and len(old.blocks) == len(old.levels) - 1
    # the released encoder has one in-place conv per residual block (its Discriminator's default), ours the
    # generator's count
    assert enc.cfg.inplace_convs == 1 and all(len(b.convs) == 1 + 1 for b in enc.blocks)
    n = g.cfg.n_inplace_convs
    assert old.cfg.inplace_convs is None and all(len(b.convs) == n + 1 for b in old.blocks)
    assert len(build_encoder(g, inplace_convs=n).blocks[0].convs) == n + 1
    with pytest.raises(ValueError, match="head"):
        build_encoder(g, head="wide")


def test_root_rotation_entity_skips_constant_placeholder_roots(model):
    from modi.models.modi.encoder.training import root_rotation_entity
    from modi.models.modi.codec import MotionCodec
    from modi.data.normalization import Normalizer
    from modi.data.representation import modi_representation
    from modi.core.skeleton import Skeleton

    g, codec, x = model
    assert root_rotation_entity(codec) == 0  # the built-in humanoid's root (hips) rotates
    # a Bandai-like rig: a placeholder root above the hips whose rotation never changes
    base = codec.skeleton
    sk = Skeleton(["joint_Root"] + list(base.names), [-1] + [p + 1 for p in base.parents],
                  np.concatenate([np.zeros((1, 3)), base.offsets]))
    rep = modi_representation(sk, [f + 1 for f in base.detect_feet()])
    std = torch.ones(rep.K, rep.n_entities)
    std[:, 0] = 1e-3  # Normalizer.fit's floor: constant in the data
    c2 = MotionCodec(rep, Normalizer(torch.zeros_like(std), std), 30.0)
    assert root_rotation_entity(c2) == 1
    std[1, 0] = 0.2  # a root that does rotate is the root
    assert root_rotation_entity(MotionCodec(rep, Normalizer(torch.zeros_like(std), std), 30.0)) == 0


def test_released_losses_weights_root_entity_and_local_positions(model):
    g, codec, x = model
    cfg = EncoderTrainConfig()
    assert (cfg.losses, cfg.lambda_rec, cfg.lambda_contact, cfg.lambda_root, cfg.lambda_pos) == \
        ("released", 10.0, 1000.0, 20.0, 1.0)
    assert cfg.lr == pytest.approx(0.002 * 16 / 17) and cfg.beta1 == 0.0 and cfg.beta2 == pytest.approx(0.99 ** (16 / 17))
    ours = EncoderTrainConfig(losses="ours", optimizer="ours")
    assert (ours.lambda_rec, ours.lambda_contact, ours.lambda_root, ours.lambda_pos, ours.lr, ours.beta1) == \
        (1.0, 100.0, 2.0, 0.1, 0.002, 0.9)
    assert EncoderTrainConfig(lambda_contact=100.0).lambda_contact == 100.0  # explicit values win
    real = x[:4]
    J = codec.rep.n_joints
    # moving the whole trajectory changes no local position: the released position term stays 0, ours does not
    shifted = real.clone()
    shifted[:, 0, J, 0] += 5.0 / codec.normalizer.std[0, J]
    scale = space.position_scale(codec)
    assert float(encoder_losses(codec, shifted, real, cfg, scale)["pos"]) == pytest.approx(0.0, abs=1e-6)
    assert float(encoder_losses(codec, shifted, real, ours, scale)["pos"]) > 1e-2
    # local positions in data units: turning the root changes them by known amounts
    noisy = real + 0.1 * torch.randn_like(real)
    out = encoder_losses(codec, noisy, real, cfg, scale, root_entity=3)
    dp, dt = codec.decode(noisy), codec.decode(real)
    local = ((dp["positions"] - dp["root"][..., None, :]) - (dt["positions"] - dt["root"][..., None, :])).pow(2).mean()
    torch.testing.assert_close(out["pos"], local)
    root = ((noisy[:, :, J] - real[:, :, J]) ** 2).mean() + ((noisy[:, :, 3] - real[:, :, 3]) ** 2).mean()
    torch.testing.assert_close(out["root"], root)
    torch.testing.assert_close(out["total"], 10 * out["rec"] + 1000 * out["contact"] + 20 * out["root"] + out["pos"])


def test_released_optimizer_and_old_checkpoints_keep_their_head(model, tmp_path):
    g, codec, x = model
    data = split_windows(x[:40], 0.2, seed=1)
    tr = EncoderTrainer((g, codec, None), data, tmp_path / "r.pt", EncoderTrainConfig(iters=1, batch=4, eval_every=0,
                                                                                       ckpt_every=0), progress=False)
    group = tr.optim.param_groups[0]
    assert group["lr"] == pytest.approx(0.002 * 16 / 17) and group["betas"] == (0.0, pytest.approx(0.99 ** (16 / 17)))
    cfg = EncoderTrainConfig(iters=1, batch=4, eval_every=0, ckpt_every=0, head="bottleneck", losses="ours",
                             optimizer="ours")
    EncoderTrainer((g, codec, None), data, tmp_path / "b.pt", cfg, progress=False).train()
    st = torch.load(tmp_path / "b.pt", weights_only=True)
    del st["encoder_config"]["head"], st["encoder_config"]["inplace_convs"]  # written before the options existed
    torch.save(st, tmp_path / "old.pt")
    bundle = load_encoder(tmp_path / "old.pt")
    assert bundle.cfg.head == "bottleneck" and bundle.cfg.inplace_convs is None
    with pytest.raises(UserError, match="losses"):
        EncoderTrainConfig(losses="paper").validate()


def test_encoder_cli_options_reach_the_config(monkeypatch, tmp_path):
    import argparse

    from modi.api import encoder as A_
    from modi.cli.commands import encoder as cmd

    seen = {}

    class Stop(Exception):
        pass

    def fake_trainer(model, data, out, cfg, **kw):
        seen["cfg"] = cfg
        raise Stop

    parser = argparse.ArgumentParser()
    cmd.register(parser.add_subparsers())
    monkeypatch.setattr(A_, "EncoderTrainer", fake_trainer)  # the command calls modi.api.encoder.train_encoder
    monkeypatch.setattr(A_, "load_encoder_data", lambda *a, **k: split_windows(torch.zeros(10, 4, 3, 16)))
    monkeypatch.setattr(A_, "load_checkpoint", lambda p: {"step": 0})
    monkeypatch.setattr(A_, "load_model", lambda st, device: (type("G", (), {
        "output_shape": (4, 3, 16)})(), None, None))
    for argv, want in ((["--quiet"], ("released", "released", "released", 10.0)),
                       (["--quiet", "--losses", "ours", "--optimizer", "ours", "--head", "bottleneck",
                         "--lambda-rec", "2"], ("ours", "ours", "bottleneck", 2.0))):
        args = parser.parse_args(["encoder", "train", "g.pt", "procedural", "--out", str(tmp_path / "e.pt"), *argv])
        with pytest.raises(Stop):
            args.func(args)
        c = seen["cfg"]
        assert (c.losses, c.optimizer, c.head, c.lambda_rec) == want


def test_inplace_convs_default_is_resolved_by_the_head_everywhere(model, tmp_path):
    """One rule for the dataclass, saved configs and build_encoder: None = by head (released 1, bottleneck the
    generator's count, kept as None); old checkpoints load with the convs they were built with."""
    from modi.models.modi.encoder.model import ENCODER_HEADS, EncoderConfig

    g, codec, x = model
    n = g.cfg.n_inplace_convs
    assert n != 1
    base = dict(in_channels=4, n_latent=3, latent_dim=16)
    assert EncoderConfig(**base).inplace_convs == 1
    assert EncoderConfig(**base, head="released", inplace_convs=None).inplace_convs == 1
    assert EncoderConfig(**base, head="bottleneck").inplace_convs is None
    assert EncoderConfig(**base, head="bottleneck", inplace_convs=3).inplace_convs == 3
    assert EncoderConfig.from_dict(dict(base)).inplace_convs is None  # the oldest: bottleneck head
    assert EncoderConfig.from_dict({**base, "head": "released", "inplace_convs": 1}).inplace_convs == 1
    assert EncoderConfig.from_dict({**base, "head": "released"}, generator_inplace_convs=n).inplace_convs == n
    for head in ENCODER_HEADS:
        enc = build_encoder(g, head=head)
        assert enc.cfg == EncoderConfig.from_dict(enc.cfg.to_dict())
        assert enc.cfg.inplace_convs == (1 if head == "released" else None)
        assert all(len(b.convs) == (1 if head == "released" else n) + 1 for b in enc.blocks)
    # a released-head checkpoint saved before inplace_convs was: built with the generator's count, loads so
    data = split_windows(x[:40], 0.2, seed=1)
    EncoderTrainer((g, codec, None), data, tmp_path / "r.pt", EncoderTrainConfig(iters=1, batch=4, eval_every=0,
                                                                                   ckpt_every=0), progress=False).train()
    st = torch.load(tmp_path / "r.pt", weights_only=True)
    assert st["encoder_config"]["inplace_convs"] == 1
    del st["encoder_config"]["inplace_convs"]
    st["encoder"] = build_encoder(g, inplace_convs=n).state_dict()
    torch.save(st, tmp_path / "old.pt")
    bundle = load_encoder(tmp_path / "old.pt")
    assert bundle.cfg.head == "released" and bundle.cfg.inplace_convs == n
    assert all(len(b.convs) == n + 1 for b in bundle.encoder.blocks)


def _encoder_cli(monkeypatch, g, codec, data):
    """``modi encoder train`` on the in-process generator and windows (no files but the encoder checkpoint)."""
    from modi.api import encoder as A_  # the command calls modi.api.encoder.train_encoder
    from modi.cli import main

    monkeypatch.setattr(A_, "load_encoder_data", lambda *a, **k: data)
    monkeypatch.setattr(A_, "load_checkpoint", lambda p: generator_bundle(g, codec))
    monkeypatch.setattr(A_, "load_model", lambda st, device: (g, codec, None))
    return lambda out, *argv: main(["encoder", "train", "g.pt", "procedural", "--out", str(out), "--batch", "4",
                                    "--eval-every", "0", "--ckpt-every", "0", "--quiet", *argv])


def test_resume_keeps_the_checkpoints_losses_optimizer_and_head(model, tmp_path, monkeypatch, capsys):
    g, codec, x = model
    train = _encoder_cli(monkeypatch, g, codec, split_windows(x[:40], 0.2, seed=1))
    enc = tmp_path / "e.pt"
    assert train(enc, "--iters", "1", "--losses", "ours", "--optimizer", "ours", "--head", "bottleneck",
                 "--lambda-pos", "0.5") == 0
    assert train(enc, "--iters", "2", "--resume") == 0, capsys.readouterr().err
    st = torch.load(enc, weights_only=True)
    tc = st["train_config"]
    assert st["step"] == 2 and st["encoder_config"]["head"] == "bottleneck"
    assert (tc["losses"], tc["optimizer"], tc["lambda_rec"], tc["lambda_pos"], tc["lr"], tc["beta1"]) == \
        ("ours", "ours", 1.0, 0.5, 0.002, 0.9)
    capsys.readouterr()
    # a given option that differs is refused, naming it (and the checkpoint's value); one that agrees is fine
    assert train(enc, "--iters", "3", "--resume", "--losses", "released", "--lambda-pos", "0.1") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--losses ours (this run: released)" in err[0] and "--lambda-pos 0.5" in err[0], err
    assert train(enc, "--iters", "3", "--resume", "--losses", "ours", "--head", "bottleneck") == 0
    # an old checkpoint (no losses/optimizer/head saved) resumes as what it was: ours, bottleneck
    st = torch.load(enc, weights_only=True)
    for k in ("losses", "optimizer", "head"):
        del st["train_config"][k]
    del st["encoder_config"]["head"], st["encoder_config"]["inplace_convs"]
    torch.save(st, tmp_path / "old.pt")
    assert train(tmp_path / "old.pt", "--iters", "4", "--resume") == 0
    assert torch.load(tmp_path / "old.pt", weights_only=True)["train_config"]["losses"] == "ours"


def test_library_resume_refuses_other_losses_or_head(model, tmp_path):
    g, codec, x = model
    data = split_windows(x[:40], 0.2, seed=1)
    cfg = EncoderTrainConfig(iters=1, batch=4, eval_every=0, ckpt_every=0, losses="ours")
    EncoderTrainer((g, codec, None), data, tmp_path / "a.pt", cfg, progress=False).train()
    with pytest.raises(CheckpointError, match="--losses ours"):
        EncoderTrainer((g, codec, None), data, tmp_path / "a.pt", EncoderTrainConfig(iters=2, batch=4),
                       progress=False, resume=tmp_path / "a.pt")
    other = EncoderTrainConfig(iters=2, batch=4, losses="ours", head="bottleneck")
    with pytest.raises(CheckpointError, match="built differently .*--head"):
        EncoderTrainer((g, codec, None), data, tmp_path / "a.pt", other, progress=False, resume=tmp_path / "a.pt")


def test_hidden_is_refused_with_the_released_head(tmp_path, capsys):
    from modi.cli import main

    rc = main(["encoder", "train", "g.pt", "procedural", "--out", str(tmp_path / "e.pt"), "--hidden", "8"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--hidden" in err[0] and "--head bottleneck" in err[0], err
    assert not (tmp_path / "e.pt").exists()
