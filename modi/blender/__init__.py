"""modi add-on for Blender: learn an armature's action with GANimator, generate variations, loops, in-betweens,
expansions, body-part edits and harmonisations as new actions on the same armature, and sample MoDi checkpoints -- by running the user's own ``modi`` command in the background (torch
never enters Blender's Python). Found in View3D > Sidebar > modi; progress also shows in the status bar."""
bl_info = {
    "name": "modi motion generation",
    "author": "modi",
    "version": (0, 3, 0),
    "blender": (3, 4, 0),
    "location": "View3D > Sidebar > modi",
    "description": "Learn an action with GANimator, generate variations, sample MoDi, via the modi command",
    "category": "Animation",
}

import atexit
import shutil
import textwrap

import bpy

from . import operators
from .operators import STATE, status_line


class ModiPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__
    modi_path: bpy.props.StringProperty(name="modi command", subtype="FILE_PATH",
                                        default=shutil.which("modi") or "modi",
                                        description="the modi executable of your Python environment")

    def draw(self, context):
        self.layout.prop(self, "modi_path")


class ModiSettings(bpy.types.PropertyGroup):
    run_dir: bpy.props.StringProperty(name="Run", subtype="DIR_PATH",
                                      description="GANimator run folder (Learn fills it in)")
    preset: bpy.props.EnumProperty(name="Preset", default="fast", items=[
        ("tiny", "tiny", "a smoke test: seconds"), ("fast", "fast", "the CPU schedule: minutes"),
        ("paper", "paper", "the published schedule: hours")])
    iterations: bpy.props.IntProperty(name="Iterations", default=0, min=0,
                                      description="iterations per block of levels (0: the preset's)")
    conditional: bpy.props.BoolProperty(name="Trajectory-conditioned", default=False,
                                        description="learn a model that follows a root path, from the trained "
                                                    "run in Run (Generate's trajectory mode needs one)")
    n: bpy.props.IntProperty(name="Variations", default=4, min=1, max=256)
    frames: bpy.props.IntProperty(name="Frames", default=0, min=0, description="0: the learned action's length")
    seed: bpy.props.IntProperty(name="Seed", default=0, min=0)
    contact_cleanup: bpy.props.BoolProperty(name="Foot contact cleanup", default=False,
                                            description="pin feet with IK where contacts are predicted")
    mode: bpy.props.EnumProperty(name="Mode", default="random", items=[
        ("random", "random", "unconditional variations"),
        ("keyframes", "key frames", "follow the coarse poses of another action on this armature"),
        ("trajectory", "trajectory", "follow another action's root path (trajectory-conditioned runs)")])
    condition_action: bpy.props.StringProperty(name="Action", description="the action with the key frames or path")
    app: bpy.props.EnumProperty(name="Make", default="loop", items=[
        ("loop", "loop", "a loop: its last frame flows into its first"),
        ("inbetween", "in-between", "frames between the end of one action and the start of another (or of the "
                                    "same action: a cycle), both kept exactly"),
        ("expand", "expand", "a longer motion holding the action unchanged"),
        ("edit", "body part", "keep the action's upper or lower body (or the selected bones), generate the rest"),
        ("harmonise", "harmonise", "blend an action pasted together by hand into the run's style")])
    app_action: bpy.props.StringProperty(name="Action", description="the action to start from (empty: the "
                                                                     "armature's own)")
    app_to_action: bpy.props.StringProperty(name="To", description="the action to end on (empty: the From action "
                                                                   "again, which makes it a cycle)")
    app_span: bpy.props.EnumProperty(name="Keep", default="poses", items=[
        ("poses", "end poses", "the new action is the transition: the From action's last pose, the frames "
                               "between, the To action's first pose"),
        ("actions", "whole actions", "the new action holds the From action, the frames between, then the To "
                                     "action (or, for one action, its first pose again: a cycle)")])
    app_frames: bpy.props.IntProperty(name="Frames", default=60, min=0,
                                      description="loop: its length (0: the learned action's); in-between: the "
                                                  "frames between; expand: the whole length")
    loop_root: bpy.props.EnumProperty(name="Root", default="travel", items=[
        ("travel", "travel", "the root moves on with each repetition"),
        ("return", "return", "the root comes back to its start")])
    expand_at: bpy.props.IntProperty(name="At", default=-1, min=-1,
                                     description="the frame of the expanded motion where the action starts "
                                                 "(-1: centred)")
    keep: bpy.props.EnumProperty(name="Keep", default="upper", items=[
        ("upper", "upper body", "keep the spine, arms and head; generate the legs"),
        ("lower", "lower body", "keep the hips and legs; generate the upper body"),
        ("selected", "selected bones", "keep the bones selected in Pose Mode")])
    content_level: bpy.props.IntProperty(name="Level", default=1, min=0, max=64,
                                         description="the pyramid level the action enters at: 0 takes only its "
                                                     "coarse motion (style transfer), finer levels keep more of it")
    modi_checkpoint: bpy.props.StringProperty(name="Checkpoint", subtype="FILE_PATH")
    modi_n: bpy.props.IntProperty(name="Motions", default=4, min=1, max=64)
    psi: bpy.props.FloatProperty(name="Truncation (psi)", default=1.0, min=-2.0, max=2.0, subtype="FACTOR")
    modi_seed: bpy.props.IntProperty(name="Seed", default=0, min=0)
    interp_from: bpy.props.IntProperty(name="From seed", default=0, min=0)
    interp_to: bpy.props.IntProperty(name="To seed", default=1, min=0)
    interp_steps: bpy.props.IntProperty(name="Steps", default=4, min=1, max=32)
    spacing: bpy.props.FloatProperty(name="Spacing", default=2.0, min=0.0, description="X offset between armatures")


