"""The roofline helpers the benchmarks share: FLOP formulas of the modi_ext ops, a FLOP counter that uses them, and
this machine's sgemm rate measured in the calling process.

Convention
----------
* 2 FLOPs per multiply-add; elementwise work (activations, bias, noise, losses, Adam, EMA) is not counted: it is
  memory-bound, and a roofline against sgemm is about the multiply-adds.
* A skeletal conv counts only the nonzero blocks of its weight: one ``(Cout, Cin, U)`` block per (output entity,
  input entity) pair of the CSR topology (``weight.shape[1]`` = nnz pairs), i.e. ``2 B T nnz Cout Cin U`` FLOPs,
  with T the frames the taps slide over (the output frames of ``skeletal_conv``/``skeletal_down``, the coarse input
  frames of ``skeletal_up``) and every tap counted, padded or not -- as ``torch.utils.flop_counter`` counts a conv.
  ``skeletal_up`` adds its FIR blur (4 multiply-adds per output); a style adds one multiply per input element and
  the demodulation ``2 nnz Cout Cin U`` (sum of squared weights) + ``2 B Eout Cout Cin`` (contraction with s^2).
* Backward: grad input and grad weight each cost one forward's multiply-adds (so fwd+bwd = 3x fwd); grad style
  costs a grad input (the transposed conv) when grad input is not computed anyway. FK: 64 FLOPs per joint and
  frame forward (quaternion product 28, rotation of the offset 33, translation 3), 2x that backward (an estimate:
  FK is latency-bound, not a GEMM).

Why count with torch's dispatch-mode FLOP counter and these formulas instead of a closed form of each step: the count follows
the ops that really run (an op the dense reference runs on the masked zeros is not counted by its dense size, and
the double backward of R1 / path length / WGAN-GP is counted from the partial backward ops it is built of, not
from an assumed multiplier), and plain torch ops (linear layers, ``mm``) get torch's own formulas. Under a dispatch
mode modi_ext leaves its eager fast path (``modi_ext/runtime/eager.py``) for the registered ops, which compute the
same values; so count in one untimed call, then time without the counter.
"""
from __future__ import annotations

import statistics
import time
from collections import defaultdict
from math import prod
from typing import Any, Callable

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import flop_registry, shape_wrapper

import modi_ext  # registers the modi_ext ops
from modi_ext.runtime import dispatch

KIND_CONV, KIND_DOWN, KIND_UP = 0, 1, 2  # modi_ext.skeletal: the ``kind`` argument of the backward ops
FK_FLOPS_PER_JOINT_FRAME = 64
BLUR_TAPS = 4


# ------------------------------------------------------------------------------------------------ formulas
def skeletal_macs(kind: int, batch: int, frames: int, nnz: int, c_out: int, c_in: int, taps: int) -> int:
    """Multiply-adds of one skeletal conv pass over the nonzero blocks (``frames``: see the module docstring)."""
    return batch * frames * nnz * c_out * c_in * taps


def skeletal_forward_flops(kind: int, x_shape, w_shape, out_shape, style: bool = False,
                           demodulate: bool = False) -> int:
    """FLOPs of ``skeletal_conv`` / ``skeletal_down`` / ``skeletal_up`` from the tensor shapes (compact weight)."""
    b, _, e_in, t_in = x_shape
    _, c_out_y, e_out, t_out = out_shape
    if kind == KIND_UP:
        c_in, nnz, c_out, u = w_shape
        flops = 2 * skeletal_macs(kind, b, t_in, nnz, c_out, c_in, u) + 2 * BLUR_TAPS * prod(out_shape)
    else:
        c_out, nnz, c_in, u = w_shape
        flops = 2 * skeletal_macs(kind, b, t_out, nnz, c_out, c_in, u)
    if style:
        flops += b * c_in * e_in * t_in
    if demodulate:
        flops += demod_flops(kind, w_shape, b, e_out)
    return flops


def demod_flops(kind: int, w_shape, batch: int, e_out: int) -> int:
    """FLOPs of the demodulation coefficients: squared-weight sums, then their contraction with the squared style."""
    c0, nnz, c1, u = w_shape
    return 2 * c0 * nnz * c1 * u + 2 * batch * e_out * c0 * c1


def conv1d_dense_flops(batch: int, c_out: int, c_in: int, frames_out: int, taps: int) -> int:
    """A plain ``conv1d`` (what ``FlopCounterMode`` counts for ``aten.convolution``)."""
    return 2 * batch * c_out * c_in * frames_out * taps


def fk_flops(batch: int, frames: int, joints: int, backward: bool = False) -> int:
    return (3 if backward else 1) * FK_FLOPS_PER_JOINT_FRAME * batch * frames * joints


# ------------------------------------------------------------------------------------------------ op formulas
def _conv_frames(kind: int, x_shape, grad_shape) -> int:
    return x_shape[-1] if kind == KIND_UP else grad_shape[-1]


