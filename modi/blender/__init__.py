"""modi add-on for Blender: runs the user's own ``modi`` command in a background process (torch never enters
Blender's Python) and polls it with a timer so the UI keeps running. Errors come back as one report line."""
bl_info = {
    "name": "modi motion generation",
    "author": "modi",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "View3D > Sidebar > modi",
    "description": "Learn an action with GANimator and generate variations, via the modi command",
    "category": "Animation",
}

import os
import shutil
import signal
import subprocess
import tempfile

import bpy

_RUN = {"proc": None, "out": None, "log": None, "ticks": 0, "status": ""}


def _prefs(context):
    return context.preferences.addons[__name__].preferences


class ModiPreferences(bpy.types.AddonPreferences):
    bl_idname = __name__
    modi_path: bpy.props.StringProperty(name="modi command", subtype="FILE_PATH",
                                        default=shutil.which("modi") or "modi")

    def draw(self, context):
        self.layout.prop(self, "modi_path")


def _one_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1] if lines else "modi failed without a message"


class MODI_OT_learn(bpy.types.Operator):
    """Export the selected armature's action to BVH and train GANimator on it in the background"""
    bl_idname = "modi.learn"
    bl_label = "Learn action (GANimator)"
    preset: bpy.props.EnumProperty(items=[(p, p, "") for p in ("tiny", "fast", "paper")], default="fast")
    out_dir: bpy.props.StringProperty(name="run folder", default="")

    def execute(self, context):
        obj = context.active_object
        if obj is None or obj.type != "ARMATURE":
            self.report({"ERROR"}, "select an armature with an action")
            return {"CANCELLED"}
        exe = _prefs(context).modi_path
        if not (shutil.which(exe) or os.access(exe, os.X_OK)):
            self.report({"ERROR"}, f"modi command not found: {exe!r} (set it in the add-on preferences)")
            return {"CANCELLED"}
        out = self.out_dir or tempfile.mkdtemp(prefix="modi_run_")
        os.makedirs(out, exist_ok=True)
        bvh = os.path.join(out, "source.bvh")
        bpy.ops.export_anim.bvh(filepath=bvh, root_transform_only=False)
        log = open(os.path.join(out, "modi.log"), "w")
        _RUN.update(proc=subprocess.Popen([exe, "ganimator", "train", bvh, "--out", out, "--preset", self.preset],
                                          stdout=log, stderr=subprocess.STDOUT),
                    out=out, log=log.name, ticks=0, status="training")
        bpy.app.timers.register(_poll, first_interval=0.5)
        return {"FINISHED"}


def _poll():
    _RUN["ticks"] += 1
    proc = _RUN["proc"]
    if proc is None:
        return None
    rc = proc.poll()
    try:
        with open(_RUN["log"]) as f:
            last = _one_line(f.read())
    except OSError:
        last = ""
    if rc is None:
        _RUN["status"] = last
        return 0.5
    _RUN["status"] = "done" if rc == 0 else f"modi exited {rc}: {last}"
    _RUN["proc"] = None
    return None


class MODI_OT_cancel(bpy.types.Operator):
    """Stop training: SIGTERM makes modi save a resumable checkpoint"""
    bl_idname = "modi.cancel"
    bl_label = "Cancel training"

    def execute(self, context):
        proc = _RUN["proc"]
        if proc is None:
            self.report({"WARNING"}, "no training is running")
            return {"CANCELLED"}
        proc.send_signal(signal.SIGTERM)
        return {"FINISHED"}


class MODI_PT_panel(bpy.types.Panel):
    bl_label = "modi"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "modi"

    def draw(self, context):
        col = self.layout.column()
        col.operator(MODI_OT_learn.bl_idname)
        col.operator(MODI_OT_cancel.bl_idname)
        if _RUN["status"]:
            col.label(text=_RUN["status"][:80])


_CLASSES = (ModiPreferences, MODI_OT_learn, MODI_OT_cancel, MODI_PT_panel)


def register():
    for c in _CLASSES:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(_CLASSES):
        bpy.utils.unregister_class(c)
