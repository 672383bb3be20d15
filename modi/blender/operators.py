"""The add-on's operators: Learn / Resume / Cancel (GANimator training), Generate (variations as actions on the
same armature), the applications Loop / In-between / Expand / Edit Body Part / Harmonise (new actions made from
the scene's actions), Sample MoDi (armatures from a MoDi checkpoint), all through the user's ``modi`` command.

Each operator starts one background ``modi`` process and is modal on a window timer, so Blender's UI keeps
running; under ``blender -b`` (no event loop) it waits for the process instead, so scripts work the same way. A
failure of any kind ends the operator with ``CANCELLED`` and one line in the report area.
"""
from __future__ import annotations

import glob
import json
import os
import re
import shutil
import tempfile

import bpy

from . import jobs, rig_io

ADDON = __package__
# the running job (one at a time) and the last outcome, for the panel, the status bar and scripts
STATE = {"job": None, "last": "", "result": None}


# ------------------------------------------------------------------------------------------------- helpers
Refused = jobs.Refused  # an operator cannot start; the message is its one report line


def modi_command(context) -> str:
    prefs = context.preferences.addons[ADDON].preferences
    exe = bpy.path.abspath(prefs.modi_path.strip()) if prefs.modi_path.strip() else ""
    found = shutil.which(exe) if exe else None
    if not found and exe and os.path.isfile(exe) and os.access(exe, os.X_OK):
        found = exe
    if not found:
        raise Refused(f"modi command not found: {exe or '(empty)'!r}; set its path in the modi add-on's "
                      "preferences (the output of 'which modi' in your environment)")
    return found


def active_armature(context, need_action: bool = True):
    obj = context.active_object
    if obj is None or obj.type != "ARMATURE":
        raise Refused("select an armature" + (" with an action" if need_action else ""))
    if need_action and (obj.animation_data is None or obj.animation_data.action is None):
        raise Refused(f"armature {obj.name!r} has no action to learn (import or key one first)")
    return obj


def frame_span(action) -> tuple[int, int]:
    """The frames of ``action`` to export: its frame range, less the closing frame of a cyclic one (that frame
    *is* the first again)."""
    lo, hi = action.frame_range
    lo, hi = int(round(lo)), int(round(hi))
    if getattr(action, "use_cyclic", False) and getattr(action, "use_frame_range", False) and hi > lo:
        hi -= 1
    return lo, hi


def scene_fps(scene) -> float:
    return scene.render.fps / scene.render.fps_base


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "motion"


def runs_root() -> str:
    """Run folders go beside the saved .blend (``//modi_runs``), else into the system's temp folder."""
    if bpy.data.filepath:
        return bpy.path.abspath("//modi_runs")
    return os.path.join(tempfile.gettempdir(), "modi_runs")


def new_folder(root: str, stem: str) -> str:
    os.makedirs(root, exist_ok=True)
    for k in range(1, 10000):
        path = os.path.join(root, f"{_slug(stem)}_{k:03d}")
        try:
            os.mkdir(path)
            return path
        except FileExistsError:
            continue
    raise Refused(f"{root}: no free run folder name")


def export_action(obj, scene, action, path: str) -> int:
    """Export ``action`` played on ``obj`` (restoring the armature's own action afterwards)."""
    keep = obj.animation_data.action
    keep_slot = getattr(obj.animation_data, "action_slot", None)
    rig_io.assign_action(obj, action)
    try:
        lo, hi = frame_span(action)
        return rig_io.export_action_bvh(obj, scene, path, lo, hi)
    finally:
        obj.animation_data.action = keep
        if keep_slot is not None:
            obj.animation_data.action_slot = keep_slot


def _redraw() -> None:
    wm = bpy.context.window_manager
    for win in getattr(wm, "windows", []):
        for area in win.screen.areas:
            area.tag_redraw()


def _status_bar(context, text) -> None:
    """The status bar's text while a job runs (what modal tools use; None gives the bar back)."""
    ws = getattr(context, "workspace", None)
    if ws is not None:
        ws.status_text_set(text)


def status_line() -> str:
    job = STATE["job"]
    return job.status() if job is not None and job.poll() is None else STATE["last"]


