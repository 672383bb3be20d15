"""``modi blender addon --out modi_blender.zip``: the Blender add-on as the zip Preferences > Add-ons > Install takes.

The add-on lives in ``modi/blender/`` and only shells out to ``modi``, so the zip holds no torch and no modi code."""
from __future__ import annotations

import zipfile
from pathlib import Path

from modi.errors import UserError

_ADDON_DIR = Path(__file__).resolve().parent.parent / "blender"
_FILES = ("__init__.py", "blender_manifest.toml")


def register(subparsers) -> None:
    p = subparsers.add_parser("blender", help="the modi add-on for Blender")
    sub = p.add_subparsers(dest="blender_cmd", required=True)
    a = sub.add_parser("addon", help="write the add-on zip (Edit > Preferences > Add-ons > Install)")
    a.add_argument("--out", required=True, help="zip file to write")
    a.set_defaults(func=_addon)


def write_addon_zip(out: Path) -> Path:
    """Zip the add-on under one folder ``modi_blender/`` (the module name Blender will give it)."""
    if not out.parent.is_dir():
        raise UserError(f"{out.parent}: no such folder")
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for name in _FILES:
            z.write(_ADDON_DIR / name, f"modi_blender/{name}")
    return out


def _addon(args) -> int:
    print(write_addon_zip(Path(args.out)))
    return 0
