"""Armature <-> BVH inside Blender, with nothing but ``mathutils``: the add-on's own exporter and importer.

Why not Blender's ``export_anim.bvh`` / ``import_anim.bvh``: the exporter writes Blender's Z-up armature space as
is (modi expects Y-up BVH: its ground, contacts and heights read the Y axis), the 3.4 importer cannot open files on
Python 3.11 (``open(..., 'rU')``), and an imported BVH makes a *new* armature whose bone rolls differ from a
Mixamo/FBX rig. Here a motion is carried by each joint's *global* rotation relative to the rest pose, which does
not depend on bone rolls: the exporter writes ``G_j = W_j @ R_j^-1`` (pose and rest world matrices of the bone),
the importer sets ``W_j = G_j @ R_j`` on the very bones that were exported, so a generated BVH lands on the
user's armature exactly (same bone names; no retargeting). Axes: Blender (X, Y, Z) = BVH (X, -Z, Y), the
convention of Blender's own BVH importer (forward -Z, up Y).
"""
from __future__ import annotations

import math
import re

from mathutils import Euler, Matrix, Vector

# Blender world -> BVH (Y up): (X, Y, Z) -> (X, Z, -Y); its inverse is its transpose.
TO_BVH = Matrix(((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)))
FROM_BVH = TO_BVH.transposed()


class RigError(ValueError):
    """A rig or file the add-on cannot carry through (one line, shown in Blender's report area)."""


def joint_name(bone_name: str) -> str:
    """BVH joint names are whitespace-separated tokens: spaces and tabs in a bone name become '_'."""
    return re.sub(r"\s+", "_", bone_name.strip()) or "_"


