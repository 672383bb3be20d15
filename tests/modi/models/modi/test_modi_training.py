"""MoDi training, checkpoints, resume, DDP, NaN handling, sampling and the train/generate CLI (tiny models)."""
from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from modi.cli import main
from modi.errors import CheckpointError, UserError
from modi.models.modi.config import MoDiConfig, make_config
from modi.models.modi.sampling import load_checkpoint, sample_motions, sample_positions
from modi.models.modi.training import NonFiniteLossError, Trainer, prepare_data, write_procedural_data

TINY = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
        "data.stride": 8, "train.batch": 4, "train.sample_every": 0, "train.ckpt_every": 0, "train.log_every": 1,
        "train.d_reg_every": 2, "train.g_reg_every": 2, "train.snapshot_every": 0}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny_cfg(*ablations: str, **kw) -> MoDiConfig:
    return make_config("small", list(ablations), **{**TINY, **kw})


@pytest.fixture(scope="module")
def proc_dir(tmp_path_factory) -> Path:
    return write_procedural_data(tmp_path_factory.mktemp("proc") / "data", n_clips=6, frames=40, seed=1)


@pytest.fixture(scope="module")
def proc_data(proc_dir):
    return prepare_data(proc_dir, tiny_cfg(), cache=False)


def make_trainer(data, run_dir, cfg=None, **kw) -> Trainer:
    kw = {"progress": False, "tensorboard": False, "write_samples": False, **kw}
    return Trainer(cfg or tiny_cfg(), data, run_dir, **kw)


def full_state(tr: Trainer) -> dict[str, torch.Tensor]:
    out = {}
    for name, module in (("G", tr.G), ("D", tr.D), ("G_ema", tr.G_ema)):
        out.update({f"{name}.{k}": v.detach().clone() for k, v in module.state_dict().items()})
    for name, opt in (("g_opt", tr.g_optim), ("d_opt", tr.d_optim)):
        for pid, st in opt.state_dict()["state"].items():
            out.update({f"{name}.{pid}.{k}": torch.as_tensor(v).clone() for k, v in st.items()})
    out["mean_path_length"] = tr.mean_path_length.clone()
    return out


# --------------------------------------------------------------------------------------------- learning signal
def _d_only_losses(tr: Trainer, steps: int) -> list[float]:
    tr.step = 1  # odd step with d_reg_every=2: plain D steps only
    losses = []
    for _ in range(steps):
        losses.append(tr.d_step()["d"])
        tr.step += 2
    return losses


def test_discriminator_learns_on_procedural_data(proc_data, tmp_path):
    torch.manual_seed(0)
    tr = make_trainer(proc_data, tmp_path)
    losses = _d_only_losses(tr, 25)
    assert np.mean(losses[-3:]) < np.mean(losses[:3]) - 0.05, losses


def _bandai_subset(shared_data: Path, tmp_path: Path) -> Path:
    """A folder linking the first 3 Bandai-Namco-1 clips (skips when the shared data is absent)."""
    src = shared_data / "bvh" / "bandai-namco-1"
    files = sorted(src.rglob("*.bvh"))[:3]
    if len(files) < 3:
        pytest.skip(f"fewer than 3 BVH files under {src}")
    sub = tmp_path / "bandai"
    sub.mkdir()
    for f in files:
        (sub / f.name).symlink_to(f)
    return sub


def test_discriminator_learns_on_real_data(shared_data, tmp_path):
    sub = _bandai_subset(shared_data, tmp_path)
    data = prepare_data(sub, tiny_cfg(), cache=False)
    assert data.skeleton.n_joints >= 20 and data.windows.shape[1:] == (4, data.codec.n_entities, 16)
    torch.manual_seed(0)
    tr = make_trainer(data, tmp_path / "run")
    losses = _d_only_losses(tr, 25)
    assert np.mean(losses[-3:]) < np.mean(losses[:3]) - 0.05, losses


