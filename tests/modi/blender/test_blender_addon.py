"""The modi Blender add-on, driven through its operators (tests/modi/blender/blender_driver.py runs
inside Blender and records; this side checks): the zip installed with Blender's own operators, a real BVH imported
with Blender's importer (in Debian's Blender 3.4 and in PyPI's bpy 4.x and 5.x, each in its own process and venv),
Learn -> Generate with the variations' joint world positions (Blender's own pose
evaluation) equal to ``modi export-positions`` of the BVH modi wrote, key-frame generation, MoDi sampling, one-line
failures with CANCELLED, and -- with a real window under xvfb -- the modal operator leaving the event loop running
while it trains, Cancel saving a resumable run and Resume finishing it. ``modi blender install`` installs into a
throwaway Blender user folder."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from modi.cli import main
from modi.cli.commands.blender import blender_env, this_modi

REPO = Path(__file__).resolve().parents[3]
BVH_DIR = REPO.parent / "shared" / "data" / "bvh"
DRIVER = Path(__file__).resolve().parent / "blender_driver.py"
BLENDER = shutil.which("blender")
XVFB = shutil.which("xvfb-run")
TOL = 1e-4  # of body height

# PyPI's bpy (Blender as a Python module), 4.x and 5.x, each in a venv of its own: torch and bpy never share one
_CACHE = Path.home() / ".cache" / "modi"
BPY_VENVS = {"bpy4": Path(os.environ.get("MODI_BPY_VENV", _CACHE / "bpy-venv")),
             "bpy5": Path(os.environ.get("MODI_BPY5_VENV", _CACHE / "bpy5-venv"))}
BPY_PINS = {"bpy4": "bpy>=4.2,<5", "bpy5": "bpy>=5,<6"}
NO_BLENDER = "blender not on PATH (Debian package 'blender', with 'python3-numpy'; .ci/install_tools installs them)"
needs_blender = pytest.mark.skipif(BLENDER is None, reason=NO_BLENDER)


def bpy_python(which: str) -> Path:
    return BPY_VENVS[which] / "bin" / "python"


def no_bpy(which: str) -> str:
    return (f"no Python with PyPI's {BPY_PINS[which]!r} at {bpy_python(which)} (set MODI_BPY_VENV / MODI_BPY5_VENV; "
            f".ci/install_tools makes it: python3 -m venv VENV && VENV/bin/pip install '{BPY_PINS[which]}')")


def _runner(which: str) -> str:
    if which == "blender" and BLENDER is None:
        pytest.skip(NO_BLENDER)
    if which != "blender" and not bpy_python(which).is_file():
        pytest.skip(no_bpy(which))
    return which


@pytest.fixture(params=["blender", "bpy4", "bpy5"], ids=["debian-blender-3.4", "pypi-bpy-4.x", "pypi-bpy-5.x"])
def runner(request) -> str:
    """Which Blender runs the headless tests: Debian's executable, or PyPI's bpy module in its own venv."""
    return _runner(request.param)


def _bvh() -> Path:
    named = BVH_DIR / "bandai-namco-1" / "data" / "dataset-1_byebye_angry_001.bvh"
    if named.is_file():
        return named
    files = sorted(BVH_DIR.rglob("*.bvh")) if BVH_DIR.is_dir() else []
    if not files:
        pytest.skip(f"no BVH under {BVH_DIR} (the shared data is absent)")
    return files[0]


@pytest.fixture(scope="module")
def addon_zip(tmp_path_factory) -> Path:
    z = tmp_path_factory.mktemp("addon") / "modi_blender.zip"
    subprocess.run([sys.executable, "-m", "modi", "blender", "addon", "--out", str(z)], check=True,
                   capture_output=True)
    return z


def _blender(tmp: Path, addon_zip: Path, steps: list[str], gui: bool = False, timeout: int = 300,
             runner: str = "blender", **cfg) -> dict:
    """Run the driver in a fresh Blender (``runner``: Debian's ``blender``, or ``bpy`` for PyPI's module) whose home
    and temp folder are ``tmp`` (run folders land in ``tmp/modi_runs``); returns its record."""
    out = tmp / "rec"
    out.mkdir()
    conf = {"out": str(out), "zip": str(addon_zip), "modi": this_modi(), "bvh": str(_bvh()), "steps": steps,
            "iterations": 2, "n": 3, "frames": 40, "seed": 5, **cfg}
    (tmp / "cfg.json").write_text(json.dumps(conf))
    env = {**blender_env(), "HOME": str(tmp / "home"), "TMPDIR": str(tmp)}
    cmd = [BLENDER, "--factory-startup", "--python", str(DRIVER), "--", str(tmp / "cfg.json")]
    if runner != "blender":
        cmd = [str(bpy_python(runner)), str(DRIVER), "--", str(tmp / "cfg.json")]
    elif gui:
        cmd = [XVFB, "-a", "-s", "-screen 0 1280x720x24", *cmd]
    else:
        cmd.insert(1, "-b")
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    log = p.stdout + p.stderr
    assert (out / "record.json").is_file(), f"the driver wrote no record (rc {p.returncode}): {log[-3000:]}"
    rec = json.loads((out / "record.json").read_text())
    assert not rec.get("error"), rec["error"]
    assert "Traceback" not in log, log[-3000:]  # an operator's failure is a report, never a traceback
    rec["_out"], rec["_log"] = out, log
    return rec


def _positions(bvh: str, tmp: Path) -> tuple[np.ndarray, list[str]]:
    """modi's own forward kinematics of a BVH (Y up), turned into Blender's frame (Z up: x, -z, y)."""
    npy, names = tmp / "p.npy", tmp / "names.txt"
    assert main(["export-positions", bvh, str(npy), "--names", str(names)]) == 0
    p = np.load(npy).astype(np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], -1), names.read_text().split()


def _rel_error(rec: dict, dump: dict, bvh: str, tmp: Path) -> float:
    want, names = _positions(bvh, tmp)
    got = np.load(rec["_out"] / dump["npy"])
    bare = [n.rsplit(":", 1)[-1] for n in dump["names"]]  # modi drops a 'mixamorig:' namespace
    got = got[:, [dump["names"].index(n) if n in dump["names"] else bare.index(n) for n in names]]
    assert got.shape == want.shape, (got.shape, want.shape)
    height = want[0, :, 2].max() - want[0, :, 2].min()
    return float(np.abs(got - want).max() / height)


def _one_line_cancel(step: dict) -> str:
    assert step["ret"] is None and step["result"][0] == "CANCELLED", step  # raised: Blender's ERROR report
    msg = step["result"][1]
    assert msg and "\n" not in msg and "Traceback" not in msg, msg
    assert step["raised"].strip() == f"Error: {msg}", step  # the one line is what the report area shows
    return msg


# ------------------------------------------------------------------------------------------ headless (blender -b)
def test_learn_generate_keyframes_and_failures(tmp_path, addon_zip, runner):
    rec = _blender(tmp_path, addon_zip, ["learn", "generate", "generate_keyframes", "generate_bad_ckpt",
                                         "generate_import_crash", "broken_path", "bad_rig", "one_frame"],
                   runner=runner)
    assert rec["blender"].startswith({"blender": "3.4", "bpy4": "4.", "bpy5": "5."}[runner]), rec["blender"]
    st = rec["steps"]
    learn = st["learn"]
    assert learn["ret"] == ["FINISHED"] and learn["result"][0] == "FINISHED", learn
    run = Path(learn["run_dir"])
    assert run.parent == tmp_path / "modi_runs" and (run / "ganimator.ckpt").is_file()
    assert json.loads((run / "progress.json").read_text())["state"] == "done"
    # the action Blender holds went out through the add-on's exporter unchanged: its BVH replays the same poses
    src, src_names = _positions(str(_bvh()), tmp_path)
    exported, names = _positions(str(run / "source.bvh"), tmp_path)
    assert sorted(names) == sorted(src_names) and exported.shape == src.shape
    exported = exported[:, [names.index(n) for n in src_names]]
    assert np.abs(exported - src).max() / (src[0, :, 2].max() - src[0, :, 2].min()) < TOL

    gen = st["generate"]
    assert gen["ret"] == ["FINISHED"], gen
    arm, base = rec["armature"], rec["source_action"]
    assert gen["new_actions"] == [f"{base}.modi.s0005.{i:03d}" for i in range(3)]  # sortable names
    assert gen["active_action"] == gen["new_actions"][0]
    for name, dump in gen["dumps"].items():
        assert dump["frames"] == 40, (name, dump["frames"])  # the request
        assert dump["fake_user"], name  # kept when the armature plays another action
        assert Path(dump["bvh"]).parent.parent == run / "variations"
        err = _rel_error(rec, dump, dump["bvh"], tmp_path)
        assert err <= TOL, f"{name}: joint positions differ from modi's by {err:.2e} of the body height"
    # distinct variations, not one motion three times
    a, b = (np.load(rec["_out"] / d["npy"]) for d in list(gen["dumps"].values())[:2])
    assert np.abs(a - b).max() > 1e-3

    key = st["generate_keyframes"]
    assert key["ret"] == ["FINISHED"] and len(key["new_actions"]) == 3, key
    for name, dump in key["dumps"].items():
        assert dump["frames"] == 40
        assert _rel_error(rec, dump, dump["bvh"], tmp_path) <= TOL
        assert (Path(dump["bvh"]).parent / "keyframes.bvh").is_file()  # the condition went to modi as a BVH

    msg = _one_line_cancel(st["generate_bad_ckpt"])
    assert msg.startswith("modi failed:") and "ganimator.ckpt" in msg, msg
    msg = _one_line_cancel(st["generate_import_crash"])  # a bug of ours: still one line, no traceback
    assert msg == "modi add-on: importing the result failed: KeyError: 'injected'", msg
    msg = _one_line_cancel(st["broken_path"])
    assert "modi command not found" in msg and "/nonexistent/modi" in msg, msg
    assert st["broken_path"]["new_run_folders"] == []  # nothing exported, nothing started
    msg = _one_line_cancel(st["bad_rig"])
    assert "root bones" in msg and "two_roots" in msg, msg
    msg = _one_line_cancel(st["one_frame"])
    assert msg.startswith("modi failed:") and "frame" in msg, msg


def _blender_positions(rec: dict, dump: dict, names: list) -> np.ndarray:
    """A dumped action's joint positions (T, J, 3) for the joints ``names`` (modi's, without a namespace)."""
    got = np.load(rec["_out"] / dump["npy"])
    bare = [n.rsplit(":", 1)[-1] for n in dump["names"]]
    return got[:, [bare.index(n) for n in names]]


def _bvh_names(bvh: str, tmp: Path) -> list:
    return _positions(bvh, tmp)[1]


@pytest.fixture(params=["blender", "bpy5"], ids=["debian-blender-3.4", "pypi-bpy-5.x"])
def oldest_and_newest(request) -> str:
    """The applications' test on the oldest and the newest Blender API only (the two ends of what rig_io bridges;
    bpy 4.x sits between them and runs the generate test above), to keep CI's time."""
    return _runner(request.param)


