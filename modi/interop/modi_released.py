"""Convert a checkpoint written by the authors' released MoDi (``train.py``) into a modi run.

The released code stores every skeletal convolution as a dense ``(Cout, Cin, E_out, E_in, U)`` weight times a
fixed 0/1 mask, with an equalised-lr factor per output entity; modi stores one ``(Cout, Cin, U)`` block per
(output, input) entity pair that the topology connects. Conversion keeps each pair's *effective* weight
(weight x mask x factor), so it refuses any weight that is non-zero outside the mask (that value would be
silently lost) and lists the offending entries.

Topology comes from the masks themselves (the released code derives them from the skeleton; reading them back
needs neither their code nor their config): each level's neighbours from its in-place convs, the pooling map
from its upsampling conv, the contact entities' feet from the finest neighbours. Where the released model differs
from modi's defaults the imported config says so: activation demodulation (``model.demodulation="activations"``),
the released "tree" neighbours and pooling, and no noise. Two released details modi has no parameter for and
which the conversion reproduces exactly: the generator's upsampling factor per coarse entity (folded into the
weights), and the discriminator's 1x1 skip, which reads only one fine entity per coarse one (modi's skip reads the
whole group: the other pairs are imported as zeros). Their generator loop reads its W+ rows in another order
(``released_style_index``); with one W per sample, as in sampling, the rows are all equal and nothing changes.

Motion layout (entities): the root's rotation, one rotation per bone (the released "edge" rotations), the
root motion, the contact labels. :func:`edge_skeleton` builds the modi skeleton whose forward kinematics
reproduces the released BVH output from that layout.
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from modi.core.skeleton import Skeleton
from modi.data.normalization import Normalizer
from modi.data.representation import MotionRepresentation
from modi.errors import CheckpointError, MaskViolation, UserError
from modi.interop.provenance import file_record, record, released_iterations, window_and_stride
from modi.interop.released_files import load_released_file, load_released_npy
from modi.models.modi.checkpoint import atomic_torch_save, checkpoint_dict
from modi.models.modi.codec import MotionCodec
from modi.models.modi.config import ModelConfig, MoDiConfig
from modi.models.modi.levels import LevelSpec
from modi.models.modi.networks import Discriminator, Generator

REQUIRED = ("g", "g_ema", "d", "args", "mean_joints", "std_joints")


# --------------------------------------------------------------------------------------------- reading
def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The released checkpoint's dict, checked for what conversion needs (as data: see ``released_files``)."""
    st = load_released_file(path, "released MoDi checkpoint")
    missing = [k for k in REQUIRED if k not in st]
    if missing:
        raise CheckpointError(f"{path}: not a released MoDi checkpoint (missing {', '.join(missing)})")
    args = st["args"]
    if not isinstance(args, argparse.Namespace):
        raise CheckpointError(f"{path}: 'args' is {type(args).__name__}, not their argparse Namespace")
    if getattr(args, "entity", "Edge") != "Edge":
        raise CheckpointError(f"{path}: entity {args.entity!r}: only the released 'Edge' (rotation) models import")
    if not getattr(args, "skeleton", False) or not (getattr(args, "conv3", False) or getattr(args, "conv3fast", False)):
        kind = "joints_pool" if getattr(args, "joints_pool", False) else "non-skeleton-aware"
        raise CheckpointError(f"{path}: a {kind} model; only the released --skeleton --conv3/--conv3fast models import")
    if getattr(args, "rotation_repr", "quaternion") != "quaternion":
        raise CheckpointError(f"{path}: rotation_repr {args.rotation_repr!r}: only quaternion models import")
    return st


# --------------------------------------------------------------------------------------------- topology
def _rows(mask: torch.Tensor) -> list[list[int]]:
    """``mask (E_out, E_in)`` -> for each output entity the input entities it reads, ascending."""
    return [[int(i) for i in torch.nonzero(mask[j] != 0).flatten()] for j in range(mask.shape[0])]


