"""Looking at motion: stick-figure GIF/MP4 previews (``render``) and a self-contained 3D HTML viewer (``viewer``).

Every GIF preview a command writes gets the viewer page beside it (``view.html``, or ``NAME.html`` where a folder
holds several previews). ``--no-view`` turns that off for one command: :func:`add_view_option` adds the option and
runs the command inside :func:`view_pages`, a context switch the writers consult, so the flag needs no plumbing
through every function between the command and the writer. Submodules are imported lazily so ``import modi.viz``
stays cheap (no Pillow, no torch) for the CLI and notebooks.
"""
from __future__ import annotations

import contextvars
from contextlib import contextmanager
from typing import Iterator

_PAGES = contextvars.ContextVar("modi_view_pages", default=True)


@contextmanager
def view_pages(enabled: bool) -> Iterator[None]:
    """Within the block, GIF writers write the viewer page beside their GIF only if ``enabled``."""
    token = _PAGES.set(bool(enabled))
    try:
        yield
    finally:
        _PAGES.reset(token)


def view_pages_enabled() -> bool:
    return _PAGES.get()


def add_view_option(parser) -> None:
    """Add ``--no-view`` to a command parser whose ``func`` is set, and honour it while the command runs."""
    func = parser.get_default("func")
    if func is None:
        raise ValueError(f"{parser.prog}: set the command's func before adding --no-view")
    parser.add_argument("--no-view", action="store_true",
                        help="do not write the 3D viewer page (view.html) beside the GIF previews")

    def run(args):
        with view_pages(not getattr(args, "no_view", False)):
            return func(args)

    parser.set_defaults(func=run)


def show(*motions, **kwargs):
    """Inline 3D viewer for notebooks; see :func:`modi.viz.viewer.show`."""
    from modi.viz.viewer import show as _show
    return _show(*motions, **kwargs)


__all__ = ["show", "view_pages", "view_pages_enabled", "add_view_option"]
