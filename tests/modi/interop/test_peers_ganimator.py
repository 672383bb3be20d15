"""The released GANimator (../shared/peers/ganimator, run on the CPU by benchmarks/peers/released_ganimator.py) is
the oracle: run folders its own ``train.py`` wrote (random initialisation, and after an iteration per block so no
weight is at its initial value) are imported with ``modi.interop.ganimator_released.import_checkpoint`` and must
compute the same thing in float64, on the same noise and data: the training tensor, each level's output, the
reconstruction, the demo's sample and its BVH, and every loss term and gradient of one D and one G step.

Where modi differs on purpose the test runs both settings and names the difference: a sample whose length is not
the training clip's has levels on modi's fixed grids (``ceil(N * rate)``) rather than the released pyramid of
``N``; modi's own BVH loader orders joints as the file does and picks units and feet from the motion.
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
from benchmarks.peers import released_ganimator as R  # noqa: E402
from modi.interop import ganimator_released as G  # noqa: E402

pytestmark = [pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning"),
              pytest.mark.filterwarnings("ignore::UserWarning")]  # the released sources' torch.cross(x, y)
TOL = 1e-5
KINDS = ("init", "trained")




@pytest.fixture(scope="session")
def released(tmp_path_factory):
    """Their train.py on the first 120 frames (60 at 30 fps) of the Mixamo walk: 0 and 1 iterations per block."""
    try:
        R.require_peer()
        src = R.require_data()
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))
    d = tmp_path_factory.getbasetemp() / "released_ganimator"
    bvh = R.trim_bvh(src, d / "data" / "walk.bvh", 120)
    torch.set_num_threads(1)
    return {"bvh": bvh, "init": R.train_released(bvh, d / "init", 0, seed=1),
            "trained": R.train_released(bvh, d / "trained", 1, seed=2)}


@pytest.fixture(scope="session")
def imported(released, tmp_path_factory):
    d = tmp_path_factory.getbasetemp() / "imported_ganimator"
    return {k: G.import_checkpoint(released[k].path, released["bvh"], d / k) for k in KINDS}


def _pair(released, imported, kind):
    """(their run in float64, our model in float64, entity permutation)."""
    from modi.models.ganimator.training import load_model

    theirs = R.ReleasedRun(released[kind].path, dtype=torch.float64)
    ours = load_model(imported[kind]).double()
    perm = G.entity_perm(ours.n_joints, len(ours.feet))
    return theirs, ours, perm


def _noises(lengths, amps, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(1, 1, L, generator=g, dtype=torch.float64) * float(a) for L, a in zip(lengths, amps)]


# other rigs (random initialisation): a 120 fps rig scaled by their 0.14 rule with every joint kept, a crab whose
# six leg tips carry contacts at their 0.006 threshold, and a Mixamo rig whose eyes their table leaves out
RIGS = {"xia": ("Xia/normal.bvh", 240), "crab": ("Crabnew/Crab-dance-long.bvh", 60),
        "mixamo-eyes": ("Malcolm/Gangnam-Style.bvh", 120)}


# --------------------------------------------------------------------------------------------- data and files
def test_released_files_and_training_moved_every_weight(released):
    r0, r1 = released["init"], released["trained"]
    assert sorted(p.name for p in r1.path.glob("gen*.pt")) == [f"gen{i:03d}.pt" for i in range(len(r1.lengths))]
    for g0, g1 in zip(r0.gens, r1.gens):
        for (k, a), b in zip(g0.state_dict().items(), g1.state_dict().values()):
            if k.endswith("mask"):
                continue
            w = a != 0  # weights outside the mask stay 0 in both
            assert bool((a[w] != b[w]).all()), k
    # their own training moved every discriminator mask off 0/1 (named in the one-iteration test)
    assert len(r1.trained_discs) == len(r1.lengths)
    for d in r1.trained_discs:
        masks = [v for k, v in d.state_dict().items() if k.endswith("mask")]
        assert masks and all(float((m - 1).abs()[m != 0].max()) > 1e-5 for m in masks)


@pytest.mark.parametrize("kind", KINDS)
def test_training_tensor_and_amplitudes_equal(released, imported, kind):
    """modi's clip of the imported run is their MotionData tensor (joint order, feet, units, labels)."""
    theirs, ours, perm = _pair(released, imported, kind)
    assert rel(ours.seqs[0].features.unsqueeze(0), G.to_modi_layout(theirs.motion_data.raw_motion, perm)) <= TOL
    assert ours.lengths[0] == theirs.lengths
    assert np.allclose(ours.amps[0], theirs.amps.numpy(), rtol=1e-6)
    assert rel(ours.z_stars[0], G.to_modi_layout(theirs.z_star, perm)) <= TOL
    assert [ours.seqs[0].skeleton.names[f] for f in ours.feet] == theirs.motion_data.bvh_file.skeleton.contact_names


