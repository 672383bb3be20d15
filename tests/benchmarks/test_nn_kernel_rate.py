"""benchmarks/nn_kernel_rate.py builds against the installed torch and prints its JSON line (no timing asserted)."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "nn_kernel_rate.py"


@pytest.mark.skipif(shutil.which("g++") is None, reason="g++ (Debian package g++) is not installed")
def test_nn_kernel_rate_builds_and_reports_a_rate():
    out = subprocess.run([sys.executable, str(SCRIPT), "9", "24", "100"], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout.strip().splitlines()[-1])
    assert (row["M"], row["K"], row["N"], row["rounds"]) == (9, 24, 100, 9)
    assert row["kernel"] in ("avx512", "avx2")
    assert row["nn_gemm_gflops"] > 0 and row["sgemm_1thread_gflops"] > 0
    assert row["frac_range"][0] <= row["nn_gemm_frac_sgemm"] <= row["frac_range"][1]
