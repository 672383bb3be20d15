"""GANimator as the authors' released code runs and measures it: the 5:1 discriminator ratio and per-block budgets,
the loss-level options (contact rescaling, first-frame contact label, bias init, rows/columns 6D), old checkpoints,
and the paper evaluation protocol (``modi ganimator evaluate --protocol paper``)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from modi.errors import UserError
from modi.ganimator import config as gconfig
from modi.ganimator.data import features_to_motion, read_clip, sequence_from_clip
from modi.ganimator.networks import EntityBias, GanimatorModel
from modi.ganimator.training import Trainer, atomic_save, load_model, read_checkpoint, run_summary, train

from test_ganimator import clip_seq, synthetic_clip, tiny_cfg, untrained_model

pytestmark = [pytest.mark.filterwarnings("ignore::RuntimeWarning"), pytest.mark.usefixtures("one_torch_thread")]

PARENTS = [-1, 0, 1, 2, 0, 4, 5]   # a root with two 3-joint legs


# ------------------------------------------------------------------------------------------- schedule


def test_every_preset_takes_five_discriminator_steps_per_generator_step():
    for name in gconfig.PRESETS:
        cfg = gconfig.preset(name)
        assert (cfg.d_steps, cfg.g_steps) == (5, 1), name
    paper, fast = gconfig.preset("paper"), gconfig.preset("fast")
    assert paper.block_budgets(4) == [15000] * 4
    # the fast preset shortens iterations, spending more on the coarsest block (the only one sampled with noise)
    assert fast.block_budgets(4) == [900, 300, 300, 300]
    assert gconfig.preset("fast", iterations=100).block_budgets(3) == [300, 100, 100]


def test_block_budgets_explicit_list_and_multiplier():
    cfg = gconfig.GanimatorConfig(iterations=50, coarse_multiplier=2.5)
    assert cfg.block_budgets(3) == [125, 50, 50]
    cfg = gconfig.GanimatorConfig(iterations=50, coarse_multiplier=2.5, block_iterations=[2000, 800])
    assert cfg.block_budgets(4) == [2000, 800, 800, 800]          # the last value repeats; the list overrides
    with pytest.raises(UserError):
        gconfig.GanimatorConfig(block_iterations=[])
    with pytest.raises(UserError):
        gconfig.GanimatorConfig(block_iterations=[10, -1])
    with pytest.raises(UserError):
        gconfig.GanimatorConfig(coarse_multiplier=0)
    for bad in (dict(sixd="diag"), dict(bias_init="normal"), dict(contact_first_frame="one")):
        with pytest.raises(UserError):
            gconfig.GanimatorConfig(**bad)


def _count_steps(trainer: Trainer, levels) -> dict:
    counts = {"D": 0, "G": 0}
    for l in levels:
        trainer._make_opts(l)
        for kind, opt in (("D", trainer.opt_d[l]), ("G", trainer.opt_g[l])):
            step = opt.step

            def counted(*a, _step=step, _kind=kind, **kw):
                counts[_kind] += 1
                return _step(*a, **kw)
            opt.step = counted
    return counts


def test_trainer_runs_each_block_for_its_budget_at_five_to_one(tmp_path):
    cfg = tiny_cfg(d_steps=5, block_iterations=[3, 1], max_levels=4, coarse_ratio=0.4, base_channels=8)
    seq = clip_seq(PARENTS, T=40, seed=1)
    trainer = Trainer([seq], cfg, tmp_path / "run")
    assert trainer.blocks == [[0, 1], [2, 3]]
    counts = _count_steps(trainer, [0, 1])
    trainer.run(progress=False, log=None)
    hist = read_checkpoint(tmp_path / "run")["state"]["history"]
    assert [h["iterations"] for h in hist] == [3, 1]
    # block 0: 3 iterations x 2 levels; 5 D steps, then 1 adversarial + 1 reconstruction G step per iteration
    assert counts == {"D": 3 * 2 * 5, "G": 3 * 2 * 2}
    assert run_summary(tmp_path / "run")["block_iterations"] == [3, 1]


def test_cli_train_selects_budgets_and_loss_options(tmp_path, capsys):
    from modi.cli import main
    from modi.ganimator.generate import write_bvh

    seq = clip_seq(PARENTS, T=40, seed=2)
    quats, root, _ = features_to_motion(seq.features, seq.n_joints, seq.root_start, sixd=seq.sixd)
    bvh = write_bvh(seq, quats, root, tmp_path / "clip.bvh")
    args = ["ganimator", "train", str(bvh), "--out", str(tmp_path / "run"), "--preset", "tiny", "--quiet",
            "--d-steps", "1", "--base-channels", "8", "--coarse-ratio", "0.4", "--block-iters", "2,1",
            "--contact-rescale", "--contact-first-frame", "copy", "--bias-init", "zeros", "--sixd", "columns"]
    assert main(args) == 0
    assert "iterations [2, 1, 1" in capsys.readouterr().out
    ck = read_checkpoint(tmp_path / "run")
    cfg = gconfig.GanimatorConfig.from_dict(ck["model"]["config"])
    assert cfg.block_iterations == [2, 1] and cfg.contact_rescale and cfg.contact_first_frame == "copy"
    assert cfg.bias_init == "zeros" and cfg.sixd == "columns" and cfg.d_steps == 1
    assert [h["iterations"] for h in ck["state"]["history"]][:2] == [2, 1]
    assert ck["model"]["clips"][0]["sixd"] == "columns"
    # defaults: the released forms
    assert main(args[:-7] + ["--out", str(tmp_path / "run2")]) == 0
    cfg2 = gconfig.GanimatorConfig.from_dict(read_checkpoint(tmp_path / "run2")["model"]["config"])
    got = (cfg2.contact_rescale, cfg2.contact_first_frame, cfg2.bias_init, cfg2.sixd)
    assert got == (False, "zero", "uniform", "rows")
    assert main(args[:2] + [str(bvh), "--out", str(tmp_path / "r3"), "--block-iters", "2,x"]) == 2


# ------------------------------------------------------------------------------------------- loss-level options


def test_rows_6d_round_trips_exactly_and_is_the_transposed_layout():
    from modi import rotations as R

    q = R.quat_normalize(torch.randn(200, 4, dtype=torch.float64))
    m = R.quat_to_matrix(q)
    rows, cols = R.matrix_to_6d(m, layout="rows"), R.matrix_to_6d(m)
    assert torch.equal(rows, torch.cat([m[..., 0, :], m[..., 1, :]], -1))
    assert torch.allclose(rows, R.matrix_to_6d(m.transpose(-1, -2)))
    torch.testing.assert_close(R.sixd_to_matrix(rows, layout="rows"), m, atol=1e-12, rtol=0)
    torch.testing.assert_close(R.sixd_to_quat(R.quat_to_6d(q, layout="rows"), layout="rows"), R.quat_canonical(q),
                               atol=1e-12, rtol=0)
    # any 6-vector decodes to a rotation, and the two layouts decode it to transposed matrices
    raw = torch.randn(50, 6, dtype=torch.float64)
    mr = R.sixd_to_matrix(raw, layout="rows")
    torch.testing.assert_close(mr @ mr.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3),
                               atol=1e-12, rtol=0)
    assert torch.allclose(torch.linalg.det(mr), torch.ones(50, dtype=torch.float64))
    torch.testing.assert_close(mr, R.sixd_to_matrix(raw).transpose(-1, -2), atol=1e-12, rtol=0)
    assert not torch.allclose(rows, cols)
    with pytest.raises(ValueError):
        R.matrix_to_6d(m, layout="diagonal")


@pytest.mark.parametrize("sixd", ["rows", "columns"])
def test_sixd_option_features_round_trip_to_bvh(tmp_path, sixd):
    from modi.ganimator.generate import decode, write_bvh

    clip = synthetic_clip(PARENTS, 50, seed=3, walk=0.03)
    seq = sequence_from_clip(clip, "rt", tiny_cfg(sixd=sixd))
    assert seq.sixd == sixd
    from modi.rotations import quat_to_6d

    expect = quat_to_6d(clip.rotations.to(torch.float32), layout=sixd).permute(2, 1, 0)
    assert torch.allclose(seq.features[:, : seq.n_joints], expect, atol=1e-6)
    model = untrained_model([seq], tiny_cfg(sixd=sixd))
    quats, root, _ = decode(model, seq.features)
    write_bvh(seq, quats, root, tmp_path / "rt.bvh")
    back = read_clip(tmp_path / "rt.bvh")
    dots = (back.rotations * clip.rotations).sum(-1).abs()
    assert torch.allclose(dots, torch.ones_like(dots), atol=1e-5)
    assert torch.allclose(back.root_positions, clip.root_positions, atol=1e-4)
    # a model refuses clips of the other layout
    with pytest.raises(ValueError):
        untrained_model([seq], tiny_cfg(sixd="columns" if sixd == "rows" else "rows"))


def test_bias_init_uniform_within_fan_in_bounds():
    seq = clip_seq(PARENTS, T=40, seed=4)
    torch.manual_seed(0)
    model = untrained_model([seq], tiny_cfg(base_channels=64))
    nb = model.neighbors
    checked = 0
    for net in list(model.gens) + list(model.discs):
        layers = list(net.body.net)
        cin = 6
        for conv, bias in zip(layers[0::1], layers[1::1]):
            if not isinstance(bias, EntityBias):
                continue
            b = bias.bias.detach()[:, :, 0]            # (C_out, E)
            bound = torch.tensor([1.0 / math.sqrt(len(n) * cin * 5) for n in nb])
            assert (b.abs() <= bound + 1e-7).all()
            assert (b.abs().amax(0) > 0.3 * bound).all()   # spread over the range, not zeros
            cin = b.shape[0]
            checked += 1
    assert checked == 2 * model.n_levels * 4 - model.n_levels   # 4 convs per generator, 3 per discriminator
    zeros = untrained_model([seq], tiny_cfg(bias_init="zeros"))
    assert all(float(m.bias.detach().abs().max()) == 0.0 for m in zeros.modules() if isinstance(m, EntityBias))


def _still_clip(T=30):
    clip = synthetic_clip(PARENTS, T, seed=5, walk=0.0)
    clip.rotations[:] = clip.rotations[:1].clone()       # a still pose: every foot is in contact
    return clip


def test_contact_label_of_the_first_frame():
    clip = _still_clip()
    feet = ["j3", "j6"]
    zero = sequence_from_clip(clip, "z", tiny_cfg(feet=feet))
    copy = sequence_from_clip(clip, "c", tiny_cfg(feet=feet, contact_first_frame="copy"))
    J = zero.n_joints
    lz, lc = zero.features[0, J + 1:], copy.features[0, J + 1:]
    assert lz.shape == (2, 30)
    assert torch.all(lz[:, 0] == 0) and torch.all(lz[:, 1:] == 1)       # the released foot_contact pads with 0
    assert torch.all(lc == 1)
    assert torch.equal(lz[:, 1:], lc[:, 1:])


def test_contact_rescale_option_chooses_the_rate_the_loss_sees(tmp_path):
    seq = clip_seq(PARENTS, T=40, seed=6)
    for rescale in (False, True):
        cfg = tiny_cfg(contact_rescale=rescale, iterations=1, max_levels=2, coarse_ratio=0.5, d_steps=0)
        trainer = Trainer([seq], cfg, tmp_path / f"r{rescale}")
        seen = set()
        inner = trainer.consistency

        def spy(x, rate=1.0, _inner=inner):
            seen.add(round(float(rate), 6))
            return _inner(x, rate)
        trainer.consistency = spy
        trainer.run(progress=False, log=None)
        rates = {round(r, 6) for r in trainer.model.rates[0]}
        assert len(rates) == 2
        assert seen == (rates if rescale else {1.0}), (rescale, seen)
    # per level frame (the released form) a coarse level's foot speed is ~1/rate larger than when rescaled
    from modi.ganimator.training import ContactConsistency

    loss = ContactConsistency(seq.skeleton, seq.feet, seq.sixd)
    x = seq.features.unsqueeze(0).clone()
    x[:, 0, seq.n_joints + 1:] = 1.0
    x[:, :, seq.n_joints, :] = 0.0                          # no root motion: only the rotations move the feet
    assert float(loss(x, 1.0)) == pytest.approx(2.0 * float(loss(x, 0.5)), rel=1e-5)


# ------------------------------------------------------------------------------------------- old checkpoints


def test_checkpoint_without_the_new_options_loads_with_the_forms_it_was_trained_with(tmp_path):
    legacy = dict(contact_rescale=True, contact_first_frame="copy", bias_init="zeros", sixd="columns")
    cfg = tiny_cfg(iterations=1, max_levels=2, coarse_ratio=0.5, **legacy)
    seq = clip_seq(PARENTS, T=40, seed=7, cfg=cfg)
    model = train([seq], cfg, tmp_path / "run", progress=False, log=None)
    ck = read_checkpoint(tmp_path / "run")
    for key in list(legacy) + ["block_iterations", "coarse_multiplier"]:
        del ck["model"]["config"][key]
    for c in ck["model"]["clips"]:
        del c["sixd"]
    atomic_save(ck, tmp_path / "old" / "ganimator.ckpt")
    old = load_model(tmp_path / "old")
    assert {k: getattr(old.cfg, k) for k in legacy} == legacy
    assert old.seqs[0].sixd == "columns" and old.cfg.block_budgets(2) == [1, 1]
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(model.sample(45, 2, generator=g1), old.sample(45, 2, generator=g2))
    assert torch.allclose(old.seqs[0].rotations(), model.seqs[0].rotations())
    assert run_summary(tmp_path / "old")["config"]["sixd"] == "columns"
