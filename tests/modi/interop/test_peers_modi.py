"""The released MoDi (../shared/peers/MoDi, run on the CPU by benchmarks/peers/released_modi.py) is the oracle:
checkpoints its own code wrote are imported with ``modi import modi-released`` and must compute the same thing,
op by op, in float64 on the same latents, noise and data batch.

Where modi defaults differently (activation demodulation, StyleGAN2 time padding, the path-length running mean,
the EMA half-life) the test runs both settings and names the difference.
"""
from __future__ import annotations

import copy
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[3]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from peers_support import rel  # noqa: E402
from benchmarks.peers import released_modi as R  # noqa: E402
from modi.interop import modi_released as M  # noqa: E402

pytestmark = [pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning"),  # the released sources' old idioms
              pytest.mark.filterwarnings("ignore::SyntaxWarning"),
              pytest.mark.filterwarnings("ignore::RuntimeWarning")]
TOL = 1e-5




@pytest.fixture(scope="session")
def files(tmp_path_factory):
    try:
        return R.session_files(tmp_path_factory.getbasetemp() / "released_modi")
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def peer():
    """Their modules, importable (and torch's CUDA calls mapped to the CPU) for this module's tests only."""
    try:
        R.require_peer()
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))
    with R.peer_runtime() as ns:
        yield ns


def _pair(files, peer, kind: str = "trained"):
    """(released checkpoint, their (G, D, G_ema) in float64, ours in float64, levels)."""
    ck = R.load_released(getattr(files, kind))
    rg, rd, rge, statics = R.models_from_checkpoint(peer, ck)
    levels = M.released_levels(ck["g_ema"], ck["args"])
    ours = (M.convert_generator(ck["g"], ck["args"], levels, 4).double(),
            M.convert_discriminator(ck["d"], ck["args"], levels, 4).double(),
            M.convert_generator(ck["g_ema"], ck["args"], levels, 4).double())
    return ck, (rg.double(), rd.double(), rge.double()), ours, statics


def _levels_out(g, wplus):
    """modi's generator, its motion at every level (the skip sum after each level), from its own modules."""
    x = g.conv1(g.const.repeat(wplus.shape[0], 1, 1, 1), wplus[:, 0])
    skip = g.to_motion1(x, wplus[:, 1])
    outs, idx = [skip], 1
    for block, to_motion in zip(g.blocks, g.to_motions):
        for j, conv in enumerate(block):
            x = conv(x, wplus[:, idx + j])
        skip = to_motion(x, wplus[:, idx + len(block)], skip)
        outs.append(skip)
        idx += len(block)
    return outs


def _real_batch(peer, files, n=4):
    statics = R.motion_statics(peer, files.args)
    data, _ = R.normalisation(peer, files.args, statics)
    return torch.from_numpy(np.ascontiguousarray(data[:n])).double().transpose(1, 2).contiguous()


