"""The MoDi encoder I (paper 001 §3.4, Fig. 4): the synthesis hierarchy reversed, predicting a W+ latent.

Like the discriminator, it reads a motion ``(B, K, E, T)`` with a per-entity input projection, then residual
skeleton-aware blocks that halve the frames and merge entities level by level (fine -> coarse). Two heads:

* ``released`` (default; the authors' code, ``models/gan.py`` ``LatentPrediction``): the features one level before
  the coarsest, flattened, through two linear layers of width n_latent x latent_dim, predicting W+ directly;
* ``bottleneck`` (this package's earlier head): every level, a last in-place conv at the coarsest level, one
  ``hidden``-wide layer and a W+ output added to the generator's mean latent w̄ (an untrained encoder then
  returns the mean motion).

For prediction from a prefix (001 §4.2) the input may carry one extra channel, 1 on the frames the encoder may
see and 0 on the zeroed ones, so "zero because unknown" is not confused with "zero because average".
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any, Sequence

import torch
from torch import Tensor, nn

from modi.models.modi.config import ModelConfig
from modi.models.modi.latent.space import mean_w
from modi.models.modi.ablations import NoStyle, PseudoImageConv
from modi.models.modi.levels import LevelSpec
from modi.models.modi.networks import ConvAct, ResBlock
from modi_ext.layers import EqualLinear, SkeletalConv

ENCODER_HEADS = ("released", "bottleneck")


@dataclass
class EncoderConfig:
    """What builds an encoder (saved in its checkpoint). ``prefix_frames``: the prefix variant sees only frames
    ``[0, prefix_frames)`` (None: the whole motion)."""

    in_channels: int
    n_latent: int
    latent_dim: int
    channel_multiplier: float = 1.0
    mask_channel: bool = False
    prefix_frames: int | None = None
    head_init: float = 0.1
    hidden: int | None = None  # width of the layer before the W+ head; None: max(latent_dim, coarsest channels)
    # "released": the authors' head (models/gan.py LatentPrediction at latent_rec_idx 4): the features one level
    # before the coarsest, flattened, through two linear layers of width n_latent x latent_dim -> W+.
    # "bottleneck": this package's earlier head: every level + a coarsest-level conv, one ``hidden``-wide layer,
    # then W+ as an offset from w̄ (head scaled by ``head_init``).
    head: str = "released"
    # in-place convs per residual block. None (the default) is resolved by the head on construction: 1 for the
    # released head (the released encoder is the released Discriminator class built without n_inplace_conv,
    # train_encoder.py), and for the bottleneck head it stays None, meaning the generator's own count.
    inplace_convs: int | None = None

    def __post_init__(self) -> None:
        if self.head not in ENCODER_HEADS:
            raise ValueError(f"encoder head must be one of {', '.join(ENCODER_HEADS)}, not {self.head!r}")
        if self.inplace_convs is None and self.head == "released":
            self.inplace_convs = 1
        if self.inplace_convs is not None and self.inplace_convs < 1:
            raise ValueError(f"inplace_convs must be >= 1 or None, not {self.inplace_convs}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], generator_inplace_convs: int | None = None) -> "EncoderConfig":
        """The config saved in a checkpoint. Fields missing from older checkpoints take their defaults
        (``hidden``), or the value those checkpoints were built with: the bottleneck ``head``, and the generator's
        count of in-place convs -- None for the bottleneck head; for a released head saved before
        ``inplace_convs`` was (``generator_inplace_convs``, when the caller knows the generator)."""
        d = {"head": "bottleneck", **d}
        if "inplace_convs" not in d and d["head"] == "released" and generator_inplace_convs is not None:
            d["inplace_convs"] = int(generator_inplace_convs)
        return cls(**d)


def _scaled_levels(levels: Sequence[LevelSpec], mult: float) -> list[LevelSpec]:
    return [LevelSpec(lv.n_entities, lv.neighbors, lv.up_pooling, lv.n_frames, max(1, int(round(lv.channels * mult))))
            for lv in levels]


class _EntityProjection(nn.Module):
    """1x1 per-entity conv (no neighbours) + bias + leaky ReLU: motion features -> the finest level's channels."""

    def __init__(self, model_cfg: ModelConfig, level: LevelSpec, in_ch: int):
        super().__init__()
        out_ch = level.channels
        if model_cfg.skeleton_aware:
            conv: nn.Module = SkeletalConv(in_ch, out_ch, [[j] for j in range(level.n_entities)], kernel_size=1,
                                           bias=False)
        else:
            conv = NoStyle(PseudoImageConv(in_ch, out_ch, 1))
        self.net = ConvAct(conv, out_ch)

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class MotionEncoder(nn.Module):
    """Motion (B, K, E, T) [+ visibility mask (B, 1, E, T)] -> W+ (B, n_latent, latent_dim)."""

    def __init__(self, model_cfg: ModelConfig, levels: Sequence[LevelSpec], cfg: EncoderConfig,
                 w_avg: Tensor | None = None):
        super().__init__()
        self.cfg = cfg
        self.model_cfg = model_cfg
        lv = _scaled_levels(levels, cfg.channel_multiplier)
        self.levels = lv
        fine = lv[-1]
        in_ch = cfg.in_channels + (1 if cfg.mask_channel else 0)
        self.from_motion = _EntityProjection(model_cfg, fine, in_ch)
        block_cfg = model_cfg if cfg.inplace_convs is None else replace(model_cfg, n_inplace_convs=cfg.inplace_convs)
        if cfg.head == "released":
            # blocks down to level 1 (one before the coarsest; the finest when there are only two levels)
            read = min(1, len(lv) - 1)
            self.blocks = nn.Sequential(*[ResBlock(block_cfg, lv[i], lv[i - 1])
                                          for i in range(len(lv) - 1, read, -1)])
            src = lv[read]
            width = cfg.n_latent * cfg.latent_dim
            self.fc = EqualLinear(src.channels * src.n_entities * src.n_frames, width, activate=True)
            self.head = EqualLinear(width, width)
            self.final_conv = None
            self.register_buffer("w_avg", torch.zeros(cfg.latent_dim) if w_avg is None else w_avg.detach().clone())
            self.input_shape = (cfg.in_channels, fine.n_entities, fine.n_frames)
            return
        self.blocks = nn.Sequential(*[ResBlock(block_cfg, lv[i], lv[i - 1]) for i in range(len(lv) - 1, 0, -1)])
        lv0 = lv[0]
        if model_cfg.skeleton_aware:
            final: nn.Module = SkeletalConv(lv0.channels, lv0.channels, lv0.neighbors,
                                            kernel_size=model_cfg.kernel_size, bias=False)
        else:
            final = NoStyle(PseudoImageConv(lv0.channels, lv0.channels, model_cfg.kernel_size))
        self.final_conv = ConvAct(final, lv0.channels)
        hidden = cfg.hidden if cfg.hidden else max(cfg.latent_dim, lv0.channels)
        self.fc = EqualLinear(lv0.channels * lv0.n_entities * lv0.n_frames, hidden, activate=True)
        self.head = EqualLinear(hidden, cfg.n_latent * cfg.latent_dim)
        with torch.no_grad():
            self.head.weight.mul_(cfg.head_init)
        self.register_buffer("w_avg", torch.zeros(cfg.latent_dim) if w_avg is None else w_avg.detach().clone())
        self.input_shape = (cfg.in_channels, fine.n_entities, fine.n_frames)

    def forward(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        if x.ndim != 4 or tuple(x.shape[1:]) != self.input_shape:
            raise ValueError(f"encoder input must be (B, {', '.join(map(str, self.input_shape))}), "
                             f"got {tuple(x.shape)}")
        if self.cfg.mask_channel:
            if mask is None:
                mask = torch.ones_like(x[:, :1])
            x = torch.cat([x, mask.to(x).expand(-1, 1, -1, -1)], 1)
        h = self.blocks(self.from_motion(x.contiguous()))
        if self.final_conv is None:  # released head: W+ itself
            return self.head(self.fc(h.flatten(1))).view(x.shape[0], self.cfg.n_latent, self.cfg.latent_dim)
        delta = self.head(self.fc(self.final_conv(h).flatten(1)))
        return self.w_avg + delta.view(x.shape[0], self.cfg.n_latent, self.cfg.latent_dim)


def build_encoder(g: Any, channel_multiplier: float = 1.0, prefix_frames: int | None = None,
                  mask_channel: bool | None = None, hidden: int | None = None,
                  head: str = "released", inplace_convs: int | None = None) -> MotionEncoder:
    """An encoder matching generator ``g`` (its levels, channels, style count and w̄); ``head``: see
    :class:`EncoderConfig` (``hidden`` applies to the bottleneck head only). ``inplace_convs`` None: by the head
    (1 with the released head, as the released encoder; the generator's count with the bottleneck head)."""
    k, e, t = g.output_shape
    if prefix_frames is not None and not 0 < prefix_frames < t:
        raise ValueError(f"prefix_frames must be in 1..{t - 1}, got {prefix_frames}")
    cfg = EncoderConfig(in_channels=k, n_latent=g.n_latent, latent_dim=g.latent_dim,
                        channel_multiplier=channel_multiplier,
                        mask_channel=(prefix_frames is not None) if mask_channel is None else bool(mask_channel),
                        prefix_frames=prefix_frames, hidden=hidden, head=head, inplace_convs=inplace_convs)

    return MotionEncoder(g.cfg, g.levels, cfg, w_avg=mean_w(g).cpu()).to(next(g.parameters()).device)


def visible_input(x: Tensor, prefix_frames: int | None) -> tuple[Tensor, Tensor | None]:
    """(input with frames >= prefix_frames zeroed, visibility mask (B, 1, E, T)); unchanged when no prefix."""
    if prefix_frames is None:
        return x, None
    mask = torch.zeros_like(x[:, :1])
    mask[..., :prefix_frames] = 1.0
    return x * mask, mask


def encode(encoder: MotionEncoder, x: Tensor, prefix_frames: int | None = None) -> Tensor:
    """W+ of motions x, applying the encoder's own prefix masking (``prefix_frames`` overrides its config)."""
    t = encoder.cfg.prefix_frames if prefix_frames is None else prefix_frames
    inp, mask = visible_input(x, t)
    return encoder(inp, mask)


__all__ = ["ENCODER_HEADS", "EncoderConfig", "MotionEncoder", "build_encoder", "visible_input", "encode"]