# --------------------------------------------------------------------------------------------- checkpoints
def test_checkpoint_roundtrip_gives_identical_samples(proc_data, tmp_path):
    tr = make_trainer(proc_data, tmp_path)
    tr.train(2)
    ckpt = tmp_path / "checkpoint.pt"
    assert ckpt.is_file() and not list(tmp_path.glob(".*.tmp"))
    st = load_checkpoint(ckpt)
    assert st["step"] == 2 and st["skeleton"]["names"] == proc_data.skeleton.names
    a = sample_motions(ckpt, 5, seed=3, psi=0.7, batch=2)
    b = sample_motions(tr.state_dict(), 5, seed=3, psi=0.7, batch=5)
    assert len(a) == 5
    for ma, mb in zip(a, b):
        assert torch.allclose(ma.rotations, mb.rotations, atol=1e-6)
        assert torch.allclose(ma.root_positions, mb.root_positions, atol=1e-5)
    first = sample_motions(ckpt, 2, seed=3, psi=0.7)
    assert torch.allclose(first[1].rotations, a[1].rotations, atol=1e-6)  # motion i does not depend on n
    other = sample_motions(ckpt, 2, seed=4, psi=0.7)
    assert not torch.allclose(other[0].rotations, a[0].rotations)
    assert a[0].n_frames == 16 and a[0].skeleton.names == proc_data.skeleton.names


def test_resume_after_interrupt_equals_uninterrupted(proc_data, tmp_path, monkeypatch):
    n = 5
    torch.manual_seed(123)  # the trainer reseeds itself; this must not matter
    straight = make_trainer(proc_data, tmp_path / "a")
    straight.train(n)
    expect = full_state(straight)

    interrupted = make_trainer(proc_data, tmp_path / "b")
    original = Trainer.run_step  # the loop's step

    def step_then_ctrl_c(self):
        out = original(self)
        if self.step == 2:
            os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C does: handled, saved at the iteration boundary
        return out

    monkeypatch.setattr(Trainer, "run_step", step_then_ctrl_c)
    res = interrupted.train(n)
    monkeypatch.setattr(Trainer, "run_step", original)
    assert res.interrupted and res.step == 2 and load_checkpoint(tmp_path / "b" / "checkpoint.pt")["step"] == 2
    del interrupted
    torch.manual_seed(999)
    resumed = make_trainer(proc_data, tmp_path / "b", resume=tmp_path / "b" / "checkpoint.pt")
    assert resumed.step == 2
    resumed.train(n)
    got = full_state(resumed)
    assert got.keys() == expect.keys()
    bad = [k for k in expect if not torch.equal(expect[k], got[k])]
    assert not bad, f"differs after resume: {bad[:5]}"


def test_nan_loss_stops_without_poisoned_checkpoint(proc_data, tmp_path):
    tr = make_trainer(proc_data, tmp_path, cfg=tiny_cfg(**{"train.ckpt_every": 1}))
    tr.train(1)
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 1
    with torch.no_grad():
        tr.D.final_linear[1].bias.fill_(float("nan"))
    with pytest.raises(NonFiniteLossError, match="at step 1"):
        tr.train(3)
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 1
    assert torch.isfinite(load_checkpoint(tmp_path / "checkpoint.pt")["D"]["final_linear.1.bias"]).all()


def test_bad_checkpoints_raise_checkpoint_error(proc_data, tmp_path):
    with pytest.raises(CheckpointError, match="no such"):
        load_checkpoint(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(os.urandom(300))
    with pytest.raises(CheckpointError, match="not a readable"):
        load_checkpoint(junk)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match="not a MoDi checkpoint"):
        sample_motions(foreign, 1)
    tr = make_trainer(proc_data, tmp_path / "run")
    good = tr.save_checkpoint()
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError):
        load_checkpoint(cut)
    assert issubclass(CheckpointError, UserError)


