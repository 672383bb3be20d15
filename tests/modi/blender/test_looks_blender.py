"""What an animator sees in Blender (issue 31): Debian's Blender 3.4 imports our default ``.glb`` with the import
dialog's defaults and no patched numpy; the ``--mesh`` body of a Bandai clip (static floor root above the hips),
rendered with Workbench, has no geometry away from the body -- no plank skinned to the floor root, no End Site boxes.
The oracle is Blender itself: its armature's bone heads, its evaluated (skinned) mesh, its rendered pixels."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from modi.cli import main
from modi.io import bvh as bvh_io
from modi.core.kinematics import bvh_positions

BANDAI = "bandai-namco-1/data/dataset-1_walk_normal_001.bvh"

DEFAULT_IMPORT_PY = r"""
import json, sys
import bpy
a = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.fps = int(a[1])                  # docs/gltf.md's step: the scene at the clip's rate before importing
bpy.ops.import_scene.gltf(filepath=a[0])   # the dialog's defaults (Shading: Use Normals)
arm = next(o for o in bpy.data.objects if o.type == "ARMATURE")
out = {"meshes": len(bpy.data.meshes), "frames": []}
for f in (0, 30, 60):
    sc.frame_set(f)
    out["frames"].append([list(arm.matrix_world @ b.head) for b in arm.pose.bones])
out["names"] = [b.name for b in arm.pose.bones]
json.dump(out, open(a[2], "w"))
"""

WORKBENCH_PY = r"""
import json, math, sys
import bpy
from mathutils import Vector
from bpy_extras.object_utils import world_to_camera_view
a = sys.argv[sys.argv.index("--") + 1:]
path, fps, png, size, ortho = a[0], int(a[1]), a[2], 256, 2.5
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.fps = fps
bpy.ops.import_scene.gltf(filepath=path, import_shading="FLAT")  # a mesh needs Flat/Smooth in Debian's 3.4
arm = next(o for o in bpy.data.objects if o.type == "ARMATURE")
body = next(o for o in bpy.data.objects if o.type == "MESH")
far = 0.0
for f in (0, 60, 120):
    sc.frame_set(f)
    ev = body.evaluated_get(bpy.context.evaluated_depsgraph_get())
    me = ev.to_mesh()
    joints = [arm.matrix_world @ b.head for b in arm.pose.bones if b.parent is not None]
    for v in me.vertices:
        w = ev.matrix_world @ v.co
        far = max(far, min((w - j).length for j in joints))
    ev.to_mesh_clear()
joints = [arm.matrix_world @ b.head for b in arm.pose.bones if b.parent is not None]
c = sum(joints, Vector()) / len(joints)
cam = bpy.data.cameras.new("cam"); cam.type = "ORTHO"; cam.ortho_scale = ortho
co = bpy.data.objects.new("cam", cam); sc.collection.objects.link(co); sc.camera = co
co.location = (c.x, c.y - 10.0, c.z); co.rotation_euler = (math.pi / 2, 0.0, 0.0)   # from the front
sc.render.engine = "BLENDER_WORKBENCH"
sc.render.resolution_x = sc.render.resolution_y = size
sc.render.film_transparent = True
sc.render.filepath = png
bpy.ops.render.render(write_still=True)
px = [world_to_camera_view(sc, co, j) for j in joints]
json.dump({"far": far, "px_per_m": size / ortho,
           "joints_px": [[p.x * size, (1.0 - p.y) * size] for p in px]}, open(png + ".json", "w"))
"""


def _blender() -> str:
    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("Debian package blender (with python3-numpy for its glTF importer) is not installed")
    return blender


def _run_blender(script: str, tmp: Path, *args: str) -> subprocess.CompletedProcess:
    (tmp / "script.py").write_text(script)
    # Blender's embedded Python takes its home from the first python3 on PATH: keep a pyenv/venv one out of it
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PYENV", "VIRTUAL_ENV"))}
    env["PATH"] = "/usr/local/bin:/usr/bin:/bin"
    return subprocess.run([_blender(), "-b", "--factory-startup", "--python", str(tmp / "script.py"), "--", *args],
                          capture_output=True, text=True, timeout=240, env=env)


@pytest.fixture(scope="module")
def bandai(shared_data):
    src = shared_data / "bvh" / BANDAI
    if not src.is_file():
        pytest.skip(f"{src} absent")
    return src


def test_default_import_without_numpy_patch_gives_the_motion(bandai, tmp_path):
    _blender()
    glb = tmp_path / "walk.glb"
    assert main(["export", "gltf", str(bandai), str(glb)]) == 0
    r = _run_blender(DEFAULT_IMPORT_PY, tmp_path, str(glb), "30", str(tmp_path / "out.json"))
    assert (tmp_path / "out.json").is_file(), r.stdout[-1500:] + r.stderr[-1500:]
    got = json.loads((tmp_path / "out.json").read_text())
    b = bvh_io.load(bandai)
    ref = bvh_positions(b)[[0, 30, 60]] * 0.01
    order = [got["names"].index(n) for n in b.names]
    z_up = np.array(got["frames"])[:, order]               # Blender is Z-up: glTF (x, y, z) = Blender (x, z, -y)
    pos = np.stack([z_up[..., 0], z_up[..., 2], -z_up[..., 1]], -1)
    assert np.abs(pos - ref).max() < 2e-3, np.abs(pos - ref).max()


def test_workbench_render_of_the_mesh_shows_only_the_body(bandai, tmp_path):
    _blender()
    from PIL import Image

    glb = tmp_path / "walk_mesh.glb"
    assert main(["export", "gltf", "--mesh", str(bandai), str(glb)]) == 0
    png = tmp_path / "walk.png"
    r = _run_blender(WORKBENCH_PY, tmp_path, str(glb), "30", str(png))
    assert png.is_file() and Path(str(png) + ".json").is_file(), r.stdout[-1500:] + r.stderr[-1500:]
    info = json.loads(Path(str(png) + ".json").read_text())
    # geometry: every skinned vertex within 0.5 m of a body joint (the old plank on the floor root was ~2 m away)
    assert info["far"] < 0.5, info["far"]
    # pixels: what is drawn lies in the box of the projected body joints, grown by 0.5 m, and fills it
    alpha = np.asarray(Image.open(png))[..., 3]
    ys, xs = np.nonzero(alpha > 0)
    assert len(xs) > 200, "nothing rendered"
    j = np.array(info["joints_px"])
    m = 0.5 * info["px_per_m"]
    assert xs.min() >= j[:, 0].min() - m and xs.max() <= j[:, 0].max() + m, (xs.min(), xs.max(), j[:, 0])
    assert ys.min() >= j[:, 1].min() - m and ys.max() <= j[:, 1].max() + m, (ys.min(), ys.max(), j[:, 1])
    assert ys.max() - ys.min() > 0.8 * (j[:, 1].max() - j[:, 1].min())
