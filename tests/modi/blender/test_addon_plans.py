"""The Blender add-on's applications without Blender: ``modi/blender/jobs.py`` is pure Python (no bpy), so the
plans (which action becomes which BVH, the ``modi ganimator generate`` flags, where the result lands, when the
add-on refuses) are checked here, and the argv a plan builds is run against a tiny trained run: the in-between's
ends are the action's poses, the loop has its length, and a request modi refuses comes back as the one line
Blender shows (``Job.outcome`` through ``jobs.last_line``). Real Blender drives the same code in
``test_blender_addon.py``."""
from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

import numpy as np
import pytest

from modi.cli import main
from modi.cli.commands.blender import this_modi

pytestmark = pytest.mark.usefixtures("one_torch_thread")

_JOBS = Path(__file__).resolve().parents[3] / "modi" / "blender" / "jobs.py"


def _load_jobs():
    """``modi/blender/jobs.py`` on its own (``modi.blender``'s package imports bpy)."""
    spec = importlib.util.spec_from_file_location("modi_blender_jobs", _JOBS)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


jobs = _load_jobs()
WALK = ("walk", 1, 60)  # (action, first frame, last frame)


# ------------------------------------------------------------------------------------------------ plans
def test_loop_plan_exports_nothing_and_marks_the_result_cyclic():
    p = jobs.plan("loop", WALK, frames=48, loop_root="return")
    assert p.exports == {} and p.cyclic and p.frame_start is None  # the scene's start
    assert p.flags("/o") == ["--loop", "--loop-root", "return", "--frames", "48"]
    assert jobs.plan("loop", WALK, frames=0).flags("/o") == ["--loop", "--loop-root", "travel"]  # the run's length
    assert p.stem == "walk.modi.loop"


def test_inbetween_of_one_action_is_its_end_back_to_its_start():
    p = jobs.plan("inbetween", WALK, frames=20)  # no To action: a cycle
    assert p.exports == {"from.bvh": "walk"}  # one export serves both ends
    assert p.flags("/o/x") == ["--inbetween", "/o/x/from.bvh@-1", "/o/x/from.bvh@0", "--frames", "20"]
    assert p.frame_start == 60 and not p.cyclic  # the transition starts on the action's last frame (same pose)
    assert p.stem == "walk.modi.cycle"
    same = jobs.plan("inbetween", WALK, to_action=("walk", 1, 60), frames=20)
    assert same.flags("/o") == p.flags("/o")
    whole = jobs.plan("inbetween", WALK, frames=20, span="actions")  # the action, then back to its first pose
    assert whole.flags("/o") == ["--inbetween", "/o/from.bvh", "/o/from.bvh@0", "--frames", "20"]
    assert whole.frame_start == 1


def test_inbetween_of_two_actions_exports_each():
    p = jobs.plan("inbetween", WALK, to_action=("run", 10, 40), frames=12)
    assert p.exports == {"from.bvh": "walk", "to.bvh": "run"}
    assert p.flags("/o") == ["--inbetween", "/o/from.bvh@-1", "/o/to.bvh@0", "--frames", "12"]
    assert p.stem == "walk.modi.to.run"
    whole = jobs.plan("inbetween", WALK, to_action=("run", 10, 40), frames=12, span="actions")
    assert whole.flags("/o") == ["--inbetween", "/o/from.bvh", "/o/to.bvh", "--frames", "12"]


def test_expand_edit_and_harmonise_plans():
    e = jobs.plan("expand", WALK, frames=100)
    assert e.exports == {"clip.bvh": "walk"}
    assert e.flags("/o") == ["--expand", "/o/clip.bvh", "--frames", "100", "--at", "20"]  # centred, said outright
    assert e.frame_start == 1 - 20  # the action's frames keep their scene frames
    assert jobs.plan("expand", WALK, frames=100, at=0).frame_start == 1
    assert jobs.plan("expand", WALK, frames=30).flags("/o") == ["--expand", "/o/clip.bvh", "--frames", "30"]  # modi says why
    ed = jobs.plan("edit", WALK, keep="lower")
    assert ed.flags("/o") == ["--edit", "/o/clip.bvh", "--keep", "lower"] and ed.frame_start == 1
    sel = jobs.plan("edit", WALK, keep="selected", selected=["mixamorig:Left Arm", "Head"])
    assert sel.flags("/o")[-1] == "Left_Arm,Head"  # the joint names modi reads (no namespace, no spaces)
    h = jobs.plan("harmonise", WALK, level=2)
    assert h.flags("/o") == ["--content", "/o/clip.bvh", "--content-level", "2"] and h.stem == "walk.modi.harmonised"
    assert jobs.plan("harmonise", WALK, level=0).stem == "walk.modi.styled"


