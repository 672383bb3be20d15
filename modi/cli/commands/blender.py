"""``modi blender addon --out modi_blender.zip`` writes the Blender add-on as the zip Preferences > Add-ons > Install
takes; ``modi blender install`` installs it into a Blender on this machine and points it at this environment's
``modi``.

The add-on lives in ``modi/blender/`` and only shells out to ``modi``, so the zip holds no torch and no modi code."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from modi.errors import UserError

_ADDON_DIR = Path(__file__).resolve().parents[2] / "blender"
_FILES = ("__init__.py", "operators.py", "jobs.py", "rig_io.py", "blender_manifest.toml")
MODULE = "modi_blender"  # the module name Blender gives the add-on (the zip's top folder)

# Run inside Blender (the user's own preferences, not --factory-startup, so nothing else of theirs changes):
# install the zip with Blender's own operator, enable it, set the modi path, save the preferences.
_INSTALL_SCRIPT = """
import json, sys, bpy
cfg = json.loads(sys.argv[sys.argv.index("--") + 1])
bpy.ops.preferences.addon_install(filepath=cfg["zip"], overwrite=True)
bpy.ops.preferences.addon_enable(module=cfg["module"])
bpy.context.preferences.addons[cfg["module"]].preferences.modi_path = cfg["modi"]
bpy.ops.wm.save_userpref()
print("MODI_INSTALLED", bpy.app.version_string, bpy.utils.user_resource("SCRIPTS", path="addons"))
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("blender", help="the modi add-on for Blender")
    sub = p.add_subparsers(dest="blender_cmd", required=True)
    a = sub.add_parser("addon", help="write the add-on zip (Edit > Preferences > Add-ons > Install)")
    a.add_argument("--out", required=True, help="zip file to write")
    a.set_defaults(func=_addon)
    i = sub.add_parser("install", help="install and enable the add-on in a Blender on this machine, with its "
                                       "modi path set to this environment's modi command")
    i.add_argument("--blender", default=None, help="the Blender executable (default: 'blender' on PATH)")
    i.add_argument("--modi", default=None, help="the modi command the add-on runs (default: this environment's)")
    i.set_defaults(func=_install)


def write_addon_zip(out: Path) -> Path:
    """Zip the add-on under one folder ``modi_blender/`` (the module name Blender will give it)."""
    if not out.parent.is_dir():
        raise UserError(f"{out.parent}: no such folder")
    if out.is_dir():
        raise UserError(f"{out}: is a folder, expected the .zip file to write")
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for name in _FILES:
            z.write(_ADDON_DIR / name, f"{MODULE}/{name}")
    return out


def this_modi() -> str:
    """The ``modi`` script of the running interpreter's environment (not a shim that needs a shell's setup)."""
    beside = Path(sys.executable).with_name("modi")
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    found = shutil.which("modi")
    if found is None:
        raise UserError("no modi command in this environment (pip install the package, or pass --modi PATH)")
    return found


def blender_env() -> dict:
    """This process's environment for running Blender, with every PATH folder that holds another ``python3``
    (a venv's, pyenv's) left out: a Blender linked to the system Python (Debian's) takes its Python home from the
    first ``python3`` on PATH, and another interpreter's standard library breaks it."""
    keep = [d for d in os.environ.get("PATH", "").split(os.pathsep)
            if d in ("/usr/bin", "/bin") or not (Path(d) / "python3").exists()]
    return {**os.environ, "PATH": os.pathsep.join(keep)}


def _addon(args) -> int:
    print(write_addon_zip(Path(args.out)))
    return 0


def _install(args) -> int:
    blender = shutil.which(args.blender or "blender")  # which() also checks an explicit path is executable
    if blender is None:
        raise UserError(f"Blender not found ({args.blender or 'no blender on PATH'}); pass --blender PATH")
    modi = args.modi or this_modi()
    if args.modi is not None and shutil.which(args.modi) is None:
        raise UserError(f"--modi {args.modi}: not an executable modi command (the output of 'which modi' in the "
                        "environment the add-on should run)")
    with tempfile.TemporaryDirectory() as tmp:
        z = write_addon_zip(Path(tmp) / f"{MODULE}.zip")
        cfg = json.dumps({"zip": str(z), "module": MODULE, "modi": modi})
        try:
            p = subprocess.run([blender, "-b", "--python-exit-code", "1", "--python-expr", _INSTALL_SCRIPT,
                                "--", cfg], capture_output=True, text=True, timeout=300, env=blender_env())
        except (OSError, subprocess.TimeoutExpired) as e:
            raise UserError(f"{blender}: could not run it ({e})") from None
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("MODI_INSTALLED ")]
    if p.returncode != 0 or not lines:
        tail = [ln for ln in (p.stdout + p.stderr).splitlines() if ln.strip()][-1:] or ["no output"]
        raise UserError(f"{blender}: installing the add-on failed: {tail[0]}")
    version, where = lines[-1].split(" ", 2)[1:]
    print(f"installed the modi add-on in Blender {version} ({where}); it runs {modi}")
    return 0