def _entity_mask(mask: torch.Tensor, name: str = "") -> torch.Tensor:
    """A dense mask (…, Cout, Cin, E_out, E_in, U) reduced to its skeletal pattern: the entity pairs connected for
    every channel pair and tap (in a released mask, exactly the pairs connected at all; see ``check_masks``)."""
    m = mask.reshape(-1, *mask.shape[-5:])  # ([1,] Cout, Cin, E_out, E_in, U) -> (n, Cout, Cin, Eo, Ei, U)
    return (m != 0).all(0).all(0).all(0).all(-1)


def n_convs_per_level(args: argparse.Namespace) -> int:
    return 1 + int(args.n_inplace_conv)


def released_levels(g_sd: dict[str, torch.Tensor], args: argparse.Namespace) -> list[Any]:
    """Coarse -> fine ``LevelSpec``s read from the generator's masks and shapes."""
    const = g_sd["input.input"]
    n_to = len({k.split(".")[1] for k in g_sd if k.startswith("to_xyzs.")})
    per = n_convs_per_level(args)
    levels = [LevelSpec(n_entities=int(const.shape[2]), neighbors=_rows(_entity_mask(g_sd["conv1.conv.mask"][0],
                        "conv1")), up_pooling=None, n_frames=int(const.shape[3]), channels=int(const.shape[1]))]
    for i in range(1, n_to + 1):
        up = f"convs.{(i - 1) * per}.conv"
        same = f"convs.{(i - 1) * per + 1}.conv"
        up_mask = _entity_mask(g_sd[f"{up}.mask"][0], up)  # (coarse, fine)
        same_mask = _entity_mask(g_sd[f"{same}.mask"][0], same)
        levels.append(LevelSpec(n_entities=int(same_mask.shape[0]), neighbors=_rows(same_mask),
                                up_pooling=_rows(up_mask), n_frames=levels[-1].n_frames * 2,
                                channels=int(g_sd[f"{same}.weight"].shape[1])))
        groups, n_coarse, n_fine = levels[-1].up_pooling, levels[-2].n_entities, levels[-1].n_entities
        covered = sorted({e for grp in groups for e in grp})
        if len(groups) != n_coarse or covered != list(range(n_fine)) or any(not grp for grp in groups):
            raise CheckpointError(
                f"{up}: the released pooling map from level {i - 1} ({n_coarse} entities) to level {i} ({n_fine}) "
                f"has {len(groups)} groups covering {len(covered)} entities, so some entity is never connected "
                "(the released --foot pooling does this on some skeletons); modi's skeletal layers need every "
                "entity pooled")
    return levels


def model_config(args: argparse.Namespace, levels: Sequence[Any]) -> Any:
    """modi's ModelConfig for a released model (see the module docstring for the named differences)."""
    return ModelConfig(latent_dim=int(args.latent), n_mlp=int(args.n_mlp), lr_mlp=0.01,
                       channels=tuple(lv.channels for lv in levels), kernel_size=3,
                       n_inplace_convs=int(args.n_inplace_conv), scaler="conv", skeleton_aware=True,
                       noise_injection=False, neighbors="tree", pooling="released", mbstd_group=4,
                       demodulation="activations", time_padding="stylegan2")


def released_style_index(n_levels: int, n_inplace: int) -> list[int]:
    """For each of modi's W+ rows, the released W+ row its layer reads.

    Both give the coarsest conv row 0 and let a level's to-motion share its row with the next level's
    upsampling conv. Modi then gives every in-place conv a row of its own; the released loop gives the first
    in-place conv its level's upsampling row again and the next ones the rows after it, so some released rows
    are never read (3, 6, 9, 12 with two in-place convs). A released W+ ``w`` is modi's ``w[:, index]``."""
    index = [0, 1]  # coarsest conv; coarsest to-motion = first upsampling conv
    i = 1  # the released loop's row of this level's upsampling conv
    for _ in range(1, n_levels):
        index += [i + j for j in range(n_inplace)]  # in-place convs: rows i, i+1, ... (the first repeats i)
        i += 1 + n_inplace
        index.append(i)  # to-motion (and the next upsampling conv): the released i + n_inplace + 1
    return index