@pytest.mark.parametrize("kind", KINDS)
def test_every_level_output_equal(released, imported, kind):
    from modi.models.ganimator.networks import synthesize

    theirs, ours, perm = _pair(released, imported, kind)
    noises = _noises(theirs.lengths, theirs.amps, seed=3)
    their_levels = theirs.level_outputs(noises)
    with torch.no_grad():
        our_levels = synthesize(ours.gens, ours.rates[0], ours.lengths[0], [n.view(1, 1, 1, -1) for n in noises],
                                ours.n_entities)
    assert len(our_levels) == len(their_levels) == len(theirs.lengths)
    for l, (a, b) in enumerate(zip(our_levels, their_levels)):
        assert rel(a, G.to_modi_layout(b, perm)) <= TOL, l


@pytest.mark.parametrize("kind", KINDS)
def test_reconstruction_equal(released, imported, kind):
    theirs, ours, perm = _pair(released, imported, kind)
    assert rel(ours.reconstruct(0), G.to_modi_layout(theirs.reconstruction()[-1], perm)) <= TOL


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_other_rigs_data_levels_and_reconstruction_equal(released, rig, tmp_path):
    from modi.models.ganimator.networks import synthesize
    from modi.models.ganimator.training import load_model

    path, n = RIGS[rig]
    if not (R.DATA / path).is_file():
        pytest.skip(f"{R.DATA / path} not found (../shared/data)")
    bvh = R.trim_bvh(R.DATA / path, tmp_path / "data" / Path(path).name, n)
    R.train_released(bvh, tmp_path / "theirs", 0, seed=14)
    theirs = R.ReleasedRun(tmp_path / "theirs", dtype=torch.float64)
    ours = load_model(G.import_checkpoint(tmp_path / "theirs", bvh, tmp_path / "ours")).double()
    perm = G.entity_perm(ours.n_joints, len(ours.feet))
    assert ours.seqs[0].skeleton.names == theirs.motion_data.bvh_file.skeleton.names
    assert rel(ours.seqs[0].features.unsqueeze(0), G.to_modi_layout(theirs.motion_data.raw_motion, perm)) <= TOL
    noises = _noises(theirs.lengths, theirs.amps, seed=15)
    with torch.no_grad():
        mine = synthesize(ours.gens, ours.rates[0], ours.lengths[0], [z.view(1, 1, 1, -1) for z in noises],
                          ours.n_entities)
    for l, (a, b) in enumerate(zip(mine, theirs.level_outputs(noises))):
        assert rel(a, G.to_modi_layout(b, perm)) <= TOL, l
    assert rel(ours.reconstruct(0), G.to_modi_layout(theirs.reconstruction()[-1], perm)) <= TOL


def _bvh_points(path, scale=1.0):
    from modi.data.motion import Motion

    m = Motion.from_bvh(path)
    pos, _ = m.forward_kinematics()
    return {n: pos[:, j] * scale for j, n in enumerate(m.skeleton.names)}