# --------------------------------------------------------------------------------------------- generator
@pytest.mark.parametrize("kind", ["init", "trained"])
def test_generator_every_level_equal(files, peer, kind):
    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer, kind)
    z = torch.randn(4, ck["args"].latent, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        theirs, _, _ = rge([z], return_sub_motions=True)
        ours = _levels_out(ge, ge.make_wplus(ge.mapping(z)))
        final = ge(z)
    assert len(ours) == len(theirs) == 5
    for level, (a, b) in enumerate(zip(ours, theirs)):
        assert a.shape == b.shape
        assert rel(a, b) <= TOL, f"level {level}"
    assert rel(final, theirs[-1]) <= TOL
    assert ge.noise_shapes() == []  # the released generator has no noise injection: nothing else random enters


def test_generator_modi_defaults_are_named_differences(files, peer):
    """modi's defaults (weight demodulation, the adjoint pair's time padding) are other functions of the same
    weights: each one alone moves the output well past the tolerance."""
    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer)
    z = torch.randn(4, ck["args"].latent, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    with torch.no_grad():
        theirs = rge([z])[0]
    from modi.models.modi.networks import Generator

    for change in ({"demodulation": "weight"}, {"time_padding": "adjoint"}):
        cfg = copy.deepcopy(ge.cfg)
        for k, v in change.items():
            setattr(cfg, k, v)
        other = Generator(cfg, ge.levels, 4).double()
        other.load_state_dict(ge.state_dict())
        with torch.no_grad():
            assert rel(other(z), theirs) > 1e-3, change


def test_style_mixing_and_truncation(files, peer):
    """Mixing at their inject index t is modi's at ``inject_index_from_released(t)``: their loop gives a level's
    first in-place conv the upsampling conv's W+ row again (named difference: at t itself modi's mix differs)."""
    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer)
    index = M.released_style_index(len(ge.levels), ck["args"].n_inplace_conv)
    assert len(index) == ge.n_latent == rge.n_latent
    gen = torch.Generator().manual_seed(3)
    z1, z2 = (torch.randn(3, ck["args"].latent, generator=gen, dtype=torch.float64) for _ in range(2))
    with torch.no_grad():  # their truncation centre (mean_latent's computation, in float64), used by both
        centre = rge.get_latent(torch.randn(256, ck["args"].latent, generator=gen, dtype=torch.float64)).mean(
            0, keepdim=True)
        theirs = rge([z1, z2], inject_index=3, truncation=0.7, truncation_latent=centre)[0]
        ge.w_avg.copy_(centre[0])
        t = M.inject_index_from_released(3, index)
        ours = ge([z1, z2], inject_index=t, truncation_psi=0.7)
        plain = ge([z1, z2], inject_index=t)
        same_t = ge([z1, z2], inject_index=3, truncation_psi=0.7)
        # a W+ in their layout, through the row map
        wplus = torch.cat([rge.get_latent(z1).unsqueeze(1).repeat(1, 3, 1),
                           rge.get_latent(z2).unsqueeze(1).repeat(1, rge.n_latent - 3, 1)], 1)
        from_wplus = ge.synthesis(M.wplus_from_released(wplus, index))
        theirs_wplus = rge([wplus], input_is_latent=True)[0]
    assert t == 4
    assert rel(ours, theirs) <= TOL
    assert rel(from_wplus, theirs_wplus) <= TOL
    assert rel(plain, theirs) > 1e-3  # truncation did something
    assert rel(same_t, theirs) > 1e-3  # the named difference


