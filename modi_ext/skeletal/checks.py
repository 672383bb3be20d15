"""The skeletal ops' argument checks: every argument validated on the host, errors naming the argument.

``check_args`` runs before any path (kernels, dense form or reference) sees a call; ``validate_csr`` checks a CSR map's
values once per (index, offsets) pair, so that a bad map is a ``ValueError`` here and never a device-side assert in a
CUDA kernel.  The C++ ops check their own arguments again (callers may bypass the Python ops).
"""
from __future__ import annotations

import weakref

import torch

from modi_ext.skeletal.reference import PADDING_MODES

__all__ = ["KIND_CONV", "KIND_DOWN", "KIND_UP", "NAMES", "kernel_args", "check_args", "validate_csr"]

KIND_CONV, KIND_DOWN, KIND_UP = 0, 1, 2  # the ``kind`` argument of the C++ backward op
NAMES = {KIND_CONV: "skeletal_conv", KIND_DOWN: "skeletal_down", KIND_UP: "skeletal_up"}  # the C++ ops


def kernel_args(kind: int, x, weight, bias, index, offsets, n_out: int, style, scale, padding_mode: str,
                act: bool = False) -> tuple:
    """The arguments of the C++ op ``NAMES[kind]`` in its schema's order (``csrc/skeletal/schema.cpp``): only the
    up op takes ``n_out`` (conv and down read their output entities off ``offsets``)."""
    if kind == KIND_UP:
        return x, weight, bias, index, offsets, n_out, style, scale, padding_mode, act
    return x, weight, bias, index, offsets, style, scale, padding_mode, act
_FLOATS = (torch.float32, torch.float64)
_CUDA_FLOATS = _FLOATS + (torch.float16, torch.bfloat16)  # the CUDA kernels accumulate half types in fp32
_CPU_FLOATS = _FLOATS + (torch.bfloat16,)  # bf16 on the CPU: the bf16 kernels or dense (``dispatch.route``)


def _allowed_floats(t: torch.Tensor) -> tuple:
    return _CUDA_FLOATS if t.is_cuda else _CPU_FLOATS


def _mixed(name: str, t: torch.Tensor, x: torch.Tensor) -> str:
    return (f"{name} dtype {t.dtype} differs from x dtype {x.dtype}: the skeletal ops take one floating dtype "
            f"(cast the inputs, or run under torch.autocast, which casts them)")


def _is_tracing() -> bool:
    try:
        return torch.compiler.is_compiling()
    except AttributeError:  # pragma: no cover - very old torch
        return False


