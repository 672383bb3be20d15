"""A 3D motion viewer as ONE self-contained HTML file: orbit/zoom, play/pause/scrub/speed, several motions side by
side or in one scene, ground grid, foot contacts, joint names on hover.

Why a single file with our own canvas renderer (``viewer.js``, inlined): it opens offline, from an e-mail or a
notebook, with no CDN and no WebGL (which headless and remote browsers often lack). Positions travel as int16 per
motion (an origin and one step: well under a millimetre for a human clip), so 16 motions of 64 frames stay far
below 2 MB. Everything is shown in metres, Y up: BVH units are guessed from the body size (``--scale`` overrides).
"""
from __future__ import annotations

import base64
import html
import importlib.resources
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from modi.core.body import Body, side_of
from modi.core.contacts import feet_of, preview_contacts
from modi.core.kinematics import bvh_positions
from modi.errors import BvhError, UserError
from modi.faults import atomic_write
from modi.io import bvh as bvh_io
from modi.io.gltf import guess_unit, load_positions

INPUT_SUFFIXES = (".bvh", ".glb", ".gltf")
_LEFT, _RIGHT = "#1e6edc", "#eb781e"  # one meaning everywhere (page legend, GIF): left blue, right orange
_COLORS = [(c, _LEFT, _RIGHT) for c in (  # per motion: (centre, left, right), as in the GIF previews
    "#283c6e", "#235f37", "#5f3723", "#502864", "#145a64", "#645a1e", "#5a1e32", "#8c1e5a")]
_STYLE = {"background": "#f7f7f4", "grid": "#d0d0cb", "shadow": "rgba(0,0,0,0.13)", "contact": "#e12828",
          "contactRing": "rgba(225,40,40,0.45)",
          "text": "#282828"}
MAX_FRAMES = 100_000  # per motion: a bound that keeps a page loadable


@dataclass
class ViewMotion:
    """One motion as the viewer shows it: global joint positions (T, J, 3) in metres, Y up."""
    title: str
    names: list[str]
    parents: list[int]
    positions: np.ndarray
    fps: float
    contacts: np.ndarray | None = None  # (T, J) bool, True where a joint touches the ground
    unit: str = ""  # how file units became metres, for the user to check a guess

    def __post_init__(self) -> None:
        p = np.asarray(self.positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[-1] != 3 or p.shape[0] < 1 or p.shape[1] < 1:
            raise ValueError(f"{self.title}: positions must be (T, J, 3), got shape {p.shape}")
        if p.shape[0] > MAX_FRAMES:
            raise ValueError(f"{self.title}: {p.shape[0]} frames; the viewer takes at most {MAX_FRAMES}")
        if not np.isfinite(p).all():
            raise ValueError(f"{self.title}: positions hold non-finite values")
        t, j = p.shape[:2]
        self.positions = p
        self.names = [str(n) for n in self.names] if self.names is not None else [f"joint{i}" for i in range(j)]
        self.parents = [int(x) for x in self.parents]
        if len(self.names) != j or len(self.parents) != j:
            raise ValueError(f"{self.title}: {j} joints but {len(self.names)} names and {len(self.parents)} parents")
        if any(not -1 <= x < j or x == i for i, x in enumerate(self.parents)):
            raise ValueError(f"{self.title}: parents must be -1 or another joint's index")
        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"{self.title}: fps must be a positive number, got {self.fps!r}")
        if self.contacts is not None:
            c = np.asarray(self.contacts).astype(bool)
            if c.shape != (t, j):
                raise ValueError(f"{self.title}: contacts must be (T, J) = {(t, j)}, got {c.shape}")
            self.contacts = c


# ------------------------------------------------------------------------------------------------ inputs
def guess_scale(height: float) -> tuple[float, str]:
    """(metres per file unit, unit name) from a body size in file units: BVH has no unit field. The same guess as
    the glTF export (:func:`modi.io.gltf.guess_unit`), so a BVH and its .glb show at the same size."""
    g = guess_unit(height)
    return g.scale, g.unit


def _to_y_up(p: np.ndarray, up: str) -> np.ndarray:
    if up == "z":  # right-handed Z-up -> Y-up
        return np.stack([p[..., 0], p[..., 2], -p[..., 1]], -1)
    if up != "y":
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    return p