# ------------------------------------------------------------------------------------------------- the modal base
class _ModiJob:
    """Start a job, poll it modally (UI) or wait for it (``blender -b``), then ``finish`` on success. Operators
    implement ``run(context)``; ``execute`` wraps it."""

    def start(self, context, job: jobs.Job, finish=None):
        STATE["job"] = job
        STATE["last"] = job.status()
        self._job, self._finish = job, finish
        if bpy.app.background:
            job.wait()
            return self.end(context)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.25, window=context.window)
        wm.modal_handler_add(self)
        _redraw()
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "TIMER":
            done = self._job.poll() is not None
            _status_bar(context, None if done else "modi " + self._job.status())
            _redraw()
            if done:
                context.window_manager.event_timer_remove(self._timer)
                return self.end(context)
        return {"PASS_THROUGH"}

    def end(self, context):
        job = self._job
        STATE["job"] = None
        if job.returncode != 0:
            return self.refuse(job.outcome(), "WARNING" if job.returncode == jobs.SIGTERM_EXIT else "ERROR")
        try:
            message = self._finish(context) if self._finish else job.outcome()
        except (rig_io.RigError, Refused, RuntimeError, OSError) as e:
            return self.refuse(str(e).splitlines()[0] if str(e) else e.__class__.__name__)
        except Exception as e:  # noqa: BLE001 -- importing the result failed: one line, not a traceback
            return self.refuse(f"modi add-on: importing the result failed: {e.__class__.__name__}: {e}")
        STATE["last"] = message
        STATE["result"] = ("FINISHED", message)
        self.report({"INFO"}, message)
        _redraw()
        return {"FINISHED"}

    def refuse(self, message: str, level: str = "ERROR"):
        message = " ".join(message.split())  # one line, whatever the source
        STATE["last"] = message
        STATE["result"] = ("CANCELLED", message)
        self.report({level}, message)
        _redraw()
        return {"CANCELLED"}

    def execute(self, context):
        """One job at a time, then ``run``; whatever goes wrong ends as one report line and CANCELLED, never a
        traceback in the console (a job this operator started is stopped: its run folder stays resumable)."""
        try:
            return self.run(context)
        except (Refused, rig_io.RigError, RuntimeError, OSError) as e:  # the expected refusals: their own line
            return self._abandon(str(e))
        except Exception as e:  # noqa: BLE001 -- the operator's contract is one line, whatever failed
            return self._abandon(f"modi add-on: {e.__class__.__name__}: {e}")

    def _abandon(self, message: str):
        job = getattr(self, "_job", None)
        if job is not None and job.poll() is None:
            job.cancel()
        return self.refuse(message)

    def busy(self) -> bool:
        job = STATE["job"]
        return job is not None and job.poll() is None


SETTINGS_NAME = "modi_addon.json"  # RUN/modi_addon.json: the training flags, so Resume passes the same ones


def _run_train(op, context, run: str, flags: list):
    argv = [modi_command(context), "ganimator", "train", os.path.join(run, "source.bvh"), "--out", run, *flags]
    job = jobs.Job("training", argv, os.path.join(run, "modi_train.log"),
                   progress_path=os.path.join(run, "progress.json"), env=jobs.modi_env())
    context.scene.modi.run_dir = run
    return op.start(context, job, lambda ctx: f"trained: {os.path.basename(run)}")


def _has_checkpoint(run: str) -> bool:
    return bool(run) and os.path.isfile(os.path.join(run, "ganimator.ckpt"))


class MODI_OT_learn(_ModiJob, bpy.types.Operator):
    """Export the active armature's action and train GANimator on it in the background"""
    bl_idname = "modi.learn"
    bl_label = "Learn Action"

    def run(self, context):
        s = context.scene.modi
        modi_command(context)  # fail before exporting anything
        obj = active_armature(context)
        action = obj.animation_data.action
        flags = ["--preset", s.preset, "--fps", str(max(1, int(round(scene_fps(context.scene)))))]
        if s.iterations > 0:
            flags += ["--iterations", str(s.iterations)]
        if s.conditional:
            base = bpy.path.abspath(s.run_dir)
            if not _has_checkpoint(base):
                raise Refused("a trajectory-conditioned run learns from a trained run: Learn the action "
                              "once without the option, then again with it (Run must hold that first run)")
            flags += ["--conditional-from", base]
        run = new_folder(runs_root(), f"{obj.name}_{action.name}" + ("_traj" if s.conditional else ""))
        export_action(obj, context.scene, action, os.path.join(run, "source.bvh"))
        with open(os.path.join(run, SETTINGS_NAME), "w") as fh:
            json.dump({"flags": flags, "armature": obj.name, "action": action.name}, fh, indent=1)
        return _run_train(self, context, run, flags)


