"""Another user's job, on demand: spinning helper processes that keep cores busy while a benchmark times.

No torch here: ``start_early`` runs before the benchmark imports modi_ext and torch, so the load is already there
when ``modi_ext.runtime.omp_wait`` looks at the machine, as it is for a user whose job starts on a shared node.
"""
from __future__ import annotations

import contextlib
import os
import time


def _spin(ready, parent: int, core: int | None) -> None:
    """Busy helper: one pure-Python spinning loop on `core`, until the parent process is gone."""
    if core is not None:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, {core})
    ready.set()
    while os.getppid() == parent:
        for _ in range(200_000):
            pass


@contextlib.contextmanager
def busy_cores(n: int):
    """Keep `n` cores busy (the last `n` this process may use, one pinned spinning process each) for the block,
    as another user's job would; yields the cores taken (None: pinning unavailable)."""
    if n <= 0:
        yield []
        return
    import multiprocessing as mp

    try:
        allowed = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        allowed = []
    cores = allowed[-n:] if len(allowed) >= n else [None] * n
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else None)
    procs, events = [], []
    try:
        for core in cores:
            ev = ctx.Event()
            p = ctx.Process(target=_spin, args=(ev, os.getpid(), core), daemon=True)
            p.start()
            procs.append(p)
            events.append(ev)
        for ev in events:
            ev.wait(30)
        time.sleep(0.2)
        yield cores
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.join(5)


class _Early(contextlib.ExitStack):
    """The helpers started by ``start_early``; ``with`` it yields their cores, as ``busy_cores`` does."""

    cores: list

    def __enter__(self) -> list:
        return self.cores


def start_early(argv: list[str]) -> _Early | None:
    """Start ``--busy N`` (or ``--busy=N``) from a raw argv before heavy imports; None when not asked for.  The
    returned stack stops the helpers when closed (they also stop when this process exits)."""
    n = 0
    for i, a in enumerate(argv):
        v = a.split("=", 1)[1] if a.startswith("--busy=") else (argv[i + 1] if a == "--busy" and i + 1 < len(argv)
                                                                 else None)
        if v is not None:
            try:
                n = int(v)
            except ValueError:
                return None  # argparse reports it
    if n <= 0:
        return None
    stack = _Early()
    stack.cores = stack.enter_context(busy_cores(n))
    return stack
