"""Runs inside Blender (``blender -b --python tests/modi/blender/blender_driver.py -- CONFIG.json``, or with a window under
xvfb): installs the add-on zip with Blender's own operators, imports a BVH with Blender's importer, then runs the
steps CONFIG names and writes what it saw to CONFIG["out"] (JSON, plus .npy joint positions) for the pytest side
to check. Nothing here decides pass or fail; it only records.

Steps (a step named twice is recorded the second time as "name#2"; each records the operator's return set and ``STATE["result"]``, the add-on's one-line outcome):
  fbx                 bones renamed Mixamo-style, the armature through Blender's FBX exporter and importer
  learn, generate     Learn the imported action; Generate variations (positions of every new action dumped)
  generate_keyframes  Generate following the source action's key frames, with foot-contact cleanup
  learn_conditional   Learn a trajectory-conditioned run from the run in Run; generate_trajectory follows the
                      source action's root path
  generate_bad_ckpt   Generate from a copy of the run whose checkpoint is junk (a failing modi command)
  generate_import_crash  Generate with an injected bug in importing the result
  bad_rig, one_frame  Learn on a copy with two root bones / with a one-frame action
  broken_path         Learn with the modi path pointing nowhere
  loop, inbetween_cycle, inbetween_two, expand, edit_lower, harmonise
                      the applications on the run in Run (a loop that returns; the source action's end back to
                      its start; the source action, a transition, then a variation; the action expanded; its
                      lower body kept; harmonised from level 1): the new actions' positions dumped
  loop_too_short, app_no_action, app_other_rig, app_nothing_selected
                      a loop modi refuses; an armature without an action; another rig's action; Edit Body Part
                      with no bone selected
  sample_modi         Sample a MoDi checkpoint (CONFIG["modi_ckpt"]); sample_modi_interpolate: between two seeds
  gui_cancel_resume   (needs a window) modal Learn, a counter timer ticking meanwhile, Cancel mid-training,
                      Resume to the end, then Learn again and quit Blender while it trains
"""
import builtins
import json
import os
import shutil
import sys
import time
import traceback

import bpy
import numpy as np

CFG = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
OUT = CFG["out"]
REC = {"blender": bpy.app.version_string, "steps": {}}

# Debian's Blender 3.4 BVH importer opens its file with mode 'rU', which Python 3.11 removed: map it to 'r'.
_open = builtins.open
builtins.open = lambda f, mode="r", *a, **k: _open(f, mode.replace("U", ""), *a, **k)


def save():
    with _open(os.path.join(OUT, "record.json"), "w") as fh:
        json.dump(REC, fh, indent=1)


# "addon": the legacy installer (Blender 3.4 and 4.x); "extension": Blender 4.2+'s extension installer
MODULE = "bl_ext.user_default.modi_blender" if CFG.get("install") == "extension" else "modi_blender"


def operators():
    import importlib
    return importlib.import_module(MODULE + ".operators")


def state():
    return operators().STATE


def call(op, **kw):
    """Run an operator; from a script Blender raises an ERROR report as RuntimeError (the UI shows a report)."""
    try:
        ret = sorted(op(**kw))
        raised = None
    except RuntimeError as e:
        ret, raised = None, str(e)
    res = state()["result"]
    return {"ret": ret, "raised": raised, "result": list(res) if res else None}


def dump_positions(obj, action, tag):
    """Every frame of ``action`` on ``obj``: the world head of each pose bone (Blender's own evaluation)."""
    scene = bpy.context.scene
    operators().rig_io.assign_action(obj, action)
    lo, hi = (int(round(v)) for v in getattr(action, "curve_frame_range", action.frame_range))  # the keyed frames
    names = [b.name for b in obj.pose.bones]
    pos = np.zeros((hi - lo + 1, len(names), 3))
    for f in range(lo, hi + 1):
        scene.frame_set(f)
        for j, pb in enumerate(obj.pose.bones):
            pos[f - lo, j] = tuple(obj.matrix_world @ pb.head)
    np.save(os.path.join(OUT, f"{tag}.npy"), pos)
    return {"names": names, "frames": hi - lo + 1, "npy": f"{tag}.npy", "first": lo}