def wplus_from_released(wplus: torch.Tensor, index: Sequence[int]) -> torch.Tensor:
    """A released-layout W+ ``(B, n, D)`` as modi's W+ (see ``released_style_index``)."""
    return wplus[:, list(index)]


def inject_index_from_released(t: int, index: Sequence[int]) -> int:
    """Style mixing at the released inject index ``t`` (rows >= t take the second latent) is modi's mixing at the
    first modi row whose released row is >= t (the map is monotone)."""
    return next(k for k, r in enumerate(index) if r >= t)


# --------------------------------------------------------------------------------------------- weights
def check_masks(sd: dict[str, torch.Tensor], where: str) -> None:
    """Refuse a state dict whose masked weights the compact form cannot hold, naming each offending entry.

    The effective weight is weight x mask. Raw weights where the mask is 0 are dead (multiplied by zero in every
    forward, so they never receive a gradient: the released code leaves them at their random initial values) and
    are dropped. What must hold: every mask is 0/1, and wherever weight x mask is non-zero the entity pair is
    connected for every channel pair and tap (the skeletal pattern a compact pair block stores)."""
    bad = []
    for k, mask in sd.items():
        if not k.endswith(".mask"):
            continue
        name = f"{where}.{k[:-5]}.weight"
        w = sd[k[: -len("mask")] + "weight"]
        if not bool(((mask == 0) | (mask == 1)).all()):
            bad.append(f"{name}: its mask holds values other than 0 and 1")
            continue
        pattern = _entity_mask(mask)  # (E_out, E_in)
        inside = pattern[..., None].expand(mask.shape[-3:])
        stray = (w * mask != 0) & ~inside
        n = int(stray.sum())
        if n:
            idx = tuple(int(i) for i in torch.nonzero(stray)[0])
            bad.append(f"{name}: {n} non-zero outside its skeletal mask (first at {idx}, "
                       f"max |w| {float((w * mask)[stray].abs().max()):.3g})")
    if bad:
        raise MaskViolation("released weights the compact per-pair form cannot hold: " + "; ".join(bad))


def _pairs(mod: Any) -> tuple[list[int], list[int]]:
    """(row, input entity) of every stored pair of a modi skeletal layer, in storage order."""
    offsets = mod.offsets.tolist()
    index = mod.index.tolist()
    rows = [r for r in range(len(offsets) - 1) for _ in range(offsets[r], offsets[r + 1])]
    return rows, index


def _pair_blocks(w: torch.Tensor, scale: torch.Tensor, rows: list[int], cols: list[int]) -> torch.Tensor:
    """Released blocks ``(Cout, nnz, Cin, U)`` of the pairs (row, col) of a masked dense weight (a pair modi
    stores that the released mask does not connect gets zeros), and each pair's released per-row factor."""
    s = scale.reshape(-1).to(torch.float64)[rows]  # one factor per released output row (E_out)
    w = w.to(torch.float64)
    return torch.stack([w[:, :, r, c, :] for r, c in zip(rows, cols)], 1), s


def _same(mod: Any, w: torch.Tensor, scale: torch.Tensor, power: int = 1) -> torch.Tensor:
    """A modi SkeletalConv/SkeletalDownsample weight ``(Cout, nnz, Cin, U)`` from a released masked dense one.

    ``power=1`` (weights): the same effective weight, w_modi = w x released factor / modi factor.
    ``power=-1`` (gradients of the same loss): g_modi = g x modi factor / released factor."""
    rows, cols = _pairs(mod)
    blocks, s_rel = _pair_blocks(w, scale, rows, cols)
    ratio = (s_rel / mod.weight_scale.to(torch.float64)) ** power
    return (blocks * ratio.view(1, -1, 1, 1)).to(mod.weight.dtype)


