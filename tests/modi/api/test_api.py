"""The public surface of ``import modi``: cheap import, lazy names, one motion type, files, topology for layers of
one's own, training from Python with the CLI's guarantees, sampling and the latent edits."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import modi
from modi.errors import UserError


REPO = Path(__file__).resolve().parents[3]
pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --------------------------------------------------------------------------------------------- the surface
def test_import_modi_is_cheap_and_every_public_name_resolves():
    code = ("import sys, modi; assert 'torch' not in sys.modules, 'import modi imported torch'; "
            "print(len(modi.__all__))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    for name in modi.__all__:
        obj = getattr(modi, name)
        assert obj is not None
        if callable(obj) and name != "__version__":
            assert obj.__doc__, f"modi.{name} has no docstring"
    assert set(modi.__all__) <= set(dir(modi))
    with pytest.raises(AttributeError):
        modi.no_such_name  # noqa: B018


def test_py_typed_ships_with_the_package():
    assert (REPO / "modi" / "py.typed").is_file()
    assert '"py.typed"' in (REPO / "setup.py").read_text()


def test_skeletal_scalers_print_their_shape():
    from modi_ext.layers import SkeletalDownsample, SkeletalUpsample

    assert repr(SkeletalDownsample(4, 8, [[0, 1], [2]])) == (
        "SkeletalDownsample(4, 8, entities=3->2, pairs=3, kernel_size=3, padding_mode='zeros', bias=True)")
    assert "entities=2->3" in repr(SkeletalUpsample(8, 4, [[0, 1], [2]]))


# --------------------------------------------------------------------------------------------- files
def test_load_reads_motions_and_gltf_back(clip, tmp_path):
    m = modi.load(clip)
    assert isinstance(m, modi.Motion) and m.fps == 30.0 and m.unit in ("metres", "centimetres")
    out = m.to_gltf(tmp_path / "clip.glb")
    g = modi.load(out)
    assert isinstance(g, modi.Motion) and g.unit == "metres" and g.skeleton.names == m.skeleton.names
    torch.testing.assert_close(g.positions(), m.positions(unit="m"), atol=1e-4, rtol=0)
    m.to_bvh(tmp_path / "back.bvh")
    assert modi.load(tmp_path / "back.bvh") == modi.Motion.from_bvh(tmp_path / "back.bvh")
    with pytest.raises(UserError, match="no such file"):
        modi.load(tmp_path / "nope.bvh")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(UserError):
        modi.load(tmp_path / "junk.pt")


def test_inspect_is_what_modi_info_prints(modi_run, capsys):
    from modi.cli import main

    info = modi.inspect(modi_run)
    assert info.kind == "MoDi generator checkpoint" and info.step == 2
    assert info.skeleton["joints"] == modi.load(modi_run).skeleton.n_joints
    assert main(["info", str(modi_run)]) == 0
    assert capsys.readouterr().out.strip() == str(info).strip()


# --------------------------------------------------------------------------------------------- topology
def test_topology_gives_joint_only_maps_that_fit_the_layers(clip):
    from modi_ext.layers import SkeletalConv, SkeletalDownsample, SkeletalUpsample

    topo = modi.Topology.from_bvh(clip)
    J = topo.skeleton.n_joints
    assert topo.entity_counts[0] == J and topo.labels(0) == topo.skeleton.names
    assert topo.entity_counts[-1] == 1
    assert all(sorted(e for g in topo.pooling(i) for e in g) == list(range(topo.entity_counts[i]))
               for i in range(topo.n_levels - 1))
    x = torch.randn(2, 4, J, 16)
    conv = SkeletalConv(4, 8, topo.neighbors(0))
    down = SkeletalDownsample(8, 8, topo.pooling(0))
    up = SkeletalUpsample(8, 4, topo.pooling(0))
    h = down(conv(x))
    assert h.shape == (2, 8, topo.entity_counts[1], 8)
    assert up(h).shape == (2, 4, J, 16)
    full = modi.Topology(topo.skeleton, entities="modi", feet=["LeftToe", "RightToe"])
    assert full.entity_counts[0] == J + 3
    assert full.labels(0)[J:] == ["<root_motion>", "<contact>LeftToe", "<contact>RightToe"]
    assert "level 0" in full.describe()


# --------------------------------------------------------------------------------------------- MoDi
def test_modi_generator_samples_interpolates_edits_and_inverts(modi_run, clip, tmp_path):
    gen = modi.load(modi_run)
    assert isinstance(gen, modi.ModiGenerator) and "16 frames" in repr(gen)
    motions = gen.generate(3, seed=4)
    assert len(motions) == 3 and all(isinstance(m, modi.Motion) for m in motions)
    m = motions[0]
    assert m.n_frames == 16 and m.fps == gen.fps and set(m.contacts) == set(gen.feet)
    torch.testing.assert_close(gen.generate(1, seed=4)[0].rotations, m.rotations)  # motion i of a seed: any n
    with pytest.warns(DeprecationWarning, match="is now ModiGenerator.generate"):  # the old verb still works
        torch.testing.assert_close(gen.sample(1, seed=4)[0].rotations, m.rotations)
    seq = gen.interpolate(0, 1, steps=2)
    assert len(seq) == 3
    torch.testing.assert_close(seq[0].rotations, gen.synthesize([0])[0].rotations)
    assert len(gen.truncate("mean", steps=1)) == 2
    assert len(gen.crowd(0, k=2, sigma=0.3)) == 3
    boundary = gen.fit_boundary("speed", n=20)
    assert len(gen.edit(0, boundary, alphas=(-1, 0, 1))) == 3
    inv = gen.invert(clip, steps=2)
    assert inv.latent.shape == (gen.n_latent, gen.latent_dim) and len(inv.history) == 3
    assert isinstance(inv.motion, modi.Motion)
    out = m.to_gltf(tmp_path / "m.glb")
    assert out.is_file()
    with pytest.raises(UserError, match="no such latent file"):
        gen.latent("nope.npy")


def test_train_modi_refuses_an_existing_run_and_resumes_with_one_argument(proc_dir, modi_run, tmp_path, tiny_modi):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(modi_run, run)
    with pytest.raises(UserError, match="exists: pass resume=True"):
        modi.train_modi(proc_dir, run, config=tiny_modi, iters=3, cache=False)
    seen = []
    gen = modi.train_modi(proc_dir, run, resume=True, iters=3, progress=seen.append, cache=False)
    assert gen.step == 3 and [p.step for p in seen] == [3] and seen[0].total == 3 and "d" in seen[0].losses
    with pytest.raises(UserError, match="keeps its checkpoint's config"):
        modi.train_modi(proc_dir, run, resume=True, config={"train.lr": 0.1})


def test_train_modi_resume_auto_and_the_refusal_name_the_options(proc_dir, modi_run, tmp_path, tiny_modi):
    """``resume="auto"`` starts a run when the folder has none and continues it when it has one; a resumed run
    refuses an option that differs from its checkpoint's config, naming it, and accepts one that agrees."""
    import shutil

    fresh = modi.train_modi(proc_dir, tmp_path / "new", config=tiny_modi, iters=1, resume="auto", cache=False)
    assert fresh.step == 1
    run = tmp_path / "run"
    shutil.copytree(modi_run, run)
    with pytest.raises(UserError, match=r"train\.seed=5 \(train\.seed is 0 in the checkpoint\)"):
        modi.train_modi(proc_dir, run, resume="auto", seed=5, iters=3, cache=False)
    gen = modi.train_modi(proc_dir, run, resume="auto", seed=0, iters=3, cache=False)
    assert gen.step == 3


