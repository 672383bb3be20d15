"""Every ``nn.Module`` of the package: the skeleton-aware layers built on ``modi_ext.skeletal.ops``, forward
kinematics for one skeleton on ``modi_ext.fk.ops`` (``ForwardKinematics``), and the StyleGAN2 pieces they are used
with: the equalised-lr linear layer (``EqualLinear``) and the fused bias + leaky ReLU.

Topology comes in as plain lists and is turned into CSR buffers (not saved in ``state_dict``: the topology is a
constructor argument).  Weights are stored compactly, one ``(Cout, Cin, U)`` block per (output entity, input entity)
pair, drawn from N(0, 1) and multiplied at run time by StyleGAN2's equalised-learning-rate factor
``1 / sqrt(fan_in)`` where ``fan_in`` counts only the connections the entity really has (|N(j)| * Cin * U), so a
joint with three neighbors and one with two start at the same output scale.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from modi_ext.act import GAIN, SLOPE, fused_leaky_relu
from modi_ext.fk import checks as fk_checks
from modi_ext.fk import ops as fk_ops
from modi_ext.skeletal import ops
from modi_ext.skeletal.reference import to_dense
from modi_ext.csr import SparseTopology, csr_from_lists

__all__ = ["SkeletalConv", "SkeletalDownsample", "SkeletalUpsample", "ModulatedSkeletalConv", "EqualLinear",
           "FusedLeakyReLU", "fused_leaky_relu", "ForwardKinematics"]


def _check_channels(**kw: int) -> None:
    for k, v in kw.items():
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValueError(f"{k} must be a positive int, got {v!r}")


def _check_conv_args(in_ch: int, out_ch: int, kernel_size: int) -> None:
    _check_channels(in_ch=in_ch, out_ch=out_ch)
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size <= 0 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd int, got {kernel_size!r}")


class _SkeletalBase(nn.Module):
    """Shared plumbing: CSR buffers, compact weight, per-pair equalised-lr scale, bias."""

    def _setup(self, topo: SparseTopology, in_ch: int, out_ch: int, kernel_size: int, padding_mode: str, bias: bool,
               up: bool = False) -> None:
        """``up``: the weight has the layout of the downsampler this layer is the adjoint of, ``(Cin, nnz, Cout, U)``,
        and the fan-in of fine entity f counts the coarse entities that contain it."""
        self.in_ch, self.out_ch, self.kernel_size, self.padding_mode = in_ch, out_ch, kernel_size, padding_mode
        self.n_out = topo.n_out
        self.n_in = topo.n_in
        self.register_buffer("index", topo.index, persistent=False)
        self.register_buffer("offsets", topo.offsets, persistent=False)
        if up:
            w_shape, fan = (in_ch, topo.nnz, out_ch, kernel_size), topo.in_degree()[topo.index]
            self.n_fine = topo.n_in
        else:
            w_shape, fan = (out_ch, topo.nnz, in_ch, kernel_size), topo.fan_in_counts()[topo.pair_entity]
        self.weight = nn.Parameter(torch.randn(w_shape))
        fan_in = fan.to(torch.float64) * in_ch * kernel_size
        scale = fan_in.rsqrt().to(torch.get_default_dtype())
        self.register_buffer("weight_scale", scale, persistent=False)  # (nnz,)
        self.bias = nn.Parameter(torch.zeros(out_ch)) if bias else None

    scale_folded = False  # set by fold_weight_scale(): the stored weight already carries the factor

    def _pair_axis_scale(self) -> torch.Tensor:
        return self.weight_scale.to(self.weight.dtype).view(1, -1, 1, 1)

    def fold_weight_scale(self, gain: float = 1.0) -> None:
        """Switch to a plain parametrisation: multiply the stored weight by its equalised-lr factor (and ``gain``)
        once, and hand the parameter itself to the op from then on.

        For models trained with plain weights (GANimator): the run-time factor would be a multiply and an autograd
        node per layer and call, for nothing.  The state is part of the module's construction, not of its
        ``state_dict``: build the module the same way before loading weights into it.
        """
        with torch.no_grad():
            self.weight.mul_(self._pair_axis_scale() * gain)
            self.weight_scale.fill_(1.0)
        self.scale_folded = True

    def _epilogue(self, act: "FusedLeakyReLU | None") -> dict:
        """The op's bias and ``act`` arguments: the layer's bias, or -- with ``act``, the activation that follows a
        bias-free layer -- that activation's bias and activation, run in the op's epilogue (``modi_ext.act``)."""
        if act is None:
            return dict(bias=self.bias)
        if self.bias is not None:
            raise ValueError(f"{type(self).__name__} has a bias of its own: build it with bias=False to fuse the "
                             f"activation that follows it (act=)")
        return dict(bias=act.bias, act=True)

    def effective_weight(self) -> torch.Tensor:
        """Compact weight as the op sees it (equalised-lr factor applied)."""
        if self.scale_folded:
            return self.weight
        return self.weight * self._pair_axis_scale()


class SkeletalConv(_SkeletalBase):
    """In-place skeletal conv: each entity mixes its neighbors' channels over a ``kernel_size`` time window."""

    def __init__(self, in_ch: int, out_ch: int, neighbors: Sequence[Sequence[int]], kernel_size: int = 3,
                 padding_mode: str = "zeros", bias: bool = True) -> None:
        super().__init__()
        _check_conv_args(in_ch, out_ch, kernel_size)
        if padding_mode not in ("zeros", "reflect"):
            raise ValueError(f"padding_mode must be 'zeros' or 'reflect', got {padding_mode!r}")
        topo = csr_from_lists(neighbors, n_in=len(neighbors) if len(neighbors) else None, name="neighbors")
        self._setup(topo, in_ch, out_ch, kernel_size, padding_mode, bias)

    def forward(self, x: torch.Tensor, act: "FusedLeakyReLU | None" = None) -> torch.Tensor:
        """``act``: the bias-free layer's following activation, fused into the op (``act(self(x))`` in one op)."""
        return ops.skeletal_conv(x, self.effective_weight(), index=self.index, offsets=self.offsets,
                                 padding_mode=self.padding_mode, **self._epilogue(act))

    def dense_weight(self) -> torch.Tensor:
        """Masked dense ``(Cout, Cin, E, E, U)`` weight, equalised-lr factor applied."""
        return to_dense(self.effective_weight(), self.index, self.offsets, self.n_in)

    def extra_repr(self) -> str:
        return (f"{self.in_ch}, {self.out_ch}, entities={self.n_out}, pairs={self.index.numel()}, "
                f"kernel_size={self.kernel_size}, padding_mode={self.padding_mode!r}, bias={self.bias is not None}")