def setup():
    if CFG.get("install") == "extension":
        bpy.ops.extensions.package_install_files(filepath=CFG["zip"], repo="user_default", enable_on_install=True)
    else:
        bpy.ops.preferences.addon_install(filepath=CFG["zip"])
        bpy.ops.preferences.addon_enable(module=MODULE)
    REC["module"] = MODULE
    bpy.context.preferences.addons[MODULE].preferences.modi_path = CFG["modi"]
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    bpy.ops.import_anim.bvh(filepath=CFG["bvh"], update_scene_fps=True, update_scene_duration=True)
    arm = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
    bpy.context.view_layer.objects.active = arm
    arm.select_set(True)
    s = bpy.context.scene.modi
    s.preset, s.iterations = "tiny", CFG.get("iterations", 2)
    REC["armature"] = arm.name
    REC["source_action"] = arm.animation_data.action.name
    REC["source_frames"] = int(round(arm.animation_data.action.frame_range[1] - arm.animation_data.action.frame_range[0])) + 1
    return arm


def active():
    return bpy.context.view_layer.objects.active


def step_learn(arm):
    r = call(bpy.ops.modi.learn)
    r["run_dir"] = bpy.path.abspath(bpy.context.scene.modi.run_dir)
    return r


def step_generate(arm, mode="random"):
    s = bpy.context.scene.modi
    s.n, s.frames, s.seed = CFG["n"], CFG["frames"], CFG["seed"]
    s.mode, s.contact_cleanup = mode, mode != "random"
    s.condition_action = REC["source_action"]
    before = set(a.name for a in bpy.data.actions)
    r = call(bpy.ops.modi.generate)
    new = sorted(a.name for a in bpy.data.actions if a.name not in before)
    r["new_actions"] = new
    r["active_action"] = arm.animation_data.action.name
    r["dumps"] = {}
    for i, name in enumerate(new):
        act = bpy.data.actions[name]
        d = dump_positions(arm, act, f"{mode}{i}")
        d["bvh"] = act.get("modi_bvh")
        d["fake_user"] = act.use_fake_user
        d["users_armature"] = arm.animation_data.action.name == name
        r["dumps"][name] = d
    return r


def step_generate_bad_ckpt(arm):
    s = bpy.context.scene.modi
    good = bpy.path.abspath(s.run_dir)
    bad = os.path.join(OUT, "bad_run")
    shutil.copytree(good, bad, ignore=shutil.ignore_patterns("variations"))
    with _open(os.path.join(bad, "ganimator.ckpt"), "wb") as fh:
        fh.write(b"this is not a checkpoint")
    s.run_dir = bad
    try:
        return call(bpy.ops.modi.generate)
    finally:
        s.run_dir = good


def step_generate_import_crash(arm):
    """Generate whose import of the result hits an unexpected bug (an injected KeyError)."""
    rig_io = __import__(MODULE + ".rig_io", fromlist=["rig_io"])
    keep = rig_io.action_from_bvh

    def broken(*a, **k):
        raise KeyError("injected")

    rig_io.action_from_bvh = broken
    try:
        s = bpy.context.scene.modi
        s.n, s.frames, s.mode = 1, 20, "random"
        return call(bpy.ops.modi.generate)
    finally:
        rig_io.action_from_bvh = keep


def step_broken_path(arm):
    prefs = bpy.context.preferences.addons[MODULE].preferences
    keep, prefs.modi_path = prefs.modi_path, "/nonexistent/modi"
    runs = sorted(os.listdir(state_runs_root())) if os.path.isdir(state_runs_root()) else []
    try:
        r = call(bpy.ops.modi.learn)
    finally:
        prefs.modi_path = keep
    r["new_run_folders"] = sorted(set(os.listdir(state_runs_root())) - set(runs)) if os.path.isdir(state_runs_root()) else []
    return r


def state_runs_root():
    return operators().runs_root()


def step_sample_modi(arm, interpolate=False):
    s = bpy.context.scene.modi
    s.modi_checkpoint, s.modi_n, s.psi, s.modi_seed = CFG["modi_ckpt"], CFG["modi_n"], 0.7, 3
    s.interp_from, s.interp_to, s.interp_steps = 1, 2, CFG["modi_n"]
    before = set(o.name for o in bpy.data.objects)
    r = call(bpy.ops.modi.sample_modi, interpolate=interpolate)
    new = [o for o in bpy.data.objects if o.name not in before]
    r["new_armatures"] = sorted(o.name for o in new if o.type == "ARMATURE")
    r["animated"] = sorted(o.name for o in new if o.type == "ARMATURE" and o.animation_data and o.animation_data.action)
    r["x"] = sorted(round(o.matrix_world.translation.x, 4) for o in new if o.type == "ARMATURE")
    r["other_objects"] = sorted(f"{o.type}:{o.name}" for o in new if o.type != "ARMATURE")
    return r