def check_args(kind: int, x, weight, bias, index, offsets, n_out: int | None, style, demodulate, padding_mode,
               act: bool = False) -> int:
    """Validate every argument; returns the number of output entities. Errors name the argument."""
    if not isinstance(act, bool):
        raise TypeError(f"act must be a bool, got {type(act).__name__}")
    for name, t in (("x", x), ("weight", weight), ("index", index), ("offsets", offsets)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if x.dim() != 4:
        raise ValueError(f"x must be 4-D (B, C, E, T), got shape {tuple(x.shape)}")
    if x.dtype not in _allowed_floats(x):
        raise TypeError(f"x must be float32, float64 or bfloat16 (or float16 on CUDA), got {x.dtype} on {x.device}")
    if weight.dim() != 4:
        raise ValueError(f"weight must be 4-D compact (C0, nnz, C1, U), got shape {tuple(weight.shape)}")
    if weight.dtype != x.dtype:
        raise TypeError(_mixed("weight", weight, x))
    if weight.device != x.device:
        raise ValueError(f"weight is on {weight.device} but x is on {x.device}")
    for name, t in (("x", x), ("weight", weight)):
        if not t.is_contiguous():
            raise ValueError(f"{name} must be contiguous (call .contiguous())")
    b, cin, e_in, t_len = x.shape
    if b == 0:
        raise ValueError("x has an empty batch (B == 0)")
    if cin == 0:  # the BLAS paths would be handed a zero leading dimension (an MKL error and garbage, not an error)
        raise ValueError("x has no channels (C == 0)")
    if t_len == 0:
        raise ValueError("x has zero frames (T == 0)")
    u = weight.shape[3]
    if u % 2 != 1:
        raise ValueError(f"weight kernel width U={u} must be odd")
    if padding_mode not in PADDING_MODES:
        raise ValueError(f"padding_mode must be one of {PADDING_MODES}, got {padding_mode!r}")
    for name, t in (("index", index), ("offsets", offsets)):
        if t.dtype != torch.int64:
            raise TypeError(f"{name} must be int64, got {t.dtype}")
        if t.dim() != 1:
            raise ValueError(f"{name} must be 1-D, got shape {tuple(t.shape)}")
        if t.device != x.device:
            raise ValueError(f"{name} is on {t.device} but x is on {x.device}")
        if not t.is_contiguous():
            raise ValueError(f"{name} must be contiguous")
    if offsets.shape[0] < 2:
        raise ValueError("offsets must have at least 2 entries (one output entity)")
    n_rows = offsets.shape[0] - 1
    if weight.shape[1] != index.shape[0]:
        raise ValueError(f"weight has {weight.shape[1]} pairs (dim 1) but index has {index.shape[0]}")
    if kind == KIND_UP:
        c_in_w, c_out = weight.shape[0], weight.shape[2]
        if n_out is None or int(n_out) <= 0:
            raise ValueError(f"n_out must be a positive int, got {n_out!r}")
        if e_in != n_rows:
            raise ValueError(f"x has {e_in} coarse entities but offsets describes {n_rows}")
        n_idx_range = int(n_out)
    else:
        c_in_w, c_out = weight.shape[2], weight.shape[0]
        if kind == KIND_CONV and e_in != n_rows:
            raise ValueError(f"x has {e_in} entities but the neighbor lists (offsets) describe {n_rows}")
        n_idx_range = e_in
    if c_in_w != cin:
        raise ValueError(f"x has {cin} channels but weight expects {c_in_w}")
    h = u // 2
    if kind == KIND_DOWN and t_len < 2:
        raise ValueError(f"x needs at least 2 frames to downsample, got {t_len}")
    if padding_mode == "reflect":
        padded_len = 2 * t_len if kind == KIND_UP else t_len
        if padded_len <= h:
            raise ValueError(f"reflect padding of {h} frames needs more than {h} frames, got {padded_len}")
    if bias is not None:
        if not isinstance(bias, torch.Tensor) or bias.dim() != 1 or bias.shape[0] != c_out:
            raise ValueError(f"bias must be a 1-D tensor of {c_out} output channels, "
                             f"got {tuple(bias.shape) if isinstance(bias, torch.Tensor) else type(bias).__name__}")
        if bias.dtype != x.dtype and bias.device == x.device:
            raise TypeError(_mixed("bias", bias, x))
        if bias.device != x.device:
            raise TypeError(f"bias must be {x.dtype} on {x.device}, got {bias.dtype} on {bias.device}")
    if style is not None:
        if not isinstance(style, torch.Tensor) or style.dim() != 2 or tuple(style.shape) != (b, cin):
            raise ValueError(f"style must be (B, Cin) = {(b, cin)}, "
                             f"got {tuple(style.shape) if isinstance(style, torch.Tensor) else type(style).__name__}")
        if style.dtype != x.dtype and style.device == x.device:
            raise TypeError(_mixed("style", style, x))
        if style.device != x.device:
            raise TypeError(f"style must be {x.dtype} on {x.device}, got {style.dtype} on {style.device}")
    if not isinstance(demodulate, bool):
        raise TypeError(f"demodulate must be a bool, got {type(demodulate).__name__}")
    if not _is_tracing() and index.device.type != "meta":
        validate_csr(index, offsets, n_idx_range)
    return int(n_out) if kind == KIND_UP else n_rows


_CSR_CACHE: dict[tuple, tuple] = {}
_CSR_CACHE_MAX = 512


def _csr_key(index: torch.Tensor, offsets: torch.Tensor, n_range: int) -> tuple:
    return (index.device, index.data_ptr(), index._version, index.shape[0], offsets.data_ptr(), offsets._version,
            offsets.shape[0], int(n_range))


def validate_csr(index: torch.Tensor, offsets: torch.Tensor, n_range: int) -> None:
    """Check a CSR map on the host before any kernel reads it, once per (index, offsets) tensor pair.

    A bad map would make the CUDA kernels stop on a device-side assert, which poisons the CUDA context for the rest
    of the process; here it is a ``ValueError`` naming the problem.  The result is cached by data pointer, version
    counter (bumped by in-place writes) and shape, and the cached entry holds weak references so a new tensor that
    reuses freed memory is never mistaken for a validated one.  On CUDA the first call copies the map to the host.
    """
    key = _csr_key(index, offsets, n_range)
    hit = _CSR_CACHE.get(key)
    if hit is not None and hit[0]() is index and hit[1]() is offsets:
        return
    _check_csr_values(index.cpu(), offsets.cpu(), n_range)
    if len(_CSR_CACHE) >= _CSR_CACHE_MAX:
        _CSR_CACHE.clear()
    _CSR_CACHE[key] = (weakref.ref(index), weakref.ref(offsets))


def _check_csr_values(index: torch.Tensor, off: torch.Tensor, n_range: int) -> None:
    if int(off[0]) != 0 or int(off[-1]) != index.shape[0]:
        raise ValueError(f"offsets must run from 0 to index.numel()={index.shape[0]}, "
                         f"got {int(off[0])}..{int(off[-1])}")
    counts = off[1:] - off[:-1]
    if bool((counts <= 0).any()):
        j = int(torch.nonzero(counts <= 0)[0, 0])
        what = "has no neighbors" if int(counts[j]) == 0 else "ends before it starts (offsets not monotone)"
        raise ValueError(f"offsets: output entity {j} {what}")
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= n_range):
        raise ValueError(f"index holds an entity out of range [0, {n_range})")