def test_generate_argv_is_bvh_only_at_each_motions_own_start():
    argv = jobs.generate_argv("/bin/modi", "/r", "/o", n=3, seed=7, ik=True, extra=["--loop"])
    assert argv == ["/bin/modi", "ganimator", "generate", "/r", "--out", "/o", "--n", "3", "--seed", "7",
                    "--no-gif", "--no-view", "--crowd-spacing", "0", "--loop", "--ik"]


# ------------------------------------------------------------------------------------------------ refusals
def _refused(fn, *a, **k) -> str:
    with pytest.raises(jobs.Refused) as e:
        fn(*a, **k)
    msg = str(e.value)
    assert msg and "\n" not in msg
    return msg


def test_bad_input_is_refused_in_one_line_before_anything_runs():
    bones = ["Hips", "Spine", "LeftUpLeg"]
    paths = ['pose.bones["Hips"].location', 'pose.bones["Hips"].rotation_quaternion']
    jobs.check_action_on_rig("walk", paths, bones, "Armature")  # fine
    msg = _refused(jobs.check_action_on_rig, "crab_walk", ['pose.bones["Claw.L"].location'], bones, "Armature")
    assert "crab_walk" in msg and "another rig" in msg and "Claw.L" in msg
    msg = _refused(jobs.check_action_on_rig, "cube", ["location"], bones, "Armature")
    assert "keys no bones" in msg
    msg = _refused(jobs.check_run_rig, ["Hips", "Spine", "Claw"], bones, "Armature", "/runs/crab_001/")
    assert "crab_001" in msg and "Claw" in msg
    jobs.check_run_rig(["Hips", "Spine"], ["mixamorig:Hips", "mixamorig:Spine"], "A", "/r")  # namespace dropped
    jobs.check_run_rig(None, bones, "A", "/r")  # a run without source.bvh: left to modi
    assert "at least 1 frame" in _refused(jobs.plan, "inbetween", WALK, frames=0)
    assert "select the bones" in _refused(jobs.plan, "edit", WALK, keep="selected", selected=[])
    assert "unknown application" in _refused(jobs.plan, "dance", WALK)


def test_action_names_keep_seed_and_index_within_blenders_63_bytes():
    assert jobs.action_name("walk.modi.loop", 5, 1) == "walk.modi.loop.s0005.001"
    long = jobs.action_name("a" * 40 + ".modi.to." + "b" * 40, 5, 12)
    assert len(long.encode()) == 63 and long.endswith(".s0005.012") and long.startswith("a" * 40)
    utf = jobs.action_name("ä" * 40, 0, 0)  # never half a character
    assert len(utf.encode()) <= 63 and utf.endswith(".s0000.000") and utf[:-10] == "ä" * 26


def test_bone_paths_and_joint_names():
    assert jobs.bones_in_paths(['pose.bones["a\\"b"].location', "location", 'pose.bones["c"].rotation_euler',
                                'pose.bones["c"].location']) == ['a"b', "c"]
    assert jobs.bare_joint("mixamorig:Left Hand") == "Left_Hand"


# ------------------------------------------------------------------------------------------------ with modi
JOE = "bvh/ganimator/Joe/Salsa-Dancing-6.bvh"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, shared_data):
    """A 2-iteration GANimator run on 60 frames of Salsa at 30 fps (every other frame of the 60 fps file)."""
    root = tmp_path_factory.mktemp("plans")
    head, motion = (shared_data / JOE).read_text().split("MOTION")
    rows = motion.strip().splitlines()[2:2 + 120:2]
    clip = root / "walk.bvh"
    clip.write_text(head + f"MOTION\nFrames: {len(rows)}\nFrame Time: 0.033333\n" + "\n".join(rows) + "\n")
    run = root / "run"
    assert main(["ganimator", "train", str(clip), "--out", str(run), "--preset", "tiny", "--iterations", "2",
                 "--threads", "1"]) == 0
    shutil.copy(clip, run / "source.bvh")  # as the add-on leaves it
    return run, clip