def test_loop_inbetween_expand_edit_harmonise_and_their_refusals(tmp_path, addon_zip, oldest_and_newest):
    """The applications from the panel, on the scene's actions: every new action lands joint for joint on what
    modi wrote, and keeps what the application promises (the loop's seam, the in-between's ends, the expanded
    action in place, the kept lower body); bad input is one line and CANCELLED."""
    rec = _blender(tmp_path, addon_zip, ["learn", "generate", "loop", "inbetween_cycle", "inbetween_two", "expand",
                                         "edit_lower", "harmonise", "loop_too_short", "app_no_action",
                                         "app_other_rig", "app_nothing_selected"],
                   runner=oldest_and_newest, n=1, frames=30, app_n=2, loop_frames=40, between=12, expand_frames=80)
    st, base = rec["steps"], rec["source_action"]
    src_dump = rec["source_dump"]
    S = src_dump["frames"]
    assert st["learn"]["ret"] == ["FINISHED"], st["learn"]

    def landed(step: str, stem: str, frames: int) -> dict:
        r = st[step]
        assert r["ret"] == ["FINISHED"], r
        want = [f"{stem}.s0005.{i:03d}" for i in range(2)]
        if len(want[0].encode()) > 63:  # Blender's longest name: the stem is cut, the seed and index kept
            want = [stem[:63 - len(".s0005.000")] + w[-len(".s0005.000"):] for w in want]
        assert r["new_actions"] == want, r["new_actions"]
        assert r["active_action"] == r["new_actions"][0]
        for name, dump in r["dumps"].items():
            assert dump["frames"] == frames, (step, name, dump["frames"])
            err = _rel_error(rec, dump, dump["bvh"], tmp_path)
            assert err <= TOL, f"{step} {name}: joint positions differ from modi's by {err:.2e} of the body height"
        return r

    # the joints modi keeps, less Bandai's static floor root: modi gives that root the pelvis's track, so only
    # there do modi's motions and the source differ in kind (every other joint holds its world position)
    names = _bvh_names(next(iter(st["loop"]["dumps"].values()))["bvh"], tmp_path)
    assert names[0] == "joint_Root", names
    names = names[1:]
    src = _blender_positions(rec, src_dump, names)
    height = src[0, :, 2].max() - src[0, :, 2].min()
    src_step = np.linalg.norm(np.diff(src, axis=0), axis=-1).max()

    loop = landed("loop", f"{base}.modi.loop", 40)
    for dump in loop["dumps"].values():
        lo, hi = dump["frame_range"]
        assert dump["cyclic"] and (lo, hi) == (dump["first"], dump["first"] + 40)  # frame hi is frame lo again
        # the seam is a step of the source's own size (loosely: a 2-iteration model; modi's tests hold it exactly)
        p = _blender_positions(rec, dump, names)
        seam = np.linalg.norm(p[0] - p[-1], axis=-1).max()
        assert seam <= 2 * src_step, (seam, src_step)

    cyc = landed("inbetween_cycle", f"{base}.modi.cycle", 12 + 2)
    for dump in cyc["dumps"].values():  # the action's last pose, 12 frames, its first pose
        p = _blender_positions(rec, dump, names)
        assert dump["first"] == src_dump["first"] + S - 1  # starts on the action's last frame
        assert np.abs(p[0] - src[-1]).max() <= TOL * height and np.abs(p[-1] - src[0]).max() <= TOL * height

    two = st["inbetween_two"]
    to_dump = two["to_dump"]
    T2 = to_dump["frames"]
    two = landed("inbetween_two", f"{base}.modi.to.{two['to_action']}", S + 12 + T2)
    to = _blender_positions(rec, to_dump, names)
    for dump in two["dumps"].values():  # the source action whole, 12 frames, then the other action whole
        p = _blender_positions(rec, dump, names)
        assert np.abs(p[:S] - src).max() <= TOL * height and np.abs(p[-T2:] - to).max() <= TOL * height

    at = (80 - S) // 2
    exp = landed("expand", f"{base}.modi.expand", 80)
    for dump in exp["dumps"].values():  # the action at its own scene frames inside the longer motion
        assert dump["first"] == src_dump["first"] - at
        p = _blender_positions(rec, dump, names)
        assert np.abs(p[at:at + S] - src).max() <= TOL * height
        assert np.abs(p[:at] - src[:1]).max() > 1e-3 * height  # the rest is generated, not a held pose

    low = landed("edit_lower", f"{base}.modi.lower", S)
    legs = [j for j, n in enumerate(names) if any(k in n for k in ("Leg", "Foot", "Toe"))]
    assert len(legs) >= 4, names
    for dump in low["dumps"].values():  # the kept legs where they were; the upper body generated
        p = _blender_positions(rec, dump, names)
        assert np.abs(p[:, legs] - src[:, legs]).max() <= TOL * height
        assert np.abs(p - src).max() > 1e-3 * height

    landed("harmonise", f"{base}.modi.harmonised", S)

    msg = _one_line_cancel(st["loop_too_short"])
    assert msg.startswith("modi failed: --loop with --frames 3: a loop needs at least"), msg
    msg = _one_line_cancel(st["app_no_action"])
    assert "no_action" in msg and "has no action" in msg, msg
    msg = _one_line_cancel(st["app_other_rig"])
    assert "crab_walk" in msg and "another rig" in msg, msg
    assert "select the bones" in _one_line_cancel(st["app_nothing_selected"])


