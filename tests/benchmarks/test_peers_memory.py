"""The peak-memory measurement of ``benchmarks/peers/speed_released.py``: the wrapper must report the peak resident
set of the process it runs (not its own, not a sum), and a timeout must stop that process, not only the wrapper.
No timing is asserted."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.peers import speed_released as S

ALLOCATE = "b = bytearray({mb} << 20); b[::4096] = b'x' * len(b[::4096])"  # touch every page: resident, not virtual


def _peak(tmp_path: Path, code: str) -> float:
    rss = tmp_path / "child.rss"
    proc = S.run_group(S.measured([sys.executable, "-c", code], rss), timeout=120)
    assert proc.returncode == 0, proc.stderr
    return S.peak_rss_mb(rss)


def test_peak_rss_is_the_measured_child_s(tmp_path):
    idle = _peak(tmp_path, "pass")
    big = _peak(tmp_path, ALLOCATE.format(mb=300))
    assert idle < 100, idle  # a bare interpreter, not the wrapper's parent (pytest with torch loaded)
    assert 290 <= big - idle < 400, (idle, big)  # MiB; the bare interpreter's pages are partly shared


def test_peak_rss_reports_the_peak_not_the_end(tmp_path):
    peak = _peak(tmp_path, ALLOCATE.format(mb=200) + "; del b")
    assert peak >= 195, peak


def test_summary_gives_the_memory_ratio_against_their_script():
    runs = {"theirs": [{"iters": [{"i": 0, "kind": "r1+path", "s": 2.0}], "peak_rss_mb": 3000.0}],
            "modi": [{"iters": [{"i": 0, "kind": "r1+path", "s": 0.2}], "peak_rss_mb": 800.0}]}
    m = S.summarise(runs, whole_cycles=True, floor_mb=200.0)["memory"]["modi/theirs"]
    assert m["peak_rss"] == pytest.approx(800 / 3000)
    assert m["above_torch_floor"] == pytest.approx(600 / 2800)
    assert m["goal_met"] is True


def test_timeout_kills_the_measured_process_too(tmp_path):
    marker = tmp_path / "alive"
    code = f"import time, pathlib\nwhile True:\n    pathlib.Path({str(marker)!r}).touch()\n    time.sleep(0.05)\n"
    with pytest.raises(subprocess.TimeoutExpired):
        S.run_group(S.measured([sys.executable, "-c", code], tmp_path / "x.rss"), timeout=3)
    time.sleep(0.5)
    marker.unlink()
    time.sleep(0.5)
    assert not marker.exists(), "the measured process outlived the timeout"
