"""Public skeletal operators: argument checks, then the sparse kernels, the dense form or the reference.

``modi_ext.dispatch.route`` picks the path per call (``MODI_EXT_IMPL=auto|ext|dense|ref``; kernels only where this
build has them for the device, only after their self-check, on CUDA only where measured faster than ``dense``).  On
the kernel path the demodulation coefficients ``d[b,o,j]`` are computed first (a ``(B, Cin) x (Cin, Cout*E)``
product of squared weights, never a per-sample weight tensor; ``modi_ext.demod``: one C++ call on the CPU, the torch
ops of ``dense.demod_scale`` elsewhere) and handed to the kernel, which applies the style on the input rows and ``d``
on the output rows.

Under ``torch.autocast`` the inputs are cast to one dtype (the autocast dtype on CUDA, where the kernels take half
types; the widest input dtype elsewhere) and the op runs with autocast off, so standard AMP works.

Autograd rules are registered with ``torch.library.register_autograd`` (what compile, opcheck and functorch use);
plain eager calls run the same rules through ``torch.autograd.Function``s that skip the dispatcher's round trip into
Python (``modi_ext.eager``).  First-order gradients use the fused C++ backward kernel, and only for the inputs whose
gradient the engine will use (``gradfix.needed``); when a graph of the gradient is requested (``create_graph=True``:
R1, path length, WGAN-GP) the backward is built from ops that are themselves differentiable (``modi_ext.gradfix``),
so every order stays on the sparse kernels.  ``MODI_EXT_DOUBLE=ref`` routes that graph through the dense reference
instead (the old behaviour, for comparison).
"""
from __future__ import annotations

import os
import weakref

import torch

from modi_ext.demod.ops import demod_scale  # noqa: F401  (re-exported: the kernels' demodulation coefficients)
from modi_ext.runtime import dispatch, eager
from modi_ext.runtime.loader import HAS_EXT
from modi_ext.skeletal import dense, reference
from modi_ext.skeletal.reference import from_dense, to_dense  # noqa: F401  (re-exported: compact <-> dense weights)

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up", "to_dense", "from_dense", "demod_scale", "validate_csr"]

_KIND_CONV, _KIND_DOWN, _KIND_UP = 0, 1, 2
_FLOATS = (torch.float32, torch.float64)
_CUDA_FLOATS = _FLOATS + (torch.float16, torch.bfloat16)  # the CUDA kernels accumulate half types in fp32


def _allowed_floats(t: torch.Tensor) -> tuple:
    return _CUDA_FLOATS if t.is_cuda else _FLOATS


def _is_tracing() -> bool:
    try:
        return torch.compiler.is_compiling()
    except AttributeError:  # pragma: no cover - very old torch
        return False


