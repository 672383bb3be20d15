"""The released MoDi encoder (their train_encoder.py, run on the CPU by benchmarks/peers/released_modi.py) against
``modi import encoder-released``: W+ codes, the reconstruction through the generator, every loss term of their
encoder step and every encoder gradient, in float64 on the same data batch.

Named differences: their W+ rows follow their generator loop (a level's first in-place conv re-reads the
upsampling conv's row, some rows are never read); the imported encoder predicts modi's layout, i.e. theirs
gathered by ``released_style_index``, so a released head row read by two layers becomes two modi rows (their
gradient is the sum of the copies'); and the position term averages over different points (see the test).
"""
from __future__ import annotations

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
from modi.interop import encoder_released as E  # noqa: E402
from modi.interop import modi_released as M  # noqa: E402

pytestmark = [pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning"),  # the released sources' old idioms
              pytest.mark.filterwarnings("ignore::SyntaxWarning"),
              pytest.mark.filterwarnings("ignore::RuntimeWarning")]
TOL = 1e-5




@pytest.fixture(scope="session")
def files(tmp_path_factory):
    try:
        f = R.session_files(tmp_path_factory.getbasetemp() / "released_modi")
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))
    f.encoder = R.session_encoder(f)
    return f


@pytest.fixture(scope="module")
def peer():
    """Their modules, importable (and torch's CUDA calls mapped to the CPU) for this module's tests only."""
    try:
        R.require_peer()
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))
    with R.peer_runtime() as ns:
        yield ns


@pytest.fixture(scope="session")
def imported(files, tmp_path_factory):
    from modi.models.modi.encoder.training import load_encoder

    run = E.import_checkpoint(files.encoder, files.trained, files.data, tmp_path_factory.mktemp("enc_run"))
    return load_encoder(run)


def _theirs(peer, files):
    """Their encoder and EMA generator (float64) from the files, built as train_encoder.py builds them."""
    est, gst = R.load_released(files.encoder), R.load_released(files.trained)
    _, _, rge, statics = R.models_from_checkpoint(peer, gst)
    with R._channels(peer, gst["args"]) as traits:
        enc = peer.gan.Discriminator(traits_class=traits, motion_statics=statics, latent_dim=est["args"].latent,
                                     latent_rec_idx=int(est["args"].encoder_latent_rec_idx),
                                     n_latent_predict=est["args"].n_latent_predict)
    enc.load_state_dict(est["e"])
    return enc.double(), rge.double(), statics, est["args"]


def _real(peer, files, n=4):
    statics = R.motion_statics(peer, files.args)
    data, norm = R.normalisation(peer, files.args, statics)
    return torch.from_numpy(np.ascontiguousarray(data[:n])).double().transpose(1, 2).contiguous(), norm