def _bvh_motion(path: Path, scale: float | None, up: str, contacts: bool) -> ViewMotion:
    b = bvh_io.load(path)
    pos = _to_y_up(np.asarray(bvh_positions(b), dtype=np.float64), up)
    height = b.skeleton().height()
    con = None
    if contacts:  # the previews' one rule (modi.core.contacts.PREVIEW_RULE), as the GIF and the glTF export show
        con = preview_contacts(pos, feet_of(b), b.fps, b.parents, b.names)

    standing = Body.of(pos, b.parents, b.names).standing_height
    if scale is None:
        scale, unit = guess_scale(height)
        note = (f"body size {height:.4g} file units looks like {unit}: x {scale:g} to metres, standing height "
                f"{standing * scale:.3g} m (--scale overrides)")
    else:
        note = f"x {scale:g} to metres (--scale), standing height {standing * scale:.3g} m"
    return ViewMotion(path.stem, list(b.names), list(b.parents), pos * scale, b.fps, con, note)


def _gltf_motion(path: Path, scale: float | None, contacts: bool) -> ViewMotion:
    names, parents, pos, fps, con = load_positions(path)
    pos = np.asarray(pos, dtype=np.float64) * (1.0 if scale is None else scale)  # glTF is metres, Y up
    mask = None
    if contacts and con is not None:
        con = np.asarray(con).astype(bool)
        if con.shape == pos.shape[:2]:
            mask = con
    return ViewMotion(path.stem, list(names), list(parents), pos, float(fps), mask,
                      "glTF: metres" if scale is None else f"x {scale:g} (--scale)")


