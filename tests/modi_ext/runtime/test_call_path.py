"""An op call a reader can follow: from the public op to ``kernels.launch`` in a few nested calls, checks included.

Counts the ``modi_ext`` frames on the stack when the kernel is launched (and when the checks run), from the public
function down: ``docs/layout.md`` shows this path, and a refactor that buries the kernel deeper fails here.
"""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch

import modi_ext
from modi_ext import HAS_EXT
from modi_ext.csr import csr_from_lists
from modi_ext.fk import fk
from modi_ext.runtime import kernels
from modi_ext.skeletal import ops

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
PKG = Path(modi_ext.__file__).resolve().parent
MAX_DEPTH = 4  # the bound: public op -> ... -> launch, at most 4 nested modi_ext calls


def _depth(public: str) -> int:
    """Nested modi_ext calls from the public function ``public`` to the recorded one, both included."""
    frames = inspect.stack()[2:]  # skip _depth and the recording wrapper
    names = []
    for f in frames:
        if Path(f.filename).resolve().is_relative_to(PKG):
            names.append(f.function)
            if f.function == public:
                return len(names) + 1  # + the recorded function itself
    raise AssertionError(f"{public} is not on the stack: {names}")


def _recording(monkeypatch, module, name: str, public: str, op: str | None = None) -> list[int]:
    """Depths of the calls of ``module.name`` made under ``public`` (only those launching ``op``, if given)."""
    depths: list[int] = []
    real = getattr(module, name)

    def wrapper(*args, **kwargs):
        if op is None or args[0] == op:
            depths.append(_depth(public))
        return real(*args, **kwargs)
    monkeypatch.setattr(module, name, wrapper)
    return depths


@needs_ext
@pytest.mark.parametrize("autocast", [False, True])
def test_skeletal_conv_reaches_launch_within_four_calls(monkeypatch, autocast):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    launches = _recording(monkeypatch, kernels, "launch", "skeletal_conv", op="skeletal_conv")
    checked = _recording(monkeypatch, ops, "check_args", "skeletal_conv")
    topo = csr_from_lists([[0, 1], [0, 1, 2], [1, 2]])
    x = torch.randn(2, 3, 3, 8)
    w = torch.randn(4, topo.index.shape[0], 3, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        ops.skeletal_conv(x, w, None, topo.index, topo.offsets, style=torch.rand(2, 3) + 0.5, demodulate=True)
    assert launches and checked
    assert max(launches) <= MAX_DEPTH and max(checked) <= MAX_DEPTH, (launches, checked)


@needs_ext
def test_fk_reaches_launch_within_four_calls(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    launches = _recording(monkeypatch, kernels, "launch", "fk", op="fk")
    parents = [-1, 0, 1, 1]
    q = torch.nn.functional.normalize(torch.randn(2, 4, 4), dim=-1)
    fk(q, torch.randn(4, 3), parents, torch.randn(2, 3))
    assert launches and max(launches) <= MAX_DEPTH, launches