def test_encoder_wplus_and_reconstruction_equal(files, peer, imported):
    enc_t, g_t, _, args = _theirs(peer, files)
    enc, g = imported.encoder.double(), imported.g.double()
    index = M.released_style_index(len(g.levels), g.cfg.n_inplace_convs)
    real, _ = _real(peer, files)
    noise = torch.randn(real.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        for x in (real, noise):
            w_t = enc_t(x)[1]
            w = enc(x)
            assert w_t.shape == (x.shape[0], g.n_latent, g.latent_dim)
            assert rel(w, w_t[:, index]) <= TOL
            assert rel(w, w_t) > 1e-3  # the row layouts differ (named above)
            assert rel(g.synthesis(w), g_t([w_t], input_is_latent=True)[0]) <= TOL
    assert imported.cfg.head == "released" and imported.cfg.prefix_frames is None  # their n_frames 0: inversion


def test_encoder_step_losses_and_gradients(files, peer, imported):
    """Their encoder step's terms (models/encoder_mask.py: rec L2, root = root motion + root rotation, FK local
    positions, contact) against modi's ``encoder_losses`` with ``losses='released'`` and the same weights, and
    every encoder parameter gradient."""
    import models.encoder_mask as em  # their module (importable inside the peer runtime)

    from modi.models.modi.encoder.training import EncoderTrainConfig, encoder_losses, root_rotation_entity

    enc_t, g_t, statics, args = _theirs(peer, files)
    enc, g, codec = imported.encoder.double(), imported.g.double(), imported.codec
    real, norm = _real(peer, files)
    mean = torch.from_numpy(norm["mean"]).double()
    std = torch.from_numpy(norm["std"]).double()

    rec_t = g_t([enc_t(real)[1]], input_is_latent=True)[0]
    pos_t = em.PositionLoss(statics, True, args.foot, args.use_velocity, mean, std,
                            local_frame=args.use_local_pos)
    pos_t.fk.offset = pos_t.fk.offset.double()
    terms_t = {"rec": em.ReconLoss(args.loss_type)(rec_t, real), "pos": pos_t(rec_t, real),
               "root": em.GlobalPosLoss(args)(rec_t, real)}

    cfg = EncoderTrainConfig(losses="released")
    assert (cfg.lambda_rec, cfg.lambda_pos, cfg.lambda_root, cfg.lambda_contact) == \
        (args.lambda_rec, args.lambda_pos, args.lambda_global_pos, args.lambda_contact)
    enc.zero_grad()
    codec.normalizer.mean, codec.normalizer.std = codec.normalizer.mean.double(), codec.normalizer.std.double()
    rec = g.synthesis(enc(real))
    terms = encoder_losses(codec, rec, real, cfg, 1.0, root_entity=root_rotation_entity(codec))
    for name in ("rec", "root"):
        assert rel(terms[name], terms_t[name]) <= TOL, name
    assert float(terms["contact"]) == 0.0  # no contact entities in this model (their term is zeroed for it too)
    # the position term: their FK points (bone ends, root at 0) are modi's decoded points, to float32 precision
    # (their FK runs in float32); named difference: modi's term averages over its skeleton's joints (bone
    # starts: each dummy of a multi-child joint counts, leaf tips do not), theirs over bone ends
    with torch.no_grad():
        theirs_pts = pos_t.get_pos(rec_t.detach())
        ours_pts = _bone_ends(codec, rec.detach())
    assert rel(ours_pts, theirs_pts.double()) <= TOL
    assert rel(terms["pos"], terms_t["pos"]) > 1e-2
    # gradients of the terms that agree, and their total
    part_t = args.lambda_rec * terms_t["rec"] + args.lambda_global_pos * terms_t["root"]
    part = cfg.lambda_rec * terms["rec"] + cfg.lambda_root * terms["root"]
    assert rel(part, part_t) <= TOL
    enc_t.zero_grad()
    part_t.backward()
    part.backward()

    sd, ones = dict(enc_t.state_dict()), dict(enc_t.state_dict())
    for name, p in enc_t.named_parameters():
        if p.requires_grad:  # not the masks and fixed factors
            sd[name] = p.grad if p.grad is not None else torch.zeros_like(p)
            ones[name] = torch.ones_like(p)
    index = M.released_style_index(len(g.levels), g.cfg.n_inplace_convs)
    want = E.encoder_state(sd, enc, index, power=-1)
    connected = E.encoder_state(ones, enc, index, power=0)
    n = 0
    for name, p in enc.named_parameters():
        grad = p.grad if p.grad is not None else torch.zeros_like(p)
        if name.startswith("head."):  # modi's rows copy theirs: their row's gradient sums its copies'
            nl, dim = enc.cfg.n_latent, enc.cfg.latent_dim
            mine = grad.reshape(nl, dim, -1)
            summed = torch.zeros_like(mine).index_add_(0, torch.tensor(index), mine)
            theirs = sd[f"latent_predictor.linear2.{name.split('.')[1]}"].double().reshape(nl, dim, -1)
            assert rel(summed, theirs) <= TOL, name
            continue
        c = connected[name].to(grad.dtype)
        assert rel(grad * c, want[name].to(grad.dtype)) <= TOL, name
        n += 1
    assert n > 10


def _bone_ends(codec, x):
    """modi's decoded points at the released joints (the ends of their bones), root translation zeroed: a
    non-leaf bone ends where its first child bone's joint starts, a leaf at its joint's End Site."""
    from modi.core.kinematics import forward_kinematics
    from modi.core.rotations import quat_apply

    quats, root, _ = codec.rep.decode_parts(codec.normalizer.denormalize(x))
    sk = codec.skeleton
    offsets = torch.as_tensor(sk.offsets, dtype=quats.dtype)
    pos, rot = forward_kinematics(quats, offsets, list(sk.parents), torch.zeros_like(root))
    pts = []
    for i in range(sk.n_joints):
        kids = sk.children(i)
        if i == 0 or kids:
            pts.append(pos[..., 0 if i == 0 else kids[0], :])
        else:
            end = torch.as_tensor(sk.end_sites[i], dtype=pos.dtype).expand_as(pos[..., i, :])
            pts.append(pos[..., i, :] + quat_apply(rot[..., i, :], end))
    return torch.stack(pts, -2)


def test_import_encoder_cli_and_refusals(files, tmp_path, capsys):
    from modi.cli import main
    from modi.models.modi.encoder.training import load_encoder

    run = tmp_path / "enc"
    assert main(["import", "encoder-released", str(files.encoder), "--generator", str(files.trained),
                 "--data", str(files.data), "--out", str(run)]) == 0
    bundle = load_encoder(run / "encoder.pt")
    assert bundle.encoder.cfg.n_latent == bundle.g.n_latent
    capsys.readouterr()
    # a generator checkpoint given as the encoder, and the encoder given as the generator: one line each
    for argv in (["import", "encoder-released", str(files.trained), "--generator", str(files.trained)],
                 ["import", "encoder-released", str(files.encoder), "--generator", str(files.encoder)]):
        assert main(argv + ["--data", str(files.data), "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a released MoDi" in err[0], err


def test_imported_encoder_records_what_the_files_say(files, tmp_path, capsys):
    """Provenance of an imported encoder: its own iteration and args (their train_encoder.py's), the generator's
    record (its file's SHA-256, its 2 iterations), the data's window and stride; ``modi info`` marks it imported."""
    import hashlib

    from modi.cli import main

    path = E.import_checkpoint(files.encoder, files.trained, files.data, tmp_path / "enc")
    st = torch.load(path, weights_only=True)  # the record is plain data
    prov = st["imported_from"]
    assert st["step"] == 2 and prov["kind"] == "encoder-released" and prov["iterations"] == 2
    assert prov["source"]["sha256"] == hashlib.sha256(files.encoder.read_bytes()).hexdigest()
    assert prov["args"]["ckpt_existing"] == str(files.trained) and prov["args"]["iter"] == 2
    assert prov["generator"]["source"]["sha256"] == hashlib.sha256(files.trained.read_bytes()).hexdigest()
    assert prov["generator"]["iterations"] == 2 and st["generator"]["step"] == 2
    assert (prov["data"]["window"], prov["data"]["stride"]) == (64, 32)
    assert st["modi_version"] and st["torch_version"]
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "MoDi encoder checkpoint (imported from the authors' released code)" in out
    assert "2 iterations, from the file name 000001.pt" in out and "generator:" in out