def load_motion(path: str | os.PathLike, scale: float | None = None, up: str = "y",
                contacts: bool = True) -> ViewMotion:
    """A .bvh (file units guessed, see :func:`guess_scale`) or .glb/.gltf file as a :class:`ViewMotion`.
    Any problem with the file is one :class:`UserError` naming it."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{p}: is a folder, expected a .bvh, .glb or .gltf file")
    if not p.is_file():
        raise UserError(f"{p}: no such file")
    ext = p.suffix.lower()
    if ext not in INPUT_SUFFIXES:
        raise UserError(f"{p}: unknown extension {ext or '(none)'!r}; the viewer reads .bvh, .glb and .gltf")
    try:
        return _bvh_motion(p, scale, up, contacts) if ext == ".bvh" else _gltf_motion(p, scale, contacts)
    except (UserError, BvhError):
        raise
    except (ValueError, KeyError, IndexError, UnicodeDecodeError) as exc:
        raise UserError(f"{p}: cannot read it as {ext[1:]}: {exc}") from None


def from_positions(positions: Any, parents: Sequence[int], names: Sequence[str] | None = None, fps: float = 30.0,
                   contacts: Any = None, title: str = "motion", scale: float = 1.0, up: str = "y") -> ViewMotion:
    """A :class:`ViewMotion` from global positions (T, J, 3) (numpy or torch) times ``scale`` metres per unit."""
    p = np.asarray(positions.detach().cpu() if hasattr(positions, "detach") else positions, dtype=np.float64)
    if p.ndim != 3:
        raise ValueError(f"{title}: positions must be (T, J, 3), got shape {p.shape}")
    return ViewMotion(title, list(names) if names is not None else None, list(parents),
                      _to_y_up(p, up) * scale, float(fps), contacts)


def _from_motion_object(m: Any, title: str) -> ViewMotion:
    """A :class:`modi.data.motion.Motion` (rotations + root; positions by the repo's FK), units guessed."""
    sk = m.skeleton
    pos = m.positions().detach().cpu().numpy()
    return from_positions(pos, sk.parents, sk.names, m.fps, title=title, scale=guess_scale(sk.height())[0])


def as_view_motions(items: Sequence[Any], **kwargs) -> list[ViewMotion]:
    """Paths, :class:`modi.data.motion.Motion` objects or :class:`ViewMotion` objects, in order."""
    out = []
    for i, it in enumerate(items):
        if isinstance(it, ViewMotion):
            out.append(it)
        elif isinstance(it, (str, os.PathLike)):
            out.append(load_motion(it, **kwargs))
        elif hasattr(it, "skeleton") and hasattr(it, "positions"):
            out.append(_from_motion_object(it, f"motion {i}"))
        else:
            raise TypeError(f"item {i}: expected a path, a Motion or a ViewMotion, got {type(it).__name__}")
    if not out:
        raise ValueError("nothing to show: give at least one motion")
    return out


# ------------------------------------------------------------------------------------------------ the page
def _side_codes(names: Sequence[str]) -> list[int]:
    return [side_of(n) for n in names]


def _body_size(p: np.ndarray) -> float:
    """Median over frames of the figure's largest extent (metres): sets the grid step, line widths, spacing."""
    return float(max(np.median(np.ptp(p, axis=1).max(axis=-1)), 1e-3))


def _pack(m: ViewMotion, index: int) -> dict:
    """int16 positions with a per-motion origin and one step (error <= step/2), contacts as a bit field."""
    p = m.positions.copy()
    p[..., 1] -= p[..., 1].min()  # the clip's lowest point stands on the grid
    lo = p.reshape(-1, 3).min(0)
    span = float((p.reshape(-1, 3).max(0) - lo).max())
    step = max(span / 65535.0, 1e-9)
    qv = np.clip(np.round((p - lo) / step) - 32768, -32768, 32767).astype("<i2")

    body = Body.of(p, m.parents, m.names)  # the same body as the GIF and the glTF: a floor root is no bone
    hide = [int(par in body.ground) for par in m.parents]
    height = _body_size(p[:, body.body_joints()])
    d = {"title": m.title, "names": m.names, "parents": m.parents, "side": _side_codes(m.names), "fps": m.fps,
         "frames": int(p.shape[0]), "origin": [float(v) for v in lo], "step": step, "color": index,
         "height": height, "hide": hide, "small": [int(x) for x in body.small], "pos": base64.b64encode(qv.tobytes()).decode("ascii"),
         "contacts": None}
    if m.contacts is not None and m.contacts.any():
        d["contacts"] = base64.b64encode(np.packbits(m.contacts.reshape(-1)).tobytes()).decode("ascii")
    return d


def _asset(name: str) -> str:
    return importlib.resources.files("modi.viz").joinpath(name).read_text(encoding="utf-8")


_CSS = """
html,body{margin:0;height:100%;background:#f7f7f4;font:13px sans-serif;color:#282828;overflow:hidden}
#stage{position:relative;height:calc(100% - 40px)}#view{display:block;width:100%;height:100%;cursor:grab}
#tip{position:absolute;display:none;background:#282828;color:#fff;padding:2px 6px;border-radius:3px;
pointer-events:none;white-space:nowrap}
#legend{white-space:nowrap;flex-shrink:0;font-size:12px}#legend span{margin-right:10px}
#legend i{display:inline-block;width:10px;height:10px;margin-right:4px;border-radius:2px}
#bar{height:40px;display:flex;align-items:center;gap:10px;padding:0 10px;background:#e9e9e4;box-sizing:border-box}
#bar label{white-space:nowrap}#scrub{flex:1;min-width:80px}#frame{min-width:175px;white-space:nowrap;font-variant-numeric:tabular-nums}#hint{color:#777;white-space:nowrap;overflow:hidden}
"""


def page_html(motions: Sequence[ViewMotion], title: str = "modi view", layout: str = "grid") -> str:
    """The whole viewer page for ``motions`` (played in sync, by time)."""
    if layout not in ("grid", "scene"):
        raise ValueError(f"layout must be 'grid' or 'scene', got {layout!r}")
    motions = list(motions)
    if not motions:
        raise ValueError("nothing to show: give at least one motion")
    data = {"motions": [_pack(m, i) for i, m in enumerate(motions)], "layout": layout, "colors": _COLORS,
            "style": _STYLE}
    blob = json.dumps(data, separators=(",", ":")).replace("<", "\\u003c")  # no "</script>" inside the JSON
    script = _asset("viewer.js")
    if "</script" in script.lower():
        raise RuntimeError("viewer.js must not contain '</script'")
    guard = ("window.addEventListener('error',function(e){var b=document.body,t=(e.message||'error')+' line '+"
             "e.lineno;b.setAttribute('data-errors',(b.getAttribute('data-errors')||'')+t+';');document.title="
             "'ERROR '+t;});")
    speeds = "".join(f'<option value="{s:g}"{" selected" if s == 1 else ""}>{s:g}&times;</option>'
                     for s in (0.25, 0.5, 1.0, 2.0))
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f'<meta name="viewport" content="width=device-width,initial-scale=1"><style>{_CSS}</style>'
        f"<script>{guard}</script></head><body>"
        '<div id="stage"><canvas id="view"></canvas><div id="tip"></div></div>'
        '<div id="bar"><button id="play">pause</button><input id="scrub" type="range" min="0" max="0" value="0">'
        f'<span id="frame"></span><label>speed <select id="speed">{speeds}</select></label>'
        '<label>layout <select id="layout"><option value="grid">side by side</option>'
        '<option value="scene">one scene</option></select></label>'
        '<label><input id="follow" type="checkbox"> follow</label><span id="legend"></span>'
        '<span id="hint">drag: orbit &middot; shift-drag: pan &middot; wheel: zoom'
        "</span></div>"
        f'<script type="application/json" id="modi-data">{blob}</script>'
        f"<script>{script}</script></body></html>\n"
    )


