"""Looking at motion: stick-figure GIF/MP4 previews (``render``) and a self-contained 3D HTML viewer (``viewer``).

Submodules are imported lazily so ``import modi.viz`` stays cheap (no Pillow, no torch) for notebooks.
"""
from __future__ import annotations


def show(*motions, **kwargs):
    """Inline 3D viewer for notebooks; see :func:`modi.viz.viewer.show`."""
    from modi.viz.viewer import show as _show
    return _show(*motions, **kwargs)


__all__ = ["show"]
