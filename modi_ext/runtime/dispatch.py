"""Which implementation a call takes: the sparse kernels (``ext``), the dense form (``dense``) or the oracle (``ref``).

``MODI_EXT_IMPL`` = ``auto`` (default) | ``ext`` | ``dense`` | ``ref``.  Under ``auto`` a call reaches a kernel only if

1. this build has kernels for the tensor's device type (probed once per device type and cached -- a per-call probe
   would be traced by ``torch.compile`` and break the graph), else ``dense``;
2. the kernels passed their self-check for this (device, dtype): on first use a tiny random problem runs through each
   kernel and the float64 reference (``modi_ext.runtime.selfcheck``); a mismatch gives one warning naming the op and the
   error and routes that (device, dtype) to ``dense`` (``MODI_EXT_SELFCHECK=0`` skips the check, ``strict`` raises);
3. on devices in ``MEASURE_DEVICES`` (CUDA): the kernel measured fastest of every correct path -- ``ext``, ``dense``
   and ``ref`` (the reference is one cuDNN conv on the masked dense weight: at large batches its TF32 tensor cores
   can beat both) -- for this (device, op, shape signature, precision settings), each timed once, a few repetitions,
   like ``cudnn.benchmark``; a path that cannot run the shape loses.  The signature holds the TF32 switches
   (``torch.backends.cudnn.allow_tf32``, ``torch.backends.cuda.matmul.allow_tf32``), since they change which path
   is fastest.  On the CPU the kernels always win.

``ext`` forces the kernels (no self-check: it is how the kernels themselves are tested); a device without kernels is
then an error naming the build.  ``dispatch_report()`` lists every decision taken so far.

bfloat16 on the CPU runs on the bf16 kernels (``csrc/skeletal/bf16k.h``: vdpbf16ps micro-kernels, fp32 accumulation)
where the CPU has AVX-512-BF16, under ``auto`` (after their own self-check) and ``ext`` alike; with
``MODI_EXT_CPU_KERNEL=bf16emu`` on the same kernels' plain-C++ emulation (slow: it exists so that the layout and
indexing are tested on any CPU).  Elsewhere -- no bf16 units and no emulation asked for, a build without the bf16
kernels, or the FK op, which has no bf16 CPU kernel -- it runs on ``dense``, never on the fp32 kernels: its GEMMs are
torch's, on oneDNN's bf16 units where the CPU has them and emulated elsewhere, fp32 accumulation either way.
``cpu_bf16_path()`` names what this CPU does (a row of the report).
"""
from __future__ import annotations

import functools
import os
import statistics
import threading
import time
import warnings
from typing import Callable

import torch

from modi_ext.runtime.kernels import KERNELS, _built, device_key, kernels_built
from modi_ext.runtime.loader import HAS_EXT, IMPLS, requested_impl, warn_not_built

__all__ = ["route", "record_path", "kernels_built", "kernels_trusted", "dispatch_report", "reset", "KERNELS",
           "device_key", "CPU_KERNEL_DTYPES", "cpu_bf16_path", "cpu_bf16_kernels"]

# ``KERNELS`` (modi_ext.runtime.kernels): the raw kernels every path calls, by name.  A test hook: replace an entry
# (then ``reset()``) to inject a wrong kernel.
CPU_KERNEL_DTYPES = (torch.float32, torch.float64)  # every CPU kernel's dtypes; bf16: ``cpu_bf16_path()``
MEASURE_DEVICES = {"cuda"}  # device types where ``auto`` times ext against dense (a test hook adds "cpu")
AUTO_REPS = 3
AUTO_PATHS = ("ext", "dense", "ref")  # the paths ``auto`` times against each other where it measures


def _default_timer(name: str, fn: Callable[[], object], device: str) -> float:
    """Seconds for one run of ``fn`` (synchronised on CUDA).  ``name`` ('ext'/'dense') lets a fake timer differ."""
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.synchronize(device)
    t = time.perf_counter()
    fn()
    if cuda:
        torch.cuda.synchronize(device)
    return time.perf_counter() - t


TIMER: Callable[[str, Callable[[], object], str], float] = _default_timer  # test hook: a fake clock

# The first-use self-check, ``(device, dtype) -> {"ok", "errors", "max_error", ...}``:
# ``modi_ext.runtime.selfcheck.run``, installed by ``modi_ext/__init__.py``.  The self-check runs the ops' references,
# whose packages import the ops, which import this module: it sits above dispatch, so dispatch is handed it instead
# of importing it.  A test hook too.
SELFCHECK: Callable[[str, torch.dtype], dict] | None = None

