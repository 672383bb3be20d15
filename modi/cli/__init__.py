"""The single ``modi`` console entry point.

Subcommands live one module per family in ``modi.cli.commands``; each module exposes
``register(subparsers)`` that adds its parsers and sets ``func`` on them. ``main``
turns user mistakes (``UserError`` and friends) into one line on stderr and exit code 2:

* bad arguments are refused by the argparse types of ``modi.cli.types`` while parsing, naming the option, in one
  line (``ModiArgumentParser.error`` prints no usage block; ``--help`` has it);
* ``UserError`` and OS errors about files (missing, a folder, not a folder, no permission, disk full) are one line;
  an output folder the command created and left empty when it failed is removed again;
* Ctrl-C at any moment -- while torch is imported, while parsing, while running -- prints ``modi: interrupted`` and
  exits 130 (``modi train``, ``modi ganimator train`` and ``modi encoder train`` catch it earlier and save a
  resumable checkpoint; SIGTERM there does the same and exits 143, see ``modi.faults``); SIGTERM elsewhere unwinds
  the same way as Ctrl-C (no temp file left behind) and exits 143;
* a full disk, a read-only folder, or a run folder another run holds is one line and exit 2 (``modi.faults``);
* a lost peer of a distributed run (a killed or hung rank, a lost machine) is one line and exit 75
  (``modi.errors.PeerLostError``, EX_TEMPFAIL: continue with ``--resume auto``, or torchrun restarts it);
* anything else is a bug: one line naming the exception, and ``MODI_TRACEBACK=1`` re-raises it with its traceback.
"""
from __future__ import annotations

import argparse
import errno
import os
import shutil
import sys
from pathlib import Path

from modi._version import __version__
from modi.errors import UserError
from modi.faults import Terminated, describe_os_error, sigterm_pending, signals_held, terminate_on_sigterm

TRACEBACK_ENV = "MODI_TRACEBACK"


class BadArguments(Exception):
    """A command line argparse refused; ``main`` prints it as one line and returns 2 (no ``SystemExit``)."""


class ModiArgumentParser(argparse.ArgumentParser):
    """argparse with a one-line error: ``modi CMD: error: argument --x: why (see 'modi CMD --help')``."""

    def error(self, message: str):  # type: ignore[override]
        raise BadArguments(f"{self.prog}: error: {message} (see '{self.prog} --help')")