def _up(mod: Any, w: torch.Tensor, scale: torch.Tensor, power: int = 1) -> torch.Tensor:
    """A modi SkeletalUpsample weight ``(Cin, nnz, Cout, U)`` from the released (Cout, Cin, coarse, fine, U)."""
    return _same(mod, w, scale, power).permute(2, 1, 0, 3).contiguous()


def _linear(dst: dict, prefix: str, sd: dict, src: str) -> None:
    dst[f"{prefix}.weight"] = sd[f"{src}.weight"].clone()
    dst[f"{prefix}.bias"] = sd[f"{src}.bias"].clone()


def convert_generator(g_sd: dict[str, torch.Tensor], args: argparse.Namespace, levels: Sequence[Any],
                      out_channels: int, w_avg: torch.Tensor | None = None) -> Any:
    """A modi ``Generator`` holding the released generator's function (float32, like the released file)."""
    check_masks(g_sd, "g")
    g = Generator(model_config(args, levels), levels, out_channels)
    g.load_state_dict(generator_state(g_sd, args, g, w_avg))
    return g


def generator_state(g_sd: dict[str, torch.Tensor], args: argparse.Namespace, g: Any,
                    w_avg: torch.Tensor | None = None, power: int = 1) -> dict[str, torch.Tensor]:
    """The state dict of modi generator ``g`` for released generator tensors ``g_sd`` (weights with masks and
    factors; with ``power=-1``, their gradients in place of the weights: see ``_same``)."""
    cfg = g.cfg
    sd: dict[str, torch.Tensor] = {}
    for i in range(1, int(args.n_mlp) + 1):
        _linear(sd, f"mapping.net.{i}", g_sd, f"style.{i}")
    sd["const"] = g_sd["input.input"].clone()
    sd["w_avg"] = torch.zeros(cfg.latent_dim) if w_avg is None else w_avg.detach().reshape(-1).float()

    def styled(dst: str, src: str, mod: Any, up: bool = False) -> None:
        w, scale = (g_sd[f"{src}.weight"] * g_sd[f"{src}.mask"])[0], g_sd[f"{src}.scale"][0]
        sd[f"{dst}.conv.weight"] = _up(mod, w, scale, power) if up else _same(mod, w, scale, power)
        _linear(sd, f"{dst}.affine", g_sd, f"{src}.modulation")

    styled("conv1.conv", "conv1.conv", g.conv1.conv.conv)
    sd["conv1.act.bias"] = g_sd["conv1.activate.bias"].clone()
    styled("to_motion1.conv", "to_xyz1.conv", g.to_motion1.conv.conv)
    sd["to_motion1.bias"] = g_sd["to_xyz1.bias"].clone()
    per = n_convs_per_level(args)
    for b, block in enumerate(g.blocks):
        for j, layer in enumerate(block):
            src = f"convs.{b * per + j}"
            styled(f"blocks.{b}.{j}.conv", f"{src}.conv", layer.conv.conv, up=j == 0)
            sd[f"blocks.{b}.{j}.act.bias"] = g_sd[f"{src}.activate.bias"].clone()
        styled(f"to_motions.{b}.conv", f"to_xyzs.{b}.conv", g.to_motions[b].conv.conv)
        sd[f"to_motions.{b}.bias"] = g_sd[f"to_xyzs.{b}.bias"].clone()
    return sd


def convert_discriminator(d_sd: dict[str, torch.Tensor], args: argparse.Namespace, levels: Sequence[Any],
                          in_channels: int) -> Any:
    """A modi ``Discriminator`` holding the released discriminator's function."""
    check_masks(d_sd, "d")
    d = Discriminator(model_config(args, levels), levels, in_channels)
    d.load_state_dict(discriminator_state(d_sd, args, d))
    return d