def test_ema_generator_and_its_update(files, peer, tmp_path):
    """The imported run's EMA and raw generators are the released ones (they differ after training), and one EMA
    update in compact weights equals theirs in dense weights. modi's own half-life differs: theirs assumes a
    batch of 32 whatever the batch (0.5 ** (32 / 10000) per step), modi's follows the batch (and ramps up)."""
    from modi.models.modi.sampling import load_generator
    from modi.models.modi.training import _accumulate

    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer)
    run = M.import_checkpoint(files.trained, files.data, tmp_path / "run")
    z = torch.randn(4, ck["args"].latent, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    with torch.no_grad():
        want_ema, want_raw = rge([z])[0], rg([z])[0]
        assert rel(want_ema, want_raw) > 1e-4  # two iterations moved g away from g_ema
        for ema, want in ((True, want_ema), (False, want_raw)):
            imported = load_generator(run, ema=ema)[0].double()
            assert rel(imported(z), want) <= TOL
    tm = R.train_module(peer)
    decay = tm.ACCUMULATE_DECAY_FACTOR
    theirs = copy.deepcopy(rge)
    tm.accumulate(theirs, rg, decay)
    ours = copy.deepcopy(ge)
    _accumulate(ours, g, decay)
    with torch.no_grad():
        assert rel(ours(z), theirs([z])[0]) <= TOL
    assert decay == pytest.approx(0.5 ** (32 / 10_000))
    assert 0.5 ** (16 / (10.0 * 1000)) != pytest.approx(decay)  # modi's half-life at their batch of 16


# --------------------------------------------------------------------------------------------- refusals
def test_weight_outside_the_mask_is_refused(files, tmp_path):
    """A mask entry switched on outside the skeletal pattern puts a weight the per-pair form cannot hold: the
    import names the layer and where; dead raw weights where the mask is 0 (all released files have them) are
    not an error."""
    ck = R.load_released(files.trained)
    mask = ck["g_ema"]["convs.4.conv.mask"]
    pattern = M._entity_mask(mask)
    j, i = [int(v) for v in torch.nonzero(~pattern)[0]]
    mask[0, 0, 0, j, i, 0] = 1.0
    bad = tmp_path / "bad.pt"
    torch.save(ck, bad)
    with pytest.raises(M.MaskViolation, match=r"g\.convs\.4\.conv\.weight: 1 non-zero outside its skeletal mask"):
        M.import_checkpoint(bad, files.data, tmp_path / "run")
    from modi.cli import main

    assert main(["import", "modi-released", str(bad), "--data", str(files.data), "--out", str(tmp_path / "r2")]) == 2
    assert not (tmp_path / "r2" / "checkpoint.pt").exists()


def test_code_in_a_released_file_is_refused(files, tmp_path, capsys):
    """Files from others are data: a checkpoint or data file naming a function is refused, never run."""
    from modi.cli import main
    from modi.errors import CheckpointError
    from modi.interop.released_files import load_released_npy

    evil = tmp_path / "evil.pt"
    torch.save({"g": print}, evil)
    assert main(["import", "modi-released", str(evil), "--data", str(files.data), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "objects other than data (print)" in err[0]

    class Boom:
        def __reduce__(self):
            return (print, ("ran",))

    arr = np.empty(1, dtype=object)
    arr[0] = Boom()
    npy = tmp_path / "evil.npy"
    np.save(npy, arr, allow_pickle=True)
    with pytest.raises(CheckpointError, match="refusing builtins.print"):
        load_released_npy(npy)
    assert "ran" not in capsys.readouterr().out


# --------------------------------------------------------------------------------------------- discriminator
@pytest.mark.parametrize("kind", ["init", "trained"])
def test_discriminator_scores_equal(files, peer, kind):
    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer, kind)
    real = _real_batch(peer, files)
    z = torch.randn(4, ck["args"].latent, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    with torch.no_grad():
        fake = rg([z])[0]
        for x in (real, fake):
            assert rel(d(x), rd(x)[0]) <= TOL


def _grads_equal(ours_module, ours_state_fn, theirs_module, what):
    """Every parameter gradient of ours equals theirs mapped by the weight conversion (``power=-1``), on the
    entity pairs the released masks connect. Returns the names of modi parameters with pairs they do not
    connect (the discriminator's 1x1 skips, which read one fine entity per coarse one in the released code)."""
    sd = {k: v for k, v in theirs_module.state_dict().items()}
    ones = dict(sd)
    for name, p in theirs_module.named_parameters():
        if p.requires_grad:
            sd[name] = p.grad if p.grad is not None else torch.zeros_like(p)
            ones[name] = torch.ones_like(p)
    want = ours_state_fn(sd, 1)
    connected = ours_state_fn(ones, 0)  # 1 on the pairs their masks connect, 0 on modi's extra pairs
    extra = []
    for name, p in ours_module.named_parameters():
        grad = p.grad if p.grad is not None else torch.zeros_like(p)  # e.g. output biases under path length
        c = connected[name].to(grad.dtype)
        if bool((c == 0).any()):
            extra.append(name)
        assert rel(grad * c, want[name].to(grad.dtype)) <= TOL, f"{what}.{name}"
    assert len(list(ours_module.parameters())) == len(want) - ("w_avg" in want)
    return extra


def test_d_step_losses_and_gradients(files, peer):
    """One discriminator step of their train(): logistic loss and scores, then R1 at its lazy interval
    (weighted by r1 / 2 * d_reg_every), each term and every parameter gradient."""
    from modi.models.modi import losses

    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer)
    tm = R.train_module(peer)
    args = ck["args"]
    real = _real_batch(peer, files)
    z = torch.randn(4, args.latent, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    with torch.no_grad():
        fake = rg([z])[0]
    # logistic loss
    rd.zero_grad()
    t_loss = tm.d_logistic_loss(rd(real)[0], rd(fake)[0])
    t_loss.backward()
    d.zero_grad()
    real_pred, fake_pred = d(real), d(fake)
    o_loss = losses.d_logistic_loss(real_pred, fake_pred)
    o_loss.backward()
    assert rel(o_loss, t_loss) <= TOL
    assert rel(real_pred.mean(), rd(real)[0].mean()) <= TOL and rel(fake_pred.mean(), rd(fake)[0].mean()) <= TOL
    dstate = lambda sd, grad: M.discriminator_state(sd, args, d, power=-1 if grad else 0)  # noqa: E731
    extra = _grads_equal(d, dstate, rd, "d")
    # named difference: modi's skips store the whole pooling group (imported as zeros); their gradients are not
    # zero, so training an imported model moves them where the released code cannot
    assert extra == [f"blocks.{b}.skip.1.weight" for b in range(len(d.blocks))]
    # R1, lazily every d_reg_every steps (their step 0 applies it, as modi's trainer does), same weighting
    from modi.models.modi.config import TrainConfig

    tc = TrainConfig()
    assert (args.d_reg_every, args.r1) == (tc.d_reg_every, tc.r1_gamma)
    for module in (rd, d):
        module.zero_grad()
    x = real.clone().requires_grad_(True)
    t_pred = rd(x)[0]
    t_r1 = tm.d_r1_loss(t_pred, x)
    (args.r1 / 2 * t_r1 * args.d_reg_every + 0 * t_pred[0]).backward()
    y = real.clone().requires_grad_(True)
    o_pred = d(y)
    o_r1 = losses.d_r1_penalty(o_pred, y)
    (args.r1 / 2 * o_r1 * args.d_reg_every + 0 * o_pred[0, 0]).backward()
    assert rel(o_r1, t_r1) <= TOL
    _grads_equal(d, dstate, rd, "d(r1)")


def test_g_step_losses_and_gradients(files, peer):
    """One generator step: the non-saturating loss through D, then path length at its lazy interval (batch
    shrunk by 2, weight path_regularize * g_reg_every), each term and every generator gradient.

    Named difference: modi's running path-length mean is detached before the penalty (StyleGAN2's reference
    code); the released one keeps it in the graph. Values agree; modi's gradients equal theirs with the mean
    detached, and differ from theirs as released."""
    from modi.models.modi import losses

    ck, (rg, rd, rge), (g, d, ge), _ = _pair(files, peer)
    tm = R.train_module(peer)
    args = ck["args"]
    for p in list(rd.parameters()) + list(d.parameters()):
        p.requires_grad_(False)
    z = torch.randn(4, args.latent, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    rg.zero_grad()
    t_loss = tm.g_nonsaturating_loss(rd(rg([z])[0])[0])
    t_loss.backward()
    g.zero_grad()
    o_loss = losses.g_nonsaturating_loss(d(g(z)))
    o_loss.backward()
    assert rel(o_loss, t_loss) <= TOL
    state = lambda sd, grad: M.generator_state(sd, args, g, power=-1 if grad else 0)  # noqa: E731
    assert _grads_equal(g, state, rg, "g") == []

    zp = z[: max(1, args.batch // args.path_batch_shrink)]
    from modi.models.modi.config import TrainConfig

    tc = TrainConfig()  # the lazy interval, weight and batch shrink modi's trainer uses are theirs
    assert (args.g_reg_every, args.path_regularize, args.path_batch_shrink) == \
        (tc.g_reg_every, tc.path_weight, tc.path_batch_shrink)
    weight = args.path_regularize * args.g_reg_every
    rg.zero_grad()
    fake_t, lat_t, _ = rg([zp], return_latents=True)
    torch.manual_seed(9)
    t_path, t_mean, t_lengths = tm.g_path_regularize(fake_t, lat_t, 0)
    (weight * t_path).backward()
    released_grads = {n: p.grad.clone() for n, p in rg.named_parameters() if p.grad is not None}

    # modi's own W+ (one row per layer) is another path: lengths differ (named difference; see the mixing test)
    fake_n, lat_n = g(zp, return_latents=True)
    torch.manual_seed(9)
    assert rel(losses.path_length_penalty(fake_n, lat_n, 0.0)[2], t_lengths) > 1e-3
    # the same W+ as theirs (their layout, read through the row map)
    index = M.released_style_index(len(g.levels), args.n_inplace_conv)
    g.zero_grad()
    lat_o = g.mapping(zp).unsqueeze(1).repeat(1, g.n_latent, 1)
    fake_o = g.synthesis(M.wplus_from_released(lat_o, index))
    torch.manual_seed(9)
    o_path, o_mean, o_lengths = losses.path_length_penalty(fake_o, lat_o, 0.0)
    (weight * o_path).backward()
    assert rel(o_path, t_path) <= TOL and rel(o_mean, t_mean) <= TOL and rel(o_lengths, t_lengths) <= TOL

    # the released penalty with its running mean detached, on their generator and their noise
    rg.zero_grad()
    fake_t, lat_t, _ = rg([zp], return_latents=True)
    torch.manual_seed(9)
    noise = torch.randn_like(fake_t) / math.sqrt(fake_t.shape[2] * fake_t.shape[3])
    (grad,) = torch.autograd.grad((fake_t * noise).sum(), lat_t, create_graph=True)
    lengths = torch.sqrt(grad.pow(2).sum(2).mean(1))
    (weight * (lengths - 0.01 * lengths.mean().detach()).pow(2).mean()).backward()
    _grads_equal(g, state, rg, "g(path, detached mean)")
    differs = max(rel(released_grads[n], p.grad) for n, p in rg.named_parameters() if n in released_grads)
    assert differs > TOL  # the released (non-detached) gradients are another function


def test_g_step_foot_terms_equal(files, peer):
    """The two foot terms of their G step with --foot (``g_foot_contact_loss_v2``: sigmoid contact x ankle speed
    per frame; ``g_encourage_contact``) against modi's released forms (``foot_contact_speed_loss`` on
    ``codec.ankles``, ``foot_touch_loss``) and their weights, on their --foot data with contact channels
    perturbed off the labels. (A --foot generator on this skeleton does not import: see docs/authors.md.)"""
    from modi.interop.released_files import load_released_npy
    from modi.models.modi import losses
    from modi.models.modi.config import TrainConfig

    args = R.make_args(files.data, feet=True)
    ckpt = files.root / "init_foot.pt"
    if not ckpt.is_file():
        R.random_init_checkpoint(args, ckpt)
    ck = R.load_released(ckpt)
    statics = R.motion_statics(peer, args)
    data, norm = R.normalisation(peer, args, statics)
    x = torch.from_numpy(np.ascontiguousarray(data[:4])).double().transpose(1, 2).contiguous()
    n_feet = len(statics.foot_indexes[-1])
    assert n_feet == 2 and x.shape[2] == 24
    x[:, 0, -n_feet:] += torch.randn(4, n_feet, x.shape[-1], generator=torch.Generator().manual_seed(11),
                                     dtype=torch.float64)
    tm = R.train_module(peer)
    nd = {"std": torch.from_numpy(norm["std"]).double(), "mean": torch.from_numpy(norm["mean"]).double()}
    theirs_fc = tm.g_foot_contact_loss_v2(x, statics, nd, args.glob_pos, args.use_velocity)
    theirs_touch = tm.g_encourage_contact(x)

    codec = M.released_codec(load_released_npy(files.data)[0], ck, statics.foot_indexes[-1], 30.0)
    codec.normalizer.mean, codec.normalizer.std = codec.normalizer.mean.double(), codec.normalizer.std.double()
    foot_pos, contact = codec.foot_terms(x, codec.ankles)
    ours_fc = losses.foot_contact_speed_loss(foot_pos, contact)
    ours_touch = losses.foot_touch_loss(contact)
    assert rel(ours_fc, theirs_fc) <= TOL and rel(ours_touch, theirs_touch) <= TOL
    tc = TrainConfig()
    assert (tc.contact_loss, tc.contact_weight, tc.touch_weight) == \
        ("released", args.g_foot_reg_weight, args.g_encourage_contact_weight)


# --------------------------------------------------------------------------------------------- BVH and CLI
def _bvh_points(path):
    """Joint and End Site positions of a BVH, by name (modi's reader and FK)."""
    from modi.data.motion import Motion
    from modi.core.rotations import quat_apply

    m = Motion.from_bvh(path)
    pos, rot = m.forward_kinematics()
    out = {n: pos[:, j] for j, n in enumerate(m.skeleton.names)}
    for j, e in m.skeleton.end_sites.items():
        off = torch.as_tensor(e, dtype=pos.dtype).expand(pos.shape[0], 3)
        out["End:" + m.skeleton.names[j]] = pos[:, j] + quat_apply(rot[:, j], off)
    return out, m


def test_bvh_from_a_sample_equals_theirs(files, peer, tmp_path):
    """Their BVH writer (train.py's) and modi's, from the same sample: every joint and End Site within 1e-5 of
    body height. Their writer adds one zero-offset dummy joint per bone of a joint with several children and
    keeps that joint too; modi's edge skeleton has the dummies only, at the same place."""
    from modi.models.modi.sampling import load_generator

    run = M.import_checkpoint(files.trained, files.data, tmp_path / "run")
    g, codec, _ = load_generator(run)
    ck = R.load_released(files.trained)
    _, _, rge, statics = R.models_from_checkpoint(peer, ck)
    z = torch.randn(1, ck["args"].latent, generator=torch.Generator().manual_seed(10), dtype=torch.float64)
    with torch.no_grad():
        theirs_path = R.write_bvh(peer, rge.double()([z])[0], ck, statics, tmp_path / "theirs.bvh")
        codec.to_motions(g.double()(z))[0].save(tmp_path / "ours.bvh")
    theirs, tm = _bvh_points(theirs_path)
    ours, _ = _bvh_points(tmp_path / "ours.bvh")
    height = float(np.ptp(tm.skeleton.rest_positions(), axis=0).max())
    assert height > 100  # Bandai, centimetres
    only_theirs = sorted(set(theirs) - set(ours))
    assert only_theirs == ["Chest"] and not set(ours) - set(theirs)
    worst = 0.0
    for name, p in theirs.items():
        q = ours[name] if name in ours else ours[next(k for k in ours if k.startswith(name + "_"))]
        worst = max(worst, float((p - q).abs().max()))
    assert worst <= 1e-5 * height


def test_import_then_generate_bvh_and_glb(files, tmp_path):
    """End to end through the CLI: modi import -> modi generate --format bvh,glb."""
    from modi.cli import main

    run = tmp_path / "run"
    assert main(["import", "modi-released", str(files.trained), "--data", str(files.data.parent),
                 "--out", str(run)]) == 0
    out = tmp_path / "gen"
    assert main(["generate", str(run / "checkpoint.pt"), "--n", "2", "--out", str(out), "--format", "bvh,glb",
                 "--gif-max", "0", "--no-view"]) == 0
    from modi.data.motion import Motion

    for i in range(2):
        m = Motion.from_bvh(out / f"motion_{i:04d}.bvh")
        assert m.n_frames == 64 and torch.isfinite(m.positions()).all()
        assert (out / f"motion_{i:04d}.glb").read_bytes()[:4] == b"glTF"


def test_import_errors_are_one_line(files, tmp_path, capsys):
    from modi.cli import main

    cases = [
        (["import", "modi-released", str(tmp_path / "missing.pt"), "--data", str(files.data), "--out",
          str(tmp_path / "r")], "no such"),
        (["import", "modi-released", str(files.data), "--data", str(files.data), "--out", str(tmp_path / "r")],
         "not a readable released MoDi checkpoint"),
        (["import", "modi-released", str(files.trained), "--data", str(tmp_path), "--out", str(tmp_path / "r")],
         "exactly one .npy"),
    ]
    for argv, text in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and text in err[0], err



def test_imported_checkpoint_records_what_the_file_says(files, tmp_path, capsys):
    """Provenance: the imported checkpoint keeps their iteration (the file 000001.pt is written after their
    iteration 1: 2 iterations), their args as the file holds them (--iter 2, not modi's 80000), their data's window
    and stride (64 every 32, read from the overlapping windows of their .npy), and the files' names and SHA-256;
    ``modi info`` prints it, marked as imported. Their random-initialisation file (no iteration in its name, no
    optimiser steps) says so instead of a made-up step."""
    import hashlib

    from modi.cli import main
    from modi.models.modi.checkpoint import load_checkpoint

    st = load_checkpoint(M.import_checkpoint(files.trained, files.data, tmp_path / "run"))
    prov = st["imported_from"]
    assert st["step"] == 2 and prov["kind"] == "modi-released" and prov["iterations"] == 2
    assert prov["source"]["name"] == "000001.pt"
    assert prov["source"]["sha256"] == hashlib.sha256(files.trained.read_bytes()).hexdigest()
    assert prov["args"]["iter"] == 2 and prov["args"]["batch"] == R.load_released(files.trained)["args"].batch
    data = prov["data"]
    assert (data["name"], data["window"], data["stride"]) == (files.data.name, 64, 32)
    assert data["sha256"] == hashlib.sha256(files.data.read_bytes()).hexdigest()
    assert st["config"]["train"]["iters"] == 2 and st["config"]["data"]["stride"] == 32
    assert prov["seed"] is None  # their train.py seeds nothing
    init = load_checkpoint(M.import_checkpoint(files.init, files.data, tmp_path / "init"))
    assert init["step"] == 0 and init["imported_from"]["iterations"] is None

    capsys.readouterr()
    assert main(["info", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "MoDi generator checkpoint (imported from the authors' released code)" in out
    assert "2 iterations, from the file name 000001.pt" in out
    assert prov["source"]["sha256"] in out.replace("\n             ", "")
    assert "windows of 64 frames every 32" in out and "--iter=2" in out
