"""GANimator as the authors' released code runs and measures it: the 5:1 discriminator ratio and per-block budgets,
the loss-level options (contact rescaling, first-frame contact label, bias init, rows/columns 6D), old checkpoints,
and the paper evaluation protocol (``modi ganimator eval --protocol paper``)."""
from __future__ import annotations

import json
import math

import pytest
import torch

from modi.errors import UserError
from modi.models.ganimator import config as gconfig
from modi.models.ganimator.data import features_to_motion, read_clip, sequence_from_clip
from modi.models.ganimator.networks import EntityBias
from modi.models.ganimator.training import Trainer, atomic_save, load_model, read_checkpoint, run_summary, train

from test_ganimator import clip_seq, synthetic_clip, tiny_cfg, untrained_model

pytestmark = [pytest.mark.filterwarnings("ignore::RuntimeWarning"), pytest.mark.usefixtures("one_torch_thread")]

PARENTS = [-1, 0, 1, 2, 0, 4, 5]   # a root with two 3-joint legs


def _exit_code(argv) -> int:
    """``modi`` exit code, whether the mistake is caught while parsing (SystemExit) or while running."""
    from modi.cli import main

    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


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
    from modi.models.ganimator.generate import write_bvh

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
    assert _exit_code(args[:2] + [str(bvh), "--out", str(tmp_path / "r3"), "--block-iters", "2,x"]) == 2


# ------------------------------------------------------------------------------------------- loss-level options


def test_rows_6d_round_trips_exactly_and_is_the_transposed_layout():
    from modi.core import rotations as R

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
    from modi.models.ganimator.generate import decode, write_bvh

    clip = synthetic_clip(PARENTS, 50, seed=3, walk=0.03)
    seq = sequence_from_clip(clip, "rt", tiny_cfg(sixd=sixd))
    assert seq.sixd == sixd
    from modi.core.rotations import quat_to_6d

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
    from modi.models.ganimator.training import ContactConsistency

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
    # resuming it needs its settings: the released defaults are refused with the differences named
    from modi.errors import CheckpointError

    new_cfg = tiny_cfg(iterations=1, max_levels=2, coarse_ratio=0.5)
    with pytest.raises(CheckpointError, match="sixd: 'columns' there, 'rows' now"):
        Trainer([clip_seq(PARENTS, T=40, seed=7, cfg=new_cfg)], new_cfg, tmp_path / "old").run(progress=False,
                                                                                              log=None)
    Trainer([seq], cfg.replace(iterations=2), tmp_path / "old").run(progress=False, log=None)
    assert [h["iterations"] for h in read_checkpoint(tmp_path / "old")["state"]["history"]] == [1]


# ------------------------------------------------------------------------------------------- paper protocol


def _rec_model(tmp_path, T=40, iterations=60):
    """A model trained only to reconstruct its clip (no adversarial steps): quick, and its z* output is close."""
    cfg = tiny_cfg(d_steps=0, g_steps=0, iterations=iterations, lr=3e-3, coarse_ratio=0.5, base_channels=16)
    seq = clip_seq(PARENTS, T=T, seed=8, cfg=cfg)
    return train([seq], cfg, tmp_path / "rec", progress=False, log=None), cfg


def test_paper_pyramid_and_raw_features():
    from modi.models.ganimator.data import pyramid_lengths
    from modi.models.ganimator.evaluate_paper import paper_features, paper_pyramid

    cfg = tiny_cfg(coarse_ratio=0.5, feet=["j3", "j6"])
    seq = clip_seq(PARENTS, T=40, seed=9, cfg=cfg)
    model = untrained_model([seq], cfg)
    assert model.lengths[0] == [20, 26, 34, 40]
    # rebuilt from the sample length by the training rule (not the training pyramid stretched)
    assert paper_pyramid(model, 80) == pyramid_lengths(80, 0.5, 1 / 0.75) == [40, 53, 70, 80]
    assert paper_pyramid(model, 200) == pyramid_lengths(200, 0.5, 1 / 0.75)[-4:]
    with pytest.raises(UserError):
        paper_pyramid(model, 3)
    J, E = seq.n_joints, seq.n_entities
    x = torch.randn(2, 6, E, 33)
    f = paper_features(x, J)
    assert f.shape == (2, 33, 6 * (E - 1)) and f.dtype == torch.float64
    assert torch.allclose(f[1, 5, :6], x[1, :, 0, 5].double())                      # joint 0's raw 6 channels
    assert torch.allclose(f[0, 7, 6 * J:6 * J + 6], x[0, :, J + 1, 7].double())     # then the first contact's
    src = paper_features(seq.features, J)[0]
    assert torch.equal(src[:, 6 * J + 1:6 * J + 6], torch.zeros(40, 5, dtype=torch.float64))  # label + 5 zeros