@needs_blender
def test_trajectory_conditioned_run_follows_an_actions_root_path(tmp_path, addon_zip):
    rec = _blender(tmp_path, addon_zip, ["learn_conditional", "learn", "learn_conditional", "generate_trajectory"],
                   n=2, frames=0)
    st = rec["steps"]
    msg = _one_line_cancel(st["learn_conditional"])  # nothing trained yet to learn trajectories from
    assert "trained run" in msg, msg
    first, cond = st["learn"], st["learn_conditional#2"]
    assert first["ret"] == ["FINISHED"] and cond["ret"] == ["FINISHED"], (first, cond)
    run = Path(cond["run_dir"])
    assert run.name.endswith("_traj_001") and (run / "ganimator.ckpt").is_file()
    flags = json.loads((run / "modi_addon.json").read_text())["flags"]
    assert flags[flags.index("--conditional-from") + 1] == first["run_dir"]  # what Resume will pass again
    gen = st["generate_trajectory"]
    assert gen["ret"] == ["FINISHED"] and len(gen["new_actions"]) == 2, gen
    for name, dump in gen["dumps"].items():
        assert dump["frames"] == rec["source_frames"], dump["frames"]  # the trajectory's length
        assert (Path(dump["bvh"]).parent / "trajectory.bvh").is_file()
        assert _rel_error(rec, dump, dump["bvh"], tmp_path) <= TOL


