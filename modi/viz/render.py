"""Stick-figure previews of motion: GIF (Pillow) or MP4 (ffmpeg), one panel per motion or many characters per scene.

Drawing is done directly with ``PIL.ImageDraw`` on palette images: no matplotlib figure per frame, so a 64-frame
preview takes a fraction of a second. A perspective camera looks at each panel's (smoothed) root so that walking
characters stay in view while the ground grid and the floor shadow show how they move over the ground.
"""
from __future__ import annotations

import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from modi.core.body import Body, metres_scale, side_of
from modi.core.contacts import feet_of, foot_joints_by_name, preview_contacts  # noqa: F401  (foot_joints_by_name: public here too)
from modi.core.kinematics import bvh_positions
from modi.errors import UserError
from modi.faults import atomic_output
from modi.io import bvh as bvh_io
from modi.io.gltf import guess_unit
from modi.viz.pages import view_pages_enabled
from modi.viz.viewer import write_beside

_BG, _GRID, _GRID_MAJOR, _SHADOW, _TEXT, _CONTACT, _BORDER = range(7)
_BASE_COLORS = [(247, 247, 244), (214, 214, 210), (185, 185, 180), (208, 208, 204), (40, 40, 40), (225, 40, 40),
                (150, 150, 150)]
# per character: (centre, left, right); left is always blue and right always orange (the viewer page's legend)
_LEFT_RGB, _RIGHT_RGB = (30, 110, 220), (235, 120, 30)
_CHAR_COLORS = [(c, _LEFT_RGB, _RIGHT_RGB) for c in (
    (40, 60, 110), (35, 95, 55), (95, 55, 35), (80, 40, 100), (20, 90, 100), (100, 90, 30), (90, 30, 50),
    (140, 30, 90))]  # no grey: a figure never reads as text
_FOV = math.radians(40.0)


# Twins: same colour, other palette index. Toggling a corner pixel to its twin keeps a frame that repeats the
# previous one distinct, because Pillow would otherwise merge identical GIF frames (and change the frame count).
_BG_TWIN = len(_BASE_COLORS) + 3 * len(_CHAR_COLORS)
_BORDER_TWIN = _BG_TWIN + 1
_TWINS = {_BG: _BG_TWIN, _BG_TWIN: _BG, _BORDER: _BORDER_TWIN, _BORDER_TWIN: _BORDER}


def _palette() -> list[int]:
    colors = list(_BASE_COLORS)
    for triple in _CHAR_COLORS:
        colors.extend(triple)
    colors += [_BASE_COLORS[_BG], _BASE_COLORS[_BORDER]]
    flat = [v for c in colors for v in c]
    return flat + [0] * (768 - len(flat))


def _char_index(i: int, part: int) -> int:
    return len(_BASE_COLORS) + 3 * (i % len(_CHAR_COLORS)) + part


def _side_of(name: str) -> int:
    """0 centre, 1 left, 2 right (:func:`modi.core.body.side_of`, shared with the viewer and the glTF export)."""
    return side_of(name)


def foot_contacts(positions: np.ndarray, feet: Sequence[int], fps: float, up: str = "y",
                  parents: Sequence[int] | None = None, names: Sequence[str] | None = None) -> np.ndarray:
    """(T, J) bool contact labels by the one rule every preview uses (:func:`modi.core.contacts.preview_contacts`:
    low above the floor and slow, in standing heights, short runs removed), for ``up`` = "y" or "z" data."""
    p = _to_y_up(np.asarray(positions, dtype=np.float64), up)
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"positions must be (T, J, 3), got {p.shape}")
    return preview_contacts(p, feet, fps, parents, names)


def _to_y_up(p: np.ndarray, up: str) -> np.ndarray:
    if up == "y":
        return p
    if up == "z":   # rotate -90 deg about X: z-up right-handed data -> y-up right-handed
        return np.stack([p[..., 0], p[..., 2], -p[..., 1]], -1)
    raise ValueError(f"up must be 'y' or 'z', got {up!r}")


