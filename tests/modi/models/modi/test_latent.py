"""Latent-space applications on a tiny in-process generator: interpolation, truncation, inversion, attribute scores,
SVM editing, crowds, clustering and the ``modi latent`` CLI."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from modi.errors import UserError
from modi.models.modi.latent import clustering, crowd, editing, inversion, space

T = 16


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def build_tiny(seed: int = 0, latent: int = 16):
    """A tiny generator on the built-in humanoid (16 frames) with a codec normalised on procedural clips."""
    from modi.models.modi.config import ModelConfig
    from modi.models.modi.levels import build_levels
    from modi.models.modi.networks import Generator
    from modi.models.modi.training import MotionCodec
    from modi.data.normalization import Normalizer
    from modi.data.procedural import KINDS, builtin_skeleton, generate_clip
    from modi.data.representation import modi_representation
    from modi.core.skeleton_graph import build_hierarchy

    torch.manual_seed(seed)
    sk = builtin_skeleton()
    feet = sk.detect_feet()
    rep = modi_representation(sk, feet)
    raw = torch.cat([rep.encode(generate_clip(k, 40, 30.0, np.random.default_rng(i))).unfold(-1, T, 8)
                     .permute(2, 0, 1, 3) for i, k in enumerate(KINDS)]).float()
    norm = Normalizer.fit(raw, skip_entities=rep.contacts)
    codec = MotionCodec(rep, norm, 30.0)
    cfg = ModelConfig(latent_dim=latent, n_mlp=2, channels=(8, 8, 8))
    g = Generator(cfg, build_levels(build_hierarchy(sk, feet), cfg, T), rep.K).eval()
    for p in g.parameters():
        p.requires_grad_(False)
    with torch.no_grad():  # what training tracks: the mean of W
        g.w_avg.copy_(g.mapping(torch.randn(2000, latent, generator=torch.Generator().manual_seed(9))).mean(0))
    return g, codec


@pytest.fixture(scope="module")
def tiny():
    return build_tiny()


# --------------------------------------------------------------------------------------------- space
def test_lerp_sequence_is_linear_with_exact_endpoints():
    a, b = torch.randn(5, 7), torch.randn(5, 7)
    seq = space.lerp_sequence(a, b, 4)
    assert seq.shape == (5, 5, 7)
    assert torch.equal(seq[0], a) and torch.equal(seq[-1], b)
    torch.testing.assert_close(seq[2], (a + b) / 2)
    torch.testing.assert_close(seq[1], 0.75 * a + 0.25 * b)
    with pytest.raises(ValueError, match="steps"):
        space.lerp_sequence(a, b, 0)


def test_interpolation_endpoints_reproduce_the_endpoint_motions(tiny):
    g, _ = tiny
    wa, wb = space.seed_w(g, [3, 4])
    x = space.synthesize(g, space.interpolation_sequence(wa, wb, 4))
    # a batch of 4 and a batch of 1 run the kernels on different tiles, so float32 sums differ in the last bits
    # (outputs reach ~20 here): equal to float32 precision, not bit for bit
    torch.testing.assert_close(x[0], space.synthesize(g, wa[None])[0], atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(x[-1], space.synthesize(g, wb[None])[0], atol=1e-5, rtol=1e-6)
    assert (x[2] - x[0]).abs().max() > 1e-3 and (x[2] - x[-1]).abs().max() > 1e-3  # really in between
    # W+ endpoint (different style per layer) with a W endpoint: the pair is lifted to W+
    wp = space.as_wplus(g, wb[None])[0].clone()
    wp[g.n_latent // 2:] = wa
    seq = space.interpolation_sequence(wa, wp, 3)
    assert seq.shape == (4, g.n_latent, g.latent_dim)
    xp = space.synthesize(g, seq)
    torch.testing.assert_close(xp[0], x[0], atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(xp[-1], space.synthesize(g, wp[None])[0], atol=1e-5, rtol=1e-6)


def test_seed_latents_match_modi_generate(tiny):
    from modi.models.modi.sampling import latents_and_noise

    g, _ = tiny
    z, _ = latents_and_noise(g, [0], 7)
    torch.testing.assert_close(space.seed_w(g, [7]), g.mapping(z))


def test_truncation_psi0_gives_the_mean_motion(tiny):
    g, _ = tiny
    # the mean motion, computed directly from the tracked mean of W
    direct = g.synthesis(g.w_avg.view(1, 1, -1).expand(1, g.n_latent, -1), noise_mode="const")
    torch.testing.assert_close(space.mean_motion(g), direct)
    for s in (1, 2):
        z = space.seed_z(g, [s])
        torch.testing.assert_close(g(z, truncation_psi=0.0, noise_mode="const"), direct, atol=2e-5, rtol=0)
        seq = space.truncation_sequence(space.seed_w(g, [s])[0], 4, space.mean_w(g))
        x = space.synthesize(g, seq)
        torch.testing.assert_close(x[-1], direct[0], atol=2e-5, rtol=0)
        torch.testing.assert_close(x[0], space.synthesize(g, space.seed_w(g, [s]))[0], atol=2e-5, rtol=0)
        # psi halfway is the halfway latent
        torch.testing.assert_close(space.truncate(seq[0], 0.5, g.w_avg), seq[2])


def test_mean_w_uses_the_tracked_mean_and_estimates_an_untracked_one(tiny):
    g, _ = tiny
    torch.testing.assert_close(space.mean_w(g), g.w_avg)
    g2, _ = build_tiny(seed=1)
    g2.w_avg.zero_()
    est = space.mean_w(g2, n=500, seed=3)
    torch.testing.assert_close(est, g2.mapping(torch.randn(500, g2.latent_dim,
                                                           generator=torch.Generator().manual_seed(3))).mean(0))


def test_latent_files_round_trip_and_bad_files_fail(tiny, tmp_path):
    g, _ = tiny
    w = space.seed_w(g, [5])[0]
    space.save_latent(tmp_path / "w.npy", w)
    back, label = space.parse_latent(g, str(tmp_path / "w.npy"))
    torch.testing.assert_close(back, w)
    wp = space.as_wplus(g, w[None])
    space.save_latent(tmp_path / "wp.npy", wp)  # a batch of one W+
    assert space.load_latent(g, tmp_path / "wp.npy").shape == (g.n_latent, g.latent_dim)
    np.save(tmp_path / "bad.npy", np.zeros(3))
    with pytest.raises(UserError, match="does not fit"):
        space.load_latent(g, tmp_path / "bad.npy")
    assert space.parse_latent(g, "seed:5")[1] == "seed 5"


def test_units_are_guessed_from_body_size():
    assert space.mm_per_unit(170.0) == 10.0
    assert space.mm_per_unit(1.7) == 1000.0
    assert space.mm_per_unit(1700.0) == 1.0
    assert space.mm_per_unit(1.7, "cm") == 10.0
    with pytest.raises(UserError, match="--units"):
        space.mm_per_unit(12000.0)


# --------------------------------------------------------------------------------------------- inversion
def test_inversion_error_falls_with_iterations(tiny):
    g, codec = tiny
    w = space.seed_w(g, [11])
    wp = space.as_wplus(g, w).clone()
    wp[:, 3:] = space.seed_w(g, [12])  # a W+ target, reachable only in W+
    target = space.synthesize(g, wp)
    res = inversion.invert(g, codec, target, steps=40, lr=0.05, progress=False)
    assert len(res.history) == 41
    assert res.history[-1] < 0.5 * res.history[0]
    assert res.rec[-1] < res.rec[0]
    assert min(res.history[20:]) < min(res.history[:10])
    final = inversion.inversion_loss(codec, res.motion, target, 1.0, space.position_scale(codec))[0]
    assert abs(float(final) - res.history[-1]) < 1e-3 * max(1.0, res.history[-1])
    with pytest.raises(ValueError, match="target"):
        inversion.invert(g, codec, target[:, :2], steps=1, progress=False)


# --------------------------------------------------------------------------------------------- scores
def _arm_motion(codec, elevations_deg: np.ndarray) -> torch.Tensor:
    """Normalised motion of the built-in humanoid standing still with the right upper arm at the given elevations
    (0 hanging down, 90 level, 180 up); the rest pose holds the arm level along -X."""
    from modi.core.rotations import quat_between

    sk, rep = codec.skeleton, codec.rep
    n = len(elevations_deg)
    rot = torch.zeros(n, sk.n_joints, 4, dtype=torch.float64)
    rot[..., 0] = 1.0
    e = torch.as_tensor(np.radians(elevations_deg))
    target = torch.stack([-torch.sin(e), -torch.cos(e), torch.zeros_like(e)], -1)
    arm = sk.index("RightArm")
    rot[:, arm] = quat_between(torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64).expand(n, 3), target)
    root = torch.tensor([0.0, 100.0, 0.0], dtype=torch.float64).expand(n, 3)
    return codec.normalizer.normalize(rep.encode_parts(rot, root).float())[None]


def test_right_arm_and_head_are_found_by_name(tiny):
    _, codec = tiny
    sk = codec.skeleton
    s, e, w = editing.find_right_arm(sk)
    assert [sk.names[j] for j in (s, e, w)] == ["RightArm", "RightForeArm", "RightHand"]
    assert sk.names[editing.find_head(sk)] == "Head"
    from modi.core.skeleton import Skeleton

    bandai = Skeleton(["Hips", "UpperArm_R", "LowerArm_R", "Hand_R"], [-1, 0, 1, 2], np.ones((4, 3)))
    assert editing.find_right_arm(bandai) == (1, 2, 3)
    with pytest.raises(UserError, match="right hand"):
        editing.find_right_arm(Skeleton(["a", "b"], [-1, 0], np.ones((2, 3))))


def test_gral_is_one_for_a_rising_arm_and_zero_for_a_falling_one(tiny):
    _, codec = tiny
    up = np.linspace(20, 160, T)
    x_up, x_down = _arm_motion(codec, up), _arm_motion(codec, up[::-1].copy())
    # the elevation really is what we built (degrees)
    p = codec.decode(x_up)["positions"][0]
    s, e, _ = editing.find_right_arm(codec.skeleton)
    np.testing.assert_allclose(editing.bone_elevation(p, s, e).numpy(), up, atol=0.5)
    assert float(editing.gral_score(codec, x_up)[0]) == pytest.approx(1.0)
    assert float(editing.gral_score(codec, x_down)[0]) == pytest.approx(0.0)
    # up for the first half, then down: windows of 8 every 4 -> 3 windows, one rise and one fall
    bump = np.concatenate([np.linspace(20, 160, 8), np.linspace(160, 20, 8)])
    assert float(editing.gral_score(codec, _arm_motion(codec, bump))[0]) == pytest.approx(0.5)


def test_rising_fraction_follows_appendix_c2():
    a = torch.tensor([[0.0] * 8 + [1.0] * 8 + [0.5] * 8])  # 24 frames: windows at 0,4,...,16 -> 5 averages
    # averages 0, 0.5, 1, 0.75, 0.5 -> increments: up, up, down, down
    torch.testing.assert_close(editing.window_means(a), torch.tensor([[0.0, 0.5, 1.0, 0.75, 0.5]]))
    assert float(editing.rising_fraction(a)[0]) == pytest.approx(0.5)


def test_verticality_and_speed_scores(tiny):
    from modi.core.rotations import axis_angle_to_quat

    _, codec = tiny
    rep, sk = codec.rep, codec.skeleton
    rot = torch.zeros(T, sk.n_joints, 4, dtype=torch.float64)
    rot[..., 0] = 1.0
    v = 3.0  # units per frame along +Z
    root = torch.stack([torch.zeros(T), torch.full((T,), 100.0), v * torch.arange(T)], -1).double()
    enc = lambda r: codec.normalizer.normalize(rep.encode_parts(r, root).float())[None]  # noqa: E731
    standing = enc(rot)
    assert float(editing.verticality_score(codec, standing)[0]) > 0.85
    flipped = rot.clone()
    flipped[:, 0] = axis_angle_to_quat(torch.tensor([math.pi, 0.0, 0.0], dtype=torch.float64))
    assert float(editing.verticality_score(codec, enc(flipped))[0]) < -0.85
    lying = rot.clone()
    lying[:, 0] = axis_angle_to_quat(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=torch.float64))
    assert abs(float(editing.verticality_score(codec, enc(lying))[0])) < 0.2
    assert float(editing.speed_score(codec, standing)[0]) == pytest.approx(v * codec.fps / codec.height, rel=1e-4)


# --------------------------------------------------------------------------------------------- editing
def test_svm_boundary_recovers_a_planted_direction():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(600, 12))
    u = rng.normal(size=12)
    u /= np.linalg.norm(u)
    scores = w @ u + 0.05 * rng.normal(size=600)
    b = editing.fit_boundary(w, scores, ratio=0.2)
    assert float(b.normal @ u) > 0.95
    assert b.accuracy > 0.95
    assert b.score_high > b.score_low
    assert b.sigma == pytest.approx(float((w @ b.normal).std()))
    with pytest.raises(UserError, match="barely varies"):
        editing.fit_boundary(w, np.zeros(600))


def test_edit_latents_moves_along_the_normal():
    w = torch.randn(3, 8)
    n = np.zeros(8)
    n[2] = 1.0
    out = editing.edit_latents(w, n, [-1.0, 0.0, 2.0])
    assert out.shape == (3, 3, 8)
    torch.testing.assert_close(out[1], w)
    torch.testing.assert_close(out[2, :, 2], w[:, 2] + 2.0)
    torch.testing.assert_close(out[2, :, :2], w[:, :2])


def test_edit_score_rises_with_alpha_on_held_out_seeds(tiny, tmp_path):
    """A boundary fitted on one stream of samples raises the attribute on other (held-out) seeds."""
    g, codec = tiny
    boundary, w, s = editing.sample_boundary(g, codec, "speed", n=300, seed=0)
    report = editing.edit_report(g, codec, boundary, seeds=list(range(500, 508)), alphas_sigma=[-2, -1, 0, 1, 2])
    assert report.scores.shape == (8, 5)
    assert report.monotonic, report.summary()
    assert report.mean[-1] > report.mean[0]
    assert report.spearman > 0.25
    # the α = 0 column is the unedited seeds' own scores
    np.testing.assert_allclose(report.scores[:, 2],
                               editing.speed_score(codec, space.synthesize(g, space.seed_w(g, report.seeds))).numpy(),
                               rtol=1e-5)
    boundary.save(tmp_path / "b.json")
    assert np.allclose(editing.Boundary.load(tmp_path / "b.json").normal, boundary.normal, atol=1e-6)
    assert editing.plot_report(report, tmp_path / "r.png").stat().st_size > 0


# --------------------------------------------------------------------------------------------- crowd
def test_crowd_latents_spread_with_sigma():
    w = torch.zeros(64)
    lat = crowd.crowd_latents(w, 200, 0.3, seed=1)
    assert lat.shape == (200, 64)
    assert float(lat.std()) == pytest.approx(0.3, rel=0.05)
    wp = torch.zeros(4, 64)
    latp = crowd.crowd_latents(wp, 5, 0.5, seed=1)
    assert torch.equal(latp[:, 0], latp[:, 3])  # one perturbation shared by every W+ layer
    with pytest.raises(UserError, match="sigma"):
        crowd.crowd_latents(w, 3, 0.0)


def test_crowd_writes_placed_bvh_files_and_one_scene(tiny, tmp_path):
    from modi.io import bvh as bvh_io
    from modi.core.kinematics import bvh_positions

    g, codec = tiny
    w = space.seed_w(g, [2])[0]
    res = crowd.simulate_crowd(g, codec, w, tmp_path, k=3, sigma=0.4, size=(160, 120))
    assert len(res.files["bvh"]) == 4 and (tmp_path / "crowd.gif").is_file()
    offsets = res.offsets
    assert len({tuple(o) for o in offsets}) == 4  # four distinct places
    # the source character is the motion of w, moved to its place on the grid
    src = codec.decode(space.synthesize(g, w[None]))["positions"][0].numpy()
    got = bvh_positions(bvh_io.load(res.files["bvh"][0]))
    np.testing.assert_allclose(got, src + offsets[0], atol=1e-2 * codec.height)
    # variations differ from the source
    other = bvh_positions(bvh_io.load(res.files["bvh"][1])) - offsets[1]
    assert np.abs(other - src).max() > 1e-3 * codec.height


# --------------------------------------------------------------------------------------------- clustering
def test_kmeans_separates_blobs_and_pick_members():
    rng = np.random.default_rng(0)
    centers = rng.normal(size=(3, 10)) * 10
    w = np.concatenate([c + rng.normal(size=(50, 10)) for c in centers])
    labels, found = clustering.kmeans(w, 3, seed=0)
    for i in range(3):
        assert len(set(labels[i * 50:(i + 1) * 50])) == 1
    members = clustering.pick_members(labels, 4, w=w, centers=found, how="nearest")
    assert all(len(m) == 4 and len({labels[i] for i in m}) == 1 for m in members)
    with pytest.raises(UserError):
        clustering.kmeans(w[:2], 3)


def test_cluster_latent_space_writes_plot_members_and_summary(tiny, tmp_path):
    g, codec = tiny
    res = clustering.cluster_latent_space(g, codec, tmp_path, n=120, k=3, per_cluster=2, tsne_max=60, seed=0)
    assert sum(res.sizes) == 120 and len(res.members) == 3
    assert (tmp_path / "tsne.png").stat().st_size > 0
    assert len(list(tmp_path.glob("cluster_*.gif"))) == 3
    summary = json.loads((tmp_path / "clusters.json").read_text())
    assert summary["sizes"] == res.sizes
    # members really belong to their cluster
    assert all(res.labels[i] == c for c, m in enumerate(res.members) for i in m)


# --------------------------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def tiny_ckpt(tiny, tmp_path_factory):
    from modi.models.modi.encoder.training import generator_bundle

    g, codec = tiny
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    torch.save(generator_bundle(g, codec), path)
    return path


def test_cli_mean_interpolate_and_errors(tiny_ckpt, tmp_path, capsys):
    from modi.cli import main

    assert main(["latent", "mean", str(tiny_ckpt), "--out", str(tmp_path / "m")]) == 0
    assert (tmp_path / "m" / "mean.bvh").is_file() and (tmp_path / "m" / "mean_w.npy").is_file()
    assert main(["latent", "interpolate", str(tiny_ckpt), "--out", str(tmp_path / "i"), "--from", "1",
                 "--to", str(tmp_path / "m" / "mean_w.npy"), "--steps", "2"]) == 0
    assert sorted(p.name for p in (tmp_path / "i").glob("*.bvh")) == ["step_00.bvh", "step_01.bvh", "step_02.bvh"]
    assert main(["latent", "truncate", str(tiny_ckpt), "--out", str(tmp_path / "t"), "--steps", "0"]) == 2
    assert main(["latent", "crowd", str(tiny_ckpt), "--out", str(tmp_path / "c"), "--latent", "nope.npy"]) == 2
    assert "no such latent file" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------- released gral
def test_released_gral_uses_arm_and_clavicle_rotation_angles(tiny):
    """latent_space_edit.py r_hand_lift_up_score: 360 - ((rotation angle + rest angle) mod 360) of RightArm and
    RightShoulder, rises counted over windows of 8 every 4, divided by the number of windows."""
    _, codec = tiny
    sk = codec.skeleton
    elev = np.linspace(160, 90, T)  # the arm comes down to level: its rotation angle |e - 90| falls 70 -> 0
    x = _arm_motion(codec, elev)
    rot = codec.decode(x)["rotations"]
    arm_a, clav_a = editing.released_arm_angles(codec, rot)
    arm, fore, clav = sk.index("RightArm"), sk.index("RightForeArm"), sk.index("RightShoulder")
    off = np.asarray(sk.offsets, dtype=np.float64)

    def rest(c, e):
        a, b = -off[c], off[e]
        return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))

    np.testing.assert_allclose(arm_a[0].numpy(), 360 - np.mod(np.abs(elev - 90) + rest(arm, fore), 360), atol=0.05)
    np.testing.assert_allclose(clav_a[0].numpy(), 360 - np.mod(rest(clav, arm), 360) * np.ones(T), atol=0.05)
    n_windows = (T - 8) // 4 + 1
    # the reversed arm angle rises in every window, the clavicle never moves
    assert float(editing.gral_released_score(codec, x)[0]) == pytest.approx(0.5 * (n_windows - 1) / n_windows)
    assert float(editing.gral_released_score(codec, _arm_motion(codec, elev[::-1].copy()))[0]) == 0.0
    a = torch.tensor([[0.0] * 8 + [1.0] * 8 + [0.5] * 8])  # 5 windows, 2 rises -> 2/5 (ours: 2/4)
    assert float(editing.released_rising_score(a)[0]) == pytest.approx(0.4)
    assert "gral_released" in editing.ATTRIBUTES


def test_released_svm_is_a_linear_kernel_svc_on_70_percent():
    rng = np.random.default_rng(1)
    w = rng.normal(size=(600, 12))
    u = rng.normal(size=12)
    u /= np.linalg.norm(u)
    scores = w @ u + 0.05 * rng.normal(size=600)
    b = editing.fit_boundary(w, scores, ratio=0.2, method="released")
    assert float(b.normal @ u) > 0.95 and b.accuracy > 0.9 and b.extra["svm"] == "released"
    assert editing.fit_boundary(w, scores, ratio=0.2).extra["svm"] == "ours"
    with pytest.raises(ValueError, match="method"):
        editing.fit_boundary(w, scores, method="rbf")


def test_cli_edit_with_the_released_gral_and_svm(tiny_ckpt, tmp_path):
    import json

    from modi.cli import main

    out = tmp_path / "e"
    assert main(["latent", "edit", str(tiny_ckpt), "--out", str(out), "--attribute", "gral_released", "--svm",
                 "released", "--n", "60", "--held-out", "2", "--render", "0", "--alphas", "-1", "0", "1"]) == 0
    b = json.loads((out / "boundary.json").read_text())
    assert b["attribute"] == "gral_released" and b["extra"]["svm"] == "released"