def discriminator_state(d_sd: dict[str, torch.Tensor], args: argparse.Namespace, d: Any,
                        power: int = 1) -> dict[str, torch.Tensor]:
    """The state dict of modi discriminator ``d`` for released discriminator tensors (``power`` as in
    ``generator_state``)."""
    sd = reverse_hierarchy_state(d_sd, d.from_motion.conv, "from_motion", d.blocks, int(args.n_inplace_conv), power)
    _conv_state(sd, d_sd, "final_conv.conv.weight", "final_conv.0", d.final_conv.conv, power)
    sd["final_conv.act.bias"] = d_sd["final_conv.1.bias"].clone()
    for i in (0, 1):
        _linear(sd, f"final_linear.{i}", d_sd, f"final_linear.{i}")
    return sd


def _conv_state(sd: dict, src_sd: dict, dst: str, src: str, mod: Any, power: int) -> None:
    sd[dst] = _same(mod, src_sd[f"{src}.weight"] * src_sd[f"{src}.mask"], src_sd[f"{src}.scale"][0, 0], power)


def reverse_hierarchy_state(src_sd: dict[str, torch.Tensor], from_motion: Any, from_prefix: str, blocks: Any,
                            n_inplace: int, power: int = 1) -> dict[str, torch.Tensor]:
    """The released ``Discriminator``'s input conv (``convs.0``) and residual blocks (``convs.1..``) as modi's
    (the discriminator's, and the encoder's: the released encoder is that class with a latent head)."""
    sd: dict[str, torch.Tensor] = {}
    _conv_state(sd, src_sd, f"{from_prefix}.conv.weight", "convs.0.0", from_motion, power)
    sd[f"{from_prefix}.act.bias"] = src_sd["convs.0.1.bias"].clone()
    for b, block in enumerate(blocks):
        src = f"convs.{b + 1}"
        for j in range(n_inplace):
            _conv_state(sd, src_sd, f"blocks.{b}.convs.{j}.conv.weight", f"{src}.convs.{j}.0", block.convs[j].conv,
                        power)
            sd[f"blocks.{b}.convs.{j}.act.bias"] = src_sd[f"{src}.convs.{j}.1.bias"].clone()
        _conv_state(sd, src_sd, f"blocks.{b}.convs.{n_inplace}.conv.1.weight", f"{src}.convs.{n_inplace}.1",
                    block.convs[n_inplace].conv[1], power)
        sd[f"blocks.{b}.convs.{n_inplace}.act.bias"] = src_sd[f"{src}.convs.{n_inplace}.2.bias"].clone()
        _conv_state(sd, src_sd, f"blocks.{b}.skip.1.weight", f"{src}.skip.1", block.skip[1], power)
    return sd


# --------------------------------------------------------------------------------------------- skeleton and codec
def edge_skeleton(parents: Sequence[int], offsets: np.ndarray, names: Sequence[str]) -> Any:
    """The modi skeleton whose joint ``i`` carries released entity ``i``'s rotation.

    Released entity ``i > 0`` is the rotation of the bone from joint ``P[i]`` to ``i`` (``P`` =
    ``parents_with_root``), composed down the chain; their BVH writer realises it by giving a joint with several
    children one zero-offset dummy child per bone (``Hips_Spine``, ``Chest_Neck``, ...). Here joint ``i`` sits
    where bone ``i`` starts: child of joint ``P[i]`` at offset ``offsets[P[i]]`` (zero when ``P[i]`` is the root),
    and a leaf bone ends in an End Site at ``offsets[i]``. Its forward kinematics is the released BVH's; it has
    the released BVH's joints except each multi-child joint, whose position its dummies share. Names follow
    their writer: the joint's own name when the bone is its only one, ``parent_child`` for a dummy."""
    P = [int(p) for p in parents]
    off = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    names = [str(n) for n in names]
    n_children = [0] * len(P)
    for p in P[1:]:
        n_children[p] += 1
    out_names, out_off, ends = [names[0]], [off[0]], {}
    for i in range(1, len(P)):
        p = P[i]
        out_names.append(names[p] if n_children[p] == 1 and p != 0 else f"{names[p]}_{names[i]}")
        out_off.append(off[p] if p != 0 else np.zeros(3))
        if n_children[i] == 0:
            ends[i] = off[i].copy()
    return Skeleton(out_names, P, np.stack(out_off), ends)