_APP_ICONS = {"loop": "FILE_REFRESH", "inbetween": "IPO_EASE_IN_OUT", "expand": "ARROW_LEFTRIGHT",
              "edit": "BONE_DATA", "harmonise": "MOD_SMOOTH"}


class MODI_PT_panel(bpy.types.Panel):
    bl_label = "modi"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "modi"

    def draw(self, context):
        s = context.scene.modi
        lay = self.layout
        running = STATE["job"] is not None and STATE["job"].poll() is None
        line = status_line()
        if line:
            box = lay.box()
            # labels do not wrap: break the line to the sidebar's width (about 7 px a character)
            width = max(20, int(context.region.width / (7 * context.preferences.system.ui_scale)) - 4)
            for k, text in enumerate(textwrap.wrap(line, width)[:6]):
                box.label(text=text, icon=("SORTTIME" if running else "INFO") if k == 0 else "BLANK1")
            if running:
                box.operator("modi.cancel", icon="CANCEL")
        col = lay.column(align=True)
        col.label(text="Learn the active action", icon="ACTION")
        col.prop(s, "preset")
        col.prop(s, "iterations")
        col.prop(s, "conditional")
        row = col.row(align=True)
        row.enabled = not running
        row.operator("modi.learn", text="Learn", icon="PLAY")
        row.operator("modi.resume", text="Resume", icon="FILE_REFRESH")
        col = lay.column(align=True)
        col.label(text="Variations (new actions)", icon="ARMATURE_DATA")
        col.prop(s, "run_dir")
        col.prop(s, "n")
        col.prop(s, "frames")
        col.prop(s, "seed")
        col.prop(s, "contact_cleanup")
        col.prop(s, "mode")
        if s.mode != "random":
            col.prop_search(s, "condition_action", bpy.data, "actions")
        sub = col.row()
        sub.enabled = not running
        sub.operator("modi.generate", text="Generate", icon="PLAY")
        col = lay.column(align=True)
        col.label(text="Loops, in-betweens, edits (new actions)", icon="ACTION_TWEAK")
        col.prop(s, "app")
        if s.app != "loop":
            col.prop_search(s, "app_action", bpy.data, "actions", text="From" if s.app == "inbetween" else "Action")
        if s.app == "inbetween":
            col.prop_search(s, "app_to_action", bpy.data, "actions")
            col.prop(s, "app_span")
        if s.app in ("loop", "inbetween", "expand"):
            col.prop(s, "app_frames", text={"loop": "Frames", "inbetween": "Frames between",
                                            "expand": "Frames in all"}[s.app])
        if s.app == "loop":
            col.prop(s, "loop_root")
        elif s.app == "expand":
            col.prop(s, "expand_at")
        elif s.app == "edit":
            col.prop(s, "keep")
        elif s.app == "harmonise":
            col.prop(s, "content_level")
        sub = col.row()
        sub.enabled = not running
        sub.operator(operators.APPLICATION_OPERATORS[s.app], icon=_APP_ICONS[s.app])
        col = lay.column(align=True)
        col.label(text="MoDi checkpoint", icon="OUTLINER_OB_ARMATURE")
        col.prop(s, "modi_checkpoint")
        col.prop(s, "modi_n")
        col.prop(s, "psi", slider=True)
        col.prop(s, "modi_seed")
        col.prop(s, "spacing")
        sub = col.row()
        sub.enabled = not running
        sub.operator("modi.sample_modi", text="Sample", icon="OUTLINER_OB_ARMATURE").interpolate = False
        col.prop(s, "interp_from")
        col.prop(s, "interp_to")
        col.prop(s, "interp_steps")
        sub = col.row()
        sub.enabled = not running
        sub.operator("modi.sample_modi", text="Interpolate", icon="IPO_EASE_IN_OUT").interpolate = True


_CLASSES = (ModiPreferences, ModiSettings, *operators.CLASSES, MODI_PT_panel)


def register():
    for c in _CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.modi = bpy.props.PointerProperty(type=ModiSettings)
    atexit.register(operators.stop_running_job)  # Blender quits: a running training saves and stops


def unregister():
    atexit.unregister(operators.stop_running_job)
    operators.stop_running_job()
    del bpy.types.Scene.modi
    for c in reversed(_CLASSES):
        bpy.utils.unregister_class(c)
