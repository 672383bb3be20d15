"""Faults a long run meets: preemption, a full disk, a second process in the same folder.

One place for what every long run needs, shared by ``modi train``, ``modi ganimator train`` and
``modi encoder train``:

* ``atomic_output`` / ``atomic_write`` / ``atomic_torch_save``: every file a command writes goes to a temp file in
  the same folder, is fsynced, then renamed over the final name, so a crash, SIGKILL or full disk never leaves half
  a file under it. A full disk or read-only folder becomes one :class:`OutputError` line naming the path (for a
  checkpoint also its size, the free space and that the previous one is intact). ``append_line`` does the same for
  append-only logs (a failed append is cut back off), ``output_errors`` for writers a library owns (TensorBoard).
* ``stop_on_signals``: within a training loop SIGINT and SIGTERM only set a flag; the loop finishes its step, saves
  a resumable checkpoint and stops (exit 130 for Ctrl-C, 143 for SIGTERM, as a shell reports a signal death);
  ``StopRequest.agreed`` makes every DDP rank stop at the same step. Outside the loops (``terminate_on_sigterm``,
  installed by ``modi.cli.main``) SIGTERM unwinds like Ctrl-C, so temp files and locks are cleared; exit 143.
* ``hold_run_folder``: an ``flock`` on ``RUN/.lock`` for the life of a run. A second run into the folder is refused
  at once, naming the holder; the kernel drops the lock when its process dies, so a killed run never leaves it stuck.
"""
from __future__ import annotations

import errno
import fcntl
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Iterable, Iterator

from modi.errors import OutputError, RunFolderBusy, UserError  # noqa: F401  (OutputError, RunFolderBusy re-exported)


def describe_os_error(exc: OSError, path: str | os.PathLike) -> str:
    """One line for an OS error writing ``path``: what a user can act on, not an errno dump."""
    if exc.errno == errno.ENOSPC:
        return f"no space left on the device writing {path}"
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return f"cannot write {path}: {exc.strerror.lower() if exc.strerror else exc}"
    return f"cannot write {path}: {exc.strerror or exc}"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_output(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temp file beside ``path`` for writing; on success fsync and rename it to ``path``; on any error
    remove it (``path`` keeps its previous content) and turn OS errors into :class:`OutputError`."""
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_output mode must be 'wb' or 'w', not {mode!r}")
    path = Path(path)
    held = _HeldSignals()  # a signal between creating the temp file and the try below would leave it behind
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except BaseException as exc:
        held.release()
        if isinstance(exc, OSError):
            raise OutputError(describe_os_error(exc, path), exc.errno) from None
        raise
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8", "newline": ""})) as f:
            held.release()  # a waiting signal lands here: the file is closed and removed below
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
        os.replace(tmp, path)
    except OSError as exc:
        _discard(tmp)
        held.release()  # (a no-op once released above)
        raise OutputError(describe_os_error(exc, path), exc.errno) from None
    except BaseException:
        _discard(tmp)
        held.release()
        raise


def atomic_write(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` (bytes, or str as UTF-8) to ``path`` atomically (see :func:`atomic_output`)."""
    with atomic_output(path, "wb") as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)


def atomic_save_npy(path: str | os.PathLike, array: Any) -> None:
    """``np.save`` through :func:`atomic_output` (to a file object, so numpy adds no ``.npy`` to the name)."""
    import numpy as np  # lazy, as torch below: the CLI imports this module first, to own Ctrl-C from the start

    with atomic_output(path, "wb") as f:
        np.save(f, array)


@contextmanager
def output_errors(path: str | os.PathLike) -> Iterator[None]:
    """OS errors inside the block (a library writing ``path``, e.g. TensorBoard's event files) become one
    :class:`OutputError` line."""
    _quiet_writer_threads()
    try:
        yield
    except OSError as exc:
        raise OutputError(describe_os_error(exc, path), exc.errno) from None


_WRITER_THREADS = ("_AsyncWriterThread",)  # tensorboard's event-file thread: it hands its error to the caller


