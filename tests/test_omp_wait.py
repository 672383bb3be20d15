"""The OpenMP wait setting (modi_ext/omp_wait.py): who sets it, when it cannot take effect, and that libgomp obeys it.

Each case runs a fresh interpreter, because libgomp reads the setting once, when torch loads it.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_REPORT = """
import json, os, sys
{imports}
from modi_ext import omp_wait
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
            if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "MODI_EXT_CPU_POOL", "OMP_NUM_THREADS")}
    base.update(env)
    base["PYTHONPATH"] = str(ROOT) + os.pathsep + base.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=base, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1]


@pytest.mark.parametrize("first", ["modi_ext", "modi"])
def test_importing_the_package_before_torch_sets_a_short_spin_and_the_own_pool(first):
    s = json.loads(_run(_REPORT.format(imports=f"import {first}")))
    assert s["source"] == "modi_ext" and s["env"] == "2000", s
    assert s["pool"] == "own" and s["cpu_pool"] == "own", s


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
    s = json.loads(_run(_REPORT.format(imports="import modi_ext"), **env))
    assert s["source"] == "user" or "MODI_EXT_CPU_POOL" in env, s
    assert s["env"] == env.get("GOMP_SPINCOUNT"), s
    assert s["pool"] == pool, s


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="needs 2 cores for an OpenMP worker")
def test_libgomp_obeys_it_idle_workers_stop_spinning():
    """The setting takes effect: after a parallel op, the idle worker burns well under a millisecond of CPU, where
    an actively waiting one (OMP_WAIT_POLICY=active, the control) burns most of the 50 ms sleep."""
    short = json.loads(_run(_IDLE_CPU.format(imports="import modi_ext")))
    active = json.loads(_run(_IDLE_CPU.format(imports="import modi_ext"), OMP_WAIT_POLICY="active"))
    assert active > 20.0, f"control: an actively waiting worker burnt only {active:.2f} ms (no OpenMP worker?)"
    assert short < 2.0, f"with the short spin the idle worker still burnt {short:.2f} ms of CPU in 50 ms"