def test_fbx_mixamo_style_character_learns_and_takes_its_variations(tmp_path, addon_zip, runner):
    """Blender's FBX importer gives the armature bone orientations and an object transform of its own and the
    bones have Mixamo's 'mixamorig:' names: the variations still land on it joint for joint."""
    rec = _blender(tmp_path, addon_zip, ["fbx", "learn", "generate"], runner=runner, n=2, frames=30)
    st = rec["steps"]
    assert st["fbx"]["bones"][0].startswith("mixamorig:"), st["fbx"]
    assert st["fbx"]["frames"] == rec["source_frames"], st["fbx"]  # the FBX carries the action, frame for frame
    assert st["learn"]["ret"] == ["FINISHED"], st["learn"]
    gen = st["generate"]
    assert gen["ret"] == ["FINISHED"] and len(gen["new_actions"]) == 2, gen
    for name, dump in gen["dumps"].items():
        assert name.startswith(st["fbx"]["action"] + ".modi.s0005.") and dump["frames"] == 30
        assert all(n.startswith("mixamorig:") for n in dump["names"])
        err = _rel_error(rec, dump, dump["bvh"], tmp_path)
        assert err <= TOL, f"{name}: joint positions differ from modi's by {err:.2e} of the body height"


def test_installs_as_a_blender_4_extension_too(tmp_path, addon_zip):
    """Blender 4.2+ also takes the zip as an extension (its manifest): the operators then live under the
    extension's module name and still find their preferences."""
    if not bpy_python("bpy4").is_file():
        pytest.skip(no_bpy("bpy4"))
    rec = _blender(tmp_path, addon_zip, ["learn", "broken_path"], runner="bpy4", install="extension")
    assert rec["module"] == "bl_ext.user_default.modi_blender"
    assert rec["steps"]["learn"]["ret"] == ["FINISHED"], rec["steps"]["learn"]
    assert "modi command not found" in _one_line_cancel(rec["steps"]["broken_path"])


