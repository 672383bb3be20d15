"""Faults a long run meets: preemption, a full disk, a second process in the same folder.

One place for the three things that belong together (issue 22):

* ``atomic_output`` / ``atomic_write``: every file a command writes goes to a temp file in the same folder, is
  fsynced, then renamed over the final name, so a crash, SIGKILL or full disk never leaves half a file under it. A
  full disk or read-only folder becomes one :class:`OutputError` line naming the path.
* (to come) the SIGINT/SIGTERM stop flag and the run-folder lock.
"""
from __future__ import annotations

import errno
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterator

from modi.errors import UserError


class OutputError(UserError):
    """An output could not be written (no space left, read-only folder, permission): the final name is untouched."""


def _describe(exc: OSError, path: Path) -> str:
    if exc.errno == errno.ENOSPC:
        return f"no space left on the device writing {path}"
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return f"cannot write {path}: {exc.strerror.lower() if exc.strerror else exc}"
    return f"cannot write {path}: {exc}"


@contextmanager
def atomic_output(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temp file beside ``path`` for writing; on success fsync and rename it to ``path``; on any error
    remove it (``path`` keeps its previous content) and turn OS errors into :class:`OutputError`."""
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_output mode must be 'wb' or 'w', not {mode!r}")
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise OutputError(_describe(exc, path)) from None
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8", "newline": ""})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        _discard(tmp)
        raise OutputError(_describe(exc, path)) from None
    except BaseException:
        _discard(tmp)
        raise


def atomic_write(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (bytes, or str as UTF-8) to ``path`` atomically (see :func:`atomic_output`)."""
    with atomic_output(path, "wb") as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)


def _discard(tmp: str) -> None:
    try:
        os.unlink(tmp)
    except OSError:
        pass


__all__ = ["OutputError", "atomic_output", "atomic_write"]
