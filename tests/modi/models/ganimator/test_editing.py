"""Constrained generation from a trained GANimator (modi.models.ganimator.editing): each application's promise,
checked exactly on a humanoid and on the crab (a hexapod-like real rig), plus its bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from modi.api.ganimator import GanimatorRun
from modi.cli import main
from modi.core.rotations import axis_angle_to_quat
from modi.core.skeleton import Skeleton
from modi.data.motion import Motion
from modi.errors import UserError
from modi.evaluation.plausibility import plausibility_metrics
from modi.io.formats import save_motion
from modi.models.ganimator import config as gconfig
from modi.models.ganimator.data import RawClip, read_clip, sequence_from_clip
from modi.models.ganimator.editing import body_halves, circular_resample, kept_joints, loop_features, wrap_pad
from modi.models.ganimator.training import train

pytestmark = [pytest.mark.filterwarnings("ignore::RuntimeWarning"), pytest.mark.usefixtures("one_torch_thread")]

HUMANOID = [  # name, parent, offset: legs down from the hips, a spine up to a head and two arms
    ("Hips", -1, (0, 0, 0)),
    ("LeftUpLeg", 0, (0.1, -0.05, 0)), ("LeftLeg", 1, (0, -0.4, 0)), ("LeftFoot", 2, (0, -0.4, 0)),
    ("LeftToe", 3, (0, -0.05, 0.1)),
    ("RightUpLeg", 0, (-0.1, -0.05, 0)), ("RightLeg", 5, (0, -0.4, 0)), ("RightFoot", 6, (0, -0.4, 0)),
    ("RightToe", 7, (0, -0.05, 0.1)),
    ("Spine", 0, (0, 0.2, 0)), ("Chest", 9, (0, 0.2, 0)), ("Head", 10, (0, 0.25, 0)),
    ("LeftArm", 10, (0.2, 0.1, 0)), ("LeftHand", 12, (0.3, 0, 0)),
    ("RightArm", 10, (-0.2, 0.1, 0)), ("RightHand", 14, (-0.3, 0, 0)),
]
ITERATIONS = 60


def humanoid_clip(T: int = 90, seed: int = 0) -> RawClip:
    """A smooth walking-on-the-spot motion (every joint a sum of slow sines), root moving along x."""
    names, parents = [n for n, _, _ in HUMANOID], [p for _, p, _ in HUMANOID]
    offsets = np.array([o for _, _, o in HUMANOID], dtype=np.float64)
    g = torch.Generator().manual_seed(seed)
    J = len(parents)
    t = torch.arange(T, dtype=torch.float64)[:, None, None]
    freq = 0.5 + 0.5 * torch.rand(1, J, 3, generator=g, dtype=torch.float64)
    phase = 6.28 * torch.rand(1, J, 3, generator=g, dtype=torch.float64)
    rot = axis_angle_to_quat(0.3 * torch.sin(2 * math.pi * freq * t / 30.0 + phase))
    root = torch.zeros(T, 3, dtype=torch.float64)
    root[:, 0] = 0.02 * torch.arange(T, dtype=torch.float64)
    root[:, 1] = 0.9
    return RawClip(Skeleton(names, parents, offsets, rotation_orders=["ZXY"] * J), rot, root, 30.0)


def _trained(tmp, clip: RawClip, **cfg_kw):
    cfg = gconfig.preset("tiny", iterations=ITERATIONS, d_steps=1, base_channels=16, fake_pool=4,
                         checkpoint_every=1e9, seed=0, coarse_ratio=0.3, **cfg_kw)
    train([sequence_from_clip(clip, "src", cfg)], cfg, tmp / "run", progress=False, log=None)
    src = tmp / "src.bvh"
    save_motion(Motion(clip.skeleton, clip.rotations, clip.root_positions, clip.fps).to_bvh(), src)
    return GanimatorRun.from_checkpoint(tmp / "run"), src


@pytest.fixture(scope="module")
def humanoid(tmp_path_factory):
    return _trained(tmp_path_factory.mktemp("humanoid"), humanoid_clip(), feet=["LeftToe", "RightToe"])


@pytest.fixture(scope="module")
def crab(tmp_path_factory, request):
    data = request.getfixturevalue("shared_data")
    clip = read_clip(data / "bvh" / "ganimator" / "Crabnew" / "Crab-dance-long.bvh")
    clip = RawClip(clip.skeleton, clip.rotations[:180:2], clip.root_positions[:180:2], clip.fps / 2)
    return _trained(tmp_path_factory.mktemp("crab"), clip)


@pytest.fixture(params=["humanoid", "crab"])
def rig(request):
    return request.getfixturevalue(request.param)


def _source(run: GanimatorRun, path) -> Motion:
    """The input as modi reads it, on the run's (reduced) rig: the reference for 'unchanged'."""
    m = Motion.from_bvh(path)
    return m.subset([m.skeleton.names.index(n) for n in run.skeleton.names]) \
        if m.skeleton.names != run.skeleton.names else m