def step_fbx(arm):
    """A Mixamo-style FBX character: bones renamed 'mixamorig:<name>', exported with Blender's FBX exporter,
    the scene emptied, imported back with Blender's FBX importer (its own bone orientations, an object transform
    of its own); the imported armature becomes the active one for the steps that follow."""
    for b in arm.data.bones:
        b.name = "mixamorig:" + b.name
    lo, hi = arm.animation_data.action.frame_range
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = int(round(lo)), int(round(hi))  # what FBX bakes
    path = os.path.join(OUT, "character.fbx")
    bpy.ops.export_scene.fbx(filepath=path, object_types={"ARMATURE"}, bake_anim=True, add_leaf_bones=False,
                             bake_anim_use_all_actions=False, bake_anim_use_nla_strips=False)
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    for a in list(bpy.data.actions):
        bpy.data.actions.remove(a)
    bpy.ops.import_scene.fbx(filepath=path, automatic_bone_orientation=True)
    new = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
    bpy.context.view_layer.objects.active = new
    new.select_set(True)
    REC["armature"], REC["source_action"] = new.name, new.animation_data.action.name
    lo, hi = new.animation_data.action.frame_range
    return {"armature": new.name, "action": new.animation_data.action.name, "frames": int(round(hi - lo)) + 1,
            "matrix_world": [list(r) for r in new.matrix_world], "bones": [b.name for b in new.data.bones][:3],
            "frame_start": int(round(lo))}


def _copy(arm, name):
    obj = arm.copy()
    obj.data = arm.data.copy()
    obj.name = name
    bpy.context.scene.collection.objects.link(obj)
    return obj


def step_bad_rig(arm):
    """A copy of the armature with a second root bone: Learn refuses before starting anything."""
    obj = _copy(arm, "two_roots")
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    child = [b for b in obj.data.edit_bones if b.parent is not None][-1]
    child.parent = None
    bpy.ops.object.mode_set(mode="OBJECT")
    try:
        return call(bpy.ops.modi.learn)
    finally:
        bpy.context.view_layer.objects.active = arm


def step_one_frame(arm):
    """A copy of the armature whose action has one frame: modi refuses to train on it (a failing command)."""
    obj = _copy(arm, "one_frame")
    act = bpy.data.actions.new("one_frame_action")
    obj.animation_data.action = act
    path = f'pose.bones["{obj.pose.bones[0].name}"].location'
    fc = (act.fcurve_ensure_for_datablock(obj, path, index=0) if hasattr(act, "fcurve_ensure_for_datablock")
          else act.fcurves.new(path, index=0))  # 4.4+ (5.0: the only way) / up to 4.3
    fc.keyframe_points.insert(1, 0.0)
    bpy.context.view_layer.objects.active = obj
    try:
        return call(bpy.ops.modi.learn)
    finally:
        bpy.context.view_layer.objects.active = arm


def step_learn_conditional(arm):
    s = bpy.context.scene.modi
    s.conditional = True
    try:
        r = step_learn(arm)
    finally:
        s.conditional = False
    return r


# ---------------------------------------------------------------------------------------------- applications
def step_app(arm, app, **settings):
    """Run application ``app`` (loop, inbetween, expand, edit, harmonise) with ``settings`` on the scene's modi
    settings; record the new actions (positions, the BVH modi wrote, frame ranges, cyclic flags) and the source
    action's positions once."""
    s = bpy.context.scene.modi
    s.n, s.seed, s.contact_cleanup = CFG.get("app_n", 2), CFG["seed"], False
    s.app_action, s.app_to_action = REC["source_action"], ""
    for k, v in settings.items():
        setattr(s, k, v)
    if "source_dump" not in REC:
        keep = arm.animation_data.action if arm.animation_data else None
        REC["source_dump"] = dump_positions(arm, bpy.data.actions[REC["source_action"]], "source")
        operators().rig_io.assign_action(arm, keep)
    before = set(a.name for a in bpy.data.actions)
    r = call(getattr(bpy.ops.modi, operators().APPLICATION_OPERATORS[app].split(".")[1]))
    new = sorted(a.name for a in bpy.data.actions if a.name not in before)
    r["new_actions"], r["dumps"] = new, {}
    r["active_action"] = arm.animation_data.action.name if arm.animation_data and arm.animation_data.action else None
    for i, name in enumerate(new):
        act = bpy.data.actions[name]
        d = dump_positions(arm, act, f"{app}{len(REC['steps'])}_{i}")
        d["bvh"] = act.get("modi_bvh")
        d["cyclic"] = bool(getattr(act, "use_cyclic", False))
        d["frame_range"] = [round(v) for v in act.frame_range]
        r["dumps"][name] = d
    return r