def test_demo_sample_and_its_bvh_equal(released, imported, tmp_path):
    """Their demo.py sample of the training length (noise at the coarsest level only) = modi's ``sample`` on the
    same noise; their BVH writer and modi's agree within 1e-5 of body height (theirs in their working units with
    frame time 1 and XYZ Euler angles, ours in the file's units: compared after modi's scale)."""
    from modi.models.ganimator.generate import decode, write_bvh

    theirs, ours, perm = _pair(released, imported, "trained")
    T = theirs.lengths[-1]
    levels, z = theirs.demo_sample(T, seed=4)
    with torch.no_grad():
        sample = ours.sample(T, noises=[z.view(1, 1, 1, -1)] + [None] * (ours.n_levels - 1))
    assert rel(sample, G.to_modi_layout(levels[-1], perm)) <= TOL
    their_bvh = theirs.write_bvh(tmp_path / "theirs.bvh", levels[-1])
    seq = ours.seqs[0]
    quats, root, contacts = decode(ours, sample[0])
    write_bvh(seq, quats, root, tmp_path / "ours.bvh", contacts=contacts)
    a, b = _bvh_points(tmp_path / "ours.bvh", seq.scale), _bvh_points(their_bvh)
    assert sorted(a) == sorted(b) == sorted(seq.skeleton.names)
    height = seq.size
    assert 1.0 < height < 3.0  # metres: their 1/100 rule for this centimetre rig
    assert max(float((a[n] - b[n]).abs().max()) for n in a) <= 1e-5 * height


def test_sample_of_another_length_named_difference(released, imported):
    """Both settings: modi's sampler on the released pyramid of N frames equals their demo; modi's default for N
    frames puts level l on the fixed grid ``ceil(N * rate_l)`` (so a longer output extends a shorter one), which is
    another pyramid: named here, not hidden."""
    from modi.models.ganimator.networks import synthesize

    theirs, ours, perm = _pair(released, imported, "trained")
    N = 100
    levels, z = theirs.demo_sample(N, seed=5)
    their_lengths = [int(x.shape[-1]) for x in levels]
    rates = [L / their_lengths[-1] for L in their_lengths]
    with torch.no_grad():
        mine = synthesize(ours.gens, rates, their_lengths, [z.view(1, 1, 1, -1)] + [None] * (ours.n_levels - 1),
                          ours.n_entities)
    assert rel(mine[-1], G.to_modi_layout(levels[-1], perm)) <= TOL
    grid = ours.level_lengths(N)
    assert grid != their_lengths and grid[-1] == their_lengths[-1] == N