def _quiet_writer_threads() -> None:
    """TensorBoard appends its event files from a thread; on a full disk that thread dies printing a traceback, and
    the library re-raises the same OSError at the next ``add_scalar``/``flush`` -- where ``output_errors`` makes it
    one line. Keep the thread's copy off stderr (installed once; other threads' errors are untouched)."""
    if getattr(threading.excepthook, "_modi_quiet", False):
        return
    previous = threading.excepthook

    def hook(args) -> None:
        if isinstance(args.exc_value, OSError) and type(args.thread).__name__ in _WRITER_THREADS:
            return
        previous(args)

    hook._modi_quiet = True  # type: ignore[attr-defined]
    threading.excepthook = hook


def append_line(path: str | os.PathLike, line: str) -> None:
    """Append one line to a log; if it cannot be written whole (disk full), cut the file back to where it was, so
    a log never ends in half a record, and raise :class:`OutputError`."""
    path = Path(path)
    data = (line if line.endswith("\n") else line + "\n").encode("utf-8")
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    except OSError as exc:
        raise OutputError(describe_os_error(exc, path), exc.errno) from None
    try:
        size = os.fstat(fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
        except OSError as exc:
            try:
                os.ftruncate(fd, size)
            except OSError:
                pass
            raise OutputError(describe_os_error(exc, path), exc.errno) from None
    finally:
        os.close(fd)


def _discard(tmp: str) -> None:
    try:
        os.unlink(tmp)
    except OSError:
        pass


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove temp files that an atomic write of ``path`` left when its process was killed mid-write (call only
    while holding the run's lock, so no live writer owns them); returns what was removed."""
    path = Path(path)
    gone = []
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            tmp.unlink()
            gone.append(tmp)
        except OSError:
            pass
    return gone


# ============================================================================================ checkpoints
class _Recorder:
    """File wrapper that keeps the OSError of a failed write: ``torch.save`` reports it as an opaque
    ``RuntimeError: [enforce fail at inline_container.cc] unexpected pos``."""

    def __init__(self, f: IO) -> None:
        self.f, self.error = f, None

    def write(self, b) -> int:
        try:
            return self.f.write(b)
        except OSError as exc:
            self.error = exc
            raise

    def flush(self) -> None:
        self.f.flush()


class _Counter:
    def __init__(self) -> None:
        self.n = 0

    def write(self, b) -> int:
        self.n += len(b)
        return len(b)

    def flush(self) -> None:
        pass


def human_bytes(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} TB"  # pragma: no cover


def _previous_text(path: Path, previous_step: int | str | None) -> str:
    if not path.is_file():
        return f"nothing was written to {path.name}"
    if previous_step is None:
        return "the previous checkpoint is intact"
    where = f"step {previous_step}" if isinstance(previous_step, int) else previous_step
    return f"the previous checkpoint ({where}) is intact"


def atomic_torch_save(obj: Any, path: str | os.PathLike, *, previous_step: int | str | None = None) -> Path:
    """``torch.save`` through :func:`atomic_output`. A full disk is one :class:`OutputError` line: the path, the
    checkpoint's size against the free space (an atomic save needs room for a second copy beside the previous
    one) and that the previous checkpoint (``previous_step``: a step, or a position such as "block 2/4, iteration
    30") is intact; a read-only folder likewise."""
    import torch  # lazy: the CLI imports this module before torch, to own Ctrl-C and SIGTERM from the start

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(describe_os_error(exc, path), exc.errno) from None
    try:
        with atomic_output(path, "wb") as f:
            rec = _Recorder(f)
            try:
                torch.save(obj, rec)
            except Exception:  # noqa: BLE001 - the OS error behind torch's opaque one, if any
                if rec.error is not None:
                    raise rec.error from None
                raise
    except OutputError as exc:
        if exc.errno == errno.ENOSPC:
            count = _Counter()
            torch.save(obj, count)
            try:
                free = human_bytes(shutil.disk_usage(path.parent).free)
            except OSError:
                free = "unknown"
            raise OutputError(
                f"no space left on the device writing {path}: the checkpoint needs {human_bytes(count.n)} "
                f"({count.n} bytes) free beside the previous one (an atomic save writes a second copy before "
                f"replacing it), {free} free; {_previous_text(path, previous_step)}", exc.errno) from None
        raise OutputError(f"{exc}; {_previous_text(path, previous_step)}", exc.errno) from None
    return path


# ============================================================================================ stop signals
def exit_code(signum: int | None) -> int:
    """The exit status of a run stopped by ``signum`` (128 + its number, as a shell reports a signal death):
    130 for Ctrl-C, 143 for SIGTERM."""
    return 128 + int(signum) if signum else 130


class StopRequest:
    """True once SIGINT/SIGTERM arrived inside :func:`stop_on_signals` (or :meth:`set` was called); ``signum`` is
    the signal (SIGTERM wins over SIGINT: it is the scheduler's word)."""

    def __init__(self) -> None:
        self.requested = False
        self.signum: int | None = None
        self.error: BaseException | None = None

    def set(self, signum: int = signal.SIGINT) -> None:
        self.requested = True
        if self.signum is None or signum == signal.SIGTERM:
            self.signum = int(signum)

    def __bool__(self) -> bool:
        return self.requested

    @property
    def exit_code(self) -> int:
        return exit_code(self.signum)

    def fail(self, exc: BaseException) -> None:
        """Record an error of this process only (rank 0 writing its log on a full disk): :meth:`agreed` raises it
        on every rank at the same step, instead of one rank leaving the others hung in a collective."""
        self.error = exc

    def agreed(self, device: Any = None) -> bool:
        """The flag as every process of a ``torch.distributed`` group sees it (a MAX all-reduce of the signal
        number and of :meth:`fail`), so all ranks stop at the same step even when only one was signalled, and a
        recorded error is raised on all of them; the local flag otherwise. Every rank must call it at the same
        point of each step."""
        import torch  # lazy: see atomic_torch_save
        import torch.distributed as dist

        distributed = dist.is_available() and dist.is_initialized()
        if not distributed:
            if self.error is not None:
                raise self.error
            return bool(self)

        t = torch.tensor([self.signum or 0, int(self.error is not None)], dtype=torch.int64, device=device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        s, failed = int(t[0].item()), int(t[1].item())
        if failed:
            if self.error is not None:
                raise self.error
            raise UserError("another process of this run could not write its output (see rank 0's message)")
        if s and (not self.requested or s == signal.SIGTERM):
            self.set(s)
        return bool(s)


@contextmanager
def stop_on_signals(unit: str = "step", stop: StopRequest | None = None, *, notice: bool = True,
                    insist: bool = True) -> Iterator[StopRequest]:
    """Within the block the first SIGINT or SIGTERM only sets the yielded flag (and says so on stderr): the loop
    is to finish its ``unit``, save and stop. A second Ctrl-C raises ``KeyboardInterrupt`` at once (the user
    insists) unless ``insist`` is False -- under torchrun, where a Ctrl-C reaches each worker twice, from the
    terminal and forwarded by the agent; a second SIGTERM is ignored -- the save is under way, and SIGKILL is the
    scheduler's way to insist. The previous handlers are restored on exit. Outside the main thread the flag never
    turns on by signal."""
    stop = stop if stop is not None else StopRequest()

    def say(text: str) -> None:
        if notice:
            print(f"\nmodi: {text}", file=sys.stderr, flush=True)

    def on_sigint(signum, frame) -> None:  # noqa: ARG001
        if stop and insist:
            raise KeyboardInterrupt
        if stop:
            return
        stop.set(signal.SIGINT)
        say(f"stopping after this {unit} and saving a checkpoint" + (" (Ctrl-C again to abort)" if insist else ""))

    def on_sigterm(signum, frame) -> None:  # noqa: ARG001
        first = stop.signum != signal.SIGTERM
        stop.set(signal.SIGTERM)
        if first:
            say(f"SIGTERM: stopping after this {unit} and saving a checkpoint")

    installed = threading.current_thread() is threading.main_thread()
    old = {}
    if installed:
        old[signal.SIGINT] = signal.signal(signal.SIGINT, on_sigint)
        old[signal.SIGTERM] = signal.signal(signal.SIGTERM, on_sigterm)
        if sigterm_pending():  # a SIGTERM before the loop whose Terminated was swallowed: stop at the first step
            on_sigterm(signal.SIGTERM, None)
    try:
        yield stop
    finally:
        for sig, handler in old.items():
            # None: the previous handler was not set from Python; Python's own default is the closest
            signal.signal(sig, handler if handler is not None else (
                signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL))


class Terminated(BaseException):
    """SIGTERM outside a training loop: unwinds like Ctrl-C (temp files removed, locks released); exit 143.
    A ``BaseException``, so the ``except Exception`` of a preview writer cannot swallow it."""


_sigterm_seen = False


def sigterm_pending() -> bool:
    """True once :func:`terminate_on_sigterm`'s handler ran. An exception raised from a signal handler is lost
    when it lands in a finaliser or a callback that Python runs with errors ignored ("Exception ignored in ..."),
    so the process would carry on as if never signalled; training loops and ``modi.cli.main`` check this flag."""
    return _sigterm_seen


@contextmanager
def terminate_on_sigterm() -> Iterator[None]:
    """Within the block SIGTERM raises :class:`Terminated` instead of killing the process outright (Python's
    default), so ``finally`` blocks run. Training loops install :func:`stop_on_signals` inside it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_sigterm(signum, frame) -> None:  # noqa: ARG001
        global _sigterm_seen
        _sigterm_seen = True
        raise Terminated()

    old = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)


class _HeldSignals:
    """SIGINT / SIGTERM arriving between construction and :meth:`release` are recorded instead of handled, then
    handed to the handlers that were in place, once each, by :meth:`release`. For the few lines where an exception
    from a handler would land between creating a resource and the ``try`` that removes it. Main thread only
    (elsewhere Python runs no handlers); a handler of ``SIG_DFL`` gets the signal re-raised, as it would have."""

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self._old: dict[int, Any] = {}
        self._got: list[int] = []
        if threading.current_thread() is threading.main_thread():
            for sig in self._SIGNALS:
                self._old[sig] = signal.signal(sig, lambda signum, frame: self._got.append(signum))

    def release(self) -> None:
        """Idempotent: a second call (after a handler raised from the first) does nothing."""
        old, self._old = self._old, {}
        got, self._got = self._got, []
        for sig, handler in old.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        for sig in dict.fromkeys(got):
            handler = old[sig]
            if callable(handler):
                handler(sig, None)
            elif handler == signal.SIG_DFL or handler is None:
                signal.raise_signal(sig)


@contextmanager
def signals_held() -> Iterator[None]:
    """SIGINT / SIGTERM wait until the block is over, then take effect as usual (Ctrl-C raises KeyboardInterrupt).

    For importing torch: torch's C++ start-up imports numpy and swallows any error from it, KeyboardInterrupt
    included, leaving a half-imported numpy behind (the next ``np.add`` is an AttributeError), and a Python error
    inside one of its pybind11 calls aborts the process. A Ctrl-C during the import therefore waits the second
    or two the import takes."""
    held = _HeldSignals()
    try:
        yield
    finally:
        held.release()


# ============================================================================================ run-folder lock
LOCK_NAME = ".lock"
_held: dict[str, list] = {}  # lock file -> [fd, depth]: this process's locks (re-entrant within a process)


def _holder_text(lock: Path) -> str:
    try:
        lines = lock.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        lines = []
    fields = dict(line.split("=", 1) for line in lines if "=" in line)
    if "pid" not in fields:
        return "another process (it has not written its pid yet)"
    cmd = fields.get("command", "").strip()
    cmd = cmd if len(cmd) <= 160 else cmd[:157] + "..."
    return (f"pid {fields['pid']} on {fields.get('host', '?')}, since {fields.get('started', '?')}"
            + (f": {cmd}" if cmd else ""))


def _command_line() -> str:
    prog = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python"
    prog = "modi" if prog in ("modi", "__main__.py", "-m") else prog
    return " ".join([prog, *sys.argv[1:]]).replace("\n", " ")


@contextmanager
def hold_run_folder(folder: str | os.PathLike, lock_name: str = LOCK_NAME, what: str | None = None
                    ) -> Iterator[Path]:
    """Hold an exclusive ``flock`` on ``folder/lock_name`` (created with the folder) for the block; the file names
    the holder (pid, host, start time, command). If another process holds it, raise :class:`RunFolderBusy` at
    once naming it. The kernel releases the lock when the process dies, however it dies; the file is removed on a
    clean exit. Re-entrant within one process (a command and the trainer it calls may both take it)."""
    folder = Path(folder)
    lock = folder / lock_name
    key = os.path.realpath(lock)
    if key in _held:
        _held[key][1] += 1
        try:
            yield lock
        finally:
            _held[key][1] -= 1
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(describe_os_error(exc, folder), exc.errno) from None
    # From creating the file to the try that removes it, a SIGTERM (Terminated) or Ctrl-C would leave the file
    # behind: they wait, and arrive inside the try.
    held = _HeldSignals()
    try:
        fd = _lock_file(lock, folder, what)
    except BaseException:
        held.release()
        raise
    info = (f"pid={os.getpid()}\nhost={socket.gethostname()}\nstarted={time.strftime('%Y-%m-%d %H:%M:%S')}\n"
            f"command={_command_line()}\n").encode("utf-8")
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, info, 0)
    except OSError:
        pass  # a full disk: the lock still works, only the holder's name is missing
    _held[key] = [fd, 1]
    try:
        held.release()
        yield lock
    finally:
        held = _HeldSignals()  # a second signal must not skip the removal either
        try:
            _held.pop(key, None)
            try:
                os.unlink(lock)  # still holding it: nobody can have locked this file meanwhile
            except OSError:
                pass
            os.close(fd)
        finally:
            held.release()


def _lock_file(lock: Path, folder: Path, what: str | None) -> int:
    """The open, exclusively flock-ed descriptor of ``lock`` (created if needed), or RunFolderBusy naming the
    holder."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise OutputError(describe_os_error(exc, lock), exc.errno) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RunFolderBusy(f"{what or folder} is in use by another run ({_holder_text(lock)}): wait for "
                                    f"it to end, or choose another --out") from None
            raise OutputError(describe_os_error(exc, lock), exc.errno) from None
        try:  # the holder we waited on may have removed the file before we locked it: lock the current one
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


__all__ = ["OutputError", "RunFolderBusy", "sigterm_pending", "atomic_output", "atomic_write", "atomic_torch_save",
           "atomic_save_npy", "append_line",
           "output_errors", "describe_os_error", "remove_stale_temps", "human_bytes", "StopRequest",
           "stop_on_signals", "exit_code", "Terminated", "terminate_on_sigterm", "hold_run_folder", "LOCK_NAME"]


def refuse_overwrite(output: str | os.PathLike, inputs: Iterable[str | os.PathLike], what: str = "output") -> None:
    """``UserError`` when ``output`` is (or links to) one of the ``inputs``: never write over what we read."""
    out = Path(output)
    if not out.exists():
        return
    for inp in inputs:
        try:
            same = Path(inp).exists() and os.path.samefile(out, inp)
        except OSError:
            same = False
        if same:
            raise UserError(f"{what} {output} is the input file {inp}; refusing to write over an input")


def unique_names(option: str, names: Iterable[str] | None) -> None:
    """``UserError`` for a joint given twice in ``option`` (e.g. ``--feet LeftToe LeftToe``)."""
    if not names:
        return
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise UserError(f"{option}: joint {n!r} is given twice")
        seen.add(n)


def existing_file(path: str | os.PathLike, what: str = "BVH file", option: str = "") -> Path:
    """``UserError`` unless ``path`` is an existing file: says whether it is missing or a folder (the one check of
    input files: the API's and the CLI's arguments alike)."""
    p = Path(path)
    pre = f"{option} " if option else ""
    if p.is_dir():
        raise UserError(f"{pre}{path}: is a folder, expected {'an' if what[:1] in 'aeiou' else 'a'} {what}")
    if not p.is_file():
        raise UserError(f"{pre}{path}: no such {what}")
    return p