# --------------------------------------------------------------------------------------------- DDP
def _ddp_worker(rank: int, world: int, init_file: str, data, cfg_dict: dict, out_dir: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        tr = Trainer(MoDiConfig.from_dict(cfg_dict), data, out_dir, progress=False, tensorboard=False,
                     write_samples=False)
        assert tr.distributed and tr.local_batch == 2
        init = torch.cat([p.detach().flatten().clone() for p in tr.G.parameters()])
        tr.train(3)
        state = {k: v.detach().clone() for k, v in full_state(tr).items()}
        torch.save({"state": state, "init": init}, Path(out_dir) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()


def test_ddp_two_cpu_processes_keep_replicas_identical(proc_data, tmp_path):
    import torch.multiprocessing as mp

    cfg = tiny_cfg()
    mp.spawn(_ddp_worker, args=(2, str(tmp_path / "init"), proc_data, cfg.to_dict(), str(tmp_path)), nprocs=2,
             join=True)
    r0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    r1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    bad = [k for k in r0["state"] if not torch.equal(r0["state"][k], r1["state"][k])]
    assert not bad, f"replicas differ: {bad[:5]}"
    g_now = torch.cat([v.flatten() for k, v in r0["state"].items() if k.startswith("G.") and "noise_const" not in k
                       and "w_avg" not in k])
    assert not torch.equal(g_now[: r0["init"].numel()], r0["init"])  # it trained
    assert load_checkpoint(tmp_path / "checkpoint.pt")["world_size"] == 2


# --------------------------------------------------------------------------------------------- ablations
@pytest.mark.parametrize("ablation", ["pool", "pseudo-image", "positions", "root-position"])
def test_ablations_train(proc_dir, tmp_path, ablation):
    cfg = tiny_cfg(ablation)
    data = prepare_data(proc_dir, cfg, cache=False)
    tr = make_trainer(data, tmp_path, cfg=cfg)
    tr.train(2)
    assert all(np.isfinite(v) for v in tr.last_losses.values())
    ckpt = tr.save_checkpoint()
    pos = sample_positions(ckpt, 2)
    assert pos[0].shape == (16, data.skeleton.n_joints, 3)
    if ablation == "positions":
        with pytest.raises(UserError, match="positions"):
            sample_motions(ckpt, 1)
    else:
        assert sample_motions(ckpt, 1)[0].n_frames == 16


# --------------------------------------------------------------------------------------------- released vs ours
@pytest.mark.parametrize("options", [[], ["noise"], ["squared-contact"], ["pre-release"]])
def test_released_defaults_and_pre_release_options_train_and_resume(proc_data, tmp_path, options):
    cfg = tiny_cfg(*options)
    tr = make_trainer(proc_data, tmp_path, cfg=cfg)
    tr.train(2)
    assert np.isfinite(tr.last_losses["contact"])
    ckpt = load_checkpoint(tr.save_checkpoint())
    saved = MoDiConfig.from_dict(ckpt["config"])
    assert saved.model.noise_injection == ("noise" in options or "pre-release" in options)
    assert saved.train.contact_loss == ("squared" if set(options) & {"squared-contact", "pre-release"} else "released")
    # a checkpoint predating the new fields loads with the behaviour it was trained with (noise on, squared)
    if options == ["pre-release"]:
        del ckpt["config"]["model"]["noise_injection"], ckpt["config"]["train"]["contact_loss"]
        sample_motions(ckpt, 1)
        make_trainer(proc_data, tmp_path / "old", cfg=MoDiConfig.from_dict(ckpt["config"]), resume=ckpt)
    # without noise injection the output is a function of the latent only: random noise (made non-zero here, so
    # it would show) changes nothing; with it, two random-noise passes of one latent differ
    import copy

    from modi.models.modi.networks import NoiseInjection

    g = copy.deepcopy(tr.G_ema).eval()
    for m in g.modules():
        if isinstance(m, NoiseInjection):
            m.weight.data.fill_(0.5)
    z = torch.randn(2, g.latent_dim, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        a, b = g(z, noise_mode="random"), g(z, noise_mode="random")
    assert torch.equal(a, b) == (not saved.model.noise_injection)


@pytest.mark.parametrize("options", [["tree-neighbors"], ["released-pooling"], ["tree-neighbors", "released-pooling"]])
def test_released_topology_options_train_and_sample(proc_dir, tmp_path, options):
    cfg = tiny_cfg(*options)
    data = prepare_data(proc_dir, cfg, cache=False)
    h = data.hierarchy
    if "released-pooling" in options:
        assert h.levels[-1].root_motion is not None and h.edge_counts[-1] <= 2  # specials reach the coarsest level
    if "tree-neighbors" in options:
        sk = data.skeleton
        for j in range(sk.n_joints):  # edges: self + parent + children only
            kin = {j, *sk.children(j)} | ({int(sk.parents[j])} if sk.parents[j] >= 0 else set())
            assert set(h.levels[0].neighbors[j]) - {h.levels[0].root_motion, *h.levels[0].contacts} == kin
    tr = make_trainer(data, tmp_path, cfg=cfg)
    tr.train(2)
    assert all(np.isfinite(v) for v in tr.last_losses.values())
    ckpt = tr.save_checkpoint()
    assert sample_motions(ckpt, 1)[0].n_frames == 16


def test_released_contact_loss_measures_the_ankles_in_data_units(proc_data):
    from modi.models.modi.losses import foot_contact_speed_loss

    codec = proc_data.codec
    x = proc_data.windows[:3]
    pos, contact = codec.foot_terms(x, codec.ankles)
    full = codec.decode(x)["positions"]
    torch.testing.assert_close(pos, full[..., codec.ankles, :])
    speed = (full[:, 1:, codec.ankles] - full[:, :-1, codec.ankles]).norm(dim=-1)  # data units per frame
    ref = (speed.transpose(1, 2) * torch.sigmoid(12 * (contact[..., 1:] - 0.5))).mean()
    torch.testing.assert_close(foot_contact_speed_loss(pos, contact), ref)


def test_sampling_does_not_import_training():
    """modi_model.sampling and modi_model.training used to import each other; sampling now needs only
    codec/checkpoint/config/networks."""
    import ast
    import inspect

    import modi.models.modi.sampling as sampling

    tree = ast.parse(inspect.getsource(sampling))
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert "modi.models.modi.training" not in imported
    for mod in ("codec", "checkpoint"):
        src = inspect.getsource(__import__(f"modi.models.modi.{mod}", fromlist=["x"]))
        assert "modi_model.training" not in src and "modi_model.sampling" not in src


# --------------------------------------------------------------------------------------------- IK cleanup
def test_ik_cleanup_pins_feet_within_1mm():
    from modi.models.modi.sampling import cleanup_feet
    from modi.data.procedural import generate_clip
    from modi.data.representation import modi_representation

    m = generate_clip("walk", 60, rng=3)
    rep = modi_representation(m.skeleton)
    rot = m.rotations.clone()
    t = torch.arange(60, dtype=torch.float32)
    wobble = torch.stack([torch.cos(0.02 * torch.sin(t / 3)), torch.sin(0.02 * torch.sin(t / 3)),
                          torch.zeros(60), torch.zeros(60)], -1)
    for j in (m.skeleton.index("LeftUpLeg"), m.skeleton.index("RightLeg")):  # make the planted feet slide
        from modi.core.rotations import quat_mul

        rot[:, j] = quat_mul(rot[:, j], wobble)
    from modi.data.motion import Motion

    sliding = Motion(m.skeleton, rot, m.root_positions, m.fps)
    contacts = rep.contacts_of(m).numpy().astype(bool)
    assert contacts.any()
    fixed = cleanup_feet(sliding, contacts, rep.feet)
    pos = fixed.positions().detach().numpy()
    for f, foot in enumerate(rep.feet):
        on = np.flatnonzero(contacts[:, f])
        runs = np.split(on, np.flatnonzero(np.diff(on) > 1) + 1)
        for run in runs:
            p = pos[run, foot]
            assert np.abs(p - p.mean(0)).max() < 0.1, "foot moved more than 1 mm (0.1 cm) while pinned"


# --------------------------------------------------------------------------------------------- CLI
def test_cli_train_resume_generate(proc_dir, tmp_path, capsys):
    run = tmp_path / "run"
    common = ["--preset", "small", "--frames", "16", "--batch", "2", "--no-tensorboard", "--no-cache",
              "--sample-every", "0"]
    assert main(["train", str(proc_dir), "--out", str(run), "--iters", "1", *common]) == 0
    assert (run / "checkpoint.pt").is_file() and (run / "config.json").is_file() and (run / "log.jsonl").is_file()
    assert main(["train", str(proc_dir), "--out", str(run), "--iters", "1", *common]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["train", str(proc_dir), "--out", str(run), "--resume", "--iters", "2", "--no-cache"]) == 0
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 2
    out = tmp_path / "gen"
    assert main(["generate", str(run / "checkpoint.pt"), "--n", "3", "--out", str(out), "--batch", "2",
                 "--psi", "0.8", "--ik"]) == 0
    assert sorted(p.name for p in out.glob("*.bvh")) == ["motion_0000.bvh", "motion_0001.bvh", "motion_0002.bvh"]
    assert (out / "samples.gif").is_file() and np.load(out / "motion_0002_contacts.npy").shape == (16, 2)
    from modi.io import bvh as bvh_io

    b = bvh_io.load(out / "motion_0000.bvh")
    assert b.n_frames == 16 and b.names == load_checkpoint(run / "checkpoint.pt")["skeleton"]["names"]
    junk = tmp_path / "junk.pt"
    junk.write_text("not a checkpoint")
    assert main(["generate", str(junk), "--n", "1", "--out", str(out)]) == 2
    assert "modi: error:" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r2")]) == 2


def test_cli_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--iters", "1", "--clips", "3", "--n", "2", "--no-progress"]) == 0
    assert len(list((out / "samples").glob("*.bvh"))) == 2
    assert (out / "samples" / "samples.gif").is_file() and (out / "training_examples.gif").is_file()
    assert load_checkpoint(out / "run" / "checkpoint.pt")["step"] == 1
    assert main(["demo", "--out", str(out), "--iters", "1"]) == 2  # refuses to overwrite a finished demo


def test_cli_released_options_reach_the_config():
    import argparse

    from modi.cli.commands import train as train_command

    parser = argparse.ArgumentParser()
    train_command.register(parser.add_subparsers())
    cfg = train_command.build_config(parser.parse_args(["train", "procedural", "--out", "r", "--preset", "small"]))
    assert cfg.model.noise_injection is False and cfg.train.contact_loss == "released"
    args = parser.parse_args(["train", "procedural", "--out", "r", "--preset", "small", "--noise-injection",
                              "--contact-loss", "squared"])
    cfg = train_command.build_config(args)
    assert cfg.model.noise_injection is True and cfg.train.contact_loss == "squared"
    args = parser.parse_args(["train", "procedural", "--out", "r", "--ablation", "pre-release"])
    cfg = train_command.build_config(args)
    assert cfg.model.noise_injection is True and cfg.train.contact_loss == "squared"
    assert (cfg.model.neighbors, cfg.model.pooling) == ("siblings", "merge")
    args = parser.parse_args(["train", "procedural", "--out", "r", "--neighbors", "tree", "--pooling", "released"])
    cfg = train_command.build_config(args)
    assert (cfg.model.neighbors, cfg.model.pooling) == ("tree", "released")


def test_bandai_released_loss_joints(shared_data, tmp_path):
    """On Bandai the contact labels sit on the toes, the released loss measures the ankles (Foot_L/R), and the
    encoder's root term must skip the constant joint_Root placeholder for Hips."""
    from modi.models.modi.encoder.training import root_rotation_entity

    sub = _bandai_subset(shared_data, tmp_path)
    for ablations, root in (((), "joint_Root"), (("released-representation",), "Hips")):
        codec = prepare_data(sub, tiny_cfg(*ablations), cache=False).codec
        names = codec.skeleton.names
        assert [names[j] for j in codec.feet] == ["Toes_L", "Toes_R"]
        assert [names[j] for j in codec.ankles] == ["Foot_L", "Foot_R"]
        assert names[0] == root and names[root_rotation_entity(codec)] == "Hips"


def test_bandai_released_representation(shared_data, tmp_path):
    """Item 4 of issue 13 on real data: the released preprocessing drops Bandai's joint_Root anchor and the leaf
    rotations, and every remaining joint's position is exactly the full representation's."""
    sub = _bandai_subset(shared_data, tmp_path)
    full = prepare_data(sub, tiny_cfg(), cache=False)
    rel = prepare_data(sub, tiny_cfg("released-representation"), cache=False)
    fr, rr = full.codec.rep, rel.codec.rep
    assert rr.n_entities == fr.n_entities - 1 and rr.skeleton.names == fr.skeleton.names[1:]
    assert [rr.skeleton.names[j] for j in rr.dropped_rotations] == ["Head", "Hand_L", "Hand_R", "Toes_L", "Toes_R"]
    assert fr.dropped_rotations == []
    xf = full.codec.normalizer.denormalize(full.windows).double()
    xr = rel.codec.normalizer.denormalize(rel.windows).double()
    assert xf.shape[0] == xr.shape[0]
    # the leaf entities hold the identity rotation in every frame: no data left in them
    leaf = xr[:, :, rr.dropped_rotations]
    assert (leaf[:, 0] - 1).abs().max() < 1e-6 and leaf[:, 1:].abs().max() < 1e-6
    # positions: every joint except the dropped anchor, exactly (float32 windows)
    pf, pr = fr.positions(xf), rr.positions(xr)
    scale = float(pf.abs().max())
    assert (pr - pf[..., 1:, :]).abs().max() <= 1e-5 * scale
    # a model's output at the leaves is ignored when decoding
    noisy = xr.clone()
    noisy[:, :, rr.dropped_rotations] += torch.randn_like(noisy[:, :, rr.dropped_rotations])
    q = rr.decode_parts(noisy)[0][..., rr.dropped_rotations, :]
    assert torch.equal(q, torch.tensor([1.0, 0, 0, 0], dtype=q.dtype).expand_as(q))