_lock = threading.RLock()
_checked: dict[tuple[str, str], dict] = {}
_auto: dict[tuple[str, str, str], dict] = {}
_paths: dict[tuple[str, str, str, str], int] = {}  # (device, dtype, op, path) -> calls: which path each op took


def record_path(op: str, x: torch.Tensor, path: str) -> None:
    """Count one eager call of ``op`` on ``x``'s device and dtype that ran ``path`` ('ext', 'dense' or 'ref').

    Skipped while ``torch.compile`` traces (a side effect there would break the graph); compiled code reports the
    path its trace took once, at the trace."""
    if torch.compiler.is_compiling():
        return
    key = (device_key(x.device), str(x.dtype).replace("torch.", ""), op, path)
    _paths[key] = _paths.get(key, 0) + 1


def reset() -> None:
    """Forget every cached decision (after changing ``KERNELS``, ``TIMER`` or the environment in tests)."""
    with _lock:
        _built.clear()
        _checked.clear()
        _auto.clear()
        _paths.clear()


def selfcheck_mode() -> str:
    mode = os.environ.get("MODI_EXT_SELFCHECK", "1").strip().lower()
    if mode not in ("0", "1", "strict"):
        raise ValueError(f"MODI_EXT_SELFCHECK must be '0', '1' or 'strict', not {mode!r}")
    return mode


@torch.compiler.assume_constant_result
def kernels_trusted(device: str, dtype_name: str) -> bool:
    """Whether the kernels passed their self-check on ``device`` (e.g. 'cuda:0'; 'cuda' is the same key,
    ``device_key``) for ``dtype_name`` ('torch.float32').

    Runs the check on first use (evaluated eagerly even inside ``torch.compile``: the answer is a constant)."""
    mode = selfcheck_mode()
    if mode == "0":
        return True
    device = device_key(device)
    key = (device, dtype_name)
    with _lock:
        if key not in _checked:
            if SELFCHECK is None:
                raise RuntimeError("modi_ext.runtime.dispatch: no self-check installed (import modi_ext)")
            res = SELFCHECK(device, getattr(torch, dtype_name.replace("torch.", "")))
            _checked[key] = res
            if not res["ok"] and mode != "strict":
                warnings.warn(_failure_message(device, dtype_name, res), RuntimeWarning, stacklevel=5)
        res = _checked[key]
    if not res["ok"] and mode == "strict":
        raise RuntimeError(_failure_message(device, dtype_name, res) + " (MODI_EXT_SELFCHECK=strict)")
    return res["ok"]


def _failure_message(device: str, dtype_name: str, res: dict) -> str:
    bad = "; ".join(f"{op}: {err}" for op, err in res["errors"].items())
    return (f"modi_ext: kernel self-check failed on {device} {dtype_name.replace('torch.', '')} ({bad}); "
            f"{device} {dtype_name.replace('torch.', '')} now uses the dense path")


def cpu_bf16_path() -> dict:
    """How bfloat16 skeletal ops run on this CPU: ``path`` "ext" on the bf16 kernels (``kernel`` "avx512_bf16", or
    "emulated" under ``MODI_EXT_CPU_KERNEL=bf16emu``), else "dense", with ``gemm`` naming what torch's GEMMs use
    there.  The kernels' choice is the extension's (CPUID, once per process; the environment is read per call)."""
    return _cpu_bf16_path(os.environ.get("MODI_EXT_CPU_KERNEL", ""))


def cuda_tensor_cores() -> dict:
    """Which CUDA kernels' GEMMs run on the tensor cores (``MODI_EXT_CUDA_MMA=1``, read per call by the C++ op):
    bf16 whenever asked; float32 as TF32 only while ``torch.backends.cudnn.allow_tf32`` is on (and the GPU has TF32,
    sm_80+), as torch's own convolutions; float16 and float64 never."""
    asked = os.environ.get("MODI_EXT_CUDA_MMA") == "1"
    return {"requested": asked, "bf16": asked, "float32_tf32": asked and bool(torch.backends.cudnn.allow_tf32),
            "cudnn_allow_tf32": bool(torch.backends.cudnn.allow_tf32)}


def _bf16_kernel() -> str | None:
    """"avx512_bf16", "emulated", or None for a build without the bf16 CPU kernels."""
    if not HAS_EXT or not kernels_built("cpu", "skeletal"):
        return None
    probe = getattr(torch.ops.modi_ext, "skeletal_cpu_bf16_kernel", None)
    try:
        return str(probe()) if probe is not None else None
    except (AttributeError, RuntimeError):  # pragma: no cover - a build that predates the probe
        return None