def bone_order(obj) -> list:
    """The armature object's bones depth first from its one root (BVH has one root joint)."""
    roots = [b for b in obj.data.bones if b.parent is None]
    if len(roots) != 1:
        raise RigError(f"armature {obj.name!r} has {len(roots)} root bones; modi needs exactly one "
                       "(parent the others under one root bone)")
    out, stack = [], [roots[0]]
    while stack:
        b = stack.pop()
        out.append(b)
        stack.extend(reversed(list(b.children)))
    names = [joint_name(b.name) for b in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise RigError(f"bone names {dup} are the same once spaces become '_' (BVH joint names are single words)")
    return out


def _fmt(v) -> str:
    return " ".join(f"{x:.6f}" for x in v)


def export_action_bvh(obj, scene, path: str, frame_start: int, frame_end: int) -> int:
    """Write the armature ``obj``'s current animation over ``frame_start..frame_end`` as a Y-up BVH (every bone;
    position channels on the root and on every bone whose head moves against its parent, as a BVH whose every
    joint has 6 channels imports). Returns the number of frames written."""
    if frame_end < frame_start:
        raise RigError(f"no frames to export ({frame_start}..{frame_end})")
    bones = bone_order(obj)
    index = {b.name: i for i, b in enumerate(bones)}
    parent = [index[b.parent.name] if b.parent else -1 for b in bones]
    M = obj.matrix_world.copy()
    rest_head = [M @ b.head_local for b in bones]
    rest_rot_inv = [(M @ b.matrix_local).to_3x3().inverted_safe() for b in bones]
    offsets = [TO_BVH @ (rest_head[i] - (rest_head[parent[i]] if parent[i] >= 0 else Vector())) for i in
               range(len(bones))]
    # pass 1: every frame's local rotation (Euler Z Y X) and position in the parent's frame, per bone
    prev = [Euler((0.0, 0.0, 0.0), "XYZ") for _ in bones]
    frames = []
    keep = scene.frame_current
    try:
        for f in range(frame_start, frame_end + 1):
            scene.frame_set(f)
            glob, heads, row = [], [], []
            for i, b in enumerate(bones):
                pb = obj.pose.bones[b.name]
                g_world = (M @ pb.matrix).to_3x3() @ rest_rot_inv[i]
                g = (TO_BVH @ g_world @ FROM_BVH).to_quaternion().to_matrix()  # drop scale: a pure rotation
                glob.append(g)
                heads.append(TO_BVH @ (M @ pb.head))
                p = parent[i]
                local = g if p < 0 else glob[p].transposed() @ g
                e = local.to_euler("XYZ", prev[i])  # Blender 'XYZ' = Rz @ Ry @ Rx = channels Z Y X
                prev[i] = e
                t = heads[i] if p < 0 else glob[p].transposed() @ (heads[i] - heads[p])
                row.append((t, e))
            frames.append(row)
    finally:
        scene.frame_set(keep)
    scale = max([v.length for v in offsets] + [1e-9])
    moves = [parent[i] < 0 or any((row[i][0] - offsets[i]).length > 1e-6 * scale for row in frames)
             for i in range(len(bones))]
    lines = ["HIERARCHY"]

    def write(i: int, depth: int) -> None:
        b, ind = bones[i], "\t" * depth
        lines.append(f"{ind}{'ROOT' if parent[i] < 0 else 'JOINT'} {joint_name(b.name)}")
        chans = ("CHANNELS 6 Xposition Yposition Zposition " if moves[i] else "CHANNELS 3 ") + \
            "Zrotation Yrotation Xrotation"
        lines.extend([f"{ind}{{", f"{ind}\tOFFSET {_fmt(offsets[i])}", f"{ind}\t{chans}"])
        kids = [index[c.name] for c in b.children]
        for k in kids:
            write(k, depth + 1)
        if not kids:
            tail = TO_BVH @ ((M @ b.tail_local) - rest_head[i])
            lines.extend([f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {_fmt(tail)}", f"{ind}\t}}"])
        lines.append(f"{ind}}}")

    write(0, 0)
    fps = scene.render.fps / scene.render.fps_base
    lines += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {1.0 / fps:.6f}"]
    for row in frames:
        out = []
        for i, (t, e) in enumerate(row):
            if moves[i]:
                out.append(_fmt(t))
            out.append(" ".join(f"{math.degrees(a):.6f}" for a in (e.z, e.y, e.x)))
        lines.append(" ".join(out))
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return len(frames)


# ------------------------------------------------------------------------------------------------- reading
class Bvh:
    """A parsed BVH: joints (names, parents, offsets, channels), frame time and the motion rows."""

    def __init__(self, names, parents, offsets, channels, frame_time, motion):
        self.names, self.parents, self.offsets, self.channels = names, parents, offsets, channels
        self.frame_time, self.motion = frame_time, motion

    @property
    def n_frames(self) -> int:
        return len(self.motion)

    def pose(self, frame: int) -> tuple[list, list]:
        """Global rotations (3x3, BVH axes, relative to the rest pose) and positions of every joint at ``frame``;
        position channels replace the OFFSET's components, as ``modi export positions`` reads them."""
        row, col = self.motion[frame], 0
        rots, pos = [], []
        for j, chans in enumerate(self.channels):
            t = list(self.offsets[j])
            order, angles = "", []
            for c in chans:
                v = row[col]
                col += 1
                axis = "XYZ".index(c[0])
                if c.endswith("position"):
                    t[axis] = v
                else:
                    order += c[0]
                    angles.append(math.radians(v))
            local = Matrix.Identity(3)
            for axis, a in zip(order, angles):  # channel order = left-to-right product
                local = local @ Matrix.Rotation(a, 3, axis)
            p = self.parents[j]
            if p < 0:
                rots.append(local)
                pos.append(Vector(t))
            else:
                rots.append(rots[p] @ local)
                pos.append(pos[p] + rots[p] @ Vector(t))
        return rots, pos


def read_bvh(path: str) -> Bvh:
    """Parse a BVH file (the subset every exporter writes: one ROOT, JOINT/End Site, CHANNELS, MOTION)."""
    try:
        with open(path) as fh:
            text = fh.read()
    except OSError as e:
        raise RigError(f"{path}: cannot read ({e.strerror})") from None
    tok = text.split()
    names, parents, offsets, channels, stack = [], [], [], [], []
    i, end_site = 0, False
    try:
        if tok[0] != "HIERARCHY":
            raise RigError(f"{path}: not a BVH file (no HIERARCHY)")
        i = 1
        while tok[i] != "MOTION":
            t = tok[i]
            if t in ("ROOT", "JOINT"):
                names.append(tok[i + 1])
                parents.append(stack[-1] if stack else -1)
                i += 2
            elif t == "End":
                end_site, i = True, i + 2
            elif t == "{":
                stack.append(-2 if end_site else len(names) - 1)
                end_site, i = False, i + 1
            elif t == "}":
                stack.pop()
                i += 1
            elif t == "OFFSET":
                if stack and stack[-1] != -2:
                    offsets.append([float(x) for x in tok[i + 1:i + 4]])
                i += 4
            elif t == "CHANNELS":
                n = int(tok[i + 1])
                channels.append(tok[i + 2:i + 2 + n])
                i += 2 + n
            else:
                raise RigError(f"{path}: unexpected {t!r} in the hierarchy")
        n_frames = int(tok[i + 2])
        frame_time = float(tok[i + 5])
        vals = [float(x) for x in tok[i + 6:]]
    except (IndexError, ValueError) as e:
        if isinstance(e, RigError):
            raise
        raise RigError(f"{path}: malformed BVH ({e.__class__.__name__}: {e})") from None
    width = sum(len(c) for c in channels)
    if len(offsets) != len(names) or len(channels) != len(names):
        raise RigError(f"{path}: malformed BVH (joints without OFFSET or CHANNELS)")
    if width == 0 or len(vals) != n_frames * width:
        raise RigError(f"{path}: {len(vals)} motion values for {n_frames} frames of {width} channels")
    motion = [vals[k * width:(k + 1) * width] for k in range(n_frames)]
    return Bvh(names, parents, offsets, channels, frame_time, motion)


# ------------------------------------------------------------------------------------------------- applying
def _fcurve_maker(action, obj):
    """``new(path, index, group)`` for a fresh ``action`` meant for ``obj``: in a slot for ``obj`` where Blender
    has slotted actions (4.4+; 5.0 has nothing else), else in the action's own F-curve list (3.x to 4.3)."""
    if not hasattr(action, "slots"):
        return lambda path, index, group: action.fcurves.new(path, index=index, action_group=group)
    slot = action.slots.new(id_type="OBJECT", name=obj.name)
    bag = action.layers.new("modi").strips.new(type="KEYFRAME").channelbag(slot, ensure=True)
    groups = {}

    def new(path, index, group):
        fc = bag.fcurves.new(path, index=index)
        if group not in groups:
            groups[group] = bag.groups.new(group)
        fc.group = groups[group]
        return fc

    return new


def assign_action(obj, action) -> None:
    """Play ``action`` on ``obj`` (and, with slotted actions, in the action's first slot when Blender picked
    none)."""
    if obj.animation_data is None:
        obj.animation_data_create()
    ad = obj.animation_data
    ad.action = action
    if action is not None and hasattr(ad, "action_slot") and ad.action_slot is None and len(action.slots):
        ad.action_slot = action.slots[0]


def _fill(fc, frames: list, values: list) -> None:
    fc.keyframe_points.add(len(frames))
    co = [0.0] * (2 * len(frames))
    co[0::2] = frames
    co[1::2] = values
    fc.keyframe_points.foreach_set("co", co)
    for kp in fc.keyframe_points:
        kp.interpolation = "LINEAR"
    fc.update()


def action_from_bvh(obj, bvh: Bvh, name: str, frame_start: int = 1):
    """A new action on armature ``obj`` that plays ``bvh`` (joints matched to bones by name, see
    :func:`joint_name`, or by the name without its namespace prefix; bones the file lacks keep their rest pose relative to their parent). Every bone the file
    has gets location and rotation keys in its own rotation mode."""
    bones = bone_order(obj)
    by_joint = {joint_name(b.name): b for b in bones}
    # a namespace prefix ('mixamorig:Hips') may be gone from the file (modi's reader drops it): match the rest too,
    # where that is unambiguous
    bare = {}
    for b in bones:
        bare.setdefault(joint_name(b.name).rsplit(":", 1)[-1], []).append(b)
    for n, bs in bare.items():
        if len(bs) == 1:
            by_joint.setdefault(n, bs[0])
    missing = [n for n in bvh.names if n not in by_joint]
    if missing:
        raise RigError(f"the BVH's joints {missing[:5]} are not bones of {obj.name!r} (it was made for another rig)")
    joint_of = {by_joint[n].name: j for j, n in enumerate(bvh.names)}
    M = obj.matrix_world
    M_inv = M.inverted_safe()
    rest = {b.name: b.matrix_local for b in bones}
    rest_world3 = {b.name: (M @ b.matrix_local).to_3x3() for b in bones}
    rest_rel_inv = {b.name: (rest[b.parent.name].inverted_safe() @ rest[b.name]).inverted_safe() if b.parent else
                    rest[b.name].inverted_safe() for b in bones}
    keyed = [b for b in bones if b.name in joint_of]
    frames = [float(frame_start + k) for k in range(bvh.n_frames)]
    loc = {b.name: [[], [], []] for b in keyed}
    rot = {b.name: [] for b in keyed}
    prev_q = {b.name: None for b in keyed}
    prev_e = {b.name: None for b in keyed}
    for k in range(bvh.n_frames):
        g_bvh, p_bvh = bvh.pose(k)
        pose = {}
        for b in bones:
            j = joint_of.get(b.name)
            if j is None:  # not in the file: rigid with its parent (basis = identity)
                pose[b.name] = pose[b.parent.name] @ (rest[b.parent.name].inverted_safe() @ rest[b.name])
                continue
            g = FROM_BVH @ g_bvh[j] @ TO_BVH
            w = (g @ rest_world3[b.name]).to_4x4()
            w.translation = FROM_BVH @ p_bvh[j]
            pose[b.name] = M_inv @ w
            parent = pose[b.parent.name] if b.parent else Matrix.Identity(4)
            basis = rest_rel_inv[b.name] @ parent.inverted_safe() @ pose[b.name]
            t, q, _s = basis.decompose()
            for a in range(3):
                loc[b.name][a].append(t[a])
            mode = obj.pose.bones[b.name].rotation_mode
            if prev_q[b.name] is not None and q.dot(prev_q[b.name]) < 0:
                q = -q  # the shorter way: no flips between keys
            prev_q[b.name] = q
            if mode == "QUATERNION":
                rot[b.name].append(tuple(q))
            elif mode == "AXIS_ANGLE":
                axis, angle = q.to_axis_angle()
                rot[b.name].append((angle, *axis))
            else:
                e = q.to_euler(mode, prev_e[b.name]) if prev_e[b.name] is not None else q.to_euler(mode)
                prev_e[b.name] = e
                rot[b.name].append(tuple(e))
    action = bpy_actions().new(name)
    action.use_fake_user = True  # kept in the .blend though only one action is assigned at a time
    new_fcurve = _fcurve_maker(action, obj)
    for b in keyed:
        base = f'pose.bones["{b.name}"]'
        for a in range(3):
            _fill(new_fcurve(base + ".location", a, b.name), frames, loc[b.name][a])
        mode = obj.pose.bones[b.name].rotation_mode
        prop, width = {"QUATERNION": ("rotation_quaternion", 4), "AXIS_ANGLE": ("rotation_axis_angle", 4)}.get(
            mode, ("rotation_euler", 3))
        for a in range(width):
            _fill(new_fcurve(f"{base}.{prop}", a, b.name), frames, [r[a] for r in rot[b.name]])
    return action


def action_fcurves(action) -> list:
    """Every F-curve of ``action``: its layers' channel bags where Blender has slotted actions (4.4+; 5.0 has
    nothing else), else the action's own list (3.x to 4.3)."""
    out = []
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            for bag in getattr(strip, "channelbags", ()):
                out.extend(bag.fcurves)
    if not out and hasattr(action, "fcurves"):
        out.extend(action.fcurves)
    return out


def set_cycle(action, first: int, n_frames: int) -> None:
    """Mark ``action`` (keys on ``first .. first + n_frames - 1``) as a cycle: its manual frame range ends on
    ``first + n_frames``, the frame that *is* ``first`` again (Blender's convention for cyclic actions), so an NLA
    strip repeating it, or a scene range of ``first .. first + n_frames - 1``, plays the loop with no frame twice."""
    if hasattr(action, "use_cyclic"):  # 3.1+
        action.use_frame_range = True
        action.frame_start, action.frame_end = first, first + n_frames
        action.use_cyclic = True


def bpy_actions():
    import bpy

    return bpy.data.actions


__all__ = ["RigError", "Bvh", "read_bvh", "export_action_bvh", "action_from_bvh", "assign_action", "joint_name",
           "bone_order", "action_fcurves", "set_cycle",
           "TO_BVH", "FROM_BVH"]
