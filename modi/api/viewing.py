"""``modi.show``: the 3D viewer (one self-contained HTML page) for motions, files and plain position arrays."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from modi.data.motion import Motion
from modi.errors import UserError
from modi.faults import existing_file, refuse_overwrite
from modi.viz.render import render_bvh
from modi.viz.viewer import ViewMotion, Viewer, as_view_motions, from_positions, load_motion, write_view
from modi.viz.viewer import show as _show_page


def _view(item: Motion, title: str) -> ViewMotion:
    sk = item.skeleton
    contacts = None
    if item.contacts:
        contacts = np.zeros((item.n_frames, sk.n_joints), dtype=bool)
        for name, c in item.contacts.items():
            contacts[:, sk.names.index(name)] = c.numpy()
    return from_positions(item.positions(unit="m").detach().cpu(), sk.parents, sk.names, item.fps,
                          contacts=contacts, title=title)


def show(*items: Any, parents: Sequence[int] | None = None, names: Sequence[str] | None = None, fps: float = 30.0,
         scale: float = 1.0, titles: Sequence[str] | None = None, out: str | os.PathLike | None = None,
         layout: str = "grid", height: int = 480) -> Viewer | None:
    """Show motions in the 3D viewer: :class:`modi.Motion` objects (in metres from their known unit, with their
    contact labels), paths to ``.bvh`` / ``.glb`` / ``.gltf`` files, or plain global position arrays ``(T, J, 3)``
    (numpy or torch) with ``parents`` (and optionally ``names``, ``fps``, and ``scale`` metres per unit).

    ``layout``: ``"grid"`` (side by side) or ``"scene"`` (one scene). ``out`` writes the page there (one HTML file
    that opens offline) and returns the :class:`~modi.viz.viewer.Viewer`. Otherwise, inside a notebook the viewer is
    displayed inline and None returned; elsewhere the Viewer is returned (``.html``, ``.save(path)``). Cost: one FK
    pass per motion and an HTML page of well under a megabyte for a few clips."""
    if len(items) == 1 and isinstance(items[0], (list, tuple)):
        items = tuple(items[0])
    if not items:
        raise UserError("nothing to show: give at least one motion")
    views: list[ViewMotion] = []
    for i, it in enumerate(items):
        title = titles[i] if titles is not None and i < len(titles) else None
        if isinstance(it, Motion):
            views.append(_view(it, title or f"motion {i}"))
        elif isinstance(it, (str, os.PathLike, ViewMotion)):
            v = as_view_motions([it])[0]
            if title:
                v.title = title
            views.append(v)
        elif hasattr(it, "shape") and len(it.shape) == 3:
            if parents is None:
                raise UserError(f"item {i}: a position array needs parents=[...] (the parent index of each joint)")
            views.append(from_positions(it, parents, names, fps, title=title or f"motion {i}", scale=scale))
        else:
            raise UserError(f"item {i}: expected a Motion, a .bvh/.glb/.gltf path or a (T, J, 3) position array, "
                            f"got {type(it).__name__}")
    if out is not None:
        viewer = Viewer(views, layout=layout, height=height)
        viewer.save(Path(out))
        return viewer
    return _show_page(*views, layout=layout, height=height)


def render(inputs: Sequence[str | os.PathLike], out: str | os.PathLike, *, fps: float = 30.0,
           size: tuple[int, int] = (320, 320), layout: str = "grid", contacts: bool = False, up: str = "y",
           scale: float | None = None, max_frames: int | None = None, azimuth: float = 35.0, elevation: float = 18.0,
           view: bool = True) -> tuple[Path, Path | None]:
    """``modi render``: a stick-figure GIF (or MP4 with ffmpeg) of BVH files, each scaled to metres (``scale``, or
    its unit guessed), and with ``view`` the 3D viewer page ``OUT.html`` beside it. Returns the preview's and the
    page's paths. Cost: drawing every frame (about a second per hundred frames and panel)."""
    for f in inputs:
        existing_file(f)
    if not str(out).lower().endswith((".gif", ".mp4")):
        raise UserError(f"{out}: the last argument is the output and must end in .gif or .mp4")
    refuse_overwrite(out, inputs)
    page = Path(out).with_suffix(".html")
    if view:
        refuse_overwrite(page, inputs, "viewer page")
    path = render_bvh(list(inputs), out, fps=fps, size=size, layout=layout, contacts=contacts, up=up,
                      max_frames=max_frames, azimuth=azimuth, elevation=elevation, scale=scale)
    if not view:
        return path, None
    write_view(page, [load_motion(f, scale=scale, up=up) for f in inputs], layout=layout)
    return path, page


def write_page(inputs: Sequence[str | os.PathLike], out: str | os.PathLike = "view.html", *,
               scale: float | None = None, up: str = "y", contacts: bool = True, title: str | None = None,
               layout: str = "grid") -> list[ViewMotion]:
    """``modi view``: one offline HTML page playing BVH/glTF files in 3D (BVH units guessed unless ``scale``).
    Returns the motions shown (each with its guessed ``unit``). Cost: one FK pass per file."""
    page = Path(out)
    if page.suffix.lower() not in (".html", ".htm"):
        raise UserError(f"--out {out}: the page must end in .html")
    for f in inputs:
        refuse_overwrite(page, [f])
    motions = [load_motion(f, scale=scale, up=up, contacts=contacts) for f in inputs]
    page.parent.mkdir(parents=True, exist_ok=True)
    write_view(page, motions, title=title, layout=layout)
    return motions


__all__ = ["show", "render", "write_page"]