def test_paper_protocol_scores_a_reconstruction_as_covered(tmp_path):
    from modi.models.ganimator.evaluate_paper import evaluate_paper, paper_features, score_samples

    model, cfg = _rec_model(tmp_path)
    seq = model.seqs[0]
    J = seq.n_joints
    src = paper_features(seq.features, J)[0]
    rec = paper_features(model.reconstruct(0).detach(), J)[0]
    untrained = paper_features(untrained_model([seq], cfg).reconstruct(0).detach(), J)[0]
    s = score_samples([src, rec, untrained], [src], ["clip"])["clip"]
    assert s["coverage"][0] == 1.0 and s["global_diversity"][0] == pytest.approx(0.0, abs=1e-6)
    assert s["coverage"][1] >= 0.9, s
    assert s["coverage"][2] < s["coverage"][1] and s["global_diversity"][2] > s["global_diversity"][1]
    # the whole protocol: samples of 2x the source length, sample count and length beside every figure
    figs = evaluate_paper(model, n=3, seed=1, batch=2)
    assert figs["samples"] == 3 and figs["frames"] == 80 and figs["levels"][-1] == 80
    f = figs["per_sequence"][seq.name]
    assert (f["samples"], f["frames"], f["source_frames"]) == (3, 80, 40)
    assert 0.0 <= f["coverage"] <= 1.0 and math.isfinite(f["global_diversity"]) and f["local_diversity"] > 0
    assert figs["released_running"][0]["coverage"] == f["coverage"]
    assert figs["reconstruction"][seq.name]["l1"] < 0.5 * float((seq.features - 0).abs().mean())
    # deterministic, and independent of the generation batch
    again = evaluate_paper(model, n=3, seed=1, batch=3)
    assert again["per_sequence"][seq.name]["coverage"] == f["coverage"]
    assert again["per_sequence"][seq.name]["global_diversity"] == pytest.approx(f["global_diversity"], rel=1e-5)


def test_released_running_average_pools_all_clips_scored_so_far(tmp_path):
    from modi.models.ganimator.data import sequence_from_clip as from_clip
    from modi.models.ganimator.evaluate_paper import evaluate_paper, summarise

    scores = {"a": {"coverage": [1.0, 1.0], "global_diversity": [1.0, 3.0], "local_diversity": [0.5, 0.5]},
              "b": {"coverage": [0.0, 0.0], "global_diversity": [5.0, 7.0], "local_diversity": [1.5, 1.5]}}
    per, running = summarise(scores, 2, 100, {"a": 40, "b": 50})
    assert per["b"]["coverage"] == 0.0 and per["b"]["global_diversity"] == 6.0 and per["b"]["source_frames"] == 50
    assert running[0]["coverage"] == 1.0 and running[0]["pairs"] == 2
    assert running[1]["coverage"] == 0.5 and running[1]["global_diversity"] == 4.0 and running[1]["pairs"] == 4
    assert running[1]["sequences"] == ["a", "b"] and running[1]["samples"] == 2 and running[1]["frames"] == 100
    # mixing: two clips of one character; samples are 2x the *total* length
    cfg = tiny_cfg(coarse_ratio=0.5)
    a = clip_seq(PARENTS, T=40, seed=10, cfg=cfg)
    b = from_clip(synthetic_clip(PARENTS, 50, seed=11), "b", cfg, like=a)
    model = untrained_model([a, b], cfg)
    figs = evaluate_paper(model, n=2)
    assert figs["frames"] == 2 * (40 + 50) and list(figs["per_sequence"]) == [a.name, "b"]
    pa, pb = figs["per_sequence"][a.name], figs["per_sequence"][b.name]
    last = figs["released_running"][-1]
    assert last["pairs"] == 4
    for k in ("coverage", "global_diversity", "local_diversity"):
        assert last[k] == pytest.approx((pa[k] + pb[k]) / 2)
        assert figs["released_running"][0][k] == pa[k]