class SkeletalDownsample(_SkeletalBase):
    """Convolutional scaler fine -> coarse: ``(B, Cin, E_fine, T) -> (B, Cout, E_coarse, T // 2)``."""

    def __init__(self, in_ch: int, out_ch: int, pooling: Sequence[Sequence[int]], kernel_size: int = 3,
                 bias: bool = True, padding_mode: str = "zeros") -> None:
        super().__init__()
        _check_conv_args(in_ch, out_ch, kernel_size)
        self._setup(csr_from_lists(pooling, name="pooling", require_cover=True), in_ch, out_ch, kernel_size,
                    padding_mode, bias)

    def forward(self, x: torch.Tensor, act: "FusedLeakyReLU | None" = None) -> torch.Tensor:
        """``act``: as :meth:`SkeletalConv.forward`'s."""
        return ops.skeletal_down(x, self.effective_weight(), index=self.index, offsets=self.offsets,
                                 padding_mode=self.padding_mode, **self._epilogue(act))

    def dense_weight(self) -> torch.Tensor:
        """Masked dense ``(Cout, Cin, E_coarse, E_fine, U)`` weight, equalised-lr factor applied."""
        return to_dense(self.effective_weight(), self.index, self.offsets, self.n_in)

    def extra_repr(self) -> str:
        return (f"{self.in_ch}, {self.out_ch}, entities={self.n_in}->{self.n_out}, pairs={self.index.numel()}, "
                f"kernel_size={self.kernel_size}, padding_mode={self.padding_mode!r}, bias={self.bias is not None}")