class MODI_OT_resume(_ModiJob, bpy.types.Operator):
    """Continue the run folder's training where it stopped (with the flags it was started with)"""
    bl_idname = "modi.resume"
    bl_label = "Resume Training"

    def run(self, context):
        run = bpy.path.abspath(context.scene.modi.run_dir)
        try:
            with open(os.path.join(run, SETTINGS_NAME)) as fh:
                flags = [str(f) for f in json.load(fh)["flags"]]
        except (OSError, ValueError, KeyError, TypeError):
            return self.refuse(f"{run or '(no run folder)'}: not a run the add-on started (no readable "
                               f"{SETTINGS_NAME}); resume it with 'modi ganimator train' and its own flags")
        return _run_train(self, context, run, flags)


class MODI_OT_cancel(bpy.types.Operator):
    """Stop the running modi command (training saves a resumable checkpoint first)"""
    bl_idname = "modi.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        job = STATE["job"]
        if job is None or not job.cancel():
            self.report({"WARNING"}, "modi is not running")
            return {"CANCELLED"}
        STATE["last"] = f"{job.kind}: stopping (saving the checkpoint)"
        return {"FINISHED"}


class MODI_OT_generate(_ModiJob, bpy.types.Operator):
    """Generate variations from the trained run, each a new action on the active armature"""
    bl_idname = "modi.generate"
    bl_label = "Generate Variations"

    def run(self, context):
        s = context.scene.modi
        exe = modi_command(context)
        obj = active_armature(context, need_action=False)
        run = bpy.path.abspath(s.run_dir)
        if not _has_checkpoint(run):
            raise Refused(f"{run or '(no run folder)'}: no trained run here (Learn an action first)")
        out = new_folder(os.path.join(run, "variations"), f"seed{s.seed}")
        extra = ["--frames", str(s.frames)] if s.frames > 0 else []
        if s.mode != "random":
            action = bpy.data.actions.get(s.condition_action)
            if action is None:
                raise Refused(f"choose the action that holds the {s.mode} (not found: {s.condition_action!r})")
            cond = os.path.join(out, f"{s.mode}.bvh")
            export_action(obj, context.scene, action, cond)
            extra += [f"--{s.mode}", cond]
        argv = jobs.generate_argv(exe, run, out, n=s.n, seed=s.seed, ik=s.contact_cleanup, extra=extra)
        base = obj.animation_data.action.name if obj.animation_data and obj.animation_data.action else obj.name
        seed, start = s.seed, context.scene.frame_start
        job = jobs.Job("generating", argv, os.path.join(out, "modi_generate.log"), env=jobs.modi_env())
        return self.start(context, job, lambda ctx: _import_results(obj, out, f"{base}.modi", seed, start))


def _import_results(obj, out: str, stem: str, seed: int, start: int, cyclic: bool = False) -> str:
    """Every ``sample*.bvh`` modi wrote to ``out`` as a new action ``<stem>.s<seed>.<i>`` on ``obj`` (the stem
    shortened to fit Blender's name length), keyed from
    scene frame ``start``; the armature plays the first. Returns the report line."""
    files = sorted(glob.glob(os.path.join(out, "sample*.bvh")))
    if not files:
        raise Refused(f"{out}: modi wrote no BVH")
    made = []
    for i, path in enumerate(files):
        bvh = rig_io.read_bvh(path)
        act = rig_io.action_from_bvh(obj, bvh, jobs.action_name(stem, seed, i), start)
        act["modi_bvh"] = path  # the file it came from
        if cyclic:
            rig_io.set_cycle(act, start, bvh.n_frames)
        made.append(act.name)
    rig_io.assign_action(obj, bpy.data.actions[made[0]])
    return f"{len(made)} new action(s) on {obj.name}: {made[0]}" + (f" .. {made[-1]}" if len(made) > 1 else "")