def _f_conv(kind: int):
    def formula(x_shape, w_shape, bias_shape, index_shape, offsets_shape, *rest, out_shape=None, **kw) -> int:
        style_shape = rest[1] if kind == KIND_UP else rest[0]
        scale_shape = rest[2] if kind == KIND_UP else rest[1]
        return skeletal_forward_flops(kind, x_shape, w_shape, out_shape, style=style_shape is not None,
                                      demodulate=False) + (prod(out_shape) if scale_shape is not None else 0)
    return formula


def _f_backward(grad_shape, out_shape_, x_shape, w_shape, bias_shape, index_shape, offsets_shape, style_shape,
                scale_shape, padding_mode, kind, n_out, output_mask, out_shape=None, **kw) -> int:
    c0, nnz, c1, u = w_shape
    macs = skeletal_macs(kind, x_shape[0], _conv_frames(kind, x_shape, grad_shape), nnz, c0, c1, u)
    want_x, want_w, want_s, want_d = (list(output_mask) + [False] * 4)[:4]
    flops = 2 * macs * (int(want_x or want_s) + int(want_w))
    if kind == KIND_UP and (want_x or want_s or want_w):
        flops += 2 * BLUR_TAPS * prod(grad_shape)  # the blur's adjoint on the incoming gradient
    if want_s and style_shape is not None:
        flops += 2 * prod(x_shape)
    if want_d and scale_shape is not None:
        flops += prod(grad_shape)
    return flops


def _f_grad_input(grad_shape, w_shape, index_shape, offsets_shape, kind, n_out, n_in, t_in, padding_mode,
                  out_shape=None, **kw) -> int:
    c0, nnz, c1, u = w_shape
    frames = t_in if kind == KIND_UP else grad_shape[-1]
    blur = 2 * BLUR_TAPS * prod(grad_shape) if kind == KIND_UP else 0
    return 2 * skeletal_macs(kind, grad_shape[0], frames, nnz, c0, c1, u) + blur


def _f_grad_weight(grad_shape, x_shape, index_shape, offsets_shape, kind, n_out, taps, padding_mode,
                   out_shape=None, **kw) -> int:
    c0, nnz, c1, u = out_shape
    blur = 2 * BLUR_TAPS * prod(grad_shape) if kind == KIND_UP else 0
    return 2 * skeletal_macs(kind, x_shape[0], _conv_frames(kind, x_shape, grad_shape), nnz, c0, c1, u) + blur


def _f_demod(w_shape, style_shape, index_shape, offsets_shape, up, n_out, eps, out_shape=None, **kw) -> int:
    return demod_flops(KIND_UP if up else KIND_CONV, w_shape, style_shape[0] if style_shape else 1, n_out)


def _f_demod_backward(grad_shape, d_shape, w_shape, style_shape, index_shape, offsets_shape, up, n_out, output_mask,
                      out_shape=None, **kw) -> int:
    one = demod_flops(KIND_UP if up else KIND_CONV, w_shape, style_shape[0] if style_shape else 1, n_out)
    return one * sum(bool(m) for m in output_mask)


def _f_fk(q_shape, offsets_shape, parents, root_shape, out_shape=None, **kw) -> int:
    return fk_flops(prod(q_shape[:-2]), 1, q_shape[-2])


def _f_fk_backward(grad_shape, gq_shape, q_shape, global_shape, offsets_shape, parents, offsets_grad,
                   out_shape=None, **kw) -> int:
    n, j = prod(q_shape[:-2]), q_shape[-2]
    return fk_flops(n, 1, j, backward=True) - fk_flops(n, 1, j)


def modi_ext_formulas() -> dict:
    """``{op packet: formula of the shapes}``; ops the build lacks are left out."""
    table = {"skeletal_conv": _f_conv(KIND_CONV), "skeletal_down": _f_conv(KIND_DOWN), "skeletal_up": _f_conv(KIND_UP),
             "skeletal_backward": _f_backward, "skeletal_grad_input": _f_grad_input,
             "skeletal_grad_weight": _f_grad_weight, "demod_scale": _f_demod,
             "demod_scale_backward": _f_demod_backward, "fk": _f_fk, "fk_backward": _f_fk_backward}
    out = {}
    for name, fn in table.items():
        try:
            out[getattr(torch.ops.modi_ext, name)] = fn
        except (AttributeError, RuntimeError):
            continue
    return out


