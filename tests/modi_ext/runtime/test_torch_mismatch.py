"""A compiled modi_ext meets a torch other than its build's: one warning naming both versions, the dense path, no
load of ``_C`` (an undefined-symbol ImportError at best, a crash on a changed C++ ABI at worst).

The other torch is simulated: a copy of the package whose build record (``_build_info.json``, written by setup.py's
build_ext) names another release, imported in a child process.
"""
from __future__ import annotations

import glob
import importlib.machinery
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import modi_ext
from modi_ext.runtime.loader import torch_mismatch

PKG = Path(modi_ext.__file__).resolve().parent
HAS_SO = bool(glob.glob(str(PKG / "_C.*.so")))
OTHER = "2.12.1+cpu" if not str(torch.__version__).startswith("2.12.") else "2.11.0+cpu"

CHILD = """
import json, sys, warnings
# an editable install's finder would serve modi_ext._C from the checkout when the copy has none
sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable__")]
warnings.simplefilter("default")
import torch
import modi_ext
from modi_ext.layers import SkeletalConv
conv = SkeletalConv(4, 6, [[0, 1], [0, 1, 2], [1, 2]], 3)
y = conv(torch.randn(2, 4, 3, 8))
y.square().sum().backward()
print(json.dumps({"has_ext": modi_ext.HAS_EXT, "c_loaded": "modi_ext._C" in sys.modules, "file": modi_ext.__file__,
                  "load_error": modi_ext.LOAD_ERROR, "shape": list(y.shape),
                  "finite": bool(torch.isfinite(conv.weight.grad).all())}))
"""


def _copy(tmp_path: Path, info: dict | None, so: str = "real") -> Path:
    """modi_ext copied under tmp_path with ``info`` as its build record; so: 'real' (the built _C, if any),
    'junk' (a file that is no library), 'none'."""
    dst = tmp_path / "modi_ext"
    shutil.copytree(PKG, dst, ignore=shutil.ignore_patterns("__pycache__", "_build_info.json", "*.so"))
    if so == "real":
        for lib in glob.glob(str(PKG / "_C.*.so")):
            shutil.copy(lib, dst)
    elif so == "junk":
        name = "_C" + next(s for s in importlib.machinery.EXTENSION_SUFFIXES if s.endswith(".so"))
        (dst / name).write_bytes(b"not a shared library\n")
    if info is not None:
        (dst / "_build_info.json").write_text(json.dumps(info))
    return tmp_path


def _run(root: Path) -> tuple[dict, list[str]]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MODI_EXT_IMPL")}
    env["PYTHONPATH"] = str(root)
    proc = subprocess.run([sys.executable, "-c", CHILD], cwd=root, env=env, capture_output=True, text=True, check=False,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert Path(out["file"]).resolve().parent == (root / "modi_ext").resolve(), "the child imported another modi_ext"
    assert out["shape"] == [2, 6, 3, 8] and out["finite"]
    return out, [line for line in proc.stderr.splitlines() if line.strip()]


def test_mismatch_rules():
    assert torch_mismatch(None, "2.13.0+cpu", None) is None
    assert torch_mismatch({"torch": "2.13.0+cpu", "cuda": None}, "2.13.0+cpu", None) is None
    # the same release with another local label: a CPU-only build shares the CPU ABI of the CUDA builds
    assert torch_mismatch({"torch": "2.13.0+cpu", "cuda": None}, "2.13.0+cu130", "13.0") is None
    why = torch_mismatch({"torch": "2.12.1+cpu", "cuda": None}, "2.13.0+cpu", None)
    assert why == "built for torch 2.12.1+cpu, but torch 2.13.0+cpu is installed"
    why = torch_mismatch({"torch": "2.13.0+cu130", "cuda": "13.0"}, "2.13.0+cpu", None)
    assert why == "built for torch 2.13.0+cu130 with CUDA 13.0, but torch 2.13.0+cpu has no CUDA"
    assert "CUDA 12.8" in torch_mismatch({"torch": "2.13.0+cu130", "cuda": "13.0"}, "2.13.0+cu128", "12.8")


def test_another_torch_gives_one_warning_and_the_dense_path(tmp_path):
    out, stderr = _run(_copy(tmp_path, {"torch": OTHER, "cuda": None, "python": "3.11", "modi": "0.1.0"}))
    assert not out["has_ext"] and not out["c_loaded"], "the extension of another torch was loaded"
    assert len(stderr) == 1, "expected one warning line, got:\n" + "\n".join(stderr)
    line = stderr[0]
    assert "RuntimeWarning" in line and OTHER in line and str(torch.__version__) in line, line
    assert "dense" in line
    assert line.split(":", 1)[0] == "<string>", f"the warning should point at the user's import: {line}"
    assert OTHER in out["load_error"]


@pytest.mark.skipif(not HAS_SO, reason="modi_ext._C is not built in this checkout (the control needs it)")
def test_control_the_same_torch_loads_the_kernels(tmp_path):
    """The same copy with a record of this torch loads _C, silently: the mismatch test is not passing vacuously."""
    out, stderr = _run(_copy(tmp_path, {"torch": str(torch.__version__), "cuda": None}))
    assert out["has_ext"] and out["c_loaded"], out["load_error"]
    assert stderr == []


@pytest.mark.parametrize("so, says", [("junk", "_C.cpython"), ("none", "no compiled _C in")])
def test_an_extension_that_does_not_load_falls_back_with_one_warning(tmp_path, so, says):
    """No record (an older in-place build) and a _C the loader cannot open, or none (an install without a compiler):
    the fallback's one warning, saying which, not a traceback."""
    out, stderr = _run(_copy(tmp_path, None, so=so))
    assert not out["has_ext"]
    assert len(stderr) == 1 and "RuntimeWarning" in stderr[0] and "not built" in stderr[0], stderr
    assert says in stderr[0] and "circular import" not in stderr[0], stderr[0]
