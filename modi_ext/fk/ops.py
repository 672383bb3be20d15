"""The fk op: argument checks, the fused C++ kernel with its fake kernels and autograd, and the ``nn.Module``.

``fk`` checks its arguments, then runs the fused C++ kernel (``torch.ops.modi_ext.fk``) when this build has it for
the tensors' device type (decided once per device type, ``modi_ext.runtime.dispatch.kernels_built``, so
``torch.compile`` traces no probe), else the torch loop ``modi_ext.fk.reference.fk_reference`` (the test oracle;
FK's dense form).  ``MODI_EXT_IMPL=ref|dense|ext|auto`` picks the path; ``auto`` also requires the kernels' first-use
self-check.  The kernel's backward is first order; when a graph of the gradient is asked for (``create_graph=True``)
it is built from the reference's torch ops instead, so second-order gradients through FK are exact.

Semantics: ``modi_ext.fk.reference`` (quaternions (w, x, y, z) in the parent's frame, joint 0 at
``root_positions``).  Inputs are expected to be unit quaternions; nothing is normalised (normalise first if a network
emits them), and for non-unit input both paths evaluate ``rotate(Q, v) = v + 2w (u x v) + 2 u x (u x v)``.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from modi_ext.fk.reference import fk_reference
from modi_ext.runtime import dispatch
from modi_ext.runtime.loader import HAS_EXT, requested_impl

__all__ = ["fk", "ForwardKinematics", "check_parents"]


# ---------------------------------------------------------------------------------------------------------
# checks
# ---------------------------------------------------------------------------------------------------------


def check_parents(parents: Sequence[int] | torch.Tensor, n_joints: int | None = None) -> tuple[int, ...]:
    """Validate a parent list (root first, ``0 <= parents[j] < j``) and return it as a tuple of ints."""
    if isinstance(parents, torch.Tensor):
        if parents.dim() != 1 or parents.dtype.is_floating_point or parents.dtype.is_complex:
            raise ValueError(f"fk: parents must be a 1-D integer list or tensor, got {parents.dtype} {tuple(parents.shape)}")
        parents = parents.tolist()
    try:
        par = tuple(int(p) for p in parents)
    except (TypeError, ValueError):
        raise ValueError(f"fk: parents must be a sequence of ints, got {parents!r}") from None
    if any(int(p) != p for p in parents):
        raise ValueError("fk: parents must be integers")
    if not par:
        raise ValueError("fk: parents is empty (need at least the root joint)")
    if n_joints is not None and len(par) != n_joints:
        raise ValueError(f"fk: parents has {len(par)} entries but local_quats has {n_joints} joints (dim -2)")
    if par[0] != -1:
        raise ValueError(f"fk: parents[0] must be -1 (joint 0 is the root), got {par[0]}")
    for j in range(1, len(par)):
        if not 0 <= par[j] < j:
            raise ValueError(
                f"fk: parents[{j}] = {par[j]} is out of range; parents must be topologically sorted (0 <= parents[j] < j)"
            )
    return par


def _check_tensors(local_quats: torch.Tensor, offsets: torch.Tensor, root_positions: torch.Tensor) -> None:
    for name, t in (("local_quats", local_quats), ("offsets", offsets), ("root_positions", root_positions)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"fk: {name} must be a torch.Tensor, got {type(t).__name__}")
    if local_quats.dim() < 2 or local_quats.shape[-1] != 4:
        raise ValueError(f"fk: local_quats must have shape (..., J, 4), got {tuple(local_quats.shape)}")
    allowed = (torch.float32, torch.float64) + ((torch.float16, torch.bfloat16) if local_quats.is_cuda else ())
    if local_quats.dtype not in allowed:
        raise ValueError(f"fk: local_quats must be float32 or float64 (or float16/bfloat16 on CUDA), got "
                         f"{local_quats.dtype} on {local_quats.device}")
    if local_quats.numel() == 0:
        raise ValueError(f"fk: local_quats is empty (shape {tuple(local_quats.shape)}): empty batch or zero frames")
    J = local_quats.shape[-2]
    for name, t in (("offsets", offsets), ("root_positions", root_positions)):
        if t.dtype != local_quats.dtype:
            raise ValueError(f"fk: {name} has dtype {t.dtype}, expected {local_quats.dtype} (same as local_quats)")
        if t.device != local_quats.device:
            raise ValueError(f"fk: {name} is on {t.device} but local_quats is on {local_quats.device}")
    if tuple(offsets.shape) != (J, 3):
        raise ValueError(f"fk: offsets must have shape (J, 3) = ({J}, 3), got {tuple(offsets.shape)}")
    if tuple(root_positions.shape) != tuple(local_quats.shape[:-2]) + (3,):
        raise ValueError(
            f"fk: root_positions must have shape {tuple(local_quats.shape[:-2]) + (3,)} (local_quats.shape[:-2] + (3,)), "
            f"got {tuple(root_positions.shape)}"
        )
    for name, t in (("local_quats", local_quats), ("offsets", offsets), ("root_positions", root_positions)):
        if not t.is_contiguous():
            raise ValueError(f"fk: {name} must be contiguous (call .contiguous() first)")


# ---------------------------------------------------------------------------------------------------------
# the op: fake kernels and autograd (registered only when the C++ library defined the schemas)
# ---------------------------------------------------------------------------------------------------------


def _op_defined() -> bool:
    return HAS_EXT and hasattr(torch.ops.modi_ext, "fk") and hasattr(torch.ops.modi_ext, "fk_backward")


if _op_defined():

    @torch.library.register_fake("modi_ext::fk")
    def _fk_fake(local_quats, offsets, parents, root_positions):
        positions = local_quats.new_empty(tuple(local_quats.shape[:-1]) + (3,))
        return positions, torch.empty_like(local_quats)

    @torch.library.register_fake("modi_ext::fk_backward")
    def _fk_backward_fake(grad_positions, grad_global_quats, local_quats, global_quats, offsets, parents, offsets_grad):
        grad_root = local_quats.new_empty(tuple(local_quats.shape[:-2]) + (3,))
        return torch.empty_like(local_quats), grad_root, offsets.new_empty((offsets.shape[0], 3))

    def _fk_setup_context(ctx, inputs, output):
        local_quats, offsets, parents, _root = inputs
        _positions, global_quats = output
        ctx.save_for_backward(local_quats, global_quats, offsets)
        ctx.parents = parents
        # An unused output (usually the rotations) then arrives as None instead of a materialised zero tensor.
        ctx.set_materialize_grads(False)

    def _fk_backward(ctx, grad_positions, grad_global_quats):
        local_quats, global_quats, offsets = ctx.saved_tensors
        if grad_positions is None:
            grad_positions = local_quats.new_zeros(tuple(local_quats.shape[:-1]) + (3,))
        if torch.is_grad_enabled():  # create_graph=True: a differentiable formulation of the same gradients
            grad_q, grad_root, grad_off = _graph_backward(grad_positions, grad_global_quats, local_quats, offsets,
                                                          ctx.parents, ctx.needs_input_grad)
        else:
            if grad_global_quats is not None:
                grad_global_quats = grad_global_quats.contiguous()
            grad_q, grad_root, grad_off = torch.ops.modi_ext.fk_backward(
                grad_positions.contiguous(), grad_global_quats, local_quats, global_quats, offsets,
                ctx.parents, bool(ctx.needs_input_grad[1]),
            )
        return (
            grad_q if ctx.needs_input_grad[0] else None,
            grad_off if ctx.needs_input_grad[1] else None,
            None,
            grad_root if ctx.needs_input_grad[3] else None,
        )

    torch.library.register_autograd("modi_ext::fk", _fk_backward, setup_context=_fk_setup_context)


def _graph_backward(grad_positions, grad_global_quats, local_quats, offsets, parents, needs):
    """``fk_backward`` as torch ops with a graph: vector-Jacobian products of ``fk_reference``.

    The root translation enters every joint's position additively, so its gradient is the sum over joints and the
    recomputation can start from a zero root."""
    q = local_quats if local_quats.requires_grad else local_quats.detach().requires_grad_()
    off = offsets if offsets.requires_grad else offsets.detach().requires_grad_()
    with torch.enable_grad():
        root = q.new_zeros(tuple(q.shape[:-2]) + (3,))
        pos, rot = fk_reference(q, off, parents, root, return_rotations=True)
        outs, grads = [pos], [grad_positions]
        if grad_global_quats is not None:
            outs.append(rot)
            grads.append(grad_global_quats)
        want = [t for t, n in ((q, needs[0]), (off, needs[1])) if n]
        got = iter(torch.autograd.grad(outs, want, grads, create_graph=True, allow_unused=True,
                                       materialize_grads=True)) if want else iter(())
    grad_q = next(got) if needs[0] else None
    grad_off = next(got) if needs[1] else None
    return grad_q, grad_positions.sum(-2), grad_off


def _use_kernel(device: torch.device, impl: str | None = None, dtype: torch.dtype = torch.float32) -> bool:
    if impl is None:
        impl = requested_impl()
    elif impl not in ("ref", "ext", "dense", "auto"):
        raise ValueError(f"fk: impl must be 'ref', 'ext' or None (or 'dense' / 'auto'), got {impl!r}")
    elif impl == "ext" and not _op_defined():
        raise RuntimeError("fk: impl='ext' but the modi_ext C++ extension is not built")
    if impl in ("ref", "dense"):
        return False
    # Devices without a kernel (e.g. CUDA when only the CPU part is built) use the reference; decided once per type.
    if not dispatch.kernels_built(device.type, "fk"):
        if impl == "ext":  # refused, not run on the reference: a benchmark would report its time as the kernel's
            raise RuntimeError(f"fk: MODI_EXT_IMPL=ext but this modi_ext build has no {device.type.upper()} FK "
                               "kernels (built without them: MODI_EXT_CUDA=0, no nvcc, or a CPU-only wheel)")
        return False
    if impl == "ext" or device.type == "meta":
        return True
    return dispatch.kernels_trusted(str(device), str(dtype))


def _fk_checked(local_quats, offsets, parents: tuple[int, ...], root_positions, return_rotations: bool,
                impl: str | None = None):
    if _use_kernel(local_quats.device, impl, local_quats.dtype):
        dispatch.record_path("fk", local_quats, "ext")
        positions, rotations = dispatch.KERNELS["fk"](local_quats, offsets, list(parents), root_positions)
        return (positions, rotations) if return_rotations else positions
    dispatch.record_path("fk", local_quats, "ref")
    return fk_reference(local_quats, offsets, parents, root_positions, return_rotations)


def fk(
    local_quats: torch.Tensor,
    offsets: torch.Tensor,
    parents: Sequence[int] | torch.Tensor,
    root_positions: torch.Tensor,
    *,
    return_rotations: bool = False,
    impl: str | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Global joint positions (..., J, 3) [and global quaternions (..., J, 4) with ``return_rotations``].

    local_quats (..., J, 4) unit (w, x, y, z); offsets (J, 3); parents: J ints, ``parents[0] == -1``,
    ``0 <= parents[j] < j``; root_positions (..., 3). All float32 or all float64, contiguous, one device.
    Differentiable w.r.t. local_quats, root_positions and offsets. Raises ValueError/TypeError naming the
    offending argument. ``impl``: "ref" or "ext" forces a path for this call (default: ``impl_choice()``, i.e.
    the kernel when built unless ``MODI_EXT_IMPL=ref``); devices without a kernel always use the reference.
    """
    _check_tensors(local_quats, offsets, root_positions)
    par = check_parents(parents, local_quats.shape[-2])
    return _fk_checked(local_quats, offsets, par, root_positions, return_rotations, impl)