def _body_height(p: np.ndarray) -> float:
    """Typical vertical extent of the figure (median over frames), robust to jumps and lying poses."""
    ext = np.ptp(p, axis=1)                                  # (T, 3)
    h = float(np.median(np.max(ext, axis=-1)))
    return h if h > 1e-9 else 1.0


def _nice_step(x: float) -> float:
    e = 10.0 ** math.floor(math.log10(x))
    return min((m * e for m in (1.0, 2.0, 5.0, 10.0)), key=lambda v: abs(math.log(v / x)))


def _smooth_track(xz: np.ndarray, window: int) -> np.ndarray:
    """Steady camera path: a least-squares line through the ``window`` frames around each frame (shifted inwards
    at the ends). It removes per-step sway but, unlike a Gaussian, follows constant-speed travel exactly, even at
    the clip's first and last frames."""
    n = len(xz)
    w = min(int(window), n)
    if w < 3:
        return xz
    t = np.arange(n, dtype=np.float64)
    lo = np.clip(t.astype(int) - w // 2, 0, n - w)
    hi = lo + w

    def wsum(v: np.ndarray) -> np.ndarray:
        c = np.concatenate([np.zeros((1,) + v.shape[1:]), np.cumsum(v, axis=0)])
        return c[hi] - c[lo]

    st, stt = wsum(t), wsum(t * t)
    sx, stx = wsum(xz), wsum(t[:, None] * xz)
    slope = (w * stx - st[:, None] * sx) / (w * stt - st * st)[:, None]
    return (sx - slope * st[:, None]) / w + slope * t[:, None]


class _Camera:
    """Perspective camera at fixed azimuth/elevation/distance looking at a moving target."""

    def __init__(self, azimuth: float, elevation: float, distance: float, width: int, height: int):
        az, el = math.radians(azimuth), math.radians(elevation)
        self.back = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        fwd = -self.back
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        self.basis = np.stack([right, np.cross(right, fwd), fwd])   # rows: right, up, forward
        self.distance = distance
        self.w, self.h = width, height
        self.focal = 0.5 * height / math.tan(0.5 * _FOV)
        self.near = 0.05 * distance

    def project(self, pts: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        eye = target + self.distance * self.back
        cam = (pts - eye) @ self.basis.T
        z = cam[..., 2]
        zs = np.maximum(z, self.near)
        xy = np.stack([self.w / 2 + self.focal * cam[..., 0] / zs, self.h / 2 - self.focal * cam[..., 1] / zs], -1)
        return xy, z

    def segments(self, a: np.ndarray, b: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Project 3-D segments (N,3)->(N,3), clipped at the near plane; returns (M, 2, 2) for the visible ones."""
        eye = target + self.distance * self.back
        ca, cb = (a - eye) @ self.basis.T, (b - eye) @ self.basis.T
        za, zb = ca[:, 2:3], cb[:, 2:3]
        keep = ((za >= self.near) | (zb >= self.near))[:, 0]
        ca, cb, za, zb = ca[keep], cb[keep], za[keep], zb[keep]
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = np.where(za < self.near, (self.near - za) / (zb - za), 0.0)
            tb = np.where(zb < self.near, (self.near - zb) / (za - zb), 0.0)
        ca, cb = ca + (cb - ca) * ta, cb + (ca - cb) * tb
        c = np.stack([ca, cb], 1)
        return np.stack([self.w / 2 + self.focal * c[..., 0] / c[..., 2],
                         self.h / 2 - self.focal * c[..., 1] / c[..., 2]], -1)


class _Panel:
    """One view: the characters it shows, its camera track and its ground grid."""

    def __init__(self, chars: list[int], pos: list[np.ndarray], size: tuple[int, int], fps: float, floor: float,
                 height: float, azimuth: float, elevation: float, title: str | None, n_frames: int,
                 centres: Sequence[int] | None = None):
        self.chars = chars
        w, h = size
        centres = [0] * len(pos) if centres is None else list(centres)   # the joint each camera follows
        roots = np.stack([_hold(pos[c][:, centres[c], :], n_frames) for c in chars])      # (C, T, 3)
        centre = roots.mean(0)[:, [0, 2]]
        track = _smooth_track(centre, round(fps))
        if len(chars) > 1:   # crowds: zoom out smoothly as the characters spread apart
            spread = np.linalg.norm(roots[:, :, [0, 2]] - track[None], axis=-1).max(0)
            spread = np.maximum(_smooth_track(spread[:, None], 2 * round(fps))[:, 0], 0.0)
        else:
            spread = np.zeros(n_frames)
        visible = np.maximum(1.45 * height, 2.2 * (spread + 0.4 * height))
        self.distances = visible / (2 * math.tan(0.5 * _FOV)) / min(1.0, w / h) + 0.4 * height
        self.cam = _Camera(azimuth, elevation, float(self.distances[0]), w, h)
        self.targets = np.stack([track[:, 0], np.full(n_frames, floor + 0.45 * height), track[:, 1]], -1)
        self.floor = floor
        self.height = height
        self.step = _nice_step(max(0.3 * height, float(np.median(visible)) / 10))
        self.cos_el = math.cos(math.radians(elevation))
        self.title = title

    def set_frame(self, t: int) -> None:
        d = float(self.distances[t])
        self.cam.distance, self.cam.near = d, 0.05 * d
        self.extent = 0.8 * d * self.cos_el   # the grid stays in front of the camera
        figure_px = self.cam.focal * self.height / d
        self.line = int(np.clip(round(figure_px / 60), 1, 6))
        self.dots = figure_px > 80

    def draw_grid(self, draw: ImageDraw.ImageDraw, target: np.ndarray, ox: int, oy: int) -> None:
        s = self.step
        n = int(math.ceil(self.extent / s))
        cx, cz = round(target[0] / s) * s, round(target[2] / s) * s   # snapped to world lines: the grid slides
        k = np.arange(-n, n + 1) * s
        # each line only spans the disc of radius ``extent`` around the target: never under or behind the camera
        half_x = np.sqrt(np.maximum(self.extent ** 2 - (cx + k - target[0]) ** 2, 0.0))
        half_z = np.sqrt(np.maximum(self.extent ** 2 - (cz + k - target[2]) ** 2, 0.0))
        lo_a, hi_a = target[2] - half_x - cz, target[2] + half_x - cz
        lo_b, hi_b = target[0] - half_z - cx, target[0] + half_z - cx
        y = np.full_like(k, self.floor)
        a = np.concatenate([np.stack([cx + k, y, cz + lo_a], -1), np.stack([cx + lo_b, y, cz + k], -1)])
        b = np.concatenate([np.stack([cx + k, y, cz + hi_a], -1), np.stack([cx + hi_b, y, cz + k], -1)])
        major = np.concatenate([np.abs(cx + k) < 1e-9 * s, np.abs(cz + k) < 1e-9 * s])
        real = np.concatenate([half_x, half_z]) > 0
        a, b, major = a[real], b[real], major[real]
        eye = target + self.cam.distance * self.cam.back
        keep = ((a - eye) @ self.cam.basis[2] >= self.cam.near) | ((b - eye) @ self.cam.basis[2] >= self.cam.near)
        segs = self.cam.segments(a, b, target)
        for seg, is_major in zip(segs, major[keep]):
            draw.line([(ox + seg[0, 0], oy + seg[0, 1]), (ox + seg[1, 0], oy + seg[1, 1])],
                      fill=_GRID_MAJOR if is_major else _GRID, width=1)


def _hold(a: np.ndarray, n: int) -> np.ndarray:
    """Pad a per-frame array to ``n`` frames by holding its last frame."""
    if len(a) >= n:
        return a[:n]
    return np.concatenate([a, np.repeat(a[-1:], n - len(a), axis=0)], axis=0)


def _as_list(positions) -> list[np.ndarray]:
    if isinstance(positions, np.ndarray) or hasattr(positions, "detach"):
        arr = np.asarray(positions.detach().cpu() if hasattr(positions, "detach") else positions, dtype=np.float64)
        if arr.ndim not in (3, 4):
            raise ValueError(f"positions must be (T, J, 3) or (N, T, J, 3), got shape {arr.shape}")
        positions = [arr] if arr.ndim == 3 else list(arr)
    out = []
    for i, p in enumerate(positions):
        a = np.asarray(p.detach().cpu() if hasattr(p, "detach") else p, dtype=np.float64)
        if a.ndim != 3 or a.shape[-1] != 3 or a.shape[0] < 1:
            raise ValueError(f"positions[{i}] must be (T, J, 3) with T >= 1, got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"positions[{i}] has non-finite values")
        out.append(a)
    if not out:
        raise ValueError("positions: nothing to render")
    return out


def render_frames(positions, parents: Sequence[int] | Sequence[Sequence[int]], fps: float = 30.0,
                  size: tuple[int, int] = (320, 320), titles: Sequence[str] | None = None, layout: str = "grid",
                  contacts: Sequence[np.ndarray | None] | None = None,
                  names: Sequence[str] | Sequence[Sequence[str]] | None = None, up: str = "y",
                  azimuth: float = 35.0, elevation: float = 18.0) -> list[Image.Image]:
    """Draw the frames (palette-mode PIL images) that :func:`render_positions` writes.

    ``parents`` (and ``names``) are one list shared by all motions or one list per motion. ``size`` is per panel
    in the grid layout (the image is cols×W by rows×H) and the whole image in the scene layout.
    """
    pos = [_to_y_up(p, up) for p in _as_list(positions)]
    n = len(pos)
    shared = not parents or isinstance(parents[0], (int, np.integer))
    par = [list(parents)] * n if shared else [list(p) for p in parents]
    if len(par) != n:
        raise ValueError(f"got {len(par)} parent lists for {n} motions")
    for i, (p, pa) in enumerate(zip(pos, par)):
        if len(pa) != p.shape[1]:
            raise ValueError(f"motion {i} has {p.shape[1]} joints but its parents list has {len(pa)}")
        if any(not (-1 <= q < len(pa)) for q in pa):
            raise ValueError(f"parents of motion {i} hold an index outside [-1, {len(pa)})")
    if names is None:
        nm: list[list[str] | None] = [None] * n
    elif names and isinstance(names[0], str):
        nm = [list(names)] * n
    else:
        nm = [list(x) for x in names]
    if len(nm) != n or any(x is not None and len(x) != pos[i].shape[1] for i, x in enumerate(nm)):
        raise ValueError("names must be one joint-name list per motion (or one shared), one name per joint")
    if titles is not None and len(titles) != n:
        raise ValueError(f"got {len(titles)} titles for {n} motions")
    if contacts is not None:
        if len(contacts) != n:
            raise ValueError(f"got {len(contacts)} contact arrays for {n} motions")
        for i, c in enumerate(contacts):
            if c is not None and np.shape(c) != pos[i].shape[:2]:
                raise ValueError(f"contacts[{i}] must be (T, J) = {pos[i].shape[:2]}, got {np.shape(c)}")
    if layout not in ("grid", "scene"):
        raise ValueError(f"layout must be 'grid' or 'scene', got {layout!r}")
    w, h = int(size[0]), int(size[1])
    if w < 16 or h < 16:
        raise ValueError(f"size must be at least 16x16 pixels, got {w}x{h}")



    bodies = [Body.of(p, par[i], nm[i]) for i, p in enumerate(pos)]   # ground root, sides, fingers, height
    # every motion in metres (a crab in m beside a human in cm): the scene layout compares true sizes
    scales = [metres_scale(b.standing_height) for b in bodies]
    if any(s != 1.0 for s in scales):
        pos = [p * s for p, s in zip(pos, scales)]
        bodies = [Body.of(p, par[i], nm[i]) for i, p in enumerate(pos)]
    # each panel frames its own figure: a standing height (never less than the figure's typical extent)
    heights = [max(b.standing_height, _body_height(p[:, b.body_joints()])) for b, p in zip(bodies, pos)]
    height = max(heights)
    floors = [b.floor for b in bodies]   # the ground: each body's lowest point (files differ)
    n_frames = max(len(p) for p in pos)
    sides = [b.sides if nm[i] else [0] * len(par[i]) for i, b in enumerate(bodies)]
    drawn = [set(b.bones()) for b in bodies]
    hidden = [set(b.ground) for b in bodies]
    small = [b.small for b in bodies]
    centres = [b.centre for b in bodies]
    con = [None if contacts is None or contacts[i] is None else _hold(np.asarray(contacts[i], bool), n_frames)
           for i in range(n)]

    if layout == "grid":
        cols = math.ceil(math.sqrt(n))
        rows = math.ceil(n / cols)
        panels = [(_Panel([i], pos, (w, h), fps, floors[i], heights[i], azimuth, elevation,
                          None if titles is None else titles[i], n_frames, centres), (i % cols) * w, (i // cols) * h)
                  for i in range(n)]
        img_size = (cols * w, rows * h)
    else:
        panels = [(_Panel(list(range(n)), pos, (w, h), fps, min(floors), height, azimuth, elevation,
                          None if titles is None else " | ".join(titles), n_frames, centres), 0, 0)]
        img_size = (w, h)

    font = ImageFont.load_default()
    palette = _palette()
    held = [_hold(p, n_frames) for p in pos]
    frames = []
    for t in range(n_frames):
        img = Image.new("P", img_size, _BG)
        img.putpalette(palette)
        for panel, px, py in panels:
            # each panel draws on its own canvas, so lines leaving it cannot spill into its neighbours
            canvas = img if len(panels) == 1 else Image.new("P", (w, h), _BG)
            if canvas is not img:
                canvas.putpalette(palette)
            draw = ImageDraw.Draw(canvas)
            ox = oy = 0
            target = panel.targets[t]
            panel.set_frame(t)
            panel.draw_grid(draw, target, ox, oy)
            lw = panel.line
            bones = []   # (depth, xy0, xy1, color)
            shadows = []
            joints = []
            for k, c in enumerate(panel.chars):
                p = held[c][t]
                xy, z = panel.cam.project(p, target)
                flat = p.copy()
                flat[:, 1] = panel.floor
                sxy, _ = panel.cam.project(flat, target)
                for j, q in enumerate(par[c]):
                    if j not in drawn[c]:   # the root, and the "bone" from a ground root
                        continue
                    if z[j] < panel.cam.near or z[q] < panel.cam.near:
                        continue
                    bones.append((0.5 * (z[j] + z[q]), xy[q], xy[j], _char_index(k, sides[c][j]), small[c][j]))
                    shadows.append((sxy[q], sxy[j]))
                for j in range(len(par[c])):
                    if j not in hidden[c] and z[j] >= panel.cam.near:
                        hit = con[c] is not None and bool(con[c][t, j])
                        joints.append((z[j], xy[j], _CONTACT if hit else _char_index(k, 0), hit, small[c][j]))
            for a, b in shadows:
                draw.line([(ox + a[0], oy + a[1]), (ox + b[0], oy + b[1])], fill=_SHADOW, width=lw + 1)
            items = [(d, 0, (a, b, col, tiny)) for d, a, b, col, tiny in bones]
            items += [(d, 1, (xy, col, hit, tiny)) for d, xy, col, hit, tiny in joints]
            items.sort(key=lambda it: -it[0])
            for _, kind, data in items:
                if kind == 0:
                    a, b, col, tiny = data
                    draw.line([(ox + a[0], oy + a[1]), (ox + b[0], oy + b[1])], fill=col,
                              width=max(1, lw // 2) if tiny else lw)
                else:
                    xy, col, hit, tiny = data
                    if not (hit or panel.dots) or (tiny and not hit):   # fingers: thin lines, no dots
                        continue
                    r = max(lw, 2) * (1.6 if hit else 0.8)
                    draw.ellipse([ox + xy[0] - r, oy + xy[1] - r, ox + xy[0] + r, oy + xy[1] + r], fill=col)
            if panel.title:
                draw.text((ox + 6, oy + 4), panel.title, fill=_TEXT, font=font)
            if panel is panels[0][0] and any(any(s) for s in sides):   # the side legend, once per image
                x = ox + 6
                for word, col in (("left", _char_index(0, 1)), ("right", _char_index(0, 2))) + (
                        (("contact", _CONTACT),) if contacts is not None else ()):
                    draw.text((x, oy + h - 14), word, fill=col, font=font)
                    x += int(draw.textlength(word + "  ", font=font))
            if layout == "grid" and n > 1:
                draw.rectangle([0, 0, w - 1, h - 1], outline=_BORDER)
            if canvas is not img:
                img.paste(canvas, (px, py))
        frames.append(img)
    return frames


def _check_out(out_path: str | Path) -> Path:
    out = Path(out_path)
    ext = out.suffix.lower()
    if ext not in (".gif", ".mp4"):
        raise UserError(f"{out}: output must end in .gif or .mp4 (got {ext or 'no extension'!r})")
    if ext == ".mp4" and shutil.which("ffmpeg") is None:
        raise UserError(f"{out}: writing .mp4 needs ffmpeg on PATH (not found); install ffmpeg or write a .gif")
    if out.parent and not out.parent.exists():
        raise UserError(f"{out}: folder {out.parent} does not exist")
    return out


def _distinct(frames: list[Image.Image]) -> list[Image.Image]:
    """Make each of our palette frames differ from the previous one in the top-left pixel's index only."""
    out, prev = [], None
    for f in frames:
        data = f.tobytes()
        if data == prev and f.mode == "P":
            px = f.getpixel((0, 0))
            if px in _TWINS:
                f = f.copy()
                f.putpixel((0, 0), _TWINS[px])
                data = f.tobytes()
        out.append(f)
        prev = data
    return out


def gif_delays(n: int, fps: float) -> list[int]:
    """Per-frame GIF delays in centiseconds whose running sum stays within half a centisecond of real time
    (frame k ends at round(100 (k+1) / fps)); at least 2 cs each, as browsers slow shorter delays to 10 cs."""
    ends = [round(100.0 * (k + 1) / fps) for k in range(n)]
    out, prev = [], 0
    for e in ends:
        d = max(2, e - prev)
        out.append(d)
        prev += d
    return out


def save_frames(frames: list[Image.Image], out_path: str | Path, fps: float = 30.0) -> Path:
    """Write frames as an endlessly looping GIF or (with ffmpeg) an H.264 MP4.

    GIF delays are whole centiseconds: :func:`gif_delays` alternates them (3, 3, 4, ... cs at 30 fps) so the clip
    keeps real time. Identical consecutive frames are kept apart (:func:`_distinct`) so no delay is merged.
    """
    out = _check_out(out_path)
    if not frames:
        raise ValueError("no frames to save")
    if out.suffix.lower() == ".gif":
        frames = _distinct(frames)
        with atomic_output(out, "wb") as fh:
            frames[0].save(fh, format="GIF", save_all=True, append_images=frames[1:],
                           duration=[10 * d for d in gif_delays(len(frames), fps)], loop=0, optimize=False)
        return out
    w, h = frames[0].size
    tmp = out.with_name(f".{out.stem}.tmp{os.getpid()}.mp4")  # ffmpeg picks the container by the extension
    cmd = ["ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
           "-r", f"{fps:g}", "-i", "-", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p",
           "-c:v", "libx264", str(tmp)]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdin is not None
    try:
        for f in frames:
            proc.stdin.write(f.convert("RGB").tobytes())
        proc.stdin.close()
    except BrokenPipeError:
        pass
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if proc.wait() != 0:
        tmp.unlink(missing_ok=True)
        raise UserError(f"{out}: ffmpeg failed: {err.strip().splitlines()[-1] if err.strip() else 'unknown error'}")
    os.replace(tmp, out)
    return out


def render_positions(positions, parents: Sequence[int] | Sequence[Sequence[int]], out_path: str | Path,
                     fps: float = 30.0, size: tuple[int, int] = (320, 320), titles: Sequence[str] | None = None,
                     layout: str = "grid", contacts: Sequence[np.ndarray | None] | None = None,
                     names: Sequence[str] | Sequence[Sequence[str]] | None = None, up: str = "y",
                     azimuth: float = 35.0, elevation: float = 18.0, view: str | None = None) -> Path:
    """Render global joint positions (each ``(T, J, 3)``, any units) to a GIF/MP4 stick-figure preview.

    ``layout="grid"``: one panel per motion, each camera following its own root; ``"scene"``: all characters in
    one panel (crowds), the camera following their mean. ``contacts``: per motion ``(T, J)`` bool (or None), joints
    drawn larger in red while set. ``names`` colours left/right limbs. ``view``: also write the same motions as
    the 3D HTML viewer under this file name in the GIF's folder (:func:`modi.viz.viewer.write_beside`) unless
    :func:`modi.viz.view_pages` turned that off.
    Returns the written path.
    """
    out = _check_out(out_path)
    frames = render_frames(positions, parents, fps=fps, size=size, titles=titles, layout=layout, contacts=contacts,
                           names=names, up=up, azimuth=azimuth, elevation=elevation)
    path = save_frames(frames, out, fps)

    if view and view_pages_enabled():  # ``--no-view`` switches it off for a whole command

        pos = [_to_y_up(p, up) for p in _as_list(positions)]
        write_beside(out, pos, parents, names=names, fps=fps, contacts=contacts, titles=titles, layout=layout,
                     name=view)
    return path


def _resample_frames(n_src: int, src_fps: float, fps: float, max_frames: int | None) -> np.ndarray:
    """Frame indices that play a clip in real time at ``fps`` (nearest frame; no interpolation needed to preview)."""
    duration = (n_src - 1) / src_fps
    n = int(math.floor(duration * fps + 1e-3)) + 1   # tolerate frame times like 0.0333333
    if max_frames is not None:
        n = min(n, int(max_frames))
    return np.clip(np.round(np.arange(n) * src_fps / fps).astype(int), 0, n_src - 1)


def render_bvh(paths: Sequence[str | Path] | str | Path, out_path: str | Path, fps: float = 30.0,
               size: tuple[int, int] = (320, 320), layout: str = "grid", titles: Sequence[str] | None = None,
               contacts: bool = False, up: str = "y", max_frames: int | None = None,
               azimuth: float = 35.0, elevation: float = 18.0, scale: float | None = None) -> Path:
    """Preview one or more BVH files (in real time at ``fps``), each scaled to metres (``scale``, or its unit
    guessed from the body size as :func:`modi.io.gltf.guess_unit` does), so a crab in metres stands beside a
    human in centimetres at their true sizes. Missing files raise ``UserError``."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise UserError("no BVH files given")
    out = _check_out(out_path)
    if not fps > 0:
        raise UserError(f"fps must be > 0, got {fps}")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"max_frames must be >= 1, got {max_frames}")
    pos, parents, names, con = [], [], [], []
    for p in paths:
        if not p.is_file():
            raise UserError(f"{p}: no such file")
        if p.suffix.lower() != ".bvh":
            raise UserError(f"{p}: expected a .bvh file")
        b = bvh_io.load(p)
        xyz = _to_y_up(np.asarray(bvh_positions(b), dtype=np.float64), up)
        keep = _resample_frames(len(xyz), b.fps, fps, max_frames)
        if contacts:   # labelled on the clip's own frames, as the viewer page and the glTF export do

            con.append(preview_contacts(xyz, feet_of(b), b.fps, b.parents, b.names)[keep])
        xyz = xyz[keep] * (guess_unit(b.skeleton().height()).scale if scale is None else float(scale))
        pos.append(xyz)
        parents.append(list(b.parents))
        names.append(list(b.names))
    return render_positions(pos, parents, out, fps=fps, size=size, titles=titles or [p.stem for p in paths],
                            layout=layout, contacts=con if contacts else None, names=names, up="y",
                            azimuth=azimuth, elevation=elevation)