def joint_of_bone_end(parents: Sequence[int], j: int) -> int:
    """The edge-skeleton joint at the *end* of released bone ``j`` (where their joint ``j`` is): a child bone's
    start, or joint ``j`` itself for a leaf (its End Site holds the exact end)."""
    kids = [i for i, p in enumerate(parents) if p == j]
    return kids[0] if kids else j


def released_codec(motion0: dict, st: dict, feet_entities: Sequence[int], fps: float) -> Any:
    """modi's ``MotionCodec`` for the released tensor layout: rotations, root motion, contacts, their statistics."""
    args = st["args"]
    P = [int(p) for p in np.asarray(motion0["parents_with_root"]).tolist()]
    offsets = np.concatenate([np.asarray(motion0["offset_root"], dtype=np.float64)[None],
                              np.asarray(motion0["offsets_no_root"], dtype=np.float64)])
    sk = edge_skeleton(P, offsets, list(np.asarray(motion0["names_with_root"]).tolist()))
    if not getattr(args, "glob_pos", False):
        raise CheckpointError("a released model without --glob_pos (no root-motion entity) is not supported")
    root = "velocity3" if getattr(args, "use_velocity", False) else "position"
    feet = [joint_of_bone_end(P, f) for f in feet_entities]
    rep = MotionRepresentation(sk, feet, rotation="quat", root=root)
    mean = torch.as_tensor(np.asarray(st["mean_joints"], dtype=np.float64)[0, :, :, 0].T)
    std = torch.as_tensor(np.asarray(st["std_joints"], dtype=np.float64)[0, :, :, 0].T)
    if tuple(mean.shape) != (rep.K, rep.n_entities):
        raise CheckpointError(f"normalisation statistics are {tuple(mean.shape)} (K, E) but the skeleton in --data "
                              f"gives ({rep.K}, {rep.n_entities}): the data is not the one this model was trained on")
    return MotionCodec(rep, Normalizer(mean.float(), std.float()), fps)


def contact_feet(levels: Sequence[Any], n_rot: int) -> list[int]:
    """Released bone of each contact entity: its neighbour other than itself at the finest level (their contact
    entities connect to their foot only)."""
    fine = levels[-1]
    out = []
    for e in range(n_rot + 1, fine.n_entities):
        other = [n for n in fine.neighbors[e] if n != e]
        if len(other) != 1 or other[0] >= n_rot:
            raise CheckpointError(f"contact entity {e}: neighbours {fine.neighbors[e]} are not one foot bone")
        out.append(other[0])
    return out


