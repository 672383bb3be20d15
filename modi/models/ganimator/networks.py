"""GANimator's per-level networks and the coarse-to-fine sampler that chains them.

Each level ``l`` has a small fully convolutional *residual* generator ``G_l`` (4 skeleton-aware convolutions,
LeakyReLU 0.2 between them) that adds high-frequency detail to the upsampled output of level ``l-1``:
``x_l = G_l(up(x_{l-1}) + z_l) + up(x_{l-1})``; level 0 starts from zeros, so it maps noise to a coarse motion.
Discriminators are PatchGANs: 3 skeleton-aware convolutions then a plain temporal convolution to one score per
frame; the loss averages the patch scores, which limits what one score can see and prevents memorising the clip.

Contacts are virtual joints wired to their foot and to the root-motion virtual joint; the root-motion joint is
wired to the root's neighbours (the authors' adjacency; ``ganimator_neighbors``). Channel widths follow the
authors: the hidden layers carry ~128 / 256 channels in total, split evenly over the entities.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from modi.core.skeleton_graph import neighbors as tree_neighbors
from modi.models.ganimator.data import K, real_pyramid, resample
from modi_ext.layers import SkeletalConv


def ganimator_neighbors(parents: Sequence[int], feet: Sequence[int], distance: int = 2) -> list[list[int]]:
    """Neighbour lists over entities ``[joints..., root motion, contacts...]`` (self included, sorted).

    Joints: tree distance ``<= distance``. Contact ``c`` of foot ``f``: ``f``'s neighbours, the contacts of ``f``
    and the root-motion entity; foot ``f`` also sees its contacts. Root motion: the root's neighbours, every
    contact and itself; those all see the root motion in turn.
    """
    J = len(parents)
    rm = J
    base = [set(n) for n in tree_neighbors(list(parents), distance, siblings=False)]
    contact_ids = [J + 1 + i for i in range(len(feet))]
    for c, f in zip(contact_ids, feet):
        base[f].add(c)
    nbrs: list[set[int]] = base + [set()] + [set(base[f]) | {c} for c, f in zip(contact_ids, feet)]
    root_side = set(base[0]) | set(contact_ids)
    for j in root_side:
        nbrs[j].add(rm)
    nbrs[rm] = root_side | {rm}
    return [sorted(n) for n in nbrs]


def per_entity_channels(total: int, n_entities: int) -> int:
    """The authors round total widths up to a multiple of the entity count."""
    return max(1, math.ceil(total / n_entities))


def _standardise(conv: nn.Module) -> nn.Module:
    """Give a ``modi_ext`` skeletal conv a plain (PyTorch-default) parametrisation.

    ``modi_ext`` layers use StyleGAN2's equalised learning rate (weights ~N(0,1) times a run-time 1/sqrt(fan-in)).
    GANimator's schedule (Adam 1e-4) was tuned for plain weights; with the run-time factor every step would be
    ~sqrt(fan-in) times smaller. So the factor is folded into the weights once, and the initial scale matches
    ``nn.Conv1d``'s default (uniform, bound 1/sqrt(fan-in): std 1/sqrt(3 fan-in)).
    """
    conv.fold_weight_scale(1.0 / math.sqrt(3.0))
    return conv


class EntityBias(nn.Module):
    """One bias per (channel, entity), as a conv over the flattened entity x channel axis would have.

    ``fan_in``: per-entity fan-in of the convolution before it; given, the biases are drawn uniform in
    ``+-1/sqrt(fan_in[j])`` (``nn.Conv1d``'s default, which the authors' skeleton-aware conv applies per joint);
    otherwise they start at zero.
    """

    def __init__(self, channels: int, n_entities: int, fan_in: Sequence[int] | None = None) -> None:
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(channels, n_entities, 1))
        if fan_in is not None:
            if len(fan_in) != n_entities:
                raise ValueError(f"fan_in: expected {n_entities} entries, got {len(fan_in)}")
            bound = torch.tensor([1.0 / math.sqrt(f) for f in fan_in]).view(1, n_entities, 1)
            with torch.no_grad():
                self.bias.uniform_(-1.0, 1.0).mul_(bound)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.bias


class SkeletalStack(nn.Module):
    """``len(channels)-1`` skeleton-aware convolutions with LeakyReLU(0.2) between (none after the last).

    ``bias_init``: ``"uniform"`` (+-1/sqrt(fan-in) of each entity: neighbours x input channels x kernel) or
    ``"zeros"``."""

    def __init__(self, channels: Sequence[int], neighbors: list[list[int]], kernel_size: int, padding_mode: str,
                 last_activation: bool = False, bias_init: str = "uniform") -> None:
        super().__init__()

        if bias_init not in ("uniform", "zeros"):
            raise ValueError(f"bias_init must be 'uniform' or 'zeros', got {bias_init!r}")
        E = len(neighbors)
        mode = "reflect" if padding_mode == "reflect" else "zeros"
        layers: list[nn.Module] = []
        for i in range(len(channels) - 1):
            conv = _standardise(SkeletalConv(channels[i], channels[i + 1], neighbors, kernel_size=kernel_size,
                                              padding_mode=mode, bias=False))
            fan_in = [len(n) * channels[i] * kernel_size for n in neighbors] if bias_init == "uniform" else None
            layers += [conv, EntityBias(channels[i + 1], E, fan_in)]
            if i < len(channels) - 2 or last_activation:
                layers.append(nn.LeakyReLU(0.2))
        self.net = nn.Sequential(*layers)
        self.receptive_radius = (len(channels) - 1) * (kernel_size // 2)

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x.contiguous())


class LevelGenerator(nn.Module):
    """Residual generator of one level; optional hard constraint on some entities (trajectory conditioning).

    ``cond_entities``: entities replaced by the condition on the way in, and whose output is forced so that
    ``prev + residual == cond`` on the way out (the paper's concatenation trick).
    """

    def __init__(self, neighbors: list[list[int]], base_channels: int = 128, n_layers: int = 4,
                 kernel_size: int = 5, padding_mode: str = "reflect",
                 cond_entities: Sequence[int] | None = None, bias_init: str = "uniform") -> None:
        super().__init__()
        E = len(neighbors)
        widths = [K] + [per_entity_channels(base_channels * 2 ** ((i + 1) // 2), E) for i in range(n_layers - 1)] + [K]
        self.widths = widths
        self.body = SkeletalStack(widths, neighbors, kernel_size, padding_mode, bias_init=bias_init)
        self.cond_entities = list(cond_entities) if cond_entities else []
        self.receptive_radius = self.body.receptive_radius

    def forward(self, x: Tensor, prev: Tensor, cond: Tensor | None = None) -> Tensor:
        ce = self.cond_entities
        if cond is not None and ce:
            x = x.clone()
            x[:, :, ce] = cond
        y = self.body(x)
        if cond is not None and ce:
            y = y.clone()
            y[:, :, ce] = cond - prev[:, :, ce]
        return y


class PatchDiscriminator(nn.Module):
    """Skeleton-aware convolutions then one temporal conv over all entities: a score per frame (patch)."""

    def __init__(self, neighbors: list[list[int]], base_channels: int = 128, n_layers: int = 4,
                 kernel_size: int = 5, padding_mode: str = "reflect", bias_init: str = "uniform") -> None:
        super().__init__()
        E = len(neighbors)
        widths = [K] + [per_entity_channels(base_channels * 2 ** ((i + 1) // 2), E) for i in range(n_layers - 1)]
        self.body = SkeletalStack(widths, neighbors, kernel_size, padding_mode, last_activation=True,
                                  bias_init=bias_init)
        pm = "reflect" if padding_mode == "reflect" else ("replicate" if padding_mode == "replicate" else "zeros")
        self.head = nn.Conv1d(widths[-1] * E, 1, kernel_size, padding=kernel_size // 2, padding_mode=pm)

    def forward(self, x: Tensor) -> Tensor:
        h = self.body(x)
        B, C, E, T = h.shape
        return score_head(self.head, h.reshape(B, C * E, T))  # (B, T)


_TORCH_PAD = {"reflect": "reflect", "replicate": "replicate", "zeros": "constant"}


def score_head(conv: nn.Conv1d, h: Tensor) -> Tensor:
    """``conv(h).squeeze(1)`` for the discriminator's one-output "same" temporal conv, as one matrix product.

    ``z = W^T h`` gives every tap's response ``(U, B, T)``; the score is the sum of the taps' shifted rows of ``z``
    padded like ``h`` would be (each of ``z``'s columns is linear in one frame of ``h``, so padding ``z`` by
    reflection, replication or zeros equals padding ``h`` -- and ``z`` has U rows where ``h`` has hundreds).
    oneDNN and the padding of ``h`` make the ``nn.Conv1d`` slow for this shape: on the 2-core machine (C=261,
    T=129) ~550 us forward+backward against ~210 us here, and 1.1 ms against 0.6 ms with the WGAN-GP's double
    backward.  Same parameters and ``state_dict`` as the ``nn.Conv1d``.
    """
    U = conv.kernel_size[0]
    if conv.out_channels != 1 or conv.stride != (1,) or conv.dilation != (1,) or conv.groups != 1 \
            or conv.padding != (U // 2,) or U % 2 != 1:
        return conv(h).squeeze(1)
    B, C, T = h.shape
    p = U // 2
    cols = h[0] if B == 1 else h.transpose(0, 1).reshape(C, B * T)
    z = torch.mm(conv.weight[0].t(), cols).view(U, B, T)
    if p:
        z = F.pad(z, (p, p), mode=_TORCH_PAD[conv.padding_mode])
    y = z[0, :, :T]
    for u in range(1, U):
        y = y + z[u, :, u:u + T]
    return y + conv.bias if conv.bias is not None else y


def make_noise(batch: int, length: int, amp: float, generator: torch.Generator | None = None,
               device: torch.device | str = "cpu") -> Tensor:
    """GANimator's noise: i.i.d. over time, shared by every channel and entity, scaled by the level amplitude."""
    if generator is not None:  # a CPU generator: draw on the CPU, so seeds mean the same on every device
        z = torch.randn(batch, 1, 1, length, generator=generator).to(device)
    else:
        z = torch.randn(batch, 1, 1, length, device=device)
    return z * float(amp)


def synthesize(gens: Sequence[nn.Module], rates: Sequence[float], lengths: Sequence[int], noises: Sequence,
               n_entities: int, start: int = 0, stop: int | None = None, prev: Tensor | None = None,
               conds: Sequence[Tensor | None] | None = None, replace: dict[int, Tensor] | None = None,
               detach_between: bool = False, batch: int = 1) -> list[Tensor]:
    """Run levels ``start..stop-1`` coarse to fine; returns each level's output ``(B, 6, E, L_l)``.

    ``prev``: the output of level ``start-1`` (required when ``start > 0``). ``noises[l]``: a tensor broadcastable
    to the level (or 0/None for none). ``conds[l]``: constraint for conditional levels. ``replace[l]``: use this
    tensor as level ``l``'s output instead of running ``G_l`` (style transfer, key-frame editing).
    Upsampling uses the fixed-grid resampler with ratio ``rates[l-1] / rates[l]``.
    """
    stop = len(gens) if stop is None else stop
    outs: list[Tensor] = []
    device = next(gens[0].parameters()).device
    for l in range(start, stop):
        if l == 0 or prev is None:
            if l > 0 and prev is None:
                raise ValueError(f"synthesize: level {l} needs the output of level {l - 1} (prev)")
            B = batch if noises[l] is None or not isinstance(noises[l], Tensor) else noises[l].shape[0]
            base = torch.zeros(B, K, n_entities, lengths[l], device=device)
        else:
            base = resample(prev, lengths[l], rates[l - 1] / rates[l])
        if replace is not None and l in replace:
            out = replace[l].to(base)
        else:
            z = noises[l] if noises is not None and l < len(noises) else None
            x = base if z is None or (not isinstance(z, Tensor) and z == 0) else base + z
            cond = conds[l] if conds is not None and l < len(conds) else None
            out = gens[l](x, base, cond) + base
        outs.append(out)
        prev = out.detach() if detach_between else out
    return outs


class GanimatorModel(nn.Module):
    """Everything needed to generate: per-level generators (and discriminators while training), the training
    clips' pyramids (lengths, rates), noise amplitudes and the fixed reconstruction noises ``z*``.

    Level rates are relative to the finest level, so a sample of any length ``N`` has levels of
    ``ceil(N * rate_l)`` frames on a grid that does not move when ``N`` changes.
    """

    def __init__(self, cfg, seqs: Sequence, lengths: Sequence[Sequence[int]], amps: Sequence[Sequence[float]],
                 z_stars: Sequence[Tensor], with_discriminators: bool = True) -> None:
        super().__init__()
        self.cfg = cfg
        self.seqs = list(seqs)
        ref = self.seqs[0]
        self.n_joints = ref.n_joints
        self.feet = list(ref.feet)
        self.n_entities = ref.n_entities
        self.neighbors = ganimator_neighbors(ref.skeleton.parents, self.feet, cfg.neighbor_distance)
        if len(self.neighbors) != self.n_entities:
            raise ValueError("entity count of the features and of the topology disagree")
        sixd = getattr(cfg, "sixd", "rows")
        if any(s.sixd != sixd for s in self.seqs):
            raise ValueError(f"the clips' 6D layout ({', '.join(sorted({s.sixd for s in self.seqs}))}) is not the "
                             f"config's ({sixd}); load them with the same config")
        self.lengths = [list(map(int, l)) for l in lengths]
        self.rates = [[x / l[-1] for x in l] for l in self.lengths]
        self.amps = [[float(a) for a in row] for row in amps]
        self.n_levels = len(self.lengths[0])
        self.z_stars = nn.ParameterList([nn.Parameter(z.clone(), requires_grad=False) for z in z_stars])
        self.cond_entities = [self.n_joints, 0] if cfg.conditional else []
        kw = dict(base_channels=cfg.base_channels, n_layers=cfg.n_layers, kernel_size=cfg.kernel_size,
                  padding_mode=cfg.padding_mode, bias_init=getattr(cfg, "bias_init", "uniform"))
        self.gens = nn.ModuleList([LevelGenerator(self.neighbors, cond_entities=self.cond_entities, **kw)
                                   for _ in range(self.n_levels)])
        self.discs = nn.ModuleList([PatchDiscriminator(self.neighbors, **kw) for _ in range(self.n_levels)]) \
            if with_discriminators else None

    @property
    def device(self) -> torch.device:
        return next(self.gens.parameters()).device

    def level_lengths(self, n_frames: int, base: int = 0) -> list[int]:
        """Level lengths for an ``n_frames`` output (the training lengths when ``n_frames`` is the clip's)."""
        if n_frames == self.lengths[base][-1]:
            return list(self.lengths[base])
        return [max(1, math.ceil(n_frames * r - 1e-6)) for r in self.rates[base]]

    def random_noises(self, lengths: Sequence[int], batch: int = 1, base: int = 0, fine_noise: bool = True,
                      generator: torch.Generator | None = None) -> list[Tensor | None]:
        amps = self.amps[base]
        out: list[Tensor | None] = []
        for l, L in enumerate(lengths):
            if l == 0 or fine_noise:
                out.append(make_noise(batch, L, amps[l], generator, self.device))
            else:
                out.append(None)
        return out

    def rec_noises(self, m: int) -> list[Tensor | None]:
        return [self.z_stars[m]] + [None] * (self.n_levels - 1)

    @torch.no_grad()
    def sample(self, n_frames: int, n: int = 1, base: int = 0, fine_noise: bool = False,
               generator: torch.Generator | None = None, conds: Sequence[Tensor | None] | None = None,
               replace: dict[int, Tensor] | None = None, noises: Sequence | None = None) -> Tensor:
        """``n`` random motions of ``n_frames`` frames, ``(n, 6, E, n_frames)``.

        ``fine_noise=False`` follows the authors' demo: only the coarsest level is random, finer levels add
        detail deterministically.
        """
        lengths = self.level_lengths(n_frames, base)
        if noises is None:
            noises = self.random_noises(lengths, n, base, fine_noise, generator)
        outs = synthesize(self.gens, self.rates[base], lengths, noises, self.n_entities, conds=conds,
                          replace=replace, batch=n)
        return outs[-1]

    @torch.no_grad()
    def reconstruct(self, m: int = 0) -> Tensor:
        """The fixed-noise reconstruction of training clip ``m`` at full rate ``(1, 6, E, T)``."""
        conds = None
        if self.cond_entities:
            reals = real_pyramid(self.seqs[m], self.lengths[m])
            conds = [r.unsqueeze(0)[:, :, self.cond_entities].to(self.device) for r in reals]
        outs = synthesize(self.gens, self.rates[m], self.lengths[m], self.rec_noises(m), self.n_entities,
                          conds=conds)
        return outs[-1]


__all__ = ["GanimatorModel", "ganimator_neighbors", "per_entity_channels", "LevelGenerator", "PatchDiscriminator", "SkeletalStack",
           "EntityBias", "make_noise", "synthesize", "score_head"]
