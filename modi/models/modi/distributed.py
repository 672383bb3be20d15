"""MoDi training across processes and machines: the process group, what a lost peer means, and each rank's shard
of the data.

* :func:`init_distributed_from_env` sets the process group up from torchrun's environment (gloo on the CPU, NCCL
  on GPUs) with a bounded timeout (:data:`DEFAULT_TIMEOUT_S`, ``--dist-timeout``), so a collective waiting on a
  peer that hangs or whose machine vanished gives up instead of blocking forever; and records every rank's host and
  pid, so a survivor can name the rank that went away.
* :func:`is_peer_failure` tells a lost peer (gloo's "Connection reset by peer", "Connection closed by peer",
  "Timed out waiting ...", a ``connectFullMesh`` or store timeout, NCCL's errors) from a bug;
  :func:`peer_lost_error` turns one into the one-line :class:`modi.errors.PeerLostError` (exit 75): which rank
  went away, at which step, the newest checkpoint and how the run continues.
* :func:`shard_indices`: the windows of global step ``s`` are positions ``s*batch ..`` of one stream made of a
  fresh permutation of all windows per epoch; rank ``r`` takes its own slice. So every window is seen once per
  epoch across the ranks, none twice, and the data of a step depends on the step only (not on the world size, nor
  on any saved state): a resume continues the same stream.
"""
from __future__ import annotations

import os
import shlex
import signal
import socket
import sys
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch.distributed.rendezvous import rendezvous

from modi.errors import PeerLostError

DEFAULT_TIMEOUT_S = 300.0
"""Seconds a collective may wait for a peer. A peer that dies on a reachable machine is noticed at once (its
sockets close); this bounds the wait for one that hangs or whose machine is gone. Longer than the longest gap
between two collectives of a healthy run (rank 0 writing a paper-sized checkpoint or a sample grid to a slow
network disk, the ranks' data loading at start), far shorter than torch's defaults (gloo 30 min, NCCL 10 min)."""

TIMEOUT_ENV = "MODI_DIST_TIMEOUT"

_state: dict[str, Any] = {"peers": [], "timeout_s": None, "rank": 0, "world": 1}


def dist_timeout_s(value: float | None = None) -> float:
    """``value``, else ``$MODI_DIST_TIMEOUT``, else :data:`DEFAULT_TIMEOUT_S`."""
    if value is not None:
        return float(value)
    env = os.environ.get(TIMEOUT_ENV, "").strip()
    try:
        return float(env) if env else DEFAULT_TIMEOUT_S
    except ValueError:
        return DEFAULT_TIMEOUT_S


def world_size_from_env() -> int:
    """The number of processes torchrun started (``WORLD_SIZE``; 1 outside torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1") or 1)


def local_rank() -> int:
    """This process's index on its machine (``LOCAL_RANK``; 0 outside torchrun): the GPU it uses."""
    return int(os.environ.get("LOCAL_RANK", "0") or 0)


def init_distributed_from_env(device: torch.device | None = None, timeout_s: float | None = None
                              ) -> tuple[int, int]:
    """Initialise the default process group when launched by ``torchrun`` (WORLD_SIZE > 1); gloo on CPU, NCCL on
    GPU, every collective (and the connection of the ranks) bounded by ``timeout_s`` (see :func:`dist_timeout_s`).

    Returns ``(rank, world_size)``; a no-op (0, 1) for a single process.
    """
    if world_size_from_env() <= 1:
        return 0, 1
    timeout = dist_timeout_s(timeout_s)
    if not dist.is_initialized():
        use_cuda = (device is not None and device.type == "cuda") or (device is None and torch.cuda.is_available())
        backend = "nccl" if use_cuda else "gloo"
        if use_cuda:
            torch.cuda.set_device(local_rank())
        # torchrun's static rendezvous (--master-addr/--master-port) keeps one store for all restarts, so the
        # restarted ranks would read the addresses the previous attempt's ranks left there and wait on dead ports
        # (gloo's connectFullMesh): each attempt gets keys of its own.
        store, rank, world = next(rendezvous("env://", timeout=timedelta(seconds=timeout)))
        store = dist.PrefixStore(f"modi/attempt_{torchrun_restart()}", store)
        # NCCL: past the timeout its watchdog aborts the process (TORCH_NCCL_ASYNC_ERROR_HANDLING, on by default),
        # which torchrun counts as a failed worker. gloo: the blocked call raises, and is reported as a lost peer.
        dist.init_process_group(backend=backend, store=store, rank=rank, world_size=world,
                                timeout=timedelta(seconds=timeout))
    rank, world = dist.get_rank(), dist.get_world_size()
    peers: list[Any] = [None] * world
    dist.all_gather_object(peers, (socket.gethostname(), os.getpid()))
    _state.update(peers=peers, timeout_s=timeout, rank=rank, world=world)
    return rank, world