# --------------------------------------------------------------------------------------------- one training step
@pytest.mark.parametrize("kind", KINDS)
def test_one_step_losses_and_gradients(released, imported, kind):
    """Level 1 on a level-0 output: their D step (loss_D, WGAN-GP with the same alpha), G step (adversarial,
    contact consistency) and reconstruction term equal modi's; so do the discriminator's gradients from the D step
    and the generator's from the G step (mapped through the same weight layout)."""
    from modi.models.ganimator.networks import PatchDiscriminator
    from modi.models.ganimator.training import ContactConsistency, gradient_penalty

    theirs, ours, perm = _pair(released, imported, kind)
    level = 1
    L1 = theirs.lengths[1]
    noises = _noises(theirs.lengths, theirs.amps, seed=6)
    base_rel = torch.nn.functional.interpolate(theirs.level_outputs(noises)[0], size=L1, mode="linear",
                                               align_corners=False)
    real_rel = theirs.reals()[level].to(torch.float64)
    x_rel = base_rel + noises[level]
    gm = theirs.gan_model(level, seed=7)
    t = theirs.losses(gm, real_rel, base_rel, gm.gen(x_rel.clone()), seed=8)

    cfg = ours.cfg
    disc = PatchDiscriminator(ours.neighbors, base_channels=cfg.base_channels, n_layers=cfg.n_layers,
                              kernel_size=cfg.kernel_size, padding_mode=cfg.padding_mode).double()
    disc.load_state_dict(G.discriminator_state(gm.disc.state_dict(), disc, perm))
    gen = ours.gens[level]
    for p in gen.parameters():
        p.requires_grad_(True)
    base = G.to_modi_layout(base_rel, perm)
    real = G.to_modi_layout(real_rel, perm)
    fake = gen(G.to_modi_layout(x_rel, perm), base) + base
    # D step
    loss_d = 0.5 * (disc(fake.detach()).mean() - disc(real).mean())
    torch.manual_seed(8)
    gp = gradient_penalty(disc, real, fake)
    (loss_d + cfg.lambda_gp * gp).backward()
    assert rel(loss_d, t["loss_D"]) <= TOL and rel(gp, t["loss_gp"]) <= TOL
    masks = {k: v for k, v in gm.disc.state_dict().items() if k.endswith("mask")}
    want = G.discriminator_state({**t["d_grads"], **masks}, disc, perm)
    for k, p in disc.named_parameters():
        assert rel(p.grad, want[k]) <= TOL, k
    # G step
    for p in disc.parameters():
        p.requires_grad_(False)
    adv = -disc(fake).mean()
    con = ContactConsistency(ours.seqs[0].skeleton, ours.feet, cfg.sixd).double()(fake, 1.0)
    (adv + cfg.lambda_contact * con).backward()
    assert rel(adv, t["loss_G"]) <= TOL and rel(con, t["loss_consistency"]) <= TOL
    # named difference: modi's earlier form (contact_rescale=True) measures velocities per source frame
    with torch.no_grad():
        scaled = ContactConsistency(ours.seqs[0].skeleton, ours.feet, cfg.sixd).double()(fake, ours.rates[0][level])
    assert rel(scaled, t["loss_consistency"]) > 1e-2
    masks = {k: v for k, v in gm.gen.state_dict().items() if k.endswith("mask")}
    want = G.generator_state({**t["g_grads"], **masks}, gen, perm)
    for k, p in gen.named_parameters():
        assert rel(p.grad, want[k]) <= TOL, k
    # reconstruction term (L1 over every channel, padding included)
    assert rel((fake - real).abs().mean(), t["loss_rec"]) <= TOL


@pytest.mark.parametrize("masks", ["frozen", "as released"])
def test_one_training_iteration_of_the_last_block(released, imported, tmp_path, masks):
    """One iteration of their ``joint_train`` (5 D steps with the WGAN-GP, a G step, a reconstruction step, their
    Adam) on the finest block against ``Trainer.run`` of the imported run with the same noise and fresh
    discriminators: the generator's and the discriminator's parameters after it.

    Both settings, named: as released, their D step re-enables gradients on the discriminators' 0/1 masks
    (``disc_requires_grad_(True)`` sets every parameter, masks included) and their Adam moves the in-mask entries
    off 1, a second factor modi does not have (its masks are structure). With their masks kept out of training
    (a harness setting) one iteration is equal; as released the discriminator, and through it the G step, differ."""
    from modi.models.ganimator.training import Trainer, blocks_of

    theirs, ours, perm = _pair(released, imported, "trained")
    blocks = blocks_of(ours.n_levels, ours.cfg.group_size)
    levels = blocks[-1]
    cfg = ours.cfg.replace(block_iterations=[0] * (len(blocks) - 1) + [1], checkpoint_every=1e9)
    gms = theirs.train_iteration(levels, seed=12, disc_seed=13, masks_trainable=masks == "as released")
    with torch.random.fork_rng(devices=[]):
        tr = Trainer(ours.seqs, cfg, tmp_path / "run")
    m = tr.model.double()
    m.load_state_dict({k: v for k, v in ours.state_dict().items() if not k.startswith("discs.")}, strict=False)
    m.amps = ours.amps
    for l in levels:
        m.discs[l].load_state_dict(G.discriminator_state(theirs.gan_model(l, seed=13 + l).disc.state_dict(),
                                                         m.discs[l], perm))
    tr.reals = [[r.double() for r in row] for row in tr.reals]
    tr.consistency.double()
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)  # the same noise draws as theirs (float64 in float64 runs)
    try:
        torch.manual_seed(12)
        tr.run(progress=False, log=None)
    finally:
        torch.set_default_dtype(default)
    worst_g = worst_d = 0.0
    for j, l in enumerate(levels):
        want_g = G.generator_state(gms[j].gen.state_dict(), m.gens[l], perm)
        want_d = G.discriminator_state(gms[j].disc.state_dict(), m.discs[l], perm, binary=False)
        worst_g = max([worst_g] + [rel(p, want_g[k]) for k, p in m.gens[l].named_parameters()])
        worst_d = max([worst_d] + [rel(p, want_d[k]) for k, p in m.discs[l].named_parameters()])
        moved = max(float((v - 1).abs()[v != 0].max()) for k, v in gms[j].disc.state_dict().items()
                    if k.endswith("mask"))
        assert (moved > 0) == (masks == "as released")
    if masks == "frozen":
        assert worst_g <= TOL and worst_d <= TOL
    else:
        assert worst_d > TOL and worst_g > TOL