# ------------------------------------------------------------------------------------------------- applications
def _selected_bones(obj) -> list:
    """The armature's selected bones (Pose Mode's selection: on the pose bone in 5.0, on the bone before)."""
    out = []
    for pb in obj.pose.bones:
        sel = pb.select if hasattr(pb, "select") else pb.bone.select
        if sel:
            out.append(pb.name)
    return out


def _action_for(obj, name: str, role: str):
    """The action ``name`` (empty: the armature's own), refused unless it animates this armature's bones."""
    if name:
        action = bpy.data.actions.get(name)
        if action is None:
            raise Refused(f"{role}: there is no action named {name!r}")
    else:
        action = obj.animation_data.action if obj.animation_data else None
        if action is None:
            raise Refused(f"armature {obj.name!r} has no action; give it one, or choose the {role.lower()} action")
    jobs.check_action_on_rig(action.name, [fc.data_path for fc in rig_io.action_fcurves(action)],
                             [b.name for b in obj.data.bones], obj.name)
    return action


class _Application(_ModiJob):
    """An application of the trained run in *Run* to the scene's actions (``app``: one of ``jobs.APPLICATIONS``):
    the actions ``jobs.plan`` names are exported next to modi's output, ``modi ganimator generate`` runs with the
    plan's flags, and each motion it writes comes back as a new action on the armature."""
    app = ""

    def run(self, context):
        s = context.scene.modi
        exe = modi_command(context)
        obj = active_armature(context, need_action=False)
        run = bpy.path.abspath(s.run_dir)
        if not _has_checkpoint(run):
            raise Refused(f"{run or '(no run folder)'}: no trained run here (Learn an action first)")
        rig_io.bone_order(obj)  # one root bone, BVH-safe names
        jobs.check_run_rig(jobs.bvh_joint_names(os.path.join(run, "source.bvh")), [b.name for b in obj.data.bones],
                           obj.name, run)
        if self.app == "loop":  # from the run alone: named after the action it learned
            own = obj.animation_data.action if obj.animation_data and obj.animation_data.action else None
            info = (_learned_action(run) or (own.name if own else obj.name), 0, 0)
            to = None
        else:
            info = _action_info(_action_for(obj, s.app_action, "From" if self.app == "inbetween" else "Action"))
            to = (_action_info(_action_for(obj, s.app_to_action, "To"))
                  if self.app == "inbetween" and s.app_to_action else None)
        plan = jobs.plan(self.app, info, to_action=to, frames=s.app_frames, span=s.app_span, loop_root=s.loop_root,
                         at=s.expand_at, keep=s.keep, selected=_selected_bones(obj) if s.keep == "selected" else (),
                         level=s.content_level)
        out = new_folder(os.path.join(run, "variations"), f"{self.app}_seed{s.seed}")
        for fname, aname in plan.exports.items():
            export_action(obj, context.scene, bpy.data.actions[aname], os.path.join(out, fname))
        argv = jobs.generate_argv(exe, run, out, n=s.n, seed=s.seed, ik=s.contact_cleanup, extra=plan.flags(out))
        seed = s.seed
        start = context.scene.frame_start if plan.frame_start is None else plan.frame_start
        job = jobs.Job("generating", argv, os.path.join(out, "modi_generate.log"), env=jobs.modi_env())
        return self.start(context, job, lambda ctx: _import_results(obj, out, plan.stem, seed, start, plan.cyclic))


def _learned_action(run: str) -> str | None:
    """The action a run the add-on started learned (``RUN/modi_addon.json``), else None."""
    try:
        with open(os.path.join(run, SETTINGS_NAME)) as fh:
            name = json.load(fh).get("action")
    except (OSError, ValueError, AttributeError):
        return None
    return name if isinstance(name, str) and name else None


def _action_info(action) -> tuple:
    return (action.name, *frame_span(action))


class MODI_OT_loop(_Application, bpy.types.Operator):
    """A loop from the trained run: Frames frames whose last flows into the first (the new action is marked
    cyclic)"""
    bl_idname = "modi.loop"
    bl_label = "Loop"
    app = "loop"


class MODI_OT_inbetween(_Application, bpy.types.Operator):
    """Frames between the end of one action and the start of another (or of the same: a cycle), both kept
    exactly"""
    bl_idname = "modi.inbetween"
    bl_label = "In-between"
    app = "inbetween"