# =============================================================================================== torchrun
def torchrun_restart() -> int:
    """How many times torchrun has restarted this job's workers (``TORCHELASTIC_RESTART_COUNT``; 0 outside it)."""
    try:
        return int(os.environ.get("TORCHELASTIC_RESTART_COUNT", "0") or 0)
    except ValueError:
        return 0


def under_torchrun() -> bool:
    return "TORCHELASTIC_RUN_ID" in os.environ or "TORCHELASTIC_RESTART_COUNT" in os.environ


def _restarts_left() -> int | None:
    try:
        return int(os.environ["TORCHELASTIC_MAX_RESTARTS"]) - torchrun_restart()
    except (KeyError, ValueError):
        return None


def without_resume(args: list[str]) -> list[str]:
    """``args`` without any ``--resume [CKPT]`` (its value is the next word unless that is an option)."""
    out, i = [], 0
    while i < len(args):
        a = args[i]
        if a == "--resume":
            i += 2 if i + 1 < len(args) and not args[i + 1].startswith("-") else 1
            continue
        if not a.startswith("--resume="):
            out.append(a)
        i += 1
    return out


def _launcher_words(args: list[str]) -> list[str] | None:
    """The launcher's command line up to this worker's arguments (``torchrun --nproc-per-node 2 ... -m modi``), read
    from the parent process on Linux; None when it cannot be told."""
    try:
        words = [w.decode() for w in Path(f"/proc/{os.getppid()}/cmdline").read_bytes().split(b"\0") if w]
    except (OSError, UnicodeDecodeError):
        return None
    n = len(args)
    for i in range(len(words) - n, 0, -1):
        if words[i:i + n] == args:
            prefix = words[:i]
            for j, w in enumerate(prefix):  # "python .../bin/torchrun ..." -> "torchrun ..."
                base = os.path.basename(w)
                if base == "torchrun" or (w == "-m" and j + 1 < len(prefix) and prefix[j + 1] in (
                        "torch.distributed.run", "modi")):
                    return ["torchrun", *prefix[j + 1:]] if base == "torchrun" else ["python", *prefix[j:]]
            return None
    return None


def continue_command(args: list[str] | None = None) -> str:
    """The command that continues this run from its newest checkpoint: the same launcher and arguments, with
    ``--resume auto``."""
    args = list(sys.argv[1:] if args is None else args)
    rest = [*without_resume(args), "--resume", "auto"]
    launcher = _launcher_words(args) if under_torchrun() else None
    if launcher is None:
        launcher = ["torchrun", "<the same options>", "-m", "modi"] if under_torchrun() else ["modi"]
    return " ".join(shlex.quote(w) if not w.startswith("<") else w for w in [*launcher, *rest])


# =============================================================================================== lost peers
_PEER_WORDS = ("connection reset by peer", "connection closed by peer", "broken pipe", "connectfullmesh",
               "timed out waiting", "socket timeout", "connection refused", "no route to host",
               "connection timed out", "watchdog caught collective operation timeout", "communicator was aborted",
               "remote process exited", "network error")


def is_peer_failure(exc: BaseException) -> bool:
    """True for the errors torch.distributed raises when a peer died, hung or became unreachable (call only in a
    run of several processes: there a gloo/NCCL/store error is about the peers, not a bug of ours)."""
    if isinstance(exc, dist.DistError):
        return True
    if not isinstance(exc, RuntimeError):
        return False
    text = str(exc).lower()
    return any(w in text for w in _PEER_WORDS)


def _is_timeout(text: str) -> bool:
    text = text.lower()
    return "timed out" in text or "timeout" in text


