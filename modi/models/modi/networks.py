"""MoDi's networks: mapping MLP, skeleton-aware StyleGAN2 synthesis network, and the reverse-hierarchy discriminator.

Shapes follow the project convention ``(B, K, E, T)``. The hierarchy runs coarse (level 0, learned constant) to
fine (last level, the motion's own entities and frames); each finer level doubles the frames and un-merges entities
along the skeleton's automatic pooling map. The layers come from ``modi_ext.layers`` (skeleton-aware convs, the
equalised-lr linear layer, the fused bias + leaky ReLU) through the factories of ``ablations``, which build the
paper's layer or an ablation's as the config asks; the levels are ``levels``, the generator's faster forms of its
std normalisation ``fastpaths``.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from modi.models.modi.ablations import act_slot, conv_layer, down_layer, modconv_layer
from modi.models.modi.config import ModelConfig
from modi.models.modi.fastpaths import std_entities_frames, std_normalised_leaky_relu_
from modi.models.modi.levels import LevelSpec, unpool_matrix
from modi_ext.fir import upsample_time as fir_upsample_time
from modi_ext.layers import EqualLinear, FusedLeakyReLU, ModulatedSkeletalConv

SQRT2 = math.sqrt(2.0)


# --------------------------------------------------------------------------------------------- small building blocks
class PixelNorm(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.rsqrt(x.pow(2).mean(1, keepdim=True) + 1e-8)


class MappingNetwork(nn.Module):
    """z -> w: pixel norm then ``n_mlp`` equalised linear layers with lr multiplier (StyleGAN's mapping)."""

    def __init__(self, latent_dim: int, n_mlp: int, lr_mul: float):
        super().__init__()
        layers: list[nn.Module] = [PixelNorm()]
        layers += [EqualLinear(latent_dim, latent_dim, lr_mul=lr_mul, activate=True) for _ in range(n_mlp)]
        self.net = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z)


class NoiseInjection(nn.Module):
    """Adds per-(entity, frame) Gaussian noise scaled by a learned scalar that starts at zero."""

    def __init__(self):
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        return x + self.weight * noise


