"""The OpenMP wait setting (modi_ext/runtime/omp_wait.py): who sets it, when it cannot take effect, and that libgomp
obeys it.

Each case runs a fresh interpreter, because libgomp reads the setting once, when torch loads it.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

_REPORT = """
import json, os, sys
{imports}
from modi_ext.runtime import omp_wait
print(json.dumps(dict(omp_wait.state(), env=os.environ.get("GOMP_SPINCOUNT"),
                      pool=os.environ.get("MODI_EXT_CPU_POOL"))))
"""

# CPU time the process burns while its main thread sleeps right after a parallel torch op: the OpenMP worker's
# idle spin.  Long spins burn milliseconds here; a short one about nothing.
_IDLE_CPU = """
import json, sys, time
{imports}
import torch
torch.set_num_threads(2)
x = torch.ones(4_000_000)
burnt = []
for _ in range(5):
    x.mul_(1.0000001)  # a parallel region: the worker runs, then waits for the next one
    t0 = time.process_time()
    time.sleep(0.05)
    burnt.append((time.process_time() - t0) * 1000)
print(json.dumps(sorted(burnt)[2]))
"""


def _run(code: str, **env) -> str:
    base = {k: v for k, v in os.environ.items()
            if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "MODI_EXT_CPU_POOL", "OMP_NUM_THREADS",
                         "MODI_EXT_SET_GOMP_SPINCOUNT", "MODI_EXT_OMP_WAIT")}
    base.update(env)
    base["PYTHONPATH"] = str(ROOT) + os.pathsep + base.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=base, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.parametrize("first", ["import modi_ext", "from modi import cli\ncli.main([])"])  # the library, the CLI
def test_short_sets_the_spin_before_torch_and_the_own_pool(first):
    s = json.loads(_run(_REPORT.format(imports=first), MODI_EXT_OMP_WAIT="short"))
    assert s["source"].startswith("modi_ext") and s["env"] == "2000", s
    assert s["pool"] == "own" and s["cpu_pool"] == "own", s


def test_long_keeps_libgomps_default_and_the_openmp_team():
    s = json.loads(_run(_REPORT.format(imports="import modi_ext"), MODI_EXT_OMP_WAIT="long"))
    assert s["env"] is None and s["pool"] == "omp", s


_SPINNER = "import os, sys\nsys.stdout.write('up\\n'); sys.stdout.flush()\nwhile True: pass\n"


def _with_spinner(fn):
    """Run fn() while another process keeps one CPU busy (as another user's job would)."""
    p = subprocess.Popen([sys.executable, "-c", _SPINNER], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "up"
        time.sleep(0.3)
        return fn()
    finally:
        p.kill()
        p.wait()


@pytest.mark.skipif(not Path("/proc/stat").is_file(), reason="no /proc/stat (not Linux)")
def test_the_probe_sees_another_process_keeping_a_cpu_busy():
    from modi_ext.runtime import omp_wait

    busy = _with_spinner(omp_wait.busy_cpus)
    assert busy is not None and busy >= 0.7, busy


@pytest.mark.skipif(not Path("/proc/stat").is_file(), reason="no /proc/stat (not Linux)")
def test_auto_chooses_short_when_another_process_holds_a_cpu_and_children_follow():
    code = ("import modi_ext, subprocess, sys, json\n"
            "child = subprocess.run([sys.executable, '-c', " + repr(_REPORT.format(imports="import modi_ext")) + "],"
            " capture_output=True, text=True, check=True).stdout\n"
            "print(json.dumps([modi_ext.runtime.omp_wait.state(), json.loads(child)]))")
    parent, child = json.loads(_with_spinner(lambda: _run(code)))
    assert parent["source"].startswith("modi_ext (auto: other processes kept"), parent
    assert parent["setting"] == "GOMP_SPINCOUNT=2000" and parent["cpu_pool"] == "own", parent
    assert child["source"] == "modi_ext, inherited" and child["env"] == "2000" and child["pool"] == "own", child


def test_torch_imported_first_leaves_libgomp_alone_and_uses_the_openmp_team():
    s = json.loads(_run(_REPORT.format(imports="import torch\nimport modi_ext")))
    assert s["env"] is None, s
    assert s["source"].startswith("libgomp default"), s
    assert s["pool"] == "omp", s


@pytest.mark.parametrize("env, pool", [({"GOMP_SPINCOUNT": "300000"}, "omp"),
                                       ({"GOMP_SPINCOUNT": "500"}, "own"),
                                       ({"OMP_WAIT_POLICY": "PASSIVE"}, "own"),
                                       ({"OMP_WAIT_POLICY": "active"}, "omp"),
                                       ({"GOMP_SPINCOUNT": "500", "MODI_EXT_CPU_POOL": "omp"}, "omp")])
def test_a_users_own_setting_is_kept(env, pool):
    s = json.loads(_run(_REPORT.format(imports="import modi_ext"), MODI_EXT_OMP_WAIT="short", **env))
    assert s["source"] == "user", s
    assert s["env"] == env.get("GOMP_SPINCOUNT"), s
    assert s["pool"] == pool, s


def test_a_bad_mode_is_one_clear_error():
    out = subprocess.run([sys.executable, "-c", "import modi_ext"], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "MODI_EXT_OMP_WAIT": "fast", "PYTHONPATH": str(ROOT)})
    assert out.returncode != 0
    assert "MODI_EXT_OMP_WAIT must be one of auto, short, long, not 'fast'" in out.stderr.strip().splitlines()[-1]


def _usable_cpus() -> int:
    """CPUs this process may run on (``taskset``, a container's cpuset), not the machine's count: with fewer CPUs
    than threads libgomp throttles its spin by itself, so the control below cannot spin."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


@pytest.mark.skipif(_usable_cpus() < 2, reason=f"needs 2 usable CPUs for a spinning OpenMP worker; this process "
                                                f"may use {_usable_cpus()}")
def test_libgomp_obeys_it_idle_workers_stop_spinning():
    """The setting takes effect: after a parallel op, the idle worker burns well under a millisecond of CPU, where
    an actively waiting one (OMP_WAIT_POLICY=active, the control) burns most of the 50 ms sleep."""
    short = json.loads(_run(_IDLE_CPU.format(imports="import modi_ext"), MODI_EXT_OMP_WAIT="short"))
    for _ in range(3):  # the control needs a free CPU for the worker to spin on: another process may hold it
        active = json.loads(_run(_IDLE_CPU.format(imports="import modi_ext"), OMP_WAIT_POLICY="active"))
        if active > 20.0:
            break
    else:
        pytest.skip(f"control: an actively waiting worker burnt only {active:.2f} ms of a 50 ms sleep in 3 tries "
                    "(no OpenMP worker, or no CPU free for it to spin on: the machine is busy)")
    assert short < 2.0, f"with the short spin the idle worker still burnt {short:.2f} ms of CPU in 50 ms"
