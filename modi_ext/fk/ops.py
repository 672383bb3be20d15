"""The public fk op: check, pick the implementation, call it.

``dispatch.route`` picks the path as for every op (``MODI_EXT_IMPL=auto|ext|dense|ref``, or this call's ``impl=``):
the fused C++ kernel (``torch.ops.modi_ext.fk``, through ``kernels.launch`` as every op's) only where this build has it
for the device and, under ``auto``, after its first-use self-check; else FK's dense form, the torch loop
(``modi_ext.fk.dense``), which is also the reference.  The kernel's autograd is ``modi_ext.fk.registration`` (first
order in C++; a gradient with a graph, ``create_graph=True``, from ``modi_ext.fk.gradfix``), the checks
``modi_ext.fk.checks``; the ``ForwardKinematics`` layer is in ``modi_ext.layers``.

Semantics: ``modi_ext.fk.reference`` (quaternions (w, x, y, z) in the parent's frame, joint 0 at
``root_positions``).  Inputs are expected to be unit quaternions; nothing is normalised (normalise first if a network
emits them), and for non-unit input both paths evaluate ``rotate(Q, v) = v + 2w (u x v) + 2 u x (u x v)``.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch

from modi_ext.fk import dense, reference, registration  # noqa: F401  (registration: fakes and autograd, on import)
from modi_ext.fk.checks import check_args, check_parents
from modi_ext.runtime import dispatch, kernels

__all__ = ["fk", "check_parents"]


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
    offending argument. ``impl``: 'ext', 'dense', 'ref' or 'auto' forces a path for this call (default:
    ``MODI_EXT_IMPL``); under ``auto`` devices without a kernel use the dense form.
    """
    parents = check_args(local_quats, offsets, parents, root_positions)
    impl = dispatch.route("fk", local_quats, "fk", impl=impl, record=True)
    if impl == "ext":
        positions, rotations = kernels.launch("fk", local_quats, offsets, list(parents), root_positions)
        return (positions, rotations) if return_rotations else positions
    if impl == "ref":
        return reference.fk_reference(local_quats, offsets, parents, root_positions, return_rotations)
    return dense.fk(local_quats, offsets, parents, root_positions, return_rotations)