class FlopCounter(TorchDispatchMode):
    """Counts the FLOPs of the ops run inside the block: torch's formulas (``torch.utils.flop_counter``) and the
    modi_ext ones above. ``FlopCounterMode`` itself is not used: its module tracker puts backward hooks on the
    inputs, which ``torch.autograd.grad`` on a leaf refuses, and the benchmarks differentiate w.r.t. leaves."""

    _SKIP = {"size", "sym_size", "stride", "sym_stride", "numel", "sym_numel", "dim", "storage_offset",
             "sym_storage_offset", "is_contiguous", "sym_is_contiguous", "is_strides_like_format",
             "is_non_overlapping_and_dense", "layout"}

    def __init__(self, device: str = "cpu", dtype: torch.dtype = torch.float32):
        super().__init__()
        if modi_ext.HAS_EXT:  # the kernels' first-use self-check, outside the mode (its ops are not the caller's)
            dispatch.kernels_trusted(device, str(dtype))
        self.registry = {**flop_registry, **{k: shape_wrapper(v) for k, v in modi_ext_formulas().items()}}
        self.by_op: dict[str, int] = defaultdict(int)

    @property
    def total(self) -> int:
        return int(sum(self.by_op.values()))

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        packet = func._overloadpacket
        if packet.__name__ in self._SKIP:
            return func(*args, **kwargs)
        if packet not in self.registry:
            with self:
                r = func.decompose(*args, **kwargs)
            if r is not NotImplemented:
                return r
            return func(*args, **kwargs)
        out = func(*args, **kwargs)
        try:
            self.by_op[str(packet)] += int(self.registry[packet](*args, **kwargs, out_val=out))
        except Exception:  # noqa: BLE001 - a shape a formula does not know (e.g. a self-check's): count nothing
            self.by_op[str(packet) + " (uncounted)"] += 0
        return out


def count_flops(fn: Callable[[], Any]) -> tuple[int, Any]:
    """(FLOPs, fn's result) of one call of ``fn`` (CPU fp32 ops)."""
    with FlopCounter() as counter:
        res = fn()
    return counter.total, res


def flops_by_op(fn: Callable[[], Any]) -> dict[str, int]:
    """``{op name: FLOPs}`` of one call of ``fn`` (for tests and reports)."""
    with FlopCounter() as counter:
        fn()
    return dict(counter.by_op)


# ------------------------------------------------------------------------------------------------ the machine
def sgemm_gflops(n: int = 1024, min_time: float = 0.3, reps: int = 5, m: int | None = None,
                 k: int | None = None) -> float:
    """This process's fp32 ``torch.mm`` rate in GF/s (median), at torch's current thread count; ``m x k @ k x n``
    (default square ``n``)."""
    m, k = m or n, k or n
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(m, k, generator=g), torch.randn(k, n, generator=g)
    c = torch.empty(m, n)
    torch.mm(a, b, out=c)
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < reps or (time.perf_counter() - start < min_time and len(times) < 200):
        t0 = time.perf_counter()
        torch.mm(a, b, out=c)
        times.append(time.perf_counter() - t0)
    return 2.0 * m * n * k / statistics.median(times) / 1e9


def blas_at_conv_shapes(n_out: int, nnz: int, c_out: int, c_in: int, taps: int, batch: int, frames: int,
                        min_time: float = 0.3) -> dict[str, float]:
    """GF/s of torch's own sgemm (``torch.bmm``, contiguous operands, no gather) at the GEMM shapes a skeletal conv is
    made of: ``n_out`` products of ``c_out x K`` by ``K x batch*frames`` with ``K = nnz/n_out * c_in * taps`` (the
    forward), and the input- and weight-gradient products of the same sizes.  The best a GEMM library does at the
    conv's own shapes: a bound for the conv that the 1024^3 rate is not (a 32-row product reuses each loaded column
    32 times, a 1024-row one 1024 times)."""
    k = max(1, round(nnz / n_out)) * c_in * taps
    n = batch * frames
    g = torch.Generator().manual_seed(0)
    r = lambda *shape: torch.randn(*shape, generator=g)  # noqa: E731
    a, b, at, gy, x = r(n_out, c_out, k), r(n_out, k, n), r(n_out, k, c_out), r(n_out, c_out, n), r(n_out, n, k)
    out = {}
    for name, (lhs, rhs) in {"fwd": (a, b), "grad_input": (at, gy), "grad_weight": (gy, x)}.items():
        torch.bmm(lhs, rhs)
        times: list[float] = []
        start = time.perf_counter()
        while len(times) < 5 or (time.perf_counter() - start < min_time and len(times) < 200):
            t0 = time.perf_counter()
            torch.bmm(lhs, rhs)
            times.append(time.perf_counter() - t0)
        out[name] = 2.0 * n_out * c_out * k * n / statistics.median(times) / 1e9
    return out


class Sgemm:
    """The sgemm rate of this run: measured at the start and again at the end (``remeasure``); the faster of the
    two is the reference (a busy moment can only slow one down)."""

    def __init__(self, n: int = 1024, min_time: float = 0.3):
        self.n, self.min_time = n, min_time
        self.threads = torch.get_num_threads()
        self.samples = [sgemm_gflops(n, min_time)]

    def remeasure(self) -> None:
        self.samples.append(sgemm_gflops(self.n, self.min_time))

    @property
    def gflops(self) -> float:
        return max(self.samples)

    def rate(self, flops: float, ms: float) -> tuple[float, float]:
        """(achieved GF/s, fraction of sgemm) of ``flops`` done in ``ms``."""
        gf = flops / (ms * 1e-3) / 1e9 if ms > 0 else float("nan")
        return gf, gf / self.gflops

    def describe(self) -> dict:
        return {"sgemm_gflops": round(self.gflops, 2), "sgemm_samples_gflops": [round(s, 2) for s in self.samples],
                "sgemm_shape": [self.n, self.n, self.n], "sgemm_threads": self.threads}