@functools.lru_cache(maxsize=None)
def _cpu_bf16_path(env: str) -> dict:
    def has(name: str) -> bool:
        probe = getattr(torch.cpu, name, None)
        try:
            return bool(probe()) if probe is not None else False
        except RuntimeError:  # pragma: no cover - a torch without the probe's backend
            return False
    try:
        onednn = torch.backends.mkldnn.is_available() and bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - a torch built without oneDNN
        onednn = False
    if onednn and has("_is_amx_tile_supported"):
        gemm = "oneDNN avx512_core_amx"
    elif onednn and has("_is_avx512_bf16_supported"):
        gemm = "oneDNN avx512_core_bf16"
    elif onednn:
        gemm = "oneDNN avx512_core, no bf16 units: converted to fp32"
    else:
        gemm = "torch's bf16 emulation, no bf16 units"
    kernel = _bf16_kernel()
    row = {"path": "dense", "kernel": kernel, "gemm": gemm, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
           "summary": f"bf16: dense ({gemm})"}
    if kernel == "avx512_bf16":
        row.update(path="ext", summary="bf16: ext (avx512_bf16 kernels)")
    elif kernel == "emulated" and env == "bf16emu":
        row.update(path="ext", summary="bf16: ext (emulated bf16 kernels, MODI_EXT_CPU_KERNEL=bf16emu)")
    elif kernel == "emulated":
        row["summary"] += " -- no avx512_bf16: the bf16 kernels would run emulated (MODI_EXT_CPU_KERNEL=bf16emu)"
    return row


@torch.compiler.assume_constant_result
def _bf16_on_ext() -> bool:
    """cpu_bf16_path()'s choice, a constant to ``torch.compile`` (the probe behind it is an op call)."""
    return cpu_bf16_path()["path"] == "ext"


def cpu_bf16_kernels(impl: str | None = None) -> bool:
    """Whether a bfloat16 skeletal call on the CPU with this ``impl`` (None: ``MODI_EXT_IMPL``) is meant for the
    bf16 kernels -- what autocast casts for (``modi_ext.runtime.amp``); ``route`` still decides the path."""
    want = requested_impl() if impl is None else impl
    return want in ("auto", "ext") and _bf16_on_ext()


def route(op: str, x: torch.Tensor, family: str = "skeletal", *, impl: str | None = None, record: bool = False,
          rerun: Callable[..., torch.Tensor] | None = None, inputs: tuple = (), options: tuple = ()) -> str:
    """'ext', 'dense' or 'ref' for one call of ``op`` on ``x``'s device and dtype (see the module docstring).

    ``impl`` overrides ``MODI_EXT_IMPL`` for this call (an op's ``impl=`` argument); ``record`` counts the call under
    the path chosen (``dispatch_report()``).  Where ``auto`` measures (CUDA), ``rerun(path, *inputs)`` runs this very
    call on a forced path with the differentiable ``inputs`` swapped for fresh leaves, and ``options`` holds the
    call's other arguments that change its cost: with the inputs' shapes they are the signature a choice is cached
    under.
    """
    path = _route(op, x, family, impl, rerun, inputs, options)
    if record and not getattr(_measuring, "active", False):
        record_path(op, x, path)
    return path


_measuring = threading.local()  # ``active`` while ``auto`` times the paths: those calls are not the op's own


def _signature(x: torch.Tensor, inputs: tuple, options: tuple, train: bool) -> str:
    shapes = " ".join(str(tuple(t.shape)) if isinstance(t, torch.Tensor) else "-" for t in inputs)
    opts = " ".join(str(o) for o in options)
    tf32 = f"tf32={int(torch.backends.cudnn.allow_tf32)}{int(torch.backends.cuda.matmul.allow_tf32)}"
    return f"{str(x.dtype).replace('torch.', '')} {shapes} {opts} {tf32} {'fwd_bwd' if train else 'fwd'}"


def _bench(rerun: Callable[..., torch.Tensor], inputs: tuple, train: bool) -> Callable[[str], Callable[[], object]]:
    """``bench(path)``: a zero-argument run of the call on ``path`` (forward, and backward for a training call)."""
    leaves = [t.detach().requires_grad_(train) if isinstance(t, torch.Tensor) else t for t in inputs]

    def bench(path: str):
        def call():
            with torch.set_grad_enabled(train):
                y = rerun(path, *leaves)
                if train:
                    torch.autograd.grad(y, [t for t in leaves if t is not None], torch.ones_like(y))
        return call
    return bench


