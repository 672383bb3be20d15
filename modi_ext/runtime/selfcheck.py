"""First-use self-check of the kernels on one (device, dtype): the shared payload against the float64 reference.

A kernel that is wrong on some GPU (a miscompile, an architecture the build did not target, a driver issue) must
never silently train a model: ``modi_ext.runtime.dispatch`` runs ``run(device, dtype)`` once per (device, dtype)
before the kernels get a real call and routes that pair to the dense path if anything here disagrees with the
reference.

The problems are ``modi_ext.runtime.payload``'s, so the check launches every kernel instantiation of its dtype -- what
MoDi trains with included: the narrow cases (32-row tiles), the wide ones (cin 34 / cout 36, B x T = 260: 64-row tiles
and the split-K weight gradient), every gradient of a modulated, demodulated, biased call, FK on every launch
plan with rotation and offsets gradients, and the demodulation coefficients with both gradients.  Milliseconds on a
GPU; about 0.5 s per dtype on the CPU emulator (``tests/modi_ext/runtime/test_cuda_emulated.py`` prints it),
0.1-0.2 s on the CPU kernels.

It calls the raw kernels of a table (``modi_ext.runtime.kernels``), never the public ops (which route through the
self-check); what it imports above the runtime is the references (so ``dispatch`` is handed ``run`` by
``modi_ext/__init__.py``).
"""
from __future__ import annotations

import os

import torch

from modi_ext.runtime import kernels, payload

TOL = payload.TOL
# float32 on the CUDA kernels' tensor cores (MODI_EXT_CUDA_MMA=1 while torch.backends.cudnn.allow_tf32 is on) multiplies
# TF32 operands, unit roundoff 2^-11: the bf16 tolerance (unit roundoff 2^-8) scaled by the ratio of the two.
TF32_TOL = TOL[torch.bfloat16] * 2.0 ** -3


def tolerance(device: str, dtype: torch.dtype, lib: str = kernels.LIB) -> float:
    """The forward tolerance of (device, dtype): TF32_TOL where the CUDA kernels (an emulated table runs them on the
    CPU) take float32 to the TF32 tensor cores, else TOL."""
    cuda_kernels = torch.device(device).type == "cuda" or lib != kernels.LIB
    if (dtype == torch.float32 and cuda_kernels and os.environ.get("MODI_EXT_CUDA_MMA") == "1"
            and torch.backends.cudnn.allow_tf32):
        return TF32_TOL
    return TOL.get(dtype, 1e-4)


def _families(lib: str, device_type: str) -> tuple[str, ...]:
    built = kernels.kernels_built if lib == kernels.LIB else (lambda d, f: kernels.registered(lib, f, d))
    return tuple(f for f in ("skeletal", "fk", "demod") if built(device_type, f))


def _op_of(case) -> str:
    if isinstance(case, payload.DemodCase):
        return "demod_scale"
    return "fk" if isinstance(case, payload.FkCase) else f"skeletal_{case.kind}"


def run(device: str, dtype: torch.dtype, lib: str = kernels.LIB) -> dict:
    """``{"ok", "errors": {op: message}, "max_error": {op: relative error}, "cases": n}`` for every kernel of
    ``lib`` (default: this build's ``torch.ops.modi_ext``, through the ``kernels.KERNELS`` hook) on (device, dtype).
    ``ok`` is False when nothing could be checked (no kernels registered for the device)."""
    tol = tolerance(device, dtype, lib)
    table = kernels.KERNELS if lib == kernels.LIB else kernels.kernel_table(lib)
    families = _families(lib, torch.device(device).type)
    if lib == kernels.LIB and torch.device(device).type == "cpu" and dtype == torch.bfloat16:
        families = tuple(f for f in families if f == "skeletal")  # the CPU's only bf16 kernels (bf16k.h)
    errors: dict[str, str] = {}
    worst: dict[str, float] = {}
    todo = payload.cases(dtype, families)
    if not todo:
        return {"ok": False, "errors": {"build": f"no {lib} kernels are registered for {torch.device(device).type}: "
                                                 "nothing was checked"}, "max_error": {}, "cases": 0}
    # first use may come inside no_grad / inference_mode / autocast: the oracle needs autograd and full precision
    with torch.inference_mode(False), torch.enable_grad(), torch.autocast(torch.device(device).type, enabled=False):
        for case in todo:
            op = _op_of(case)
            if op in errors:
                continue
            try:
                fwd, bwd = payload.run_case(table, case, device, dtype)
            except Exception as exc:  # noqa: BLE001 - a kernel that raises has failed its check
                msg = str(exc).splitlines()[0] if str(exc) else ""
                errors[op] = f"raised {type(exc).__name__}: {msg} ({case.name})"
                continue
            worst[op] = max(worst.get(op, 0.0), fwd, bwd)
            if fwd > tol:
                errors[op] = f"forward error {fwd:.3g} > {tol:.1g} ({case.name})"
            elif bwd > payload.GRAD_FACTOR * tol:
                errors[op] = f"backward error {bwd:.3g} > {payload.GRAD_FACTOR * tol:.1g} ({case.name})"
    return {"ok": not errors, "errors": errors, "max_error": worst, "cases": len(todo)}