def step_inbetween_two(arm):
    """In-between from the source action to a second action on the rig (a copy of the source named "second",
    its first 30 frames), keeping both whole."""
    to = bpy.data.actions[REC["source_action"]].copy()
    to.name = "second"
    lo = int(round(to.frame_range[0]))
    for fc in operators().rig_io.action_fcurves(to):  # keep frames lo .. lo + 29
        for kp in reversed(list(fc.keyframe_points)):
            if kp.co[0] > lo + 29:
                fc.keyframe_points.remove(kp)
    r = step_app(arm, "inbetween", app_to_action=to.name, app_span="actions", app_frames=CFG.get("between", 12))
    r["to_action"], r["to_dump"] = to.name, dump_positions(arm, to, "to_action")
    return r


def step_app_no_action(arm):
    """In-between on a copy of the armature without an action: refused before anything starts."""
    obj = _copy(arm, "no_action")
    obj.animation_data_clear()
    bpy.context.view_layer.objects.active = obj
    s = bpy.context.scene.modi
    s.app_action, s.app_to_action = "", ""
    try:
        return call(bpy.ops.modi.inbetween)
    finally:
        bpy.context.view_layer.objects.active = arm


def step_app_other_rig(arm):
    """In-between from an action that keys bones this armature does not have (another rig's action)."""
    act = bpy.data.actions.new("crab_walk")
    path = 'pose.bones["Claw.L"].location'
    if hasattr(act, "fcurve_ensure_for_datablock"):  # 4.4+ (5.0: the only way)
        other = bpy.data.objects.new("crab", bpy.data.armatures.new("crab"))
        bpy.context.scene.collection.objects.link(other)
        operators().rig_io.assign_action(other, act)
        fc = act.fcurve_ensure_for_datablock(other, path, index=0)
    else:
        fc = act.fcurves.new(path, index=0)
    fc.keyframe_points.insert(1, 0.0)
    fc.keyframe_points.insert(20, 1.0)
    s = bpy.context.scene.modi
    s.app_action = act.name
    return call(bpy.ops.modi.inbetween)


def step_app_nothing_selected(arm):
    """Edit Body Part keeping the selected bones, with none selected."""
    for pb in arm.pose.bones:
        if hasattr(pb, "select"):
            pb.select = False
        else:
            pb.bone.select = False
    s = bpy.context.scene.modi
    s.app_action, s.keep = REC["source_action"], "selected"
    try:
        return call(bpy.ops.modi.edit_part)
    finally:
        s.keep = "upper"


STEPS = {"fbx": step_fbx, "generate_import_crash": step_generate_import_crash, "learn_conditional": step_learn_conditional,
         "generate_trajectory": lambda arm: step_generate(arm, "trajectory"), "bad_rig": step_bad_rig, "one_frame": step_one_frame, "learn": step_learn, "generate": step_generate, "generate_bad_ckpt": step_generate_bad_ckpt,
         "generate_keyframes": lambda arm: step_generate(arm, "keyframes"),
         "broken_path": step_broken_path, "sample_modi": step_sample_modi,
         "sample_modi_interpolate": lambda arm: step_sample_modi(arm, True),
         "loop": lambda arm: step_app(arm, "loop", app_frames=CFG.get("loop_frames", 40), loop_root="return"),
         "inbetween_cycle": lambda arm: step_app(arm, "inbetween", app_span="poses",
                                                 app_frames=CFG.get("between", 12)),
         "inbetween_two": step_inbetween_two,
         "expand": lambda arm: step_app(arm, "expand", app_frames=CFG.get("expand_frames", 80), expand_at=-1),
         "edit_lower": lambda arm: step_app(arm, "edit", keep="lower"),
         "harmonise": lambda arm: step_app(arm, "harmonise", content_level=1),
         "loop_too_short": lambda arm: step_app(arm, "loop", app_frames=3),
         "app_no_action": step_app_no_action, "app_other_rig": step_app_other_rig,
         "app_nothing_selected": step_app_nothing_selected}