def build_parser() -> argparse.ArgumentParser:
    import importlib
    import pkgutil

    parser = ModiArgumentParser(
        prog="modi",
        description="MoDi and GANimator motion synthesis: data tools, training, generation, evaluation.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=version_line(),
                        help="print modi's version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=ModiArgumentParser)
    import modi.cli.commands as commands

    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"modi.cli.commands.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    from modi.cli.types import use_help_formatter

    use_help_formatter(parser)  # no "(default: None)" in any help
    return parser


def _say(message: str) -> None:
    print(f"modi: error: {message}", file=sys.stderr, flush=True)


_OUTPUT_DESTS = ("out", "out_dir")  # argument names of output folders (or files) across the commands


def _new_output_roots(args: argparse.Namespace) -> list[Path]:
    """For each output path of the command, the top-most part of it that does not exist yet (what it creates)."""
    roots = []
    for dest in _OUTPUT_DESTS:
        value = getattr(args, dest, None)
        if not isinstance(value, str) or not value:
            continue
        p = Path(value).absolute()
        if p.exists():
            continue
        while not p.parent.exists() and p.parent != p:
            p = p.parent
        roots.append(p)
    return roots


def _remove_if_empty(root: Path) -> None:
    """Remove a folder tree that holds no file (what a command that failed early leaves behind)."""
    try:
        if root.is_dir() and not any(q.is_file() or q.is_symlink() for q in root.rglob("*")):
            shutil.rmtree(root)
    except OSError:
        pass


def version_line() -> str:
    """What ``modi --version`` prints: the one version string (``modi/_version.py``)."""
    return f"modi {__version__}"


def _run(argv: list[str] | None) -> int:
    if (sys.argv[1:] if argv is None else list(argv))[:1] == ["--version"]:  # answered before torch is imported
        print(version_line())
        return 0
    with signals_held():  # a Ctrl-C inside torch's C++ start-up would half-import numpy or abort: it waits
        import modi_ext  # noqa: F401  first, before the commands import torch: it picks the OpenMP spin (omp_wait)
        import numpy  # noqa: F401
        import torch  # noqa: F401
    from modi.models.optim import retain_freed_memory  # imports torch: after the held start-up above

    retain_freed_memory()  # every command's tensors: freed blocks reused, not page-faulted in anew
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    created = _new_output_roots(args)
    try:
        from modi.io.formats import requested  # --format / --gltf-scale of commands that write motion

        with requested(getattr(args, "format", None), getattr(args, "gltf_scale", None), vars(args).values()):
            return int(func(args) or 0)
    except BaseException:
        for root in created:  # a user error found after the output folder was made: leave nothing behind
            _remove_if_empty(root)
        raise


_kept: list = []  # what leave_without_teardown keeps alive until os._exit


def leave_without_teardown(*keep) -> None:
    """Have :func:`main` end the process with ``os._exit`` once its line is printed, keeping ``keep`` alive until
    then: a command that used a torch.distributed process group must not tear it down. Freeing DDP's reducer frees
    the gloo group, whose destructor joins gloo's worker threads while holding the GIL -- and a worker thread still
    releasing the tensors of its last collective waits for the GIL: a deadlock, seen under torchrun as a worker
    that never exits; after a lost peer, interpreter shutdown can abort instead ("terminate called without an
    active exception"). Every file the command wrote is closed (and checkpoints fsynced) by then."""
    _kept.append(keep)


def main(argv: list[str] | None = None) -> int:
    code = _main(argv)
    if _kept:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    return code


def _main(argv: list[str] | None = None) -> int:
    try:
        with terminate_on_sigterm():
            code = _run(argv)
            if sigterm_pending() and code == 0:  # signalled, but its Terminated was swallowed on the way
                raise Terminated()
            return code
    except Terminated:
        print("\nmodi: terminated (SIGTERM)", file=sys.stderr, flush=True)
        return 143
    except BadArguments as exc:
        print(exc, file=sys.stderr, flush=True)
        return 2
    except UserError as exc:  # 2, or 75 for a lost peer of a distributed run (PeerLostError)
        _say(str(exc))
        return int(getattr(exc, "exit_code", 2))
    except KeyboardInterrupt:
        print("\nmodi: interrupted", file=sys.stderr, flush=True)
        return 130
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, FileExistsError, PermissionError) as exc:
        what = {FileNotFoundError: "no such file or folder", IsADirectoryError: "is a folder, expected a file",
                NotADirectoryError: "a part of the path is a file, not a folder",
                FileExistsError: "already exists", PermissionError: "permission denied"}.get(type(exc))
        _say(f"{exc.filename}: {what or exc.strerror}" if exc.filename else str(exc))
        return 2
    except BrokenPipeError:  # `modi info RUN | head`: the reader left; say nothing, as a shell tool killed by SIGPIPE
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        except OSError:
            pass
        return 141
    except MemoryError:
        _say("out of memory: ask for fewer or shorter motions, or a smaller --batch")
        return 2
    except OSError as exc:  # disk full, read-only file system, ...: the environment, not a bug
        if exc.filename and exc.errno in (errno.ENOSPC, errno.EROFS):
            _say(describe_os_error(exc, exc.filename))
        else:
            _say(f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror or exc}")
        return 2
    except Exception as exc:  # noqa: BLE001 - last resort: a bug
        text = str(exc)
        if type(exc).__name__ == "OutOfMemoryError" or (isinstance(exc, RuntimeError) and (
                "can't allocate memory" in text or "out of memory" in text.lower())):  # torch's allocators
            _say("out of memory: ask for fewer or shorter motions, a lower --fps or a smaller --batch")
            return 2
        if isinstance(exc, RuntimeError) and "inline_container" in text and "unexpected pos" in text:
            _say("a torch file could not be written whole (torch's 'unexpected pos': the disk is most likely full)")
            return 2
        if os.environ.get(TRACEBACK_ENV, "") not in ("", "0"):
            raise
        lines = text.strip().splitlines()
        print(f"modi: internal error (a bug): {type(exc).__name__}: {lines[0][:300] if lines else ''} "
              f"-- run again with {TRACEBACK_ENV}=1 for the traceback", file=sys.stderr, flush=True)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
