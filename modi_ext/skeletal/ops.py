"""The public skeletal ops: check, pick the implementation, call it.

``_call`` is the whole path of a call, in four steps a reader follows on one screen:

1. under ``torch.autocast``, the inputs go to one dtype and the op runs with autocast off (``modi_ext.runtime.amp``:
   the autocast dtype on CUDA, as torch's own convolutions; on the CPU under bf16 autocast the bf16 kernels where
   they run, else the fp32 kernels with the output rounded to bf16);
2. ``check_args`` validates every argument (``modi_ext.skeletal.checks``);
3. ``dispatch.route`` picks the path: ``impl=`` for this call, else ``MODI_EXT_IMPL=auto|ext|dense|ref`` (kernels
   only where this build has them for the device, after their first-use self-check, on CUDA only where measured
   faster than ``dense``);
4. on the kernels, the demodulation coefficients ``d[b, o, j]`` (``modi_ext.demod``: a ``(B, Cin) x (Cin, Cout*E)``
   product of squared weights, never a per-sample weight tensor) and ``kernels.launch`` -- the C++ op with its
   autograd (``modi_ext.skeletal.registration``; gradients of any order: ``modi_ext.skeletal.gradfix``), which
   applies the style on the input rows and ``d`` on the output rows; else the dense form or the reference.
"""
from __future__ import annotations

import torch

from modi_ext.act import fused_leaky_relu
from modi_ext.demod.ops import demod_scale  # noqa: F401  (re-exported: the kernels' demodulation coefficients)
from modi_ext.runtime import amp, dispatch, kernels
from modi_ext.skeletal import dense, reference, registration  # noqa: F401  (registration: fakes, autograd on import)
from modi_ext.skeletal.checks import (KIND_CONV, KIND_DOWN, KIND_UP, NAMES, check_args, kernel_args,  # noqa: F401
                                      validate_csr)
from modi_ext.skeletal.reference import from_dense, to_dense  # noqa: F401  (re-exported: compact <-> dense weights)

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up", "to_dense", "from_dense", "demod_scale", "validate_csr"]


def _call(kind: int, impl: str | None, x, weight, bias, index, offsets, n_out, style, demodulate: bool,
          padding_mode: str, act: bool) -> torch.Tensor:
    """One call of ``NAMES[kind]``: autocast, checks, path, kernel (see the module docstring)."""
    device = amp.autocast_device(x)
    if device is not None:
        (x, weight, bias, style), out_dtype = amp.cast(device, x, weight, bias, style,
                                                       bf16_kernels=dispatch.cpu_bf16_kernels(impl))
        with torch.autocast(device, enabled=False):
            y = _call(kind, impl, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode, act)
        return y if out_dtype is None else y.to(out_dtype)
    n_out = check_args(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode, act)
    path = dispatch.route(NAMES[kind], x, impl=impl, record=True, inputs=(x, weight, style),
                          options=(n_out, demodulate, bias is not None, padding_mode, act),
                          rerun=lambda p, x, weight, style: _call(kind, p, x, weight, bias, index, offsets, n_out,
                                                                  style, demodulate, padding_mode, act))
    if path == "ext":
        up = kind == KIND_UP
        scale = demod_scale(weight, index, offsets, style, up, n_out, x.shape[0]) if demodulate else None
        return kernels.launch(NAMES[kind], *kernel_args(kind, x, weight, bias, index, offsets, n_out, style, scale,
                                                        padding_mode, act))
    form = reference if path == "ref" else dense
    b = None if act else bias  # with act, the bias goes in before the activation, below
    if kind == KIND_UP:
        y = form.skeletal_up(x, weight, b, index, offsets, n_out, style, demodulate, padding_mode)
    else:
        fn = form.skeletal_conv if kind == KIND_CONV else form.skeletal_down
        y = fn(x, weight, b, index, offsets, style, demodulate, padding_mode)
    return fused_leaky_relu(y, bias) if act else y


def skeletal_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, *, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros", act: bool = False, impl: str | None = None) -> torch.Tensor:
    """In-place skeletal conv ``(B, Cin, E, T) -> (B, Cout, E, T)``; weight ``(Cout, nnz, Cin, U)``.

    ``(index, offsets)`` is the CSR neighbor map (``modi_ext.csr.csr_from_lists``).  Exact semantics in
    ``modi_ext.skeletal.reference``.  ``impl``: 'auto', 'ext', 'dense' or 'ref' forces a path for this call
    (default: ``MODI_EXT_IMPL``), as every op's.  ``act``: StyleGAN2's bias activation after the bias
    (``modi_ext.act``), in the kernels' epilogue: ``fused_leaky_relu(skeletal_conv(x, w, None, ...), bias)`` in one op.
    """
    return _call(KIND_CONV, impl, x, weight, bias, index, offsets, None, style, demodulate, padding_mode, act)


def skeletal_down(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, *, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros", act: bool = False, impl: str | None = None) -> torch.Tensor:
    """Convolutional scaler ``(B, Cin, E_fine, T) -> (B, Cout, E_coarse, T // 2)``; CSR = coarse -> fine map."""
    return _call(KIND_DOWN, impl, x, weight, bias, index, offsets, None, style, demodulate, padding_mode, act)


def skeletal_up(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                offsets: torch.Tensor, n_out: int, *, style: torch.Tensor | None = None, demodulate: bool = False,
                padding_mode: str = "zeros", act: bool = False, impl: str | None = None) -> torch.Tensor:
    """Coarse -> fine ``(B, Cin, E_coarse, T) -> (B, Cout, n_out, 2T)``: adjoint of down, then [1,3,3,1] blur.

    weight ``(Cin, nnz, Cout, U)`` (the layout of the down op it is the adjoint of); CSR = coarse -> fine map.
    """
    return _call(KIND_UP, impl, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode, act)
