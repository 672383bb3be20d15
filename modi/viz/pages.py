"""Whether GIF writers put the 3D viewer page beside their GIF: a context switch (``--no-view``) that the writers
consult, so the flag needs no plumbing through every function between the command and the writer."""
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