def test_cli_evaluate_both_protocols_report_samples_and_length(tmp_path, capsys):
    from modi.cli import main

    _rec_model(tmp_path, iterations=2)
    run = str(tmp_path / "rec")
    assert main(["ganimator", "eval", run, "--protocol", "paper", "--n", "2", "--json",
                 str(tmp_path / "p.json")]) == 0
    out = capsys.readouterr().out
    assert "protocol paper" in out and "(2 samples x 80 frames" in out
    figs = json.loads((tmp_path / "p.json").read_text())
    assert figs["protocol"] == "paper" and figs["samples"] == 2 and figs["frames"] == 80
    assert all(f["samples"] == 2 and f["frames"] == 80 for f in figs["per_sequence"].values())
    assert main(["ganimator", "evaluate", run, "--n", "2", "--json", "-"]) == 0  # the old spelling still works
    cap = capsys.readouterr()
    ours = json.loads(cap.out)
    assert "modi: note: 'evaluate' is now 'eval'" in cap.err
    assert ours["protocol"] == "ours" and all(f["samples"] == 2 and f["frames"] == 40 for f in ours["metrics"].values())
    assert ours["iterations_per_block"] == [2, 2]
    assert main(["ganimator", "generate", run, "--n", "2", "--frames", "45", "--out", str(tmp_path / "g"),
                 "--no-gif", "--eval"]) == 0
    out = capsys.readouterr().out
    assert '"samples": 2' in out and '"frames": 45' in out
    assert main(["ganimator", "generate", run, "--n", "1", "--frames", "45", "--out", str(tmp_path / "g2"),
                 "--no-gif", "--evaluate"]) == 0
    cap = capsys.readouterr()
    assert '"samples": 1' in cap.out and "modi: note: --evaluate is now --eval" in cap.err
    assert _exit_code(["ganimator", "eval", run, "--protocol", "paper", "--n", "0"]) == 2
    assert _exit_code(["ganimator", "evaluate", run, "--protocol", "paper", "--frames", "10"]) == 2


def test_paper_protocol_on_a_real_clip(shared_data):
    from modi.models.ganimator.data import load_sequence
    from modi.models.ganimator.evaluate_paper import paper_features, paper_pyramid, score_samples

    cfg = gconfig.preset("fast")
    salsa = load_sequence(shared_data / "bvh" / "ganimator" / "Joe" / "Salsa-Dancing-6.bvh", cfg)
    assert salsa.sixd == "rows"
    J = salsa.n_joints
    labels = salsa.features[0, J + 1:]
    assert torch.all(labels[:, 0] == 0) and labels[:, 1:].sum() > 0           # released foot_contact: frame 0 is 0
    model = untrained_model([salsa], cfg)
    # the released evaluate.py's pyramid for 2 x 648 frames (int(n / 5), then x 4/3, the last level the length)
    assert paper_pyramid(model, 1296) == [259, 345, 460, 613, 817, 1089, 1296]
    src = paper_features(salsa.features, J)[0]
    assert src.shape == (648, 6 * (24 + 4))
    s = score_samples([src[:120], src], [src], ["salsa"])["salsa"]
    assert s["coverage"][1] == 1.0 and 0.0 < s["coverage"][0] < 1.0        # a part of the clip covers a part of it
    assert s["global_diversity"][1] == pytest.approx(0.0, abs=1e-6)