# --------------------------------------------------------------------------------------------- end to end
def test_import_then_generate_equals_their_sample(released, tmp_path):
    """``modi import ganimator-released`` -> ``modi ganimator generate --format bvh,glb``: the BVH equals their
    demo's sample for the same coarsest noise (modi's --seed draws it), within 1e-5 of body height."""
    from modi.cli import main
    from modi.models.ganimator.training import load_model

    run = tmp_path / "run"
    assert main(["import", "ganimator-released", str(released["trained"].path / "gen000.pt"), "--data",
                 str(released["bvh"]), "--out", str(run)]) == 0
    out = tmp_path / "gen"
    assert main(["ganimator", "generate", str(run), "--out", str(out), "--seed", "11", "--no-gif", "--no-view",
                 "--format", "bvh,glb"]) == 0
    assert (out / "sample.glb").read_bytes()[:4] == b"glTF"
    model = load_model(run)
    theirs = R.ReleasedRun(released["trained"].path, dtype=torch.float64)
    L0 = theirs.lengths[0]
    z = torch.randn(1, 1, 1, L0, generator=torch.Generator().manual_seed(11)).to(torch.float64) * float(theirs.amps[0])
    levels = theirs.draw("random", theirs.lengths, theirs.amps * 0, [z.view(1, 1, -1)])
    their_bvh = theirs.write_bvh(tmp_path / "theirs.bvh", levels[-1])
    a, b = _bvh_points(out / "sample.bvh", model.seqs[0].scale), _bvh_points(their_bvh)
    assert max(float((a[n] - b[n]).abs().max()) for n in b) <= 1e-5 * model.seqs[0].size


def test_import_finds_the_bvh_named_in_args_txt(released, tmp_path):
    """Without --data the BVH is their --bvh_prefix/--bvh_name (here absolute): the same run as with it."""
    from modi.models.ganimator.training import load_model

    run = G.import_checkpoint(released["init"].path, None, tmp_path / "run")
    with_data = G.import_checkpoint(released["init"].path, released["bvh"], tmp_path / "run2")
    a, b = load_model(run), load_model(with_data)
    assert torch.equal(a.seqs[0].features, b.seqs[0].features)
    assert all(torch.equal(x, y) for x, y in zip(a.gens.state_dict().values(), b.gens.state_dict().values()))


