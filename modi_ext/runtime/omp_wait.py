"""How long idle OpenMP threads spin before they sleep: the setting that decides speed on a busy machine.

torch's CPU wheels run every parallel op (and these kernels) on one libgomp thread team.  By default libgomp keeps a
thread that has run out of work spinning for 300,000 iterations (milliseconds) before it sleeps.  On a quiet machine
that saves a wake-up between back-to-back ops (a GANimator training step, thousands of small ops, ran 30-45% slower
with a short spin).  When another process holds a core it is the main cost: the spinning thread keeps its core while
the thread it waits for sits descheduled, so parallel regions last scheduler time slices (the same step ran 3.5-12x
slower with the long spin).  Measured: ``benchmarks/RESULTS.md``, "Busy machine".

libgomp reads the setting once, when ``import torch`` loads it, and cannot be told later, so ``apply()`` decides
before torch is imported (from ``modi_ext/__init__.py``; the ``modi`` command imports modi_ext before torch):

* ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` set by the user: kept.
* ``MODI_EXT_OMP_WAIT=short``: ``GOMP_SPINCOUNT=2000`` (20-90 us, depending on the CPU's pause instruction);
  ``long``: libgomp's default; ``auto`` (default): look at the CPUs this process may use for 50 ms and choose
  ``short`` when other processes keep at least half a CPU busy, ``long`` otherwise.  A job that starts on a quiet
  machine and is joined by another later keeps ``long``: set ``MODI_EXT_OMP_WAIT=short`` where that is expected.
* torch already imported: nothing can change; ``state()`` says so.

The decision is passed to child processes (data loader workers, DDP ranks) through the environment, so they follow
the parent rather than look at a machine the parent itself keeps busy.  The same decision picks the threads the CPU
kernels run on (``MODI_EXT_CPU_POOL``, read by ``csrc/common/tasks.h``): with the short spin their own helper threads
(``own``: the caller never waits for a helper that has claimed no task; idle helpers sleep), with the long one
torch's OpenMP team (``omp``), whose spinning workers would otherwise hold the cores the helpers need.

This module imports nothing heavy: it must run before torch.
"""
from __future__ import annotations

import os
import sys
import time

DEFAULT_SPINCOUNT = "2000"
SHORT_SPINCOUNT = 100_000  # at most this many spins counts as short (libgomp's default is 300,000)
BUSY_CPUS = 0.5  # other processes' load (in CPUs, over the CPUs this process may use) that makes `auto` choose short
PROBE_S = 0.05
MODES = ("auto", "short", "long")
POOLS = ("own", "omp")
_USER_VARS = ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")
_MARK = "MODI_EXT_SET_GOMP_SPINCOUNT"  # tells child processes the value is modi_ext's, not the user's

_state: dict = {}


def apply() -> dict:
    """Choose the spin (see the module docstring) unless torch is already loaded; idempotent."""
    if _state:
        return dict(_state)
    chosen = {k: os.environ[k] for k in _USER_VARS if os.environ.get(k, "") != ""}
    mode = os.environ.get("MODI_EXT_OMP_WAIT", "auto").strip().lower() or "auto"
    if mode not in MODES:
        raise ValueError(f"MODI_EXT_OMP_WAIT must be one of {', '.join(MODES)}, not {mode!r}")
    if chosen and chosen == {"GOMP_SPINCOUNT": os.environ.get(_MARK)}:  # set by modi_ext in a parent process
        _state.update(source="modi_ext, inherited", setting=f"GOMP_SPINCOUNT={chosen['GOMP_SPINCOUNT']}")
    elif chosen:
        _state.update(source="user", setting=" ".join(f"{k}={v}" for k, v in chosen.items()))
    elif "torch" in sys.modules:
        _state.update(source="libgomp default (torch was imported before modi_ext)",
                      setting="GOMP_SPINCOUNT=300000")
    else:
        why = f"MODI_EXT_OMP_WAIT={mode}"
        if mode == "auto":
            busy = busy_cpus()
            mode = "short" if busy is not None and busy >= BUSY_CPUS else "long"
            why = ("auto: no /proc/stat to look at" if busy is None else
                   f"auto: other processes kept {busy:.2f} CPUs busy at start")
            os.environ["MODI_EXT_OMP_WAIT"] = mode  # children follow this decision
        if mode == "short":
            os.environ["GOMP_SPINCOUNT"] = os.environ[_MARK] = DEFAULT_SPINCOUNT
            _state.update(source=f"modi_ext ({why})", setting=f"GOMP_SPINCOUNT={DEFAULT_SPINCOUNT}")
        else:
            _state.update(source=f"modi_ext ({why})", setting="GOMP_SPINCOUNT=300000 (libgomp default)")
    pool = os.environ.get("MODI_EXT_CPU_POOL", "").strip().lower()
    if pool not in POOLS:
        pool = "own" if _spin_is_short(os.environ) else "omp"
        os.environ["MODI_EXT_CPU_POOL"] = pool  # read by csrc/common/tasks.h on every call
    _state["cpu_pool"] = pool
    return dict(_state)


def busy_cpus(window_s: float = PROBE_S) -> float | None:
    """CPUs' worth of time spent busy, over the CPUs this process may use, during `window_s` (this process sleeps
    meanwhile, so the load is other processes'; time stolen by a hypervisor counts as busy).  None off Linux."""
    try:
        allowed = {f"cpu{c}" for c in os.sched_getaffinity(0)}
    except (AttributeError, OSError):
        allowed = None

    def sample() -> dict[str, tuple[int, int]]:
        out = {}
        with open("/proc/stat", encoding="ascii") as f:
            for line in f:
                name, _, rest = line.partition(" ")
                if not name.startswith("cpu") or name == "cpu" or (allowed is not None and name not in allowed):
                    continue
                v = [int(x) for x in rest.split()[:8]]  # user nice system idle iowait irq softirq steal
                out[name] = (sum(v), v[3] + v[4])
        return out

    try:
        a = sample()
        time.sleep(window_s)
        b = sample()
    except (OSError, ValueError):
        return None
    busy = 0.0
    for name, (total, idle) in b.items():
        if name in a and total > a[name][0]:
            dt = total - a[name][0]
            busy += (dt - (idle - a[name][1])) / dt
    return busy if b else None


def _spin_is_short(env) -> bool:
    """True when libgomp's idle threads spin briefly (as set here, or by the user) and then sleep."""
    if env.get("OMP_WAIT_POLICY", "").strip().lower() == "passive":
        return True
    try:
        return int(env.get("GOMP_SPINCOUNT", "").strip()) <= SHORT_SPINCOUNT
    except ValueError:  # unset (libgomp's default), "infinity", or a suffixed value: treat as long
        return False


def state() -> dict:
    """``{"source": ..., "setting": ..., "cpu_pool": ...}``: the wait policy this process's OpenMP threads run with."""
    return apply()


def describe() -> str:
    s = state()
    pool = "their own helper threads" if s["cpu_pool"] == "own" else "the OpenMP team"
    return f"{s['setting']}, {s['source']}; CPU kernels on {pool}"