def _alive(pid: int) -> bool:
    """Whether ``pid`` (on this host) is a live process: a zombie (killed, not yet reaped) is not."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True
    return stat.rsplit(")", 1)[-1].split()[0] not in ("Z", "X")


def gone_ranks(settle_s: float = 2.0) -> tuple[list[int], bool]:
    """``(ranks, certain)``: the ranks whose process on this host has ended; else, in a run of two, the other rank
    (``certain`` False: it may be alive on another machine, or hung). A killed process closes its sockets before
    it is marked ended, so a survivor may hear of it first: the ranks on this host are looked at again for up to
    ``settle_s`` seconds."""
    peers, me = _state["peers"], _state["rank"]
    host = socket.gethostname()
    local = [r for r, p in enumerate(peers) if r != me and p and p[0] == host]
    deadline = time.monotonic() + settle_s
    while True:
        gone = [r for r in local if not _alive(int(peers[r][1]))]
        if gone:
            return gone, True
        if not local or time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    if len(peers) == 2:
        return [1 - me], False
    return [], False


def stopped_for_a_lost_peer() -> BaseException | None:
    """Called on a SIGTERM that reached this rank outside its training loop: when a rank on this host has already
    ended, the SIGTERM is torchrun's reaction to that loss, and the loss is the story (the error to report, which
    this returns), not the signal. Looked at once, without waiting: a job stopped as a whole sends every rank its
    SIGTERM at once, and none of them has ended by the time the first one handles it."""
    ranks, certain = gone_ranks(settle_s=0.0)
    if not (ranks and certain):
        return None
    return RuntimeError("torchrun stopped this worker (SIGTERM) after the loss")


def peer_lost_error(exc: BaseException, *, step: int | None, checkpoint: Path | None,
                    checkpoint_step: int | None) -> PeerLostError:
    """The one line for a peer lost while this rank was at ``step``: who went away (when known) and why it is
    thought so, the newest checkpoint (step and file, written atomically so whole), and how the run continues."""
    text = str(exc)
    timeout = _state["timeout_s"]
    ranks, certain = gone_ranks()
    peers = _state["peers"]

    def who(r: int) -> str:
        p = peers[r] if r < len(peers) else None
        where = f" (pid {p[1]} on {p[0]})" if p else ""
        return f"rank {r}{where}"

    if ranks and certain:
        subject = ", ".join(who(r) for r in ranks) + (" has" if len(ranks) == 1 else " have") + " ended"
    elif ranks and _is_timeout(text):
        subject = f"{who(ranks[0])} did not answer within {timeout:g} s (hung, or its machine is unreachable)"
    elif ranks:
        subject = f"{who(ranks[0])} went away"
    elif _is_timeout(text):
        subject = f"a process of the run did not answer within {timeout:g} s"
    else:
        subject = "a process of the run went away"
    cause = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    if "] " in cause:  # "[/.../gloo/transport/tcp/pair.cc:537] Read error ..." -> "Read error ..."
        cause = cause.split("] ", 1)[1]
    cause = cause.split(". This is typically", 1)[0][:160]
    at = f" at step {step}" if step is not None else ""
    if checkpoint is not None and checkpoint_step is not None:
        saved = f"the newest checkpoint, step {checkpoint_step} in {checkpoint}, is intact"
    elif checkpoint is not None:
        saved = f"the newest checkpoint, {checkpoint}, is intact"
    else:
        saved = "no checkpoint was written yet"
    left = _restarts_left()
    if left is not None and left > 0:
        then = f"torchrun restarts the job from it (restart {torchrun_restart() + 1} of " \
               f"{os.environ.get('TORCHELASTIC_MAX_RESTARTS')}); by hand: {continue_command()}"
    else:
        then = f"to continue: {continue_command()}"
    return PeerLostError(f"{subject}{at} ({cause}); {saved}; {then}")


def leave_quietly_on_signals() -> None:
    """Once a peer is lost this process is leaving: torchrun's SIGTERM (sent to every worker when one fails) must
    not replace the lost-peer line by "terminated" on the way out."""
    try:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread
        pass


# =============================================================================================== sharding
def epoch_order(n: int, seed: int, epoch: int) -> torch.Tensor:
    """The order of the ``n`` windows in ``epoch``: a permutation drawn from ``(seed, epoch)`` alone, so every rank
    draws the same one."""
    g = torch.Generator().manual_seed((int(seed) * 1_000_003 + 7_919 * int(epoch) + 17) % (2 ** 63))
    return torch.randperm(n, generator=g)


def shard_indices(n: int, batch: int, world: int, rank: int, seed: int, step: int,
                  orders: dict[int, torch.Tensor] | None = None) -> torch.Tensor:
    """Indices of the windows rank ``rank`` trains on at global step ``step``: positions ``step*batch + rank*b ..
    + b`` (``b = batch // world``) of the stream ``epoch_order(0) ++ epoch_order(1) ++ ...``. ``orders`` caches
    the permutations (the two newest epochs are kept)."""
    if n < 1:
        raise ValueError("no training windows")
    local = batch // world
    pos = torch.arange(local, dtype=torch.int64) + (int(step) * batch + rank * local)
    epochs, within = pos // n, pos % n
    out = torch.empty(local, dtype=torch.int64)
    orders = {} if orders is None else orders
    for e in epochs.unique().tolist():
        if e not in orders:
            orders[e] = epoch_order(n, seed, e)
            for old in sorted(orders)[:-2]:
                del orders[old]
        m = epochs == e
        out[m] = orders[e][within[m]]
    return out


__all__ = ["DEFAULT_TIMEOUT_S", "TIMEOUT_ENV", "dist_timeout_s", "world_size_from_env", "local_rank",
           "init_distributed_from_env",
           "torchrun_restart", "under_torchrun", "without_resume", "continue_command", "is_peer_failure",
           "gone_ranks", "stopped_for_a_lost_peer", "peer_lost_error", "leave_quietly_on_signals", "epoch_order",
           "shard_indices"]