def test_modi_loader_differs_by_name(released, imported):
    """Named difference: modi's own loader (``modi ganimator train`` on the same BVH) keeps the file's joint order
    (spine first) where the released rig table lists the legs first, and detects its own feet."""
    from modi.models.ganimator.data import load_sequence
    from modi.models.ganimator.training import load_model

    mine = load_sequence(released["bvh"])
    imp = load_model(imported["trained"]).seqs[0]
    assert sorted(mine.skeleton.names) == sorted(imp.skeleton.names)
    assert mine.skeleton.names[1] == "Spine" and imp.skeleton.names[1] == "LeftUpLeg"


def test_bad_inputs_are_one_line(released, tmp_path, capsys):
    from modi.cli import main

    import shutil

    other = R.DATA / "Xia" / "normal.bvh"
    cond = tmp_path / "conditional"
    shutil.copytree(released["init"].path, cond, ignore=shutil.ignore_patterns("logs"))
    (cond / "args.txt").write_text((cond / "args.txt").read_text().strip() + " --conditional_generator=1")
    cases = [
        ([str(tmp_path / "missing")], "no such"),
        ([str(released["bvh"].parent)], "not a released GANimator run"),
        ([str(cond), "--data", str(released["bvh"])], "--conditional_generator=1"),
        ([str(released["init"].path), "--data", str(tmp_path)], "no walk.bvh in this folder"),
    ]
    if other.is_file():  # another rig
        cases.append(([str(released["trained"].path), "--data", str(other)], "pass the BVH the model was trained on"))
    salsa = R.DATA / "Joe" / "Salsa-Dancing-6.bvh"
    if salsa.is_file():  # the same rig and length, another motion: caught by the amplitudes
        same_rig = R.trim_bvh(salsa, tmp_path / "salsa.bvh", 120)
        cases.append(([str(released["trained"].path), "--data", str(same_rig)], "noise amplitudes"))
    for i, (argv, text) in enumerate(cases):
        capsys.readouterr()
        assert main(["import", "ganimator-released", *argv, "--out", str(tmp_path / f"r{i}")]) == 2
        err = capsys.readouterr().err.strip()
        assert text in err and len(err.splitlines()) == 1, err


def test_code_in_a_released_file_is_refused(released, tmp_path, capsys):
    """A gen000.pt that names code (a pickled callable) is refused without running it."""
    import shutil

    from modi.cli import main

    run = tmp_path / "run"
    shutil.copytree(released["init"].path, run, ignore=shutil.ignore_patterns("logs"))
    flag = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (flag,))

    torch.save({"layers.0.0.weight": Payload()}, run / "gen000.pt")
    assert main(["import", "ganimator-released", str(run), "--data", str(released["bvh"]), "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "refused" in err and not flag.exists()


# --------------------------------------------------------------------------------------------- a rig of one's own
# A Bandai-Namco clip: a static floor root (joint_Root) above an animated Hips, trained the way their README asks for
# a BVH of one's own (a skeleton-table entry, R.BANDAI_TABLE: every joint from joint_Root down, the toes as
# contacts). Their loader keeps joint_Root's static channels as the root track and Hips at its OFFSET (modi's own
# reader folds Hips's translation into the root). In this clip one foot speed (Toes_L, frame 94 to 95) lies within
# float32 rounding of their 0.018 threshold: their label and a float64 reading of the file differ there.
BANDAI_CLIP = "dataset-1_guide_happy_001.bvh"
BANDAI_FLIP = {"frame": 95, "joint": "Toes_L"}


@pytest.fixture(scope="module")
def bandai(tmp_path_factory):
    """Their train.py on the Bandai clip with the table entry, 2 iterations per block, and modi's import of it."""
    try:
        R.require_peer()
        src = R.require_data(R.BANDAI / BANDAI_CLIP)
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))
    d = tmp_path_factory.mktemp("bandai")
    bvh = R.trim_bvh(src, d / "data" / "happy.bvh", 105)  # the whole clip
    torch.set_num_threads(1)
    R.train_released(bvh, d / "theirs", 2, seed=5, table=R.BANDAI_TABLE)
    return {"bvh": bvh, "theirs": d / "theirs", "ours": G.import_checkpoint(d / "theirs", bvh, d / "ours")}