class SkeletalUpsample(_SkeletalBase):
    """Coarse -> fine: transposed conv scaler (time x2) followed by the [1,3,3,1] blur.

    ``.weight`` is ``(Cin, nnz, Cout, U)``: the layout of the downsampler it is the adjoint of.
    """

    def __init__(self, in_ch: int, out_ch: int, pooling: Sequence[Sequence[int]], kernel_size: int = 3,
                 bias: bool = True, padding_mode: str = "zeros") -> None:
        super().__init__()
        _check_conv_args(in_ch, out_ch, kernel_size)
        self._setup(csr_from_lists(pooling, name="pooling", require_cover=True), in_ch, out_ch, kernel_size,
                    padding_mode, bias, up=True)

    def forward(self, x: torch.Tensor, act: "FusedLeakyReLU | None" = None) -> torch.Tensor:
        """``act``: as :meth:`SkeletalConv.forward`'s."""
        return ops.skeletal_up(x, self.effective_weight(), index=self.index, offsets=self.offsets, n_out=self.n_fine,
                               padding_mode=self.padding_mode, **self._epilogue(act))

    def dense_weight(self) -> torch.Tensor:
        """Masked dense ``(Cout, Cin, E_fine, E_coarse, U)``: entry [o,i,f,c,u] carries x[i,c,t] to fine frame 2t+u-U//2."""
        d = to_dense(self.effective_weight(), self.index, self.offsets, self.n_fine)  # (Ci, Co, Ec, Ef, U)
        return d.permute(1, 0, 3, 2, 4)

    def extra_repr(self) -> str:
        return (f"{self.in_ch}, {self.out_ch}, entities={self.n_out}->{self.n_fine}, pairs={self.index.numel()}, "
                f"kernel_size={self.kernel_size}, padding_mode={self.padding_mode!r}, bias={self.bias is not None}")


class FusedLeakyReLU(nn.Module):
    """:func:`fused_leaky_relu` with a learned per-channel bias (starting at zero)."""

    def __init__(self, channels: int, bias: bool = True):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(channels)) if bias else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return fused_leaky_relu(x, self.bias)


class EqualLinear(nn.Module):
    """StyleGAN2 equalised-lr linear layer: ``y = x @ (W * lr_mul / sqrt(in)).T + b * lr_mul``.

    ``lr_mul`` is the learning-rate multiplier (MoDi's mapping network: 0.01); ``activate`` follows the layer with
    :func:`fused_leaky_relu`, its bias added there. Parameters: ``weight`` ``(out, in)`` and ``bias`` ``(out,)``
    (none with ``bias=False``)."""

    def __init__(self, in_dim: int, out_dim: int, bias: bool = True, bias_init: float = 0.0,
                 lr_mul: float = 1.0, activate: bool = False) -> None:
        super().__init__()
        _check_channels(in_dim=in_dim, out_dim=out_dim)
        self.weight = nn.Parameter(torch.randn(out_dim, in_dim) / lr_mul)
        self.bias = nn.Parameter(torch.full((out_dim,), float(bias_init) / lr_mul)) if bias else None
        self.scale = lr_mul / math.sqrt(in_dim)
        self.lr_mul = lr_mul
        self.activate = activate

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.bias is not None and x.ndim == 2:
            # the factors (and the activation's gain, which leaky ReLU's homogeneity lets in) as addmm's alpha and
            # beta: one op where scaling the weight and the bias first would be three, forward and backward alike
            gain = GAIN if self.activate else 1.0
            y = torch.addmm(self.bias, x, self.weight.t(), beta=self.lr_mul * gain, alpha=self.scale * gain)
            return F.leaky_relu_(y, SLOPE) if self.activate else y
        b = self.bias * self.lr_mul if self.bias is not None else None
        if self.activate:
            return fused_leaky_relu(F.linear(x, self.weight * self.scale), b)
        return F.linear(x, self.weight * self.scale, b)