# --------------------------------------------------------------------------------------------- generator
class StyledConv(nn.Module):
    """Modulated conv -> [noise injection] -> fused bias + leaky ReLU.

    The released MoDi has no noise injection (modulated conv + bias + leaky ReLU); StyleGAN2's per-(entity, frame)
    noise is the ``use_noise`` option.  With nothing between the skeletal conv and its activation (no noise, no
    activation demodulation), the activation runs in the op's epilogue (``fuse_act``)."""

    def __init__(self, conv: nn.Module, out_ch: int, n_entities: int, n_frames: int, use_noise: bool,
                 demodulate_activations: bool = False, stylegan2_up: bool = False):
        super().__init__()
        self.conv = conv
        self.demodulate_activations = demodulate_activations  # released MoDi: out / std over (entities, frames)
        self.stylegan2_up = stylegan2_up  # upsampler with StyleGAN2's padding: one zero frame in, two frames cropped
        self.noise = NoiseInjection() if use_noise else None
        self.act = FusedLeakyReLU(out_ch)
        self.noise_shape = (n_entities, n_frames)
        self.fuse_act = isinstance(conv, ModulatedSkeletalConv) and not use_noise and not demodulate_activations

    def forward(self, x: torch.Tensor, w: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        if self.fuse_act:  # the crop of the StyleGAN2 upsampler commutes with the activation
            if self.stylegan2_up:
                return self.conv(F.pad(x, (1, 0)), w, act=self.act)[..., 2:].contiguous()
            return self.conv(x, w, act=self.act)
        x = self.conv(F.pad(x, (1, 0)), w)[..., 2:] if self.stylegan2_up else self.conv(x, w)
        if self.demodulate_activations and self.noise is None and self.act.bias is not None \
                and not torch.is_grad_enabled():  # sampling: the same values without the autograd form's tensors
            return std_normalised_leaky_relu_(x, self.act.bias)
        if self.demodulate_activations:
            x = x / std_entities_frames(x)
        if self.noise is not None:
            if noise is None:
                noise = x.new_empty(x.shape[0], 1, x.shape[2], x.shape[3]).normal_()
            x = self.noise(x, noise)
        return self.act(x)


class ToMotion(nn.Module):
    """Per-entity 1x1 modulated projection (no demodulation) to the motion features, plus the upsampled skip."""

    def __init__(self, cfg: ModelConfig, in_ch: int, out_ch: int, level: LevelSpec):
        super().__init__()
        self.conv = modconv_layer(cfg, in_ch, out_ch, level, "same", kernel_size=1, demodulate=False, per_entity=True)
        self.bias = nn.Parameter(torch.zeros(1, out_ch, 1, 1))
        self.skeleton_aware = cfg.skeleton_aware
        self.size = (level.n_entities, level.n_frames)
        if level.up_pooling is not None and cfg.skeleton_aware:
            self.register_buffer("unpool", unpool_matrix(level.up_pooling, level.n_entities), persistent=False)
        else:
            self.unpool = None

    def forward(self, x: torch.Tensor, w: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        if isinstance(self.conv, ModulatedSkeletalConv):  # the bias in the op's epilogue
            out = self.conv(x, w, bias=self.bias.view(-1))
        else:
            out = self.conv(x, w) + self.bias
        if skip is not None:
            if self.skeleton_aware:
                skip = fir_upsample_time(torch.einsum("bket,fe->bkft", skip, self.unpool))
            else:
                skip = F.interpolate(skip, size=self.size, mode="bilinear", align_corners=False)
            out = out + skip
        return out


class Generator(nn.Module):
    """Mapping network + skeleton-aware synthesis network with skip (to-motion) outputs summed across levels.

    Style indices follow StyleGAN2 (rosinality): the coarsest conv takes w[0], its to-motion w[1]; each finer
    level's upsampling conv re-uses the previous to-motion index, then its in-place convs and to-motion follow.
    """

    def __init__(self, cfg: ModelConfig, levels: Sequence[LevelSpec], out_channels: int):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.levels = list(levels)
        self.out_channels = out_channels
        self.latent_dim = cfg.latent_dim
        self.mapping = MappingNetwork(cfg.latent_dim, cfg.n_mlp, cfg.lr_mlp)
        self.register_buffer("w_avg", torch.zeros(cfg.latent_dim))

        lv0 = self.levels[0]
        self.const = nn.Parameter(torch.randn(1, lv0.channels, lv0.n_entities, lv0.n_frames))
        noise, act_demod = cfg.noise_injection, cfg.demodulation == "activations"
        self.conv1 = StyledConv(modconv_layer(cfg, lv0.channels, lv0.channels, lv0, "same"),
                                lv0.channels, lv0.n_entities, lv0.n_frames, noise, act_demod)
        self.to_motion1 = ToMotion(cfg, lv0.channels, out_channels, lv0)

        self.blocks = nn.ModuleList()
        self.to_motions = nn.ModuleList()
        n_inplace = cfg.inplace_convs_per_level
        self.n_inplace = n_inplace
        for i in range(1, len(self.levels)):
            prev, lv = self.levels[i - 1], self.levels[i]
            sg2_up = cfg.time_padding == "stylegan2" and cfg.skeleton_aware and cfg.scaler == "conv"
            convs = [StyledConv(modconv_layer(cfg, prev.channels, lv.channels, lv, "up"),
                                lv.channels, lv.n_entities, lv.n_frames, noise, act_demod, sg2_up)]
            for _ in range(n_inplace):
                convs.append(StyledConv(modconv_layer(cfg, lv.channels, lv.channels, lv, "same"),
                                        lv.channels, lv.n_entities, lv.n_frames, noise, act_demod))
            self.blocks.append(nn.ModuleList(convs))
            self.to_motions.append(ToMotion(cfg, lv.channels, out_channels, lv))
        self.n_latent = 2 + (len(self.levels) - 1) * (1 + n_inplace)

        if cfg.noise_injection:  # fixed noise maps for noise_mode="const" (none exist when noise is off)
            g = torch.Generator().manual_seed(0x5EED)
            for i, layer in enumerate(self.styled_layers()):
                e, t = layer.noise_shape
                self.register_buffer(f"noise_const_{i}", torch.randn(1, 1, e, t, generator=g))

    # -- introspection
    def styled_layers(self) -> list[StyledConv]:
        return [self.conv1] + [c for block in self.blocks for c in block]

    @property
    def uses_noise(self) -> bool:
        """Whether the styled convs add per-frame noise (``ModelConfig.noise_injection``; off in the released MoDi)."""
        return bool(self.cfg.noise_injection)

    def noise_shapes(self) -> list[tuple[int, int]]:
        """(entities, frames) of each noise input, in the order ``synthesis(noise=...)`` expects; empty when the
        model has no noise injection (then nothing random enters the synthesis besides the latent)."""
        if not self.uses_noise:
            return []
        return [layer.noise_shape for layer in self.styled_layers()]

    @property
    def output_shape(self) -> tuple[int, int, int]:
        lv = self.levels[-1]
        return (self.out_channels, lv.n_entities, lv.n_frames)

    # -- latent handling
    def make_wplus(self, ws: torch.Tensor | Sequence[torch.Tensor],
                   inject_index: int | torch.Tensor | None = None) -> torch.Tensor:
        """W (B, D), W+ (B, n_latent, D) or two Ws to mix at ``inject_index`` (random when None) -> W+.

        ``inject_index`` may be a 0-d integer tensor: styles ``>= inject_index`` from the second W (``n_latent``:
        none, no mixing), chosen on the tensor's device with no host read."""
        if isinstance(ws, torch.Tensor):
            if ws.ndim == 3:
                if ws.shape[1] != self.n_latent:
                    raise ValueError(f"W+ must have {self.n_latent} styles, got {ws.shape[1]}")
                return ws
            if ws.ndim != 2:
                raise ValueError(f"w must be (B, {self.latent_dim}) or (B, {self.n_latent}, {self.latent_dim})")
            return ws.unsqueeze(1).expand(-1, self.n_latent, -1)
        ws = list(ws)
        if len(ws) == 1:
            return self.make_wplus(ws[0])
        if len(ws) != 2:
            raise ValueError("style mixing takes exactly two latents")
        if isinstance(inject_index, torch.Tensor):  # on the device: the same ops for every index (training)
            later = torch.arange(self.n_latent, device=inject_index.device) >= inject_index
            return torch.where(later[None, :, None], ws[1].unsqueeze(1), ws[0].unsqueeze(1))
        if inject_index is None:
            inject_index = int(torch.randint(1, self.n_latent, ()).item())
        a = ws[0].unsqueeze(1).expand(-1, inject_index, -1)
        b = ws[1].unsqueeze(1).expand(-1, self.n_latent - inject_index, -1)
        return torch.cat([a, b], 1)

    def truncate(self, w: torch.Tensor, psi: float) -> torch.Tensor:
        """Move w (or W+) toward the tracked mean of W: w_avg + psi * (w - w_avg)."""
        if psi == 1.0:
            return w
        return self.w_avg.to(w.dtype) + psi * (w - self.w_avg.to(w.dtype))

    # -- synthesis
    def synthesis(self, wplus: torch.Tensor, noise: Sequence[torch.Tensor | None] | None = None,
                  noise_mode: str = "random") -> torch.Tensor:
        """W+ (B, n_latent, D) -> motion (B, K, E, T). ``noise_mode``: 'random' | 'const' | 'none'.

        Without noise injection (``cfg.noise_injection=False``) ``noise`` and ``noise_mode`` are ignored (an empty
        ``noise`` list is what ``noise_shapes()`` describes) and the output depends on ``wplus`` alone."""
        if wplus.ndim != 3 or wplus.shape[1] != self.n_latent or wplus.shape[2] != self.latent_dim:
            raise ValueError(f"wplus must be (B, {self.n_latent}, {self.latent_dim}), got {tuple(wplus.shape)}")
        layers = self.styled_layers()
        if noise_mode not in ("random", "const", "none"):
            raise ValueError(f"noise_mode must be 'random', 'const' or 'none', not {noise_mode!r}")
        if not self.uses_noise:
            noise = [None] * len(layers)
        elif noise is None:
            if noise_mode == "random":
                noise = [None] * len(layers)
            elif noise_mode == "const":
                noise = [getattr(self, f"noise_const_{i}") for i in range(len(layers))]
            elif noise_mode == "none":
                noise = [torch.zeros((), dtype=wplus.dtype, device=wplus.device)] * len(layers)
            else:
                raise ValueError(f"noise_mode must be 'random', 'const' or 'none', not {noise_mode!r}")
        elif len(noise) != len(layers):
            raise ValueError(f"expected {len(layers)} noise tensors, got {len(noise)}")
        b = wplus.shape[0]
        ws = wplus.unbind(1)  # one view per style; their gradients meet in one stack (a select each: a copy and an add)
        x = self.const.repeat(b, 1, 1, 1)
        x = self.conv1(x, ws[0], noise[0])
        skip = self.to_motion1(x, ws[1])
        idx, n_idx = 1, 1
        for block, to_motion in zip(self.blocks, self.to_motions):
            for j, conv in enumerate(block):
                x = conv(x, ws[idx + j], noise[n_idx])
                n_idx += 1
            skip = to_motion(x, ws[idx + len(block)], skip)
            idx += len(block)
        return skip

    def forward(self, z: torch.Tensor | Sequence[torch.Tensor], *, input_is_w: bool = False,
                truncation_psi: float = 1.0, inject_index: int | None = None,
                noise: Sequence[torch.Tensor | None] | None = None, noise_mode: str = "random",
                return_latents: bool = False):
        """z (B, D) or [z1, z2] for style mixing (or w / W+ with ``input_is_w``) -> motion (B, K, E, T).

        With ``return_latents`` returns ``(motion, wplus)`` where ``wplus`` is the tensor the synthesis used
        (the path-length regulariser differentiates with respect to it).
        """
        if input_is_w:
            ws = z
        elif isinstance(z, torch.Tensor):
            ws = self.mapping(z)
        else:
            ws = [self.mapping(zi) for zi in z]
        if truncation_psi != 1.0:
            ws = self.truncate(ws, truncation_psi) if isinstance(ws, torch.Tensor) else \
                [self.truncate(w, truncation_psi) for w in ws]
        wplus = self.make_wplus(ws, inject_index)
        motion = self.synthesis(wplus, noise=noise, noise_mode=noise_mode)
        return (motion, wplus) if return_latents else motion


# --------------------------------------------------------------------------------------------- discriminator
class ConvAct(nn.Module):
    """A bias-free conv, then bias + leaky ReLU: in the skeletal op's epilogue where ``ablations.act_slot`` finds
    one."""

    def __init__(self, conv: nn.Module, out_ch: int):
        super().__init__()
        self.conv = conv
        self.act = FusedLeakyReLU(out_ch)
        self.slot = act_slot(conv)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.slot is None:
            return self.act(self.conv(x))
        if self.slot < 0:
            return self.conv(x, act=self.act)
        for i, m in enumerate(self.conv):
            x = m(x, act=self.act) if i == self.slot else m(x)
        return x.contiguous()  # after a crop: the next op takes contiguous input


class ResBlock(nn.Module):
    """In-place convs then a downscaling conv, plus a 1x1 downscaling skip; summed and divided by sqrt(2)."""

    def __init__(self, cfg: ModelConfig, fine: LevelSpec, coarse: LevelSpec):
        super().__init__()
        cin, cout = fine.channels, coarse.channels
        n_inplace = cfg.inplace_convs_per_level
        convs: list[nn.Module] = [ConvAct(conv_layer(cfg, cin, cin, fine), cin) for _ in range(n_inplace)]
        convs.append(ConvAct(down_layer(cfg, cin, cout, fine, coarse, cfg.kernel_size), cout))
        self.convs = nn.Sequential(*convs)
        self.skip = down_layer(cfg, cin, cout, fine, coarse, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (self.convs(x) + self.skip(x)) / SQRT2


def minibatch_stddev(x: torch.Tensor, group: int) -> torch.Tensor:
    """Append the mean per-group standard deviation as one extra channel (StyleGAN2)."""
    b, c, e, t = x.shape
    g = max(d for d in range(1, min(group, b) + 1) if b % d == 0)
    y = x.view(g, -1, c, e, t)
    std = torch.sqrt(y.var(0, unbiased=False) + 1e-8).mean([1, 2, 3])  # (B/g,)
    std = std.view(-1, 1, 1, 1).repeat(g, 1, e, t)
    return torch.cat([x, std], 1)


class Discriminator(nn.Module):
    """The synthesis hierarchy reversed: per-entity input conv, residual blocks fine -> coarse, mbstd, linear head."""

    def __init__(self, cfg: ModelConfig, levels: Sequence[LevelSpec], in_channels: int):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.levels = list(levels)
        fine = self.levels[-1]
        self.from_motion = ConvAct(conv_layer(cfg, in_channels, fine.channels, fine, kernel_size=1, per_entity=True),
                                   fine.channels)
        self.blocks = nn.Sequential(*[ResBlock(cfg, self.levels[i], self.levels[i - 1])
                                      for i in range(len(self.levels) - 1, 0, -1)])
        lv0 = self.levels[0]
        self.final_conv = ConvAct(conv_layer(cfg, lv0.channels + 1, lv0.channels, lv0), lv0.channels)
        self.final_linear = nn.Sequential(
            EqualLinear(lv0.channels * lv0.n_entities * lv0.n_frames, lv0.channels, activate=True),
            EqualLinear(lv0.channels, 1),
        )
        self.input_shape = (in_channels, fine.n_entities, fine.n_frames)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or tuple(x.shape[1:]) != self.input_shape:
            raise ValueError(f"discriminator input must be (B, {', '.join(map(str, self.input_shape))}), "
                             f"got {tuple(x.shape)}")
        out = self.blocks(self.from_motion(x))
        out = self.final_conv(minibatch_stddev(out, self.cfg.mbstd_group))
        return self.final_linear(out.flatten(1))