class MODI_OT_expand(_Application, bpy.types.Operator):
    """A longer motion that holds the action unchanged at its place"""
    bl_idname = "modi.expand"
    bl_label = "Expand"
    app = "expand"


class MODI_OT_edit_part(_Application, bpy.types.Operator):
    """Keep the action's upper or lower body (or the selected bones) and generate the rest to go with it"""
    bl_idname = "modi.edit_part"
    bl_label = "Edit Body Part"
    app = "edit"


class MODI_OT_harmonise(_Application, bpy.types.Operator):
    """Blend an action (e.g. pasted together by hand) into the run's style from a pyramid level"""
    bl_idname = "modi.harmonise"
    bl_label = "Harmonise"
    app = "harmonise"


APPLICATION_OPERATORS = {"loop": "modi.loop", "inbetween": "modi.inbetween", "expand": "modi.expand",
                         "edit": "modi.edit_part", "harmonise": "modi.harmonise"}


class MODI_OT_sample_modi(_ModiJob, bpy.types.Operator):
    """Sample a MoDi checkpoint (seeds with truncation, or an interpolation) as armatures with actions"""
    bl_idname = "modi.sample_modi"
    bl_label = "Sample MoDi"

    interpolate: bpy.props.BoolProperty(name="Interpolate", default=False)

    def run(self, context):
        s = context.scene.modi
        exe = modi_command(context)
        ckpt = bpy.path.abspath(s.modi_checkpoint)
        if not os.path.isfile(ckpt):
            raise Refused(f"{ckpt or '(no checkpoint)'}: choose a MoDi checkpoint ('modi train' writes one)")
        out = new_folder(os.path.join(os.path.dirname(ckpt), "blender_samples"),
                         "interp" if self.interpolate else f"psi{s.psi:.2f}_seed{s.modi_seed}")
        if self.interpolate:
            argv = [exe, "latent", "interpolate", ckpt, "--from", str(s.interp_from), "--to", str(s.interp_to),
                    "--steps", str(s.interp_steps), "--format", "glb", "--no-view", "--out", out]
        else:
            argv = [exe, "generate", ckpt, "--n", str(s.modi_n), "--psi", f"{s.psi:g}", "--seed", str(s.modi_seed),
                    "--format", "glb", "--gif-max", "0", "--no-view", "--out", out]
        job = jobs.Job("sampling", argv, os.path.join(out, "modi_sample.log"), env=jobs.modi_env())
        spacing = s.spacing
        label = "interp" if self.interpolate else f"psi{s.psi:g}.s{s.modi_seed:04d}"

        def finish(ctx):
            files = sorted(glob.glob(os.path.join(out, "**", "*.glb"), recursive=True))
            if not files:
                raise Refused(f"{out}: modi wrote no glTF")
            made = []
            for i, path in enumerate(files):
                before = set(bpy.data.objects)
                bpy.ops.import_scene.gltf(filepath=path)
                new = [o for o in bpy.data.objects if o not in before]
                arms = [o for o in new if o.type == "ARMATURE"]
                if not arms:
                    raise Refused(f"{path}: no armature in the file")
                roots = [o for o in new if o.parent is None]
                for o in roots:
                    o.location.x += i * spacing
                arm = arms[0]
                arm.name = f"modi.{label}.{i:03d}"
                arm["modi_glb"] = path
                made.append(arm.name)
            return f"{len(made)} MoDi armature(s): {made[0]}" + (f" .. {made[-1]}" if len(made) > 1 else "")

        return self.start(context, job, finish)


def stop_running_job(wait: float = 20.0) -> None:
    """Blender is quitting or the add-on is being disabled: SIGTERM the running job (training saves a resumable
    checkpoint first) and give it ``wait`` seconds, so no orphaned modi keeps running unseen."""
    job = STATE["job"]
    if job is not None and job.poll() is None:
        job.cancel()
        job.wait(timeout=wait)
    STATE["job"] = None


CLASSES = (MODI_OT_learn, MODI_OT_resume, MODI_OT_cancel, MODI_OT_generate, MODI_OT_loop, MODI_OT_inbetween,
           MODI_OT_expand, MODI_OT_edit_part, MODI_OT_harmonise, MODI_OT_sample_modi)
__all__ = ["STATE", "CLASSES", "APPLICATION_OPERATORS", "status_line", "stop_running_job", "Refused"]