class ForwardKinematics(nn.Module):
    """FK for one fixed skeleton: ``forward(local_quats (B,T,J,4), root_positions (B,T,3)) -> (B,T,J,3)``.

    The offsets are a buffer (they follow ``.to()`` and are saved in the state dict, but are not trained);
    they are cast to the input's dtype. Non-contiguous inputs (e.g. permuted network outputs) are made
    contiguous here, so the module is a drop-in for any layout.
    """

    def __init__(self, parents: Sequence[int], offsets: torch.Tensor | Sequence[Sequence[float]]) -> None:
        super().__init__()
        off = torch.as_tensor(offsets, dtype=torch.get_default_dtype())
        if off.dim() != 2 or off.shape[1] != 3:
            raise ValueError(f"ForwardKinematics: offsets must have shape (J, 3), got {tuple(off.shape)}")
        self.parents = check_parents(parents, off.shape[0])
        self.register_buffer("offsets", off.detach().clone().contiguous())

    @property
    def n_joints(self) -> int:
        return len(self.parents)

    def forward(
        self, local_quats: torch.Tensor, root_positions: torch.Tensor, return_rotations: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        offsets = self.offsets.to(dtype=local_quats.dtype)
        local_quats, root_positions = local_quats.contiguous(), root_positions.contiguous()
        _check_tensors(local_quats, offsets, root_positions)
        if local_quats.shape[-2] != self.n_joints:
            raise ValueError(
                f"ForwardKinematics: local_quats has {local_quats.shape[-2]} joints, the skeleton has {self.n_joints}"
            )
        return _fk_checked(local_quats, offsets, self.parents, root_positions, return_rotations)

    def extra_repr(self) -> str:
        return f"n_joints={self.n_joints}"
