"""The public skeletal ops: argument checks, then the sparse kernels, the dense form or the reference.

``modi_ext.runtime.dispatch.route`` picks the path per call (``MODI_EXT_IMPL=auto|ext|dense|ref``; kernels only where
this build has them for the device, only after their self-check, on CUDA only where measured faster than ``dense``).
On the kernel path the demodulation coefficients ``d[b,o,j]`` are computed first (a ``(B, Cin) x (Cin, Cout*E)``
product of squared weights, never a per-sample weight tensor; ``modi_ext.demod.ops``: one C++ call on the CPU, the
torch form elsewhere) and handed to the kernel, which applies the style on the input rows and ``d`` on the output rows.

Under ``torch.autocast`` the inputs are cast to one dtype and the op runs with autocast off, so standard AMP works:
the autocast dtype, as torch's own convolutions (on CUDA, and on the CPU for bfloat16, which runs on the dense path:
oneDNN's bf16 GEMMs with fp32 accumulation where the CPU has bf16 units, torch's emulation elsewhere); the widest
input dtype, at least float32, when an input is float64 (autocast leaves float64 alone) or the CPU autocast dtype is
float16 (no CPU path takes it).

The checks are ``modi_ext.skeletal.checks``; the kernel call with its autograd (eager fast path, first-order fused
backward, differentiable backward of any order, ``MODI_EXT_DOUBLE=ref``) is ``modi_ext.skeletal.autograd``.
"""
from __future__ import annotations

import torch

from modi_ext.demod.ops import demod_scale  # noqa: F401  (re-exported: the kernels' demodulation coefficients)
from modi_ext.runtime import dispatch
from modi_ext.skeletal import dense, reference
from modi_ext.skeletal.autograd import NAMES, launch
from modi_ext.skeletal.checks import KIND_CONV, KIND_DOWN, KIND_UP, check_args, validate_csr  # noqa: F401
from modi_ext.skeletal.reference import from_dense, to_dense  # noqa: F401  (re-exported: compact <-> dense weights)

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up", "to_dense", "from_dense", "demod_scale", "validate_csr"]


def _run(kind: int, impl: str, x, weight, bias, index, offsets, n_out: int, style, demodulate: bool,
         padding_mode: str) -> torch.Tensor:
    """The checked call on one path ('ext', 'dense' or 'ref')."""
    if impl == "ref" or impl == "dense":
        mod = reference if impl == "ref" else dense
        if kind == KIND_UP:
            return mod.skeletal_up(x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
        fn = mod.skeletal_conv if kind == KIND_CONV else mod.skeletal_down
        return fn(x, weight, bias, index, offsets, style, demodulate, padding_mode)
    scale = demod_scale(weight, index, offsets, style, kind == KIND_UP, n_out, x.shape[0]) if demodulate else None
    return launch(kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode)


def _autocast_device(x: torch.Tensor) -> str | None:
    dev = x.device.type
    try:
        return dev if torch.is_autocast_enabled(dev) else None
    except (RuntimeError, TypeError):  # a device type autocast does not know
        return None


def _amp_cast(dev: str, x, weight, bias, style):
    """One dtype for every floating input under autocast (the kernels and the checks want one), and the dtype of
    the output (None: the inputs').

    On the CPU the inputs go to the widest of their dtypes, at least float32, so the fp32 kernels run; under bf16
    autocast the output is then rounded to bf16, autocast's rule for convolutions. The fp32 kernels are 3.5x faster
    than the only bf16 path the CPU has today (the dense form on oneDNN's bf16 GEMMs, docs/results.md) and more
    accurate; explicit bf16 inputs outside autocast still take that bf16 path."""
    floats = [t for t in (x, weight, bias, style) if isinstance(t, torch.Tensor) and t.is_floating_point()]
    target, out = torch.get_autocast_dtype(dev), None
    if dev != "cuda":
        if target == torch.bfloat16 and all(t.dtype != torch.float64 for t in floats):
            out = torch.bfloat16
        target = torch.float32
        for t in floats:
            target = torch.promote_types(target, t.dtype)
    cast = lambda t: t.to(target) if isinstance(t, torch.Tensor) and t.is_floating_point() else t  # noqa: E731
    return cast(x), cast(weight), cast(bias), cast(style), out


def _op(kind: int, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode) -> torch.Tensor:
    amp = _autocast_device(x) if isinstance(x, torch.Tensor) else None
    if amp is not None:
        x, weight, bias, style, out = _amp_cast(amp, x, weight, bias, style)
        with torch.autocast(amp, enabled=False):
            y = _op_checked(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
        return y if out is None else y.to(out)
    return _op_checked(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)


def _op_checked(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode) -> torch.Tensor:
    n_out = check_args(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
    args = (x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)

    def signature() -> str:
        train = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, weight, style))
        return (f"{str(x.dtype).replace('torch.', '')} x{tuple(x.shape)} w{tuple(weight.shape)} out{n_out} "
                f"style={style is not None} demod={demodulate} bias={bias is not None} {padding_mode} "
                f"{'fwd_bwd' if train else 'fwd'}")

    def bench(impl: str):
        train = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, weight, style))
        leaves = [t.detach().requires_grad_(train) if isinstance(t, torch.Tensor) else t for t in (x, weight, style)]

        def call():
            with torch.set_grad_enabled(train):
                y = _run(kind, impl, leaves[0], leaves[1], bias.detach() if bias is not None else None, index,
                         offsets, n_out, leaves[2], demodulate, padding_mode)
                if train:
                    torch.autograd.grad(y, [t for t in leaves if t is not None], torch.ones_like(y))
        return call

    impl = dispatch.route(NAMES[kind], x, "skeletal", signature, bench)
    dispatch.record_path(NAMES[kind], x, impl)
    return _run(kind, impl, *args)


def skeletal_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, *, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """In-place skeletal conv ``(B, Cin, E, T) -> (B, Cout, E, T)``; weight ``(Cout, nnz, Cin, U)``.

    ``(index, offsets)`` is the CSR neighbor map (``modi_ext.csr.csr_from_lists``).  Exact semantics in
    ``modi_ext.skeletal.reference``.
    """
    return _op(KIND_CONV, x, weight, bias, index, offsets, None, style, demodulate, padding_mode)


def skeletal_down(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, *, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """Convolutional scaler ``(B, Cin, E_fine, T) -> (B, Cout, E_coarse, T // 2)``; CSR = coarse -> fine map."""
    return _op(KIND_DOWN, x, weight, bias, index, offsets, None, style, demodulate, padding_mode)


def skeletal_up(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                offsets: torch.Tensor, n_out: int, *, style: torch.Tensor | None = None, demodulate: bool = False,
                padding_mode: str = "zeros") -> torch.Tensor:
    """Coarse -> fine ``(B, Cin, E_coarse, T) -> (B, Cout, n_out, 2T)``: adjoint of down, then [1,3,3,1] blur.

    weight ``(Cin, nnz, Cout, U)`` (the layout of the down op it is the adjoint of); CSR = coarse -> fine map.
    """
    return _op(KIND_UP, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