def _positions(bvh: Path, tmp: Path, names: list | None = None) -> np.ndarray:
    """modi's joint positions of a BVH (T, J, 3), the joints ordered as ``names`` (default: the run's, as
    ``run/source.bvh`` reduced)."""
    npy, txt = tmp / (bvh.parent.name + bvh.stem + ".npy"), tmp / (bvh.parent.name + bvh.stem + ".txt")
    assert main(["export-positions", str(bvh), str(npy), "--names", str(txt)]) == 0
    have = [n.rsplit(":", 1)[-1] for n in txt.read_text().split()]  # modi writes 'mixamorig7:Hips' as 'Hips'
    return np.load(npy)[:, [have.index(n) for n in (names or have)]]


def _names(bvh: Path, tmp: Path) -> list:
    txt = tmp / "names.txt"
    assert main(["export-positions", str(bvh), str(tmp / "names.npy"), "--names", str(txt)]) == 0
    return txt.read_text().split()


def _run_plan(p, run: Path, clip: Path, out: Path, seed=3) -> list[Path]:
    out.mkdir()
    for name in p.exports:  # what the operator exports from the scene: the action, here the clip itself
        shutil.copy(clip, out / name)
    argv = jobs.generate_argv(this_modi(), str(run), str(out), n=2, seed=seed, extra=p.flags(str(out)))
    assert main(argv[1:]) == 0
    return sorted(out.glob("sample*.bvh"))


def test_plans_run_on_a_trained_run(tiny_run, tmp_path):
    run, clip = tiny_run
    jobs.check_run_rig(jobs.bvh_joint_names(str(run / "source.bvh")), jobs.bvh_joint_names(str(clip)), "A", str(run))
    files = _run_plan(jobs.plan("inbetween", ("walk", 1, 60), frames=16), run, clip, tmp_path / "cycle")
    assert len(files) == 2
    names = _names(files[0], tmp_path)  # the run's joints (modi drops the fingers and end sites)
    src = _positions(clip, tmp_path, names)
    height = src[0, :, 1].max() - src[0, :, 1].min()
    for f in files:  # the action's last pose, 16 generated frames, its first pose: both ends exact
        got = _positions(f, tmp_path, names)
        assert got.shape == (18, *src.shape[1:])
        assert np.abs(got[0] - src[-1]).max() <= 1e-4 * height
        assert np.abs(got[-1] - src[0]).max() <= 1e-4 * height
    files = _run_plan(jobs.plan("inbetween", ("walk", 1, len(src)), frames=16, span="actions"), run, clip,
                      tmp_path / "whole")
    got = _positions(files[0], tmp_path, names)
    assert got.shape[0] == len(src) + 17 and np.abs(got[:len(src)] - src).max() <= 1e-4 * height
    files = _run_plan(jobs.plan("loop", ("walk", 1, len(src)), frames=40, loop_root="return"), run, clip,
                      tmp_path / "loop")
    assert _positions(files[0], tmp_path).shape[0] == 40


def test_a_request_modi_refuses_is_the_one_line_blender_shows(tiny_run, tmp_path):
    run, _clip = tiny_run
    out = tmp_path / "short"
    out.mkdir()
    p = jobs.plan("loop", ("walk", 1, 60), frames=3)
    argv = jobs.generate_argv(this_modi(), str(run), str(out), n=1, seed=0, extra=p.flags(str(out)))
    job = jobs.Job("generating", argv, str(out / "modi_generate.log"), env=jobs.modi_env())
    assert job.wait(timeout=300) == 2
    msg = job.outcome()
    assert msg.startswith("modi failed: --loop with --frames 3: a loop needs at least"), msg
    assert "\n" not in msg and not list(out.glob("sample*.bvh"))
