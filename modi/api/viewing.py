"""``modi.show``: the 3D viewer (one self-contained HTML page) for motions, files and plain position arrays."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from modi.data.motion import Motion
from modi.errors import UserError
from modi.viz.viewer import ViewMotion, Viewer, as_view_motions, from_positions
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


__all__ = ["show"]
