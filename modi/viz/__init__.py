"""Looking at motion: stick-figure GIF/MP4 previews (``render``) and a self-contained 3D HTML viewer (``viewer``).

Every GIF preview a command writes gets the viewer page beside it (``view.html``, or ``NAME.html`` where a folder
holds several previews). ``--no-view`` turns that off for one command: :func:`add_view_option` adds the option and
runs the command inside :func:`view_pages`, a context switch the writers consult, so the flag needs no plumbing
through every function between the command and the writer. Submodules are imported lazily so ``import modi.viz``
stays cheap (no Pillow, no torch) for the CLI and notebooks.
"""
from __future__ import annotations

from modi.viz.pages import add_view_option, view_pages, view_pages_enabled
from modi.viz.viewer import show as _show


def show(*motions, **kwargs):
    """Inline 3D viewer for notebooks; see :func:`modi.viz.viewer.show`."""
    return _show(*motions, **kwargs)


__all__ = ["show", "view_pages", "view_pages_enabled", "add_view_option"]