def test_bandai_floor_root_run_imports_and_samples_equal(bandai):
    """The run imports; modi's clip is their training tensor (the label rounding decided included), and every
    level's output, the reconstruction and their demo's sample equal theirs in float64."""
    from modi.models.ganimator.networks import synthesize
    from modi.models.ganimator.training import load_model

    theirs = R.ReleasedRun(bandai["theirs"], dtype=torch.float64, table=R.BANDAI_TABLE)
    ours = load_model(bandai["ours"]).double()
    perm = G.entity_perm(ours.n_joints, len(ours.feet))
    seq = ours.seqs[0]
    assert seq.skeleton.names == theirs.motion_data.bvh_file.skeleton.names and seq.skeleton.names[0] == "joint_Root"
    assert [seq.skeleton.names[f] for f in ours.feet] == ["Toes_L", "Toes_R"]
    assert rel(seq.features.unsqueeze(0), G.to_modi_layout(theirs.motion_data.raw_motion, perm)) <= TOL
    assert np.allclose(ours.amps[0], theirs.amps.numpy(), rtol=1e-6)
    noises = _noises(theirs.lengths, theirs.amps, seed=21)
    with torch.no_grad():
        mine = synthesize(ours.gens, ours.rates[0], ours.lengths[0], [z.view(1, 1, 1, -1) for z in noises],
                          ours.n_entities)
    for l, (a, b) in enumerate(zip(mine, theirs.level_outputs(noises))):
        assert rel(a, G.to_modi_layout(b, perm)) <= TOL, l
    assert rel(ours.reconstruct(0), G.to_modi_layout(theirs.reconstruction()[-1], perm)) <= TOL
    T = theirs.lengths[-1]
    levels, z = theirs.demo_sample(T, seed=22)
    with torch.no_grad():
        sample = ours.sample(T, noises=[z.view(1, 1, 1, -1)] + [None] * (ours.n_levels - 1))
    assert rel(sample, G.to_modi_layout(levels[-1], perm)) <= TOL


def test_bandai_reading_and_label_rounding_named(bandai):
    """Both readings, named: modi's own reader folds Hips's animated translation into the root track, theirs keeps
    joint_Root's static channels (the import reads theirs); and the one label whose foot speed is within float32
    rounding of the threshold is settled by amps.pt and recorded."""
    from modi.models.ganimator.data import read_clip
    from modi.models.ganimator.training import read_checkpoint

    folded, kept = read_clip(bandai["bvh"]), read_clip(bandai["bvh"], fold_root=False)
    assert float(np.ptp(folded.root_positions.numpy(), axis=0).max()) > 1.0
    assert float(np.ptp(kept.root_positions.numpy(), axis=0).max()) == 0.0
    prov = read_checkpoint(bandai["ours"])["state"]["imported_from"]
    assert prov["data"]["flipped_labels"] == [BANDAI_FLIP] and prov["data"]["floor_root"]
    assert prov["data"]["amplitude_error"] <= G.EXACT