def mean_w(g: Any, n: int = 4096, seed: int = 0) -> torch.Tensor:
    """The centre of W for truncation: the released generate.py's ``mean_latent`` (the mean of ``n`` mapped
    z), from a fixed seed so an import is reproducible."""
    z = torch.randn(n, g.latent_dim, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        return g.mapping(z).mean(0)


# --------------------------------------------------------------------------------------------- the run
def _find_data(data: Path) -> Path:
    if data.is_file():
        return data
    if data.is_dir():
        found = sorted(data.glob("*.npy"))
        if len(found) == 1:
            return found[0]
        raise UserError(f"--data {data}: expected the released training .npy (edge_rot_*.npy) or a folder with "
                        f"exactly one .npy, found {len(found)}")
    raise UserError(f"--data {data}: no such file or folder")


def import_checkpoint(ckpt: Path | str, data: Path | str, out: Path | str, fps: float = 30.0) -> Path:
    """Write ``out/checkpoint.pt``, a modi run holding the released G, EMA G and D; returns its path."""
    state = convert_checkpoint(ckpt, data, fps)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "checkpoint.pt"
    atomic_torch_save(state, path)
    return path


def convert_checkpoint(ckpt: Path | str, data: Path | str, fps: float = 30.0) -> dict[str, Any]:
    """The modi checkpoint dict (format ``modi-checkpoint``) of a released MoDi checkpoint and its data."""
    st = read_checkpoint(ckpt)
    motions = load_released_npy(_find_data(Path(data)))
    if motions.ndim != 1 or len(motions) == 0 or not isinstance(motions[0], dict) or \
            "parents_with_root" not in motions[0]:
        raise UserError(f"--data {data}: not the released edge-rotation data (no 'parents_with_root' per clip)")
    args = st["args"]
    levels = released_levels(st["g_ema"], args)
    n_rot = len(np.asarray(motions[0]["parents_with_root"]))
    codec = released_codec(motions[0], st, contact_feet(levels, n_rot) if getattr(args, "foot", False) else [], fps)
    if codec.n_entities != levels[-1].n_entities:
        raise CheckpointError(f"the model's finest level has {levels[-1].n_entities} entities, the data's skeleton "
                              f"{codec.n_entities}: --data is not this model's training data")
    K = codec.n_channels
    g = convert_generator(st["g"], args, levels, K)
    g_ema = convert_generator(st["g_ema"], args, levels, K)
    w = mean_w(g_ema)
    g.w_avg.copy_(w)
    g_ema.w_avg.copy_(w)
    d = convert_discriminator(st["d"], args, levels, K)
    window, stride = window_and_stride(motions)
    iterations, known = released_iterations(ckpt, st.get("g_optim"), int(getattr(args, "g_reg_every", 0) or 0))
    cfg = MoDiConfig(model=model_config(args, levels), preset="released-import")
    cfg.data.n_frames = levels[-1].n_frames
    cfg.data.fps = float(fps)
    if stride is not None:
        cfg.data.stride = stride
    _train_options(cfg.train, args)
    cfg.validate()
    data_path = _find_data(Path(data))
    prov = record("modi-released", file_record(ckpt), iterations=iterations, iterations_from=known,
                  args=args, data={**file_record(data_path), "clips": int(len(motions)), "window": window,
                                   "stride": stride, "fps": float(fps)}, seed=None)
    return checkpoint_dict(config=cfg, codec=codec, levels=levels, G=g, G_ema=g_ema, D=d, step=iterations or 0,
                           imported_from=prov)


# their train.py option -> modi's TrainConfig field, for the options with the same meaning
_TRAIN_OPTIONS = {"iter": "iters", "batch": "batch", "r1": "r1_gamma", "d_reg_every": "d_reg_every",
                  "g_reg_every": "g_reg_every", "path_regularize": "path_weight",
                  "path_batch_shrink": "path_batch_shrink", "mixing": "mixing", "g_foot_reg_weight": "contact_weight",
                  "g_encourage_contact_weight": "touch_weight"}


def _train_options(train: Any, args: argparse.Namespace) -> None:
    """Their training options as the file states them (so ``modi info`` shows theirs, not modi's defaults)."""
    for theirs, mine in _TRAIN_OPTIONS.items():
        if getattr(args, theirs, None) is not None:
            setattr(train, mine, type(getattr(train, mine))(getattr(args, theirs)))
    g_lr, d_lr = getattr(args, "g_lr", None), getattr(args, "d_lr", None)
    if g_lr is not None and g_lr == d_lr:  # modi has one rate for both
        train.lr = float(g_lr)


__all__ = ["convert_checkpoint", "released_style_index", "wplus_from_released", "inject_index_from_released", "import_checkpoint", "edge_skeleton", "released_codec", "contact_feet", "mean_w", "MaskViolation", "read_checkpoint", "released_levels", "model_config", "check_masks",
           "convert_generator", "convert_discriminator", "generator_state", "discriminator_state",
           "reverse_hierarchy_state"]