class ModulatedSkeletalConv(nn.Module):
    """StyleGAN2 modulated skeletal conv (in place, up or down), with its own affine style layer.

    ``forward(x, w, act=None)``: ``s = affine(w)`` (bias initialised to 1), then the fused modulated op; no bias of
    its own: the generator's bias + leaky ReLU follows, fused into the op when passed as ``act``.  ``topology`` is the
    neighbor list for ``mode="same"`` and the coarse -> fine pooling map for ``"up"`` / ``"down"``.
    """

    def __init__(self, in_ch: int, out_ch: int, style_dim: int, topology: Sequence[Sequence[int]],
                 kernel_size: int = 3, mode: str = "same", demodulate: bool = True,
                 padding_mode: str = "zeros") -> None:
        super().__init__()
        if mode not in ("same", "up", "down"):
            raise ValueError(f"mode must be 'same', 'up' or 'down', got {mode!r}")
        _check_channels(style_dim=style_dim)
        self.mode, self.demodulate = mode, bool(demodulate)
        self.in_ch, self.out_ch, self.style_dim = in_ch, out_ch, style_dim
        if mode == "same":
            self.conv = SkeletalConv(in_ch, out_ch, topology, kernel_size, padding_mode, bias=False)
        elif mode == "down":
            self.conv = SkeletalDownsample(in_ch, out_ch, topology, kernel_size, bias=False,
                                           padding_mode=padding_mode)
        else:
            self.conv = SkeletalUpsample(in_ch, out_ch, topology, kernel_size, bias=False,
                                         padding_mode=padding_mode)
        self.affine = EqualLinear(style_dim, in_ch, bias_init=1.0)

    @property
    def weight(self) -> nn.Parameter:
        return self.conv.weight

    def dense_weight(self) -> torch.Tensor:
        return self.conv.dense_weight()

    def forward(self, x: torch.Tensor, w: torch.Tensor, act: "FusedLeakyReLU | None" = None,
                bias: torch.Tensor | None = None) -> torch.Tensor:
        """``act``: the activation that follows, fused into the op (as :meth:`SkeletalConv.forward`'s); or ``bias``
        ``(out_ch,)``: a bias that follows, added in the op's epilogue."""
        if act is not None and bias is not None:
            raise ValueError("pass act= (its bias is the activation's) or bias=, not both")
        if w.dim() != 2 or w.shape[1] != self.style_dim:
            raise ValueError(f"w must be (B, {self.style_dim}), got shape {tuple(w.shape)}")
        if w.shape[0] != x.shape[0]:
            raise ValueError(f"w has batch {w.shape[0]} but x has {x.shape[0]}")
        s = self.affine(w)
        c = self.conv
        epi = c._epilogue(act) if bias is None else dict(bias=bias)
        kw = dict(style=s, demodulate=self.demodulate, padding_mode=c.padding_mode, **epi)
        if self.mode == "same":
            return ops.skeletal_conv(x, c.effective_weight(), index=c.index, offsets=c.offsets, **kw)
        if self.mode == "down":
            return ops.skeletal_down(x, c.effective_weight(), index=c.index, offsets=c.offsets, **kw)
        return ops.skeletal_up(x, c.effective_weight(), index=c.index, offsets=c.offsets, n_out=c.n_fine, **kw)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}, demodulate={self.demodulate}, style_dim={self.style_dim}"


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
        self.parents = fk_checks.check_parents(parents, off.shape[0])
        self.register_buffer("offsets", off.detach().clone().contiguous())

    @property
    def n_joints(self) -> int:
        return len(self.parents)

    def forward(
        self, local_quats: torch.Tensor, root_positions: torch.Tensor, return_rotations: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        offsets = self.offsets.to(dtype=local_quats.dtype)
        local_quats, root_positions = local_quats.contiguous(), root_positions.contiguous()
        fk_checks.check_tensors(local_quats, offsets, root_positions)
        if local_quats.shape[-2] != self.n_joints:
            raise ValueError(
                f"ForwardKinematics: local_quats has {local_quats.shape[-2]} joints, the skeleton has {self.n_joints}"
            )
        return fk_ops.fk(local_quats, offsets, self.parents, root_positions, return_rotations=return_rotations)

    def extra_repr(self) -> str:
        return f"n_joints={self.n_joints}"
