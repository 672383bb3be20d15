"""Ctrl-C during a training loop: finish the current step, save a checkpoint, then stop (a second Ctrl-C aborts).

    with stop_on_sigint("iteration") as stop:
        while ...:
            train_one_step()
            if stop:
                save(); raise SomethingInterrupted(...)

Outside the main thread (where Python cannot install signal handlers) the flag simply never turns on.
"""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Iterator


class StopRequest:
    """True once Ctrl-C was pressed inside :func:`stop_on_sigint` (or :meth:`set` was called)."""

    def __init__(self) -> None:
        self.requested = False

    def set(self) -> None:
        self.requested = True

    def __bool__(self) -> bool:
        return self.requested


@contextmanager
def stop_on_sigint(unit: str = "step") -> Iterator[StopRequest]:
    """Within the block, the first SIGINT only sets the yielded flag and prints a notice to stderr (the loop is
    to finish its ``unit``, save and stop); a second one raises ``KeyboardInterrupt`` at once. The previous
    handler is restored on exit."""
    stop = StopRequest()

    def on_sigint(signum, frame) -> None:  # noqa: ARG001
        if stop:
            raise KeyboardInterrupt
        stop.set()
        print(f"\nmodi: stopping after this {unit} and saving a checkpoint (Ctrl-C again to abort)",
              file=sys.stderr, flush=True)

    installed = threading.current_thread() is threading.main_thread()
    old_handler = signal.signal(signal.SIGINT, on_sigint) if installed else None
    try:
        yield stop
    finally:
        if installed:
            # None: the previous handler was not set from Python; Python's own default is the closest
            signal.signal(signal.SIGINT, old_handler if old_handler is not None else signal.default_int_handler)


__all__ = ["StopRequest", "stop_on_sigint"]