def test_bandai_table_without_the_floor_root_imports(bandai, tmp_path):
    """The other table a user may write, starting at Hips: their loader then places Hips on joint_Root's static
    track (no OFFSET), and their forward kinematics takes Hips for its own parent (its rotation twice, at twice its
    OFFSET) when it labels contacts. Read that way, the clip and the reconstruction equal theirs."""
    import dataclasses

    from modi.models.ganimator.training import load_model

    table = dataclasses.replace(R.BANDAI_TABLE, name="Bandai-from-Hips", corps=R.BANDAI_TABLE.corps[1:])
    R.train_released(bandai["bvh"], tmp_path / "theirs", 0, seed=6, table=table)
    theirs = R.ReleasedRun(tmp_path / "theirs", dtype=torch.float64, table=table)
    ours = load_model(G.import_checkpoint(tmp_path / "theirs", bandai["bvh"], tmp_path / "ours")).double()
    perm = G.entity_perm(ours.n_joints, len(ours.feet))
    assert ours.seqs[0].skeleton.names[0] == "Hips" and ours.seqs[0].scale == 0.01  # their 1/100 rule for Hips
    assert rel(ours.seqs[0].features.unsqueeze(0), G.to_modi_layout(theirs.motion_data.raw_motion, perm)) <= TOL
    assert rel(ours.reconstruct(0), G.to_modi_layout(theirs.reconstruction()[-1], perm)) <= TOL


def test_bandai_refusal_names_the_cause(bandai, tmp_path, capsys):
    """Another motion of the same rig and length: refused with what was compared, not "pass the BVH it was
    trained on"."""
    from modi.cli import main

    other = R.BANDAI / "dataset-1_walk_normal_001.bvh"
    if not other.is_file():
        pytest.skip(f"{other} not found (../shared/data)")
    same_rig = R.trim_bvh(other, tmp_path / "walk.bvh", 105)
    capsys.readouterr()
    assert main(["import", "ganimator-released", str(bandai["theirs"]), "--data", str(same_rig), "--out",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "read as their loader reads it (root track from joint_Root's channels" in err
    assert "noise amplitudes are off by" in err and "the motion is not the one this run was trained on" in err
    assert "pass the BVH" not in err


def test_imported_run_records_what_the_files_say(bandai, capsys):
    """Provenance of an imported GANimator run: their iterations (--num_iters per block x blocks), the options
    args.txt states (not modi's defaults), no seed (their train.py sets none), the clip's rate as its Frame Time
    states it, their frame stride, and each file's SHA-256; ``modi info`` shows it, marked as imported."""
    import hashlib

    from modi.cli import main
    from modi.models.ganimator.training import load_model, read_checkpoint

    ck = read_checkpoint(bandai["ours"])
    prov = ck["state"]["imported_from"]
    n_blocks = len(G.blocks_of(len(ck["model"]["lengths"][0]), 2))
    assert prov["kind"] == "ganimator-released" and prov["iterations"] == 2 * n_blocks
    assert prov["args"] == {"bvh_prefix": str(bandai["bvh"].parent), "bvh_name": "happy",
                            "save_path": str(bandai["theirs"]), "num_iters": 2, "silent": 1, "device": "cpu"}
    assert prov["seed"] is None
    files = {f["name"]: f["sha256"] for f in prov["source"]["files"]}
    assert set(files) >= {"args.txt", "amps.pt", "z_star.pt", "gen000.pt"}
    assert all(files[n] == hashlib.sha256((bandai["theirs"] / n).read_bytes()).hexdigest() for n in files)
    data = prov["data"]
    assert data["sha256"] == hashlib.sha256(bandai["bvh"].read_bytes()).hexdigest()
    assert data["frame_time"] == pytest.approx(0.0333333, abs=1e-12) and data["stride"] == 1
    model = load_model(bandai["ours"])
    # modi's one reader takes a rounded 1/30 (Frame Time: 0.0333333) as 30 fps; the record keeps the file's figure
    assert model.cfg.fps == model.seqs[0].fps == 30.0 and data["fps"] == pytest.approx(1 / 0.0333333, rel=1e-12)
    capsys.readouterr()
    assert main(["info", str(bandai["ours"])]) == 0
    out = capsys.readouterr().out
    assert "GANimator checkpoint (imported from the authors' released code)" in out
    assert f"{2 * n_blocks} iterations, from args.txt" in out and "Frame Time 0.0333333" in out
    assert "--num_iters=2" in out and "their seed:  none" in out
    assert "settled by amps.pt (frame 95 Toes_L)" in out.replace("\n             ", " ")