# ---------------------------------------------------------------------------------------------- the GUI run
def gui_cancel_resume(arm):
    """Drive the modal operators from a timer, as a user's clicks would, while the event loop runs."""
    win = bpy.context.window_manager.windows[0]
    area = max(win.screen.areas, key=lambda a: a.width * a.height)
    g = {"phase": "start", "ticks": 0, "ticks_training": 0, "t0": time.time(), "events": []}
    REC["steps"]["gui_cancel_resume"] = g

    def op(fn, **kw):
        with bpy.context.temp_override(window=win, area=area, region=area.regions[-1]):
            return sorted(fn(**kw))

    def progress():
        try:
            with _open(os.path.join(bpy.path.abspath(bpy.context.scene.modi.run_dir), "progress.json")) as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def tick():
        g["ticks"] += 1
        st = state()
        job = st["job"]
        running = job is not None and job.poll() is None
        try:
            if g["phase"] == "start":
                g["learn_ret"] = op(bpy.ops.modi.learn)
                g["phase"] = "training"
            elif g["phase"] == "training":
                if running:
                    g["ticks_training"] += 1
                    g.setdefault("training_since", time.time())
                    p = progress()
                    g["status_seen"] = job.status()
                    if p and p.get("state") == "training" and p.get("done_iterations", 0) >= CFG["cancel_after"]:
                        g["progress_at_cancel"] = p
                        g["cancel_ret"] = op(bpy.ops.modi.cancel)
                        g["phase"] = "cancelling"
                elif st["job"] is None:
                    g["phase"], g["error"] = "done", f"training ended before cancel: {st['result']}"
            elif g["phase"] == "cancelling" and st["job"] is None:
                g["after_cancel"] = list(st["result"])
                g["progress_after_cancel"] = progress()
                run = bpy.path.abspath(bpy.context.scene.modi.run_dir)
                g["ckpt_after_cancel"] = os.path.isfile(os.path.join(run, "ganimator.ckpt"))
                g["resume_ret"] = op(bpy.ops.modi.resume)
                g["phase"] = "resuming"
            elif g["phase"] == "resuming" and running:
                g.setdefault("resume_ticks", []).append(round(time.time(), 3))
            elif g["phase"] == "resuming" and st["job"] is None:
                g["after_resume"] = list(st["result"])
                g["progress_after_resume"] = progress()
                g["relearn_ret"] = op(bpy.ops.modi.learn)  # a new run, then Blender quits while it trains
                g["quit_run"] = bpy.path.abspath(bpy.context.scene.modi.run_dir)
                g["phase"] = "quit_while_training"
            elif g["phase"] == "quit_while_training":
                p = progress()
                if p and p.get("state") == "training" and p.get("done_iterations", 0) >= 1:
                    g["progress_before_quit"] = p
                    g["phase"] = "done"
        except Exception:
            g["error"] = traceback.format_exc()
            g["phase"] = "done"
        if g["phase"] == "done" or time.time() - g["t0"] > CFG.get("gui_timeout", 240):
            g["seconds"] = round(time.time() - g["t0"], 1)
            save()
            bpy.ops.wm.quit_blender()
            return None
        return 0.1

    bpy.app.timers.register(tick, first_interval=1.0)


try:
    ARM = setup()
    for name in CFG["steps"]:
        if name == "gui_cancel_resume":
            gui_cancel_resume(ARM)
            break  # the event loop takes over; the timer saves and quits
        t = time.time()
        key = name if name not in REC["steps"] else f"{name}#{sum(k.split('#')[0] == name for k in REC['steps']) + 1}"
        REC["steps"][key] = STEPS[name](active())
        REC["steps"][key]["seconds"] = round(time.time() - t, 2)
        save()
except Exception:
    REC["error"] = traceback.format_exc()
save()
if bpy.app.background:
    sys.exit(0)
