"""The example of docs/api.md runs, as a user's script in a fresh process: examples/quickstart.py reads a BVH,
trains a tiny GANimator and generates, trains/loads a MoDi checkpoint and samples, writes BVH, glTF and the viewer
page, and compiles a network of modi_ext layers on the clip's skeleton with torch.compile."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def test_quickstart_runs_end_to_end(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, str(REPO / "examples" / "quickstart.py"), "--out", str(tmp_path / "qs")],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert p.stdout.strip().endswith("done")
    assert "Traceback" not in p.stderr
    for name in ("ganimator_0.bvh", "ganimator_0.glb", "modi_0.bvh", "modi_0.gltf", "view.html"):
        assert (tmp_path / "qs" / name).is_file(), name
    assert "torch.compile'd skeletal autoencoder" in p.stdout
