"""The modi Blender add-on in Debian's headless Blender 3.4: installed from the zip through Blender's own
operators, a real BVH imported with Blender's importer, and a broken modi path giving one error line + CANCELLED."""
import ast
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BVH_DIR = REPO.parent / "shared" / "data" / "bvh"
BLENDER = shutil.which("blender")


def _bvh():
    files = sorted(BVH_DIR.rglob("*.bvh")) if BVH_DIR.is_dir() else []
    if not files:
        pytest.skip(f"no BVH under {BVH_DIR}")
    return files[0]


@pytest.mark.skipif(BLENDER is None, reason="blender not on PATH")
def test_addon_installs_and_broken_modi_path_cancels_with_one_line(tmp_path):
    bvh = _bvh()
    z = tmp_path / "modi_blender.zip"
    subprocess.run([sys.executable, "-m", "modi", "blender", "addon", "--out", str(z)], check=True)
    script = tmp_path / "s.py"
    script.write_text(textwrap.dedent(f"""
        import builtins, bpy, sys
        # Debian's Blender 3.4 BVH importer opens with mode 'rU', which Python 3.11 removed: map it to 'r'.
        _open = builtins.open
        builtins.open = lambda f, mode="r", *a, **k: _open(f, mode.replace("U", ""), *a, **k)
        bpy.ops.preferences.addon_install(filepath={str(z)!r})
        bpy.ops.preferences.addon_enable(module="modi_blender")
        bpy.ops.import_anim.bvh(filepath={str(bvh)!r})
        arm = [o for o in bpy.data.objects if o.type == "ARMATURE"][0]
        bpy.context.view_layer.objects.active = arm
        bpy.context.preferences.addons["modi_blender"].preferences.modi_path = "/nonexistent/modi"
        # From a script, Blender raises an operator's ERROR report as RuntimeError (the UI shows it as a report).
        try:
            r = bpy.ops.modi.learn(preset="tiny", out_dir={str(tmp_path / "run")!r})
            print("RESULT", sorted(r))
        except RuntimeError as e:
            print("REPORT", repr(str(e)))
        sys.exit(0)
    """))
    env = {"HOME": str(tmp_path), "PATH": "/usr/bin:/bin"}
    p = subprocess.run([BLENDER, "-b", "--factory-startup", "--python", str(script)],
                       capture_output=True, text=True, timeout=120, env=env)
    out = p.stdout + p.stderr
    reports = [ln for ln in out.splitlines() if ln.startswith("REPORT ")]
    assert len(reports) == 1, out[-3000:]
    assert "modi command not found" in reports[0] and "/nonexistent/modi" in reports[0], reports
    msg = ast.literal_eval(reports[0][len("REPORT "):])
    assert "\n" not in msg.strip(), msg  # one line
    assert not (tmp_path / "run" / "modi.log").exists()  # nothing was started
