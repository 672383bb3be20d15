"""Exceptions that mean "the user gave us something wrong", or the environment did (as opposed to a bug): every
user-facing error type of modi is declared here.

The CLI turns any ``UserError`` into one clear line and a non-zero exit; everything
else is a bug and keeps its traceback. The modules that raise these errors re-export them under their old names
(``modi.faults.OutputError``, ``modi.io.safe_load.UnsafeFileError``, ...). The Blender add-on declares its own
(``RigError``), since it runs inside Blender without modi; so does the NumPy-only ONNX runner (``ContractError``),
which is copied next to an exported model and run without modi.
"""
from __future__ import annotations

from pathlib import Path


class UserError(Exception):
    """Bad input or arguments from the user, or the environment (a full disk): printed as one line by the CLI,
    which exits with ``exit_code``."""

    exit_code = 2


class BvhError(UserError, ValueError):
    """A malformed BVH file. ``line`` is the 1-based line number where the problem was found."""

    def __init__(self, message: str, line: int | None = None, path: str | None = None):
        self.line = line
        self.path = path
        where = ""
        if path is not None:
            where += f"{path}:"
        if line is not None:
            where += f"{line}:"
        super().__init__(f"{where} {message}".strip() if where else message)


class CheckpointError(UserError):
    """A checkpoint that cannot be read or does not hold what is needed."""


class PeerLostError(UserError):
    """A process of a distributed run went away (killed, preempted, its machine lost) or stopped answering: not a
    bug, and not the user's mistake. Exit 75 (``EX_TEMPFAIL`` of sysexits.h: a temporary failure, to be retried):
    the run continues from its newest checkpoint (torchrun's restart, or ``--resume auto``)."""

    exit_code = 75


class OutputError(UserError):
    """An output could not be written (no space left, read-only folder, permission): the final name is untouched.
    ``errno`` is the OS error number when one caused it."""

    def __init__(self, message: str, errno_: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno_


class RunFolderBusy(UserError):
    """Another live process holds the run folder's lock."""


class UnreadableFileError(CheckpointError):
    """Not a torch file at all, or a truncated/corrupt one; ``reason`` is torch's first line."""

    def __init__(self, message: str, path: Path, reason: str) -> None:
        super().__init__(message)
        self.path, self.reason = path, reason


class UnsafeFileError(CheckpointError):
    """The file names code (a global outside the allow-list): refused without calling anything."""

    def __init__(self, message: str, path: Path, global_name: str) -> None:
        super().__init__(message)
        self.path, self.global_name = path, global_name


class MaskViolation(CheckpointError):
    """A released weight is non-zero where its mask is zero (the compact form cannot hold it)."""


class OnnxExportError(UserError):
    """The export could not be done (a missing package, a model kind the graph cannot express)."""


class NonFiniteLossError(UserError, RuntimeError):
    """A loss (or, for GANimator at a save, a weight) became NaN/inf: training stops before that optimiser step and
    writes nothing, so the checkpoint on disk is the last good one (one line from the CLI, exit 2). Also a
    ``RuntimeError``, as MoDi's trainer raised it before both trainers shared this class."""


__all__ = ["UserError", "BvhError", "CheckpointError", "PeerLostError", "OutputError", "RunFolderBusy",
           "UnreadableFileError", "UnsafeFileError", "MaskViolation", "OnnxExportError", "NonFiniteLossError"]
