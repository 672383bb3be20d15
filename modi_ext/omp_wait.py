"""How long idle OpenMP threads spin before they sleep: the setting that decides speed on a busy machine.

torch's CPU wheels run every parallel op (and these kernels) on one libgomp thread team.  By default libgomp keeps a
thread that has run out of work spinning for 300,000 iterations (milliseconds) before it sleeps.  On a quiet machine
that saves a wake-up between back-to-back ops; when another process holds a core it is the main cost: the spinning
thread keeps its core while the thread it waits for sits descheduled in the other core's queue, so every parallel
region lasts a scheduler time slice.  Measured on the 2-core machine with one core busy (``benchmarks/RESULTS.md``,
"Busy machine"): 2 threads ran 3-4x slower than 1 thread with the default spin, and within 1.2x of it with a short one.

libgomp reads ``GOMP_SPINCOUNT`` once, when it is loaded (by ``import torch``), so ``apply()`` runs before torch is
imported: from ``modi_ext/__init__.py`` and ``modi/__init__.py`` (the ``modi`` command).  It sets
``GOMP_SPINCOUNT=2000`` (about 20-90 us, depending on the CPU's pause instruction) unless the user chose a wait policy
(``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` set); ``GOMP_SPINCOUNT=300000`` restores libgomp's default.  When torch was
imported first, nothing can change and ``state()`` says so.  The variable is inherited by child processes (data
loader workers, DDP ranks), which is what they need too.  Other OpenMP runtimes ignore it.

The same setting picks the threads the CPU kernels run on (``MODI_EXT_CPU_POOL``, set here when the user has not):
with a short spin, the kernels' own helper threads (``own``: the calling thread never waits for a helper that has
claimed no task, and helpers sleep when idle), measured faster with a core busy and as fast on a quiet machine; with
libgomp's long spin, torch's OpenMP team (``omp``), because the team's spinning threads would hold the cores the
helpers need.

This module imports nothing heavy: it must run before torch.
"""
from __future__ import annotations

import os
import sys

DEFAULT_SPINCOUNT = "2000"
SHORT_SPINCOUNT = 100_000  # at most this many spins counts as short (libgomp's default is 300,000)
_USER_VARS = ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")
POOLS = ("own", "omp")

_state: dict = {}


def apply() -> dict:
    """Set the short spin unless the user chose one or torch (and so libgomp) is already loaded; idempotent."""
    if _state:
        return dict(_state)
    chosen = {k: os.environ[k] for k in _USER_VARS if os.environ.get(k, "") != ""}
    if chosen:
        _state.update(source="user", setting=" ".join(f"{k}={v}" for k, v in chosen.items()))
    elif "torch" in sys.modules:
        _state.update(source="libgomp default (torch was imported before modi/modi_ext)",
                      setting="GOMP_SPINCOUNT=300000")
    else:
        os.environ["GOMP_SPINCOUNT"] = DEFAULT_SPINCOUNT
        _state.update(source="modi_ext", setting=f"GOMP_SPINCOUNT={DEFAULT_SPINCOUNT}")
    pool = os.environ.get("MODI_EXT_CPU_POOL", "").strip().lower()
    if pool not in POOLS:
        pool = "own" if _spin_is_short(os.environ) else "omp"
        os.environ["MODI_EXT_CPU_POOL"] = pool  # read by csrc/cpu/tasks.h on every call
    _state["cpu_pool"] = pool
    return dict(_state)


def _spin_is_short(env) -> bool:
    """True when libgomp's idle threads spin briefly (as set here, or by the user) and then sleep."""
    if env.get("OMP_WAIT_POLICY", "").strip().lower() == "passive":
        return True
    try:
        return int(env.get("GOMP_SPINCOUNT", "").strip()) <= SHORT_SPINCOUNT
    except ValueError:  # unset (libgomp's default), "infinity", or a suffixed value: treat as long
        return False


def state() -> dict:
    """``{"source": ..., "setting": ...}``: the wait policy this process's OpenMP threads run with."""
    return apply()


def describe() -> str:
    s = state()
    return f"{s['setting']} ({s['source']}); CPU kernels on {'their own helper threads' if s['cpu_pool'] == 'own' else 'the OpenMP team'}"