def _route(op, x, family, impl, rerun, inputs, options) -> str:
    if impl is None:
        want = requested_impl()
    elif impl in IMPLS:
        want = impl
    else:
        raise ValueError(f"{op}: impl must be 'auto', 'ext', 'dense' or 'ref' (None: MODI_EXT_IMPL), got {impl!r}")
    if want in ("ref", "dense"):
        return want
    dev_type = x.device.type
    if dev_type == "cpu" and x.dtype not in CPU_KERNEL_DTYPES:
        if not (family == "skeletal" and x.dtype == torch.bfloat16 and _bf16_on_ext()):
            return "dense"  # no CPU kernel for this dtype -- never the fp32 kernels, never their self-check
    if not kernels_built(dev_type, family):
        if want == "ext":
            kinds = "FK kernels" if family == "fk" else "kernels"  # "no CPU FK kernels for fk"
            raise RuntimeError(f"MODI_EXT_IMPL=ext but this modi_ext build has no {dev_type.upper()} {kinds} for "
                               f"{op} (built without them: MODI_EXT_CUDA=0, no nvcc, or a CPU-only wheel)")
        if not HAS_EXT and not torch.compiler.is_compiling():
            warn_not_built()
        return "dense"
    if want == "ext" or dev_type == "meta":
        return "ext"
    if not kernels_trusted(device_key(x.device), str(x.dtype)):
        return "dense"
    if dev_type in MEASURE_DEVICES and rerun is not None:
        train = torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad for t in inputs)
        sig = _signature(x, inputs, options, train)
        if torch.compiler.is_compiling():
            return _cached_choice(op, device_key(x.device), sig)
        return _measured(op, device_key(x.device), sig, _bench(rerun, inputs, train))
    return "ext"


@torch.compiler.assume_constant_result
def _cached_choice(op: str, device: str, sig: str) -> str:
    rec = _auto.get((device, op, sig))
    return rec["choice"] if rec else "ext"


def _measured(op: str, device: str, sig: str, bench: Callable[[str], Callable[[], object]]) -> str:
    """The fastest of ``AUTO_PATHS`` for this call signature, timed once and cached (``dispatch_report``'s "auto"
    rows: each path's median ms, or the error that made it lose)."""
    key = (device, op, sig)
    with _lock:
        rec = _auto.get(key)
        if rec is not None:
            return rec["choice"]
        fns: dict[str, Callable[[], object]] = {}
        times: dict[str, list[float]] = {}
        errors: dict[str, str] = {}

        def attempt(path: str, run: Callable[[], object]) -> None:
            try:
                run()
            except Exception as exc:  # noqa: BLE001 - a path that cannot run this shape loses
                errors[path] = f"{type(exc).__name__}: {exc}"
                fns.pop(path, None)
                times.pop(path, None)

        _measuring.active = True
        try:
            for path in AUTO_PATHS:  # build and warm up each (allocator, cuDNN plans)
                attempt(path, lambda path=path: fns.__setitem__(path, bench(path)) or fns[path]())
            for _ in range(AUTO_REPS):  # the paths interleaved, so that a drifting clock skews none
                for path, fn in list(fns.items()):
                    attempt(path, lambda path=path, fn=fn: times.setdefault(path, []).append(TIMER(path, fn, device)))
        finally:
            _measuring.active = False
        ms = {path: round(statistics.median(t) * 1e3, 4) for path, t in times.items()}
        rec = {"choice": min(ms, key=ms.get) if ms else "dense", **{f"{p}_ms": v for p, v in ms.items()}}
        if errors:
            rec["error"] = "; ".join(f"{p}: {e}" for p, e in errors.items())
        _auto[key] = rec
        return rec["choice"]


def dispatch_report() -> list[dict]:
    """Every decision so far: the requested path, kernel availability per device type, self-checks, auto timings,
    and per op, device and dtype the path that ran (``kind: "path"``, with its number of calls)."""
    with _lock:
        rows: list[dict] = [{"kind": "config", "impl": os.environ.get("MODI_EXT_IMPL", "auto"),
                             "selfcheck": os.environ.get("MODI_EXT_SELFCHECK", "1"), "extension_built": HAS_EXT}]
        rows += [{"kind": "build", "device_type": d, "family": f, "kernels": v} for (d, f), v in _built.items()]
        rows += [{"kind": "bf16", "device": "cpu", **cpu_bf16_path()}]
        rows += [{"kind": "tensor_cores", "device": "cuda", **cuda_tensor_cores()}]
        rows += [{"kind": "selfcheck", "device": d, "dtype": t.replace("torch.", ""), "ok": r["ok"],
                  "errors": dict(r["errors"]), "max_error": dict(r["max_error"])} for (d, t), r in _checked.items()]
        rows += [{"kind": "auto", "device": d, "op": op, "signature": sig, **r} for (d, op, sig), r in _auto.items()]
        rows += [{"kind": "path", "device": d, "dtype": t, "op": op, "path": path, "calls": n}
                 for (d, t, op, path), n in sorted(_paths.items())]
        return rows