def _check(kind: int, x, weight, bias, index, offsets, n_out: int | None, style, demodulate, padding_mode) -> int:
    """Validate every argument; returns the number of output entities. Errors name the argument."""
    for name, t in (("x", x), ("weight", weight), ("index", index), ("offsets", offsets)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if x.dim() != 4:
        raise ValueError(f"x must be 4-D (B, C, E, T), got shape {tuple(x.shape)}")
    if x.dtype not in _allowed_floats(x):
        raise TypeError(f"x must be float32 or float64 (or float16/bfloat16 on CUDA), got {x.dtype} on {x.device}")
    if weight.dim() != 4:
        raise ValueError(f"weight must be 4-D compact (C0, nnz, C1, U), got shape {tuple(weight.shape)}")
    if weight.dtype != x.dtype:
        raise TypeError(f"weight dtype {weight.dtype} differs from x dtype {x.dtype}")
    if weight.device != x.device:
        raise ValueError(f"weight is on {weight.device} but x is on {x.device}")
    for name, t in (("x", x), ("weight", weight)):
        if not t.is_contiguous():
            raise ValueError(f"{name} must be contiguous (call .contiguous())")
    b, cin, e_in, t_len = x.shape
    if b == 0:
        raise ValueError("x has an empty batch (B == 0)")
    if t_len == 0:
        raise ValueError("x has zero frames (T == 0)")
    u = weight.shape[3]
    if u % 2 != 1:
        raise ValueError(f"weight kernel width U={u} must be odd")
    if padding_mode not in reference.PADDING_MODES:
        raise ValueError(f"padding_mode must be one of {reference.PADDING_MODES}, got {padding_mode!r}")
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
    if kind == _KIND_UP:
        c_in_w, c_out = weight.shape[0], weight.shape[2]
        if n_out is None or int(n_out) <= 0:
            raise ValueError(f"n_out must be a positive int, got {n_out!r}")
        if e_in != n_rows:
            raise ValueError(f"x has {e_in} coarse entities but offsets describes {n_rows}")
        n_idx_range = int(n_out)
    else:
        c_in_w, c_out = weight.shape[2], weight.shape[0]
        if kind == _KIND_CONV and e_in != n_rows:
            raise ValueError(f"x has {e_in} entities but the neighbor lists (offsets) describe {n_rows}")
        n_idx_range = e_in
    if c_in_w != cin:
        raise ValueError(f"x has {cin} channels but weight expects {c_in_w}")
    h = u // 2
    if kind == _KIND_DOWN and t_len < 2:
        raise ValueError(f"x needs at least 2 frames to downsample, got {t_len}")
    if padding_mode == "reflect":
        padded_len = 2 * t_len if kind == _KIND_UP else t_len
        if padded_len <= h:
            raise ValueError(f"reflect padding of {h} frames needs more than {h} frames, got {padded_len}")
    if bias is not None:
        if not isinstance(bias, torch.Tensor) or bias.dim() != 1 or bias.shape[0] != c_out:
            raise ValueError(f"bias must be a 1-D tensor of {c_out} output channels, "
                             f"got {tuple(bias.shape) if isinstance(bias, torch.Tensor) else type(bias).__name__}")
        if bias.dtype != x.dtype or bias.device != x.device:
            raise TypeError(f"bias must be {x.dtype} on {x.device}, got {bias.dtype} on {bias.device}")
    if style is not None:
        if not isinstance(style, torch.Tensor) or style.dim() != 2 or tuple(style.shape) != (b, cin):
            raise ValueError(f"style must be (B, Cin) = {(b, cin)}, "
                             f"got {tuple(style.shape) if isinstance(style, torch.Tensor) else type(style).__name__}")
        if style.dtype != x.dtype or style.device != x.device:
            raise TypeError(f"style must be {x.dtype} on {x.device}, got {style.dtype} on {style.device}")
    if not isinstance(demodulate, bool):
        raise TypeError(f"demodulate must be a bool, got {type(demodulate).__name__}")
    if not _is_tracing() and index.device.type != "meta":
        validate_csr(index, offsets, n_idx_range)
    return int(n_out) if kind == _KIND_UP else n_rows


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


_NAMES = {_KIND_CONV: "skeletal_conv", _KIND_DOWN: "skeletal_down", _KIND_UP: "skeletal_up"}
_EAGER: dict[int, type] = {}  # kind -> the op's plain autograd.Function (modi_ext.eager), filled at registration


def _run(kind: int, impl: str, x, weight, bias, index, offsets, n_out: int, style, demodulate: bool,
         padding_mode: str) -> torch.Tensor:
    """The checked call on one path ('ext', 'dense' or 'ref')."""
    if impl == "ref" or impl == "dense":
        mod = reference if impl == "ref" else dense
        if kind == _KIND_UP:
            return mod.skeletal_up(x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
        fn = mod.skeletal_conv if kind == _KIND_CONV else mod.skeletal_down
        return fn(x, weight, bias, index, offsets, style, demodulate, padding_mode)
    scale = demod_scale(weight, index, offsets, style, kind == _KIND_UP, n_out, x.shape[0]) if demodulate else None
    return _launch(kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode)


def plain_op(kind: int, x: torch.Tensor, weight: torch.Tensor, index: torch.Tensor, offsets: torch.Tensor,
             n_out: int, padding_mode: str) -> torch.Tensor:
    """``A_W x`` (no bias, style or scale) on the kernels, differentiable to any order; no argument checks."""
    return _launch(kind, x, weight, None, index, offsets, n_out, None, None, padding_mode)


def _launch(kind: int, x, weight, bias, index, offsets, n_out: int, style, scale, padding_mode: str) -> torch.Tensor:
    """The kernel call with autograd: the eager Function where it applies, else the registered op."""
    if kind == _KIND_UP:
        args = (x, weight, bias, index, offsets, n_out, style, scale, padding_mode)
    else:
        args = (x, weight, bias, index, offsets, style, scale, padding_mode)
    if kind in _EAGER and eager.usable(x, weight, bias, style, scale, index, offsets):
        return _EAGER[kind].apply(*args)
    return dispatch.KERNELS[_NAMES[kind]](*args)


def _autocast_device(x: torch.Tensor) -> str | None:
    dev = x.device.type
    try:
        return dev if torch.is_autocast_enabled(dev) else None
    except (RuntimeError, TypeError):  # a device type autocast does not know
        return None


def _amp_cast(dev: str, x, weight, bias, style):
    """One dtype for every floating input under autocast (the kernels and the checks want one)."""
    floats = [t for t in (x, weight, bias, style) if isinstance(t, torch.Tensor) and t.is_floating_point()]
    if dev == "cuda":
        target = torch.get_autocast_dtype(dev)
    else:  # the CPU kernels take float32/float64 only: the widest input dtype, at least float32
        target = torch.float32
        for t in floats:
            target = torch.promote_types(target, t.dtype)
    cast = lambda t: t.to(target) if isinstance(t, torch.Tensor) and t.is_floating_point() else t  # noqa: E731
    return cast(x), cast(weight), cast(bias), cast(style)


def _op(kind: int, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode) -> torch.Tensor:
    amp = _autocast_device(x) if isinstance(x, torch.Tensor) else None
    if amp is not None:
        x, weight, bias, style = _amp_cast(amp, x, weight, bias, style)
        with torch.autocast(amp, enabled=False):
            return _op_checked(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
    return _op_checked(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)


def _op_checked(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode) -> torch.Tensor:
    n_out = _check(kind, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)
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

    impl = dispatch.route(_NAMES[kind], x, "skeletal", signature, bench)
    return _run(kind, impl, *args)


def skeletal_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, *, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """In-place skeletal conv ``(B, Cin, E, T) -> (B, Cout, E, T)``; weight ``(Cout, nnz, Cin, U)``.

    ``(index, offsets)`` is the CSR neighbor map (``modi_ext.topology_tensors.csr_from_lists``).  Exact semantics in
    ``modi_ext.reference``.
    """
    return _op(_KIND_CONV, x, weight, bias, index, offsets, None, style, demodulate, padding_mode)


def skeletal_down(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                  offsets: torch.Tensor, *, style: torch.Tensor | None = None, demodulate: bool = False,
                  padding_mode: str = "zeros") -> torch.Tensor:
    """Convolutional scaler ``(B, Cin, E_fine, T) -> (B, Cout, E_coarse, T // 2)``; CSR = coarse -> fine map."""
    return _op(_KIND_DOWN, x, weight, bias, index, offsets, None, style, demodulate, padding_mode)


def skeletal_up(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, index: torch.Tensor,
                offsets: torch.Tensor, n_out: int, *, style: torch.Tensor | None = None, demodulate: bool = False,
                padding_mode: str = "zeros") -> torch.Tensor:
    """Coarse -> fine ``(B, Cin, E_coarse, T) -> (B, Cout, n_out, 2T)``: adjoint of down, then [1,3,3,1] blur.

    weight ``(Cin, nnz, Cout, U)`` (the layout of the down op it is the adjoint of); CSR = coarse -> fine map.
    """
    return _op(_KIND_UP, x, weight, bias, index, offsets, n_out, style, demodulate, padding_mode)


# ----------------------------------------------------------------------------------------------------------------
# Extension registration: fake kernels (for torch.compile / meta) and autograd.

def _double_backward_on_reference() -> bool:
    """``MODI_EXT_DOUBLE=ref``: build the graph of a gradient through the dense reference instead of
    ``modi_ext.gradfix`` (the behaviour before gradfix existed; a debugging and benchmarking switch)."""
    return os.environ.get("MODI_EXT_DOUBLE", "ext").strip().lower() == "ref"


def _reference_graph_backward(kind, grad, x, weight, bias, index, offsets, style, scale, padding_mode, n_out, need):
    """Gradients as a differentiable graph by re-running the op on the dense reference (slow, exact)."""
    args = dict(x=x, weight=weight, bias=bias, style=style, scale=scale)
    wanted = [k for k, v in need.items() if v and args[k] is not None]
    res = dict.fromkeys(need)
    if not wanted:
        return res
    if kind == _KIND_UP:
        y = reference.skeletal_up(x, weight, None, index, offsets, n_out, style, False, padding_mode)
    elif kind == _KIND_DOWN:
        y = reference.skeletal_down(x, weight, None, index, offsets, style, False, padding_mode)
    else:
        y = reference.skeletal_conv(x, weight, None, index, offsets, style, False, padding_mode)
    if scale is not None:
        y = y * scale.unsqueeze(-1)
    if bias is not None:
        y = y + bias.view(1, -1, 1, 1)
    grads = torch.autograd.grad(y, [args[k] for k in wanted], grad, create_graph=True, allow_unused=True)
    res.update(zip(wanted, grads))
    return res


def _out_shape(kind, x, weight, offsets, n_out):
    b, _, _, t = x.shape
    if kind == _KIND_UP:
        return (b, weight.shape[2], n_out, 2 * t)
    e_out = offsets.shape[0] - 1
    return (b, weight.shape[0], e_out, t if kind == _KIND_CONV else t // 2)


def _autograd_rules(kind: int):
    """``(setup_context, backward)`` of one op: registered with torch.library and reused by ``modi_ext.eager``."""
    up = kind == _KIND_UP

    def setup_context(ctx, inputs, output):
        if up:
            x, weight, bias, index, offsets, n_out, style, scale, padding_mode = inputs
        else:
            x, weight, bias, index, offsets, style, scale, padding_mode = inputs
            n_out = offsets.shape[0] - 1
        ctx.save_for_backward(x, weight, bias, index, offsets, style, scale, output)
        ctx.meta = (padding_mode, n_out)

    def backward(ctx, grad):
        x, weight, bias, index, offsets, style, scale, out = ctx.saved_tensors
        padding_mode, n_out = ctx.meta
        want = lambda i: gradfix.needed(ctx, i)  # noqa: E731  (not just requires_grad: what the engine will use)
        if up:
            need = dict(x=want(0), weight=want(1), bias=want(2), style=want(6), scale=want(7))
        else:
            need = dict(x=want(0), weight=want(1), bias=want(2), style=want(5), scale=want(6))
        if torch.is_grad_enabled():  # create_graph: a differentiable backward made of the kernels themselves
            if _double_backward_on_reference():
                res = _reference_graph_backward(kind, grad, x, weight, bias, index, offsets, style, scale,
                                                padding_mode, n_out, need)
            else:
                res = gradfix.graph_backward(kind, grad, out, x, weight, bias, index, offsets, style, scale,
                                             padding_mode, n_out, need)
            gx, gw, gb, gs, gd = res["x"], res["weight"], res["bias"], res["style"], res["scale"]
        else:
            mask = [bool(need["x"]), bool(need["weight"]), bool(need["style"]), bool(need["scale"])]
            gx, gw, gb, gs, gd = torch.ops.modi_ext.skeletal_backward(
                grad.contiguous(), out, x, weight, bias, index, offsets, style, scale, padding_mode, kind,
                n_out, mask)
            gx = gx if need["x"] else None
            gw = gw if need["weight"] else None
            gb = gb if (need["bias"] and bias is not None) else None
            gs = gs if (need["style"] and style is not None) else None
            gd = gd if (need["scale"] and scale is not None) else None
        if up:
            return gx, gw, gb, None, None, None, gs, gd, None
        return gx, gw, gb, None, None, gs, gd, None

    return setup_context, backward


def _register_ext() -> None:
    lib = torch.library
    gradfix.set_plain_forward(plain_op)

    def make_fake(kind):
        if kind == _KIND_UP:
            def fake(x, weight, bias, index, offsets, n_out, style, scale, padding_mode):
                return x.new_empty(_out_shape(kind, x, weight, offsets, n_out))
        else:
            def fake(x, weight, bias, index, offsets, style, scale, padding_mode):
                return x.new_empty(_out_shape(kind, x, weight, offsets, None))
        return fake

    lib.register_fake("modi_ext::skeletal_conv")(make_fake(_KIND_CONV))
    lib.register_fake("modi_ext::skeletal_down")(make_fake(_KIND_DOWN))
    lib.register_fake("modi_ext::skeletal_up")(make_fake(_KIND_UP))

    @lib.register_fake("modi_ext::skeletal_backward")
    def _bwd_fake(grad, out, x, weight, bias, index, offsets, style, scale, padding_mode, kind, n_out, output_mask):
        gx = torch.empty_like(x) if output_mask[0] else x.new_empty(0)
        gw = torch.empty_like(weight) if output_mask[1] else x.new_empty(0)
        gb = x.new_empty(bias.shape) if bias is not None else x.new_empty(0)
        gs = torch.empty_like(style) if (style is not None and output_mask[2]) else x.new_empty(0)
        gd = torch.empty_like(scale) if (scale is not None and output_mask[3]) else x.new_empty(0)
        return gx, gw, gb, gs, gd

    for kind, name in _NAMES.items():
        setup_context, backward = _autograd_rules(kind)
        lib.register_autograd(f"modi_ext::{name}", backward, setup_context=setup_context)
        _EAGER[kind] = eager.make_function(
            f"{name}_eager", lambda *a, n=name: dispatch.KERNELS[n](*a), setup_context, backward)


if HAS_EXT and hasattr(torch.ops.modi_ext, "skeletal_conv"):
    from modi_ext.skeletal import autograd as gradfix  # registers the differentiable backward ops (needs the C++ schemas loaded)

    _register_ext()