def test_the_run_lock_holds_from_python(proc_dir, tmp_path, tiny_modi):
    from modi import faults

    run = tmp_path / "locked"
    script = ("import sys, time; from modi import faults\n"
              "with faults.hold_run_folder(sys.argv[1]):\n    print('held', flush=True); time.sleep(30)\n")
    p = subprocess.Popen([sys.executable, "-c", script, str(run)], stdout=subprocess.PIPE, text=True,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    try:
        assert p.stdout.readline().strip() == "held"
        with pytest.raises(faults.RunFolderBusy):
            modi.train_modi(proc_dir, run, config=tiny_modi, iters=1)
        with pytest.raises(UserError):
            modi.train_ganimator(proc_dir / "nope.bvh", run, preset="tiny")
    finally:
        p.kill()
        p.wait()


# --------------------------------------------------------------------------------------------- GANimator
def test_ganimator_run_generates_motions_in_the_file_units(gan_run, clip):
    run = modi.load(gan_run)
    assert isinstance(run, modi.GanimatorRun)
    src = modi.load(clip)
    assert run.unit == src.unit and run.fps == src.fps
    motions = run.generate(2, frames=50, seed=1)
    assert [m.n_frames for m in motions] == [50, 50] and motions[0].skeleton == run.skeleton
    assert set(motions[0].contacts) == set(run.feet)
    assert motions[0] == run.generate(1, frames=50, seed=1)[0]  # no crowd offset by default: one motion = the first
    # the root starts where the training clip's does, in the file's units
    torch.testing.assert_close(motions[0].root_positions[0, [0, 2]].float(),
                               src.root_positions[0, [0, 2]].float(), atol=1e-4, rtol=1e-4)
    kf = run.generate(1, keyframes=clip, seed=0)[0]
    assert kf.n_frames == run.n_frames
    style = run.generate(1, style=clip, seed=0)[0]
    assert style.n_frames == src.n_frames
    with pytest.raises(UserError, match="trajectory-conditioned"):
        run.generate(1, trajectory=clip)
    metrics = run.metrics(motions)
    assert set(metrics[run.clips[0]]) >= {"coverage", "global_diversity", "local_diversity"}


def test_train_ganimator_guarantees_and_progress(clip, gan_run, tmp_path, tiny_ganimator):
    import shutil

    run = tmp_path / "g"
    shutil.copytree(gan_run, run)
    with pytest.raises(UserError, match="exists: pass resume=True"):
        modi.train_ganimator(clip, run, preset="tiny", **tiny_ganimator)
    seen = []
    again = modi.train_ganimator(clip, run, preset="tiny", resume=True, progress=seen.append, **tiny_ganimator)
    assert seen == [] and isinstance(again, modi.GanimatorRun)  # already fully trained: nothing to do
    fresh = tmp_path / "fresh"
    modi.train_ganimator(clip, fresh, preset="tiny", progress=seen.append, **tiny_ganimator)
    assert seen and seen[-1].model == "ganimator" and seen[-1].step == seen[-1].total
    # losses at the log iterations (every 10th and a block's last), read from the device there only
    assert all(bool(p.losses) == (p.step % 10 == 0 or p.step == p.total) for p in seen)
    assert {"D", "G", "rec", "con", "gp"} <= set(seen[-1].losses) and all(isinstance(v, float)
                                                                          for v in seen[-1].losses.values())
    with pytest.raises(UserError, match="unknown GANimator option"):
        modi.train_ganimator(clip, tmp_path / "x", preset="tiny", no_such_option=1)
    with pytest.raises(UserError, match="unknown preset"):
        modi.train_ganimator(clip, tmp_path / "y", preset="huge")


# --------------------------------------------------------------------------------------------- evaluation, show
def test_evaluate_single_scores_generated_motions(gan_run, clip):
    run = modi.load(gan_run)
    res = modi.evaluate_single(run.generate(2, frames=60, seed=0), clip)
    assert 0.0 <= res["coverage"] <= 1.0 and res["protocol"]["n_samples"] == 2


def test_show_writes_the_page_for_motions_files_and_arrays(clip, tmp_path):
    m = modi.load(clip)
    pos = m.positions(unit="m").numpy()
    viewer = modi.show(m, clip, pos, parents=m.skeleton.parents, out=tmp_path / "view.html")
    assert (tmp_path / "view.html").is_file() and len(viewer.motions) == 3
    np.testing.assert_allclose(viewer.motions[0].positions, viewer.motions[2].positions, atol=1e-9)
    with pytest.raises(UserError, match="parents"):
        modi.show(pos)
