"""The paper's ablations of MoDi's layers, and the factories that build a layer as the config asks.

``ModelConfig`` has three switches for the ablations of the paper's Table 4: ``skeleton_aware=False`` (motion as a
pseudo-image: dense 2D convs over (entity, frame)), ``scaler="pool"`` (skeletal pooling / unpooling around an in-place
conv instead of the convolutional scaler) and ``time_padding`` (the released code's StyleGAN2 padding at the scalers,
or the adjoint pair).  ``networks`` holds the paper's model and calls the factories here (``modconv_layer``,
``conv_layer``, ``down_layer``), which return MoDi's skeleton-aware layer or the ablation's, so the model reads the
same for every variant.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from modi.models.modi.config import ModelConfig
from modi.models.modi.levels import LevelSpec, pool_matrix, unpool_matrix
from modi_ext import layers as ext
from modi_ext.fir import blur_time as fir_blur_time
from modi_ext.fir import downsample_time as fir_downsample_time
from modi_ext.fir import upsample_time as fir_upsample_time
from modi_ext.layers import EqualLinear

__all__ = ["PseudoImageConv", "PooledUp", "SkeletalPoolDown", "Blur", "CropStart", "NoStyle", "modconv_layer",
           "conv_layer", "down_layer"]


class PseudoImageConv(nn.Module):
    """Dense 2D conv over (entity index, frame), i.e. motion as a pseudo-image (the non-skeleton-aware ablation).

    Optionally modulated/demodulated by a style (generator) and resized to ``out_size`` before (generator,
    bilinear) or after (discriminator, area average) the conv: entity rows are treated like image rows.
    """

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int, style_dim: int | None = None,
                 demodulate: bool = True, out_size: tuple[int, int] | None = None, resize: str | None = None):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(out_ch, in_ch, kernel_size, kernel_size))
        self.scale = 1.0 / math.sqrt(in_ch * kernel_size * kernel_size)
        self.modulation = EqualLinear(style_dim, in_ch, bias_init=1.0) if style_dim else None
        self.demodulate = demodulate
        self.out_size = out_size
        self.resize = resize
        self.pad = kernel_size // 2

    def forward(self, x: torch.Tensor, w: torch.Tensor | None = None) -> torch.Tensor:
        if self.resize == "before":
            x = F.interpolate(x, size=self.out_size, mode="bilinear", align_corners=False)
        b, cin, e, t = x.shape
        if self.modulation is None:
            out = F.conv2d(x, self.weight * self.scale, padding=self.pad)
        else:
            s = self.modulation(w)  # (B, Cin)
            weight = self.scale * self.weight.unsqueeze(0) * s.view(b, 1, cin, 1, 1)
            if self.demodulate:
                weight = weight * torch.rsqrt(weight.pow(2).sum([2, 3, 4], keepdim=True) + 1e-8)
            out = F.conv2d(x.reshape(1, b * cin, e, t), weight.reshape(-1, cin, *weight.shape[-2:]),
                           padding=self.pad, groups=b)
            out = out.view(b, -1, e, t)
        if self.resize == "after":
            out = F.adaptive_avg_pool2d(out, self.out_size)
        return out


class PooledUp(nn.Module):
    """Pooling ablation, generator side: skeletal unpool (copy) + FIR time upsample, then an in-place modulated conv."""

    def __init__(self, conv: nn.Module, pooling: list[list[int]], n_fine: int):
        super().__init__()
        self.conv = conv
        self.register_buffer("unpool", unpool_matrix(pooling, n_fine), persistent=False)

    def forward(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        x = fir_upsample_time(torch.einsum("bcet,fe->bcft", x, self.unpool))
        return self.conv(x.contiguous(), w)


class SkeletalPoolDown(nn.Module):
    """Pooling ablation, discriminator side: skeletal mean pooling + anti-aliased time downsampling."""

    def __init__(self, pooling: list[list[int]], n_fine: int):
        super().__init__()
        self.register_buffer("pool", pool_matrix(pooling, n_fine), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return fir_downsample_time(torch.einsum("bcft,ef->bcet", x, self.pool)).contiguous()


def modconv_layer(cfg: ModelConfig, cin: int, cout: int, level: LevelSpec, mode: str, kernel_size: int | None = None,
             demodulate: bool = True, per_entity: bool = False) -> nn.Module:
    """A modulated conv ``forward(x, w)`` for the generator: in place ('same') or coarse->fine ('up').

    ``per_entity`` gives every entity its own weights with no neighbours (the to-motion 1x1 projection)."""
    k = cfg.kernel_size if kernel_size is None else kernel_size
    demodulate = demodulate and cfg.demodulation == "weight"  # "activations": StyledConv normalises instead
    if not cfg.skeleton_aware:
        size = (level.n_entities, level.n_frames)
        return PseudoImageConv(cin, cout, k, style_dim=cfg.latent_dim, demodulate=demodulate,
                               out_size=size, resize="before" if mode == "up" else None)
    if mode == "up":
        if cfg.scaler == "pool":
            conv = ext.ModulatedSkeletalConv(cin, cout, cfg.latent_dim, level.neighbors, kernel_size=k,
                                                mode="same", demodulate=demodulate)
            return PooledUp(conv, level.up_pooling, level.n_entities)
        return ext.ModulatedSkeletalConv(cin, cout, cfg.latent_dim, level.up_pooling, kernel_size=k,
                                            mode="up", demodulate=demodulate)
    topo = [[j] for j in range(level.n_entities)] if per_entity else level.neighbors
    return ext.ModulatedSkeletalConv(cin, cout, cfg.latent_dim, topo, kernel_size=k, mode="same",
                                        demodulate=demodulate)


def conv_layer(cfg: ModelConfig, cin: int, cout: int, level: LevelSpec, kernel_size: int | None = None,
          per_entity: bool = False) -> nn.Module:
    """An unmodulated, bias-free in-place conv for the discriminator."""
    k = cfg.kernel_size if kernel_size is None else kernel_size
    if not cfg.skeleton_aware:
        return NoStyle(PseudoImageConv(cin, cout, k))
    topo = [[j] for j in range(level.n_entities)] if per_entity else level.neighbors
    return ext.SkeletalConv(cin, cout, topo, kernel_size=k, bias=False)


def down_layer(cfg: ModelConfig, cin: int, cout: int, fine: LevelSpec, coarse: LevelSpec, kernel_size: int) -> nn.Module:
    """A bias-free fine->coarse conv for the discriminator (conv scaler, or conv + skeletal pooling)."""
    if not cfg.skeleton_aware:
        return NoStyle(PseudoImageConv(cin, cout, kernel_size, out_size=(coarse.n_entities, coarse.n_frames),
                                        resize="after"))
    if cfg.scaler == "pool":
        topo = fine.neighbors if kernel_size > 1 else [[j] for j in range(fine.n_entities)]
        return nn.Sequential(ext.SkeletalConv(cin, cout, topo, kernel_size=kernel_size, bias=False),
                             SkeletalPoolDown(fine.up_pooling, fine.n_entities))
    if cfg.time_padding == "stylegan2":  # 2 more zero frames before the blur, the extra coarse frame cropped
        return nn.Sequential(Blur(2), ext.SkeletalDownsample(cin, cout, fine.up_pooling, kernel_size=kernel_size,
                                                                 bias=False), CropStart(1))
    return nn.Sequential(Blur(), ext.SkeletalDownsample(cin, cout, fine.up_pooling, kernel_size=kernel_size,
                                                            bias=False))


FUSABLE = (ext.SkeletalConv, ext.SkeletalDownsample, ext.SkeletalUpsample)


def act_slot(conv: nn.Module) -> int | None:
    """Where the bias + leaky ReLU after a discriminator layer of the factories above can run in a skeletal op's
    epilogue (``act=``): ``-1`` for the layer itself, the index of that op in an ``nn.Sequential`` that has only
    crops after it (a crop commutes with an elementwise activation), or None (a dense ablation, or pooling between
    the conv and the activation)."""
    if isinstance(conv, FUSABLE):
        return -1 if conv.bias is None else None
    if isinstance(conv, nn.Sequential):
        for i in range(len(conv) - 1, -1, -1):
            if isinstance(conv[i], FUSABLE):
                return i if conv[i].bias is None else None
            if not isinstance(conv[i], CropStart):
                return None
    return None


class Blur(nn.Module):
    def __init__(self, pad_start: int = 0):
        super().__init__()
        self.pad_start = pad_start

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return fir_blur_time(F.pad(x, (self.pad_start, 0)) if self.pad_start else x)


class CropStart(nn.Module):
    def __init__(self, n: int):
        super().__init__()
        self.n = n

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., self.n:]


class NoStyle(nn.Module):
    def __init__(self, conv: nn.Module):
        super().__init__()
        self.conv = conv

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)