@pytest.fixture(scope="module")
def modi_checkpoint(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("modi") / "run"
    subprocess.run([sys.executable, "-m", "modi", "train", "procedural", "--out", str(run), "--iters", "1",
                    "--preset", "small", "--frames", "16", "--batch", "2", "--no-tensorboard", "--sample-every", "0",
                    "--no-cache", "--threads", "1"], check=True, capture_output=True)
    return run / "checkpoint.pt"


def test_sample_modi_imports_armatures(tmp_path, addon_zip, modi_checkpoint, runner):
    rec = _blender(tmp_path, addon_zip, ["sample_modi", "sample_modi_interpolate"], runner=runner,
                   modi_ckpt=str(modi_checkpoint), modi_n=3)
    s = rec["steps"]["sample_modi"]
    assert s["ret"] == ["FINISHED"], s
    assert s["new_armatures"] == [f"modi.psi0.7.s0003.{i:03d}" for i in range(3)]
    assert s["animated"] == s["new_armatures"]  # each came with its action
    assert s["x"] == [0.0, 2.0, 4.0]  # laid out side by side, not on top of each other
    i = rec["steps"]["sample_modi_interpolate"]
    assert i["ret"] == ["FINISHED"], i
    assert i["new_armatures"] == [f"modi.interp.{k:03d}" for k in range(4)]  # --steps 3: both ends + 2 between
    assert i["animated"] == i["new_armatures"]


# ------------------------------------------------------------------------------------------ a real window (xvfb)
@needs_blender
@pytest.mark.skipif(XVFB is None, reason="xvfb-run not on PATH (Debian packages 'xvfb' and 'xauth')")
def test_modal_training_keeps_the_ui_running_cancel_saves_and_resume_finishes(tmp_path, addon_zip):
    rec = _blender(tmp_path, addon_zip, ["gui_cancel_resume"], gui=True, timeout=400, iterations=8,
                   cancel_after=2)
    g = rec["steps"]["gui_cancel_resume"]
    assert not g.get("error"), g.get("error")
    assert g["learn_ret"] == ["RUNNING_MODAL"] and g["resume_ret"] == ["RUNNING_MODAL"], g  # modal, not blocking
    assert g["ticks_training"] >= 2 and g["status_seen"].startswith("training: levels"), g
    # the event loop kept running while modi trained: a 0.1 s timer kept firing throughout the resumed training
    # (a blocking operator would give one gap as long as the training); on a busy 2-core machine with a software
    # renderer a tick can wait a second or two for a redraw
    ticks = g["resume_ticks"]
    span, gap = ticks[-1] - ticks[0], max(b - a for a, b in zip(ticks, ticks[1:]))
    assert span > 3.0 and len(ticks) >= 5 and gap < min(5.0, span / 3), (span, gap, len(ticks))
    assert g["cancel_ret"] == ["FINISHED"]
    assert g["after_cancel"][0] == "CANCELLED" and "Resume" in g["after_cancel"][1], g
    assert g["ckpt_after_cancel"] and g["progress_after_cancel"]["state"] == "stopped", g
    stopped = g["progress_after_cancel"]
    assert 0 < stopped["done_iterations"] < stopped["total_iterations"], stopped
    assert g["after_resume"][0] == "FINISHED", g
    done = g["progress_after_resume"]
    assert done["state"] == "done" and done["done_iterations"] == done["total_iterations"], done
    # Blender quit while a second run trained: the add-on stopped it the way Cancel does, nothing left running
    quit_run = Path(g["quit_run"])
    assert g["relearn_ret"] == ["RUNNING_MODAL"] and quit_run.name.endswith("_002"), quit_run
    after_quit = json.loads((quit_run / "progress.json").read_text())
    assert after_quit["state"] == "stopped" and (quit_run / "ganimator.ckpt").is_file(), after_quit
    assert "SIGTERM" in (quit_run / "modi_train.log").read_text()


# ------------------------------------------------------------------------------------------ modi blender install
@needs_blender
def test_install_enables_the_addon_with_this_environments_modi(tmp_path):
    env = {**blender_env(), "HOME": str(tmp_path)}
    p = subprocess.run([sys.executable, "-m", "modi", "blender", "install", "--blender", BLENDER],
                       capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    assert str(tmp_path) in p.stdout and this_modi() in p.stdout, p.stdout
    check = ("import bpy, addon_utils; print('ENABLED', addon_utils.check('modi_blender')[1], "
             "bpy.context.preferences.addons['modi_blender'].preferences.modi_path)")
    q = subprocess.run([BLENDER, "-b", "--python-expr", check], capture_output=True, text=True, env=env, timeout=120)
    assert f"ENABLED True {this_modi()}" in q.stdout, q.stdout[-2000:] + q.stderr[-2000:]
    bad = subprocess.run([sys.executable, "-m", "modi", "blender", "install", "--blender", "/nonexistent/blender"],
                         capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "/nonexistent/blender" in bad.stderr