def _pose_steps(m: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame pose change (root-relative joint positions, mean over joints) from frame t to t+1, and velocity
    change from step t to t+1, for a motion read as a loop (the last entry of each is across the seam)."""
    p = m.positions().numpy()
    rel = p - p[:, :1]
    vel = np.roll(rel, -1, axis=0) - rel                    # vel[t]: t -> t+1, vel[-1]: last -> first
    acc = np.roll(vel, -1, axis=0) - vel
    return np.linalg.norm(vel, axis=-1).mean(-1), np.linalg.norm(acc, axis=-1).mean(-1)


# ------------------------------------------------------------------------------------------- loop


def test_one_level_on_a_circle_is_shift_equivariant(humanoid):
    """What makes the seam like any other frame: a level run on its wrap-padded input commutes with a roll."""
    run, _ = humanoid
    g = run.model.gens[2]
    R = g.receptive_radius
    x = torch.randn(1, 6, run.model.n_entities, 30, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        y = g(wrap_pad(x, R), wrap_pad(x, R), None)[..., R:R + 30]
        y7 = g(wrap_pad(x.roll(7, -1), R), wrap_pad(x.roll(7, -1), R), None)[..., R:R + 30]
    torch.testing.assert_close(y7, y.roll(7, -1), rtol=0, atol=1e-6)
    # and padding by more than the receptive radius changes nothing: R covers the whole stack
    with torch.no_grad():
        y3 = g(wrap_pad(x, 3 * R), wrap_pad(x, 3 * R), None)[..., 3 * R:3 * R + 30]
    torch.testing.assert_close(y3, y, rtol=0, atol=1e-6)


def test_circular_resample_of_a_sine_is_a_sine():
    t = torch.arange(36, dtype=torch.float64)
    y = circular_resample(torch.sin(2 * math.pi * t / 36)[None], 48)[0]
    want = torch.sin(2 * math.pi * ((torch.arange(48, dtype=torch.float64) + 0.5) * 0.75 - 0.5) / 36)
    assert (y - want).abs().max() < 2 * (1 - math.cos(2 * math.pi / 36))  # linear interpolation's own error


def test_the_seam_is_a_typical_step_of_the_loop(humanoid):
    """Over seeds, the feature step across the seam is an ordinary step of the loop (on grids that all start at the
    same place it was the largest step in most seeds: 1.9x the mean on white noise)."""
    run, _ = humanoid
    m, J = run.model, run.model.n_joints
    ratios = []
    for seed in range(8):
        f = loop_features(m, 120, generator=torch.Generator().manual_seed(seed))[0, :, :J]
        step = (f.roll(-1, -1) - f).norm(dim=0).mean(0)
        ratios.append(float(step[-1] / step.mean()))
    assert 0.5 < float(np.mean(ratios)) < 1.3, ratios


@pytest.mark.parametrize("root", ["travel", "return"])
def test_loop_seam_is_within_the_source_frame_to_frame_steps(rig, root):
    run, src_path = rig
    T = 2 * run.n_frames
    loop = run.generate(1, frames=T, loop=True, loop_root=root, seed=1)[0]
    assert loop.n_frames == T
    steps, accel = _pose_steps(loop)
    src_steps, _ = _pose_steps(_source(run, src_path))
    src_steps = src_steps[:-1]  # the source is not a loop: drop its last -> first entry
    assert steps[-1] <= src_steps.max(), (steps[-1], src_steps.max())
    # velocity: the change across the seam is one of the output's own frame-to-frame velocity changes
    assert accel[-2:].max() <= np.quantile(accel[:-2], 0.99) * 1.5, (accel[-2:], np.quantile(accel[:-2], 0.99))
    if root == "return":  # the root comes back: last -> first is one more horizontal step of the motion's own
        r = loop.root_positions.numpy()[:, [0, 2]]
        step = np.linalg.norm(np.roll(r, -1, axis=0) - r, axis=-1)
        assert step[-1] <= 1.5 * step[:-1].max(), (step[-1], step[:-1].max())


# ------------------------------------------------------------------------------------------- in-between


def test_inbetween_starts_and_ends_exactly_at_the_given_poses(rig):
    run, src_path = rig
    src = _source(run, src_path)
    out = run.generate(1, frames=40, inbetween=(f"{src_path}@3", f"{src_path}@-1"), seed=2)[0]
    assert out.n_frames == 42
    assert torch.equal(out.rotations[0], src.rotations[3])
    assert torch.equal(out.rotations[-1], src.rotations[-1])
    tol = 1e-9 * run.body_size
    torch.testing.assert_close(out.root_positions[0], src.root_positions[3], rtol=0, atol=tol)
    torch.testing.assert_close(out.root_positions[-1], src.root_positions[-1], rtol=0, atol=tol)


def test_inbetween_of_two_clips_keeps_both_clips(humanoid):
    run, src_path = humanoid
    src = _source(run, src_path)
    out = run.generate(1, frames=30, inbetween=(src_path, src_path), seed=3)[0]
    T = src.n_frames
    assert out.n_frames == 2 * T + 30
    assert torch.equal(out.rotations[:T], src.rotations) and torch.equal(out.rotations[T + 30:], src.rotations)
    assert not torch.equal(out.rotations[T:T + 30], src.rotations[:30])  # the gap comes from the model


# ------------------------------------------------------------------------------------------- expansion


def test_expansion_holds_the_clip_unchanged_at_its_place(rig):
    run, src_path = rig
    src = _source(run, src_path)
    T = src.n_frames
    out = run.generate(1, frames=T + 70, expand=src_path, at=25, seed=4)[0]
    assert out.n_frames == T + 70
    assert torch.equal(out.rotations[25:25 + T], src.rotations)
    torch.testing.assert_close(out.root_positions[25:25 + T], src.root_positions, rtol=0,
                               atol=1e-9 * run.body_size)


# ------------------------------------------------------------------------------------------- body parts


def test_upper_and_lower_are_found_from_the_tree(humanoid):
    run, _ = humanoid
    names = run.skeleton.names
    lower = sorted(names[j] for j in kept_joints(run.model, "lower"))
    upper = sorted(names[j] for j in kept_joints(run.model, "upper"))
    assert lower == sorted(["Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToe", "RightUpLeg", "RightLeg",
                            "RightFoot", "RightToe"])
    assert upper == sorted(["Spine", "Chest", "Head", "LeftArm", "LeftHand", "RightArm", "RightHand"])


def test_a_tree_with_only_legs_has_no_upper_body():
    # a hexapod's body: six legs with feet hang from the root, nothing else
    parents = [-1] + [x for leg in range(6) for x in (0, 1 + 3 * leg, 2 + 3 * leg)]
    feet = [3 + 3 * leg for leg in range(6)]
    with pytest.raises(UserError, match="humanoid"):
        body_halves(parents, feet, [f"j{j}" for j in range(len(parents))])


@pytest.mark.parametrize("keep", ["upper", "lower", "LeftArm,Head"])
def test_kept_joints_are_unchanged_bit_for_bit(humanoid, keep):
    run, src_path = humanoid
    src = _source(run, src_path)
    out = run.generate(1, edit=src_path, keep=keep, seed=5)[0]
    kept = kept_joints(run.model, keep)
    rest = [j for j in range(run.skeleton.n_joints) if j not in kept]
    assert out.n_frames == src.n_frames
    assert torch.equal(out.rotations[:, kept], src.rotations[:, kept])
    assert not torch.equal(out.rotations[:, rest], src.rotations[:, rest])
    if 0 in kept:
        torch.testing.assert_close(out.root_positions, src.root_positions, rtol=0, atol=1e-9 * run.body_size)


def test_the_crab_keeps_its_legs_or_named_joints(crab):
    """On the crab, 'lower' is the pelvis chain and the six legs (every foot is in it), 'upper' the eyes and claws."""
    run, src_path = crab
    src = _source(run, src_path)
    names = run.skeleton.names
    lower = kept_joints(run.model, "lower")
    assert {names.index(f) for f in run.feet} <= set(lower)
    assert all("Eye" in names[j] or "Arm" in names[j] or "Pelvis" in names[j] for j in kept_joints(run.model, "upper"))
    claw = [n for n in names if "Arm_L" in n]
    for keep, idx in (("lower", lower), (claw, [names.index(n) for n in claw])):
        out = run.generate(1, edit=src_path, keep=keep, seed=6)[0]
        assert torch.equal(out.rotations[:, idx], src.rotations[:, idx])


# ------------------------------------------------------------------------------------------- harmonisation


def test_harmonisation_keeps_more_of_the_content_the_finer_the_level(humanoid):
    run, src_path = humanoid
    src = _source(run, src_path)
    top = run.model.n_levels - 2

    def err(level):
        out = run.generate(1, style=src_path, style_level=level, seed=7)[0]
        return float((out.positions() - out.positions()[:, :1] - (src.positions() - src.positions()[:, :1]))
                     .norm(dim=-1).mean())

    assert err(top) < err(0)
    with pytest.raises(UserError, match="content-level"):
        run.generate(1, style=src_path, style_level=top + 1)


# ------------------------------------------------------------------------------------------- plausibility


def test_outputs_are_as_plausible_as_the_model_s_own_motion(humanoid):
    """Foot skating and jitter of each application against the source and the run's random motions: the constraint
    must not add artefacts of its own (a hard paste at a span's edge gave 12x the random motions' jitter there).
    The bound is 2x the worst reference: this 60-iteration model's own random motions already span 1.4x in
    foot skating and 2.4x in jitter across seeds. docs/single_clip.md has the figures on real runs."""
    run, src_path = humanoid
    src = _source(run, src_path)
    feet = [run.skeleton.names.index(f) for f in run.feet]

    def fig(m: Motion) -> dict:
        return plausibility_metrics(m.positions().numpy(), m.fps, feet)

    ref = [fig(m) for m in run.generate(3, frames=150, seed=10)] + [fig(src)]
    outs = {"loop": run.generate(1, frames=150, loop=True, seed=11)[0],
            "inbetween": run.generate(1, frames=40, inbetween=(f"{src_path}@0", f"{src_path}@-1"), seed=12)[0],
            "expand": run.generate(1, frames=150, expand=src_path, seed=13)[0],
            "edit": run.generate(1, edit=src_path, keep="lower", seed=14)[0]}
    for key in ("jitter", "foot_skating"):
        bound = 2.0 * max(r[key] for r in ref)
        for name, m in outs.items():
            assert fig(m)[key] <= bound, (name, key, fig(m)[key], bound)


# ------------------------------------------------------------------------------------------- bad input


def _cli(run_dir, tmp_path, *args) -> tuple[int, bool]:
    out = tmp_path / "gen"
    rc = main(["ganimator", "generate", str(run_dir), "--out", str(out), "--no-gif", *args])
    return rc, out.exists()


@pytest.mark.parametrize("case", ["other rig", "frame outside", "too short", "short loop", "keep all", "keep none",
                                  "keep unknown", "at outside", "two modes"])
def test_bad_input_is_one_line_exit_2_and_nothing_written(humanoid, tmp_path, capsys, case):
    run, src = humanoid
    other = tmp_path / "other.bvh"
    sk = Skeleton(["root", "a", "b"], [-1, 0, 1], np.array([[0, 0, 0], [0, 0.5, 0], [0, 0.5, 0]]))
    save_motion(Motion(sk, torch.tensor([[[1.0, 0, 0, 0]] * 3] * 5, dtype=torch.float64),
                       torch.zeros(5, 3, dtype=torch.float64), 30.0).to_bvh(), other)
    every = ",".join(run.skeleton.names)
    args = {"other rig": ["--inbetween", str(other), str(src), "--frames", "40"],
            "frame outside": ["--inbetween", f"{src}@999", f"{src}@0", "--frames", "40"],
            "too short": ["--inbetween", f"{src}@0", f"{src}@1", "--frames", "2"],
            "short loop": ["--loop", "--frames", "5"],
            "keep all": ["--edit", str(src), "--keep", every],
            "keep none": ["--edit", str(src), "--keep", ","],
            "keep unknown": ["--edit", str(src), "--keep", "Tail"],
            "at outside": ["--expand", str(src), "--frames", "120", "--at", "50"],
            "two modes": ["--loop", "--expand", str(src), "--frames", "120"]}[case]
    rc, wrote = _cli(run.path, tmp_path, *args)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and not wrote
    assert len(err) == 1 and err[0].startswith("modi: error:"), err


def test_the_cli_writes_a_loop_with_contact_labels(humanoid, tmp_path):
    run, _ = humanoid
    rc, wrote = _cli(run.path, tmp_path, "--loop", "--frames", "120", "--format", "bvh,glb")
    assert rc == 0 and (tmp_path / "gen" / "sample.bvh").is_file() and (tmp_path / "gen" / "sample.glb").is_file()
    assert read_clip(tmp_path / "gen" / "sample.bvh").rotations.shape[0] == 120
