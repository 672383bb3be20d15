"""``modi torchrun``: torchrun itself (the same options), with the exit codes and one-line reports of ``modi``.

Plain torchrun ends with a Python traceback and exit 1 when a scheduler stops it with SIGTERM (or Ctrl-C), even
though its workers saved a checkpoint and stopped cleanly; and with a traceback and a table when the workers fail
past ``--max-restarts``. Here the first is exit 143 / 130 and one line, and the second one line naming the first
failed rank and its exit code, which is also the exit code (75: a peer was lost; 2: a mistake; see
docs/distributed.md).
"""
from __future__ import annotations

import argparse
import signal
import sys


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "torchrun", add_help=False, prefix_chars="\0",
        help="torchrun with modi's exit codes: 143 / 130 when stopped by SIGTERM / Ctrl-C, one line on failure",
        description="Run torchrun (every option is torchrun's: modi torchrun --help shows them). Stopped by SIGTERM "
                    "or Ctrl-C, torchrun passes the signal to its workers (which save a checkpoint) and exits 143 / "
                    "130; when the workers fail past --max-restarts it exits with the first failed rank's code.")
    p.add_argument("argv", nargs=argparse.REMAINDER, help="torchrun's options, then the program and its arguments")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # torch's launcher, imported here: the other modi commands need none of it
    from torch.distributed import run as torchrun
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError

    options = torchrun.parse_args(args.argv)
    try:
        torchrun.run(options)
    except SignalException as exc:
        sig = int(exc.sigval)
        name = signal.Signals(sig).name
        print(f"modi torchrun: {name}: the workers were told to stop (they save a checkpoint at their next step "
              f"boundary; continue with --resume auto)", file=sys.stderr, flush=True)
        return 128 + sig
    except ChildFailedError as exc:
        rank, failure = exc.get_first_failure()
        code = int(failure.exitcode)
        how = f"exit code {code}" if code >= 0 else f"signal {_signal_name(-code)}"
        print(f"modi torchrun: the job failed: rank {rank} (pid {failure.pid}) ended with {how} "
              f"(its own message is above)", file=sys.stderr, flush=True)
        return code if code > 0 else 128 - code if code < 0 else 1
    return 0


def _signal_name(sig: int) -> str:
    try:
        return signal.Signals(sig).name
    except ValueError:
        return str(sig)
