"""Exceptions that mean "the user gave us something wrong" (as opposed to a bug).

The CLI turns any ``UserError`` into one clear line and a non-zero exit; everything
else is a bug and keeps its traceback.
"""


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