def write_view(path: str | os.PathLike, motions: Sequence[ViewMotion], title: str | None = None,
               layout: str = "grid") -> Path:
    """Write the viewer page for ``motions`` to ``path`` (atomically)."""
    path = Path(path)
    page = page_html(motions, title=title or path.stem, layout=layout)
    atomic_write(path, page)
    return path


def write_beside(gif_path: str | os.PathLike, positions: Sequence[Any], parents: Any, names: Any = None,
                 fps: float = 30.0, contacts: Sequence[Any] | None = None, titles: Sequence[str] | None = None,
                 layout: str = "grid", name: str = "view.html", scale: float | None = None) -> Path:
    """The viewer page of what a GIF preview shows, written as ``name`` in the GIF's folder.

    ``parents``/``names`` are one list shared by all motions or one per motion (as for the GIF renderer);
    ``scale`` is metres per unit (guessed from the body size when None).
    """
    n = len(positions)
    shared = not parents or isinstance(parents[0], (int, np.integer))
    par = [list(parents)] * n if shared else [list(p) for p in parents]
    if names is None or (names and isinstance(names[0], str)):
        nm = [list(names) if names is not None else None] * n
    else:
        nm = [list(x) for x in names]
    motions = []
    for i, p in enumerate(positions):
        p = np.asarray(p.detach().cpu() if hasattr(p, "detach") else p, dtype=np.float64)
        s = scale if scale is not None else guess_scale(float(np.median(np.ptp(p, axis=1).max(-1))))[0]
        title = titles[i] if titles is not None else (f"{i}" if n > 1 else Path(gif_path).stem)
        motions.append(from_positions(p, par[i], nm[i], fps, None if contacts is None else contacts[i],
                                      title=title, scale=s))
    return write_view(Path(gif_path).parent / name, motions, title=Path(gif_path).stem, layout=layout)


# ------------------------------------------------------------------------------------------------ notebooks
class Viewer:
    """The viewer page for some motions; Jupyter shows it inline (``_repr_html_``: an iframe with ``srcdoc``)."""

    def __init__(self, motions: Sequence[ViewMotion], layout: str = "grid", height: int = 480,
                 title: str = "modi view"):
        self.motions = list(motions)
        self.height = int(height)
        self.html = page_html(self.motions, title=title, layout=layout)

    def _repr_html_(self) -> str:
        return (f'<iframe srcdoc="{html.escape(self.html, quote=True)}" style="width:100%;height:{self.height}px;'
                'border:1px solid #ddd" sandbox="allow-scripts"></iframe>')

    def save(self, path: str | os.PathLike) -> Path:
        atomic_write(path, self.html)
        return Path(path)

    def __str__(self) -> str:
        return self.html


def show(*items: Any, layout: str = "grid", height: int = 480, **load_kwargs) -> Viewer | None:
    """Show motions (paths to .bvh/.glb/.gltf, ``Motion`` or ``ViewMotion`` objects) in the 3D viewer.

    In a running IPython kernel the viewer is displayed inline and None returned (so it is not shown twice);
    elsewhere the :class:`Viewer` is returned (``.html`` is the page, ``.save(path)`` writes it, and a notebook
    shows it as the cell's result).
    """
    if len(items) == 1 and isinstance(items[0], (list, tuple)):
        items = tuple(items[0])
    viewer = Viewer(as_view_motions(items, **load_kwargs), layout=layout, height=height)
    try:
        from IPython import get_ipython  # optional: only inside a notebook
        from IPython.display import HTML, display
    except ImportError:
        return viewer
    shell = get_ipython()
    if shell is None or not hasattr(shell, "kernel"):
        return viewer
    display(HTML(viewer._repr_html_()))
    return None


__all__ = ["ViewMotion", "guess_scale", "load_motion", "from_positions", "as_view_motions", "page_html",
           "write_view", "write_beside", "Viewer", "show", "INPUT_SUFFIXES"]
