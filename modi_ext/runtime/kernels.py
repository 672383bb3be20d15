"""The compiled kernels by name, which device types a build covers, and one cache key per device.

Below ``dispatch`` and ``selfcheck`` in the package's import layers (``tests/modi_ext/test_modi_ext_imports.py``):
everything that runs or asks about the raw ``torch.ops`` kernels goes through here.

* ``KERNELS``: the raw ops of ``torch.ops.modi_ext`` by name -- a test hook (replace an entry, then
  ``dispatch.reset()``, to inject a wrong kernel); ``kernel_table(lib)`` is the same table for another op namespace
  (the emulated CUDA kernels are ``torch.ops.modi_ext_emu``, CPU dispatch key only).
* ``kernels_built(device_type, family)``: whether this build registered a family's kernels for a device type, probed
  once and cached (a per-call probe would be traced by ``torch.compile``).
* ``device_key(device)``: ``"cuda"`` and ``"cuda:0"`` (the current device) are one key, for the self-check cache of
  ``dispatch`` and for ``validate`` alike.
* ``launch(name, *args)``: one kernel call with its autograd -- the op's eager ``autograd.Function`` (``EAGER``, filled
  by each op's registration; ``modi_ext.runtime.eager``) where the fast path applies, else the registered op.
"""
from __future__ import annotations

import threading
from typing import Callable

import torch

from modi_ext.runtime import eager
from modi_ext.runtime.loader import HAS_EXT

__all__ = ["LIB", "FAMILY_OPS", "KERNELS", "EAGER", "launch", "kernel_table", "registered", "kernels_built",
           "device_key"]

LIB = "modi_ext"
FAMILY_OPS = {"skeletal": ("skeletal_conv", "skeletal_down", "skeletal_up", "skeletal_backward"),
              "fk": ("fk", "fk_backward"), "demod": ("demod_scale", "demod_scale_backward")}
OPS = FAMILY_OPS["skeletal"] + FAMILY_OPS["fk"] + FAMILY_OPS["demod"]


def kernel_table(lib: str = LIB) -> dict[str, Callable]:
    """``{op name: callable}`` of the raw kernels of the op namespace ``lib`` (looked up at call time)."""
    return {op: (lambda *a, op=op: getattr(getattr(torch.ops, lib), op)(*a)) for op in OPS}


KERNELS: dict[str, Callable] = kernel_table(LIB)
EAGER: dict[str, type] = {}  # op name -> its plain autograd.Function (eager.make_function), set by its registration


def launch(name: str, *args):
    """``KERNELS[name](*args)`` with the op's autograd: through its eager Function where ``eager.usable`` allows
    (plain tensors, no compile, tracing or transform), else through the registered op (the dispatcher)."""
    fn = EAGER.get(name)
    if fn is not None and eager.usable(*args):
        return fn.apply(*args)
    return KERNELS[name](*args)


def registered(lib: str, family: str, device_type: str) -> bool:
    """Whether every op of ``family`` in namespace ``lib`` has a kernel for ``device_type`` (an uncached probe)."""
    try:
        return all(torch._C._dispatch_has_kernel_for_dispatch_key(f"{lib}::{op}", device_type.upper())
                   for op in FAMILY_OPS[family])
    except RuntimeError:  # op not defined, or an unknown dispatch key
        return False


_lock = threading.RLock()
_built: dict[tuple[str, str], bool] = {}  # (device type, family) -> kernels registered; dispatch.reset() clears it


@torch.compiler.assume_constant_result
def kernels_built(device_type: str, family: str = "skeletal") -> bool:
    """Whether this build registered the ``family``'s kernels for ``device_type``: probed once, then cached."""
    if not HAS_EXT:
        return False
    key = (device_type, family)
    with _lock:
        if key not in _built:
            _built[key] = True if device_type == "meta" else registered(LIB, family, device_type)  # meta: fakes
        return _built[key]


def device_key(device: str | torch.device) -> str:
    """The one cache key of a device: ``'cuda'`` means the current CUDA device, so it is ``'cuda:<index>'``."""
    d = torch.device(device)
    if d.type == "cuda" and d.index is None:
        try:
            index = torch.cuda.current_device()
        except (RuntimeError, AssertionError):  # no CUDA here: the key stays well-formed
            index = 0
        d = torch.device("cuda", index)
    return str(d)
