"""From a BVH file to GANimator's training tensor, and back.

GANimator learns from one (or a few) short clips of *any* skeleton, so everything that the authors kept in a
per-character table is derived here from the file itself, and can be overridden:

* **joint reduction** drops hand/finger detail and head-top end joints (a Mixamo rig goes from 65 to 24 joints);
* **feet** are the chain ends that spend their time near the ground (toes of a biped, hooves and front "hands" of a
  quadruped, leg tips of a crab); contact labels are "foot speed below a fraction of the body size";
* **units** are metres when the rig looks centimetre-sized (the authors' 1/100 rule) and the clip is brought to
  ~30 fps by integer striding.

Feature layout, ``(K=6, E, T)``: entities ``0..J-1`` hold each joint's local rotation as 6D (the first two rows
of the matrix, as the authors' code, or columns: ``GanimatorConfig.sixd``, recorded in :attr:`Sequence.sixd`);
entity ``J`` is the root-motion "virtual joint" ``[dx, y, dz, 0, 0, 0]`` (per-frame horizontal displacement,
absolute height); entities ``J+1..`` are contact virtual joints ``[label, 0, 0, 0, 0, 0]`` (the first frame's label
0 by default, as the authors'). All time resampling uses one fixed-grid linear interpolator, so a level's frame ``i`` sits at the same instant whatever the total length — this is what
makes generation of any length and streaming exact.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence as Seq

import numpy as np
import torch
from torch import Tensor

from modi.core.joint_reduction import reduce_joints  # noqa: F401  (re-exported: GANimator's joint reduction)
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import quat_to_6d, sixd_to_quat
from modi.core.skeleton import Skeleton, strip_namespace  # noqa: F401  (strip_namespace: re-exported)
from modi.data.motion import Motion
from modi.errors import UserError
from modi.io import bvh as bvh_io
from modi.models.ganimator.config import GanimatorConfig

K = 6  # feature width of every entity (6D rotation)


# ------------------------------------------------------------------------------------------ skeleton choices


def body_height(positions: np.ndarray) -> float:
    """A size of the body (its largest extent over the clip, averaged): scale-free thresholds divide by it."""
    ext = positions.max(axis=1) - positions.min(axis=1)  # (T, 3)
    return float(np.median(ext.max(axis=1)))


def detect_feet(skeleton: Skeleton, positions: np.ndarray, rel_height: float = 0.12) -> list[int]:
    """Joints that carry ground contact: chain ends (leaves and their parents) whose median height above the
    ground stays under ``rel_height`` of the body size. ``positions`` is ``(T, J, 3)``, y up."""
    J = skeleton.n_joints
    children = [[] for _ in range(J)]
    for j, p in enumerate(skeleton.parents):
        if p >= 0:
            children[p].append(j)
    leaves = [j for j in range(1, J) if not children[j]]
    candidates = set(leaves)
    for leaf in leaves:
        p = skeleton.parents[leaf]
        # a short last bone (toe tip after a long foot) makes its parent (the toe) a contact point as well
        if p > 0 and len(children[p]) == 1 and \
                np.linalg.norm(skeleton.offsets[leaf]) < 0.75 * np.linalg.norm(skeleton.offsets[p]):
            candidates.add(p)
    h = positions[..., 1]
    ground = float(np.quantile(h.min(axis=1), 0.05))
    size = body_height(positions)
    med = np.median(h - ground, axis=0)
    feet = sorted(j for j in candidates if med[j] < rel_height * size)
    return feet


def contact_labels(positions: np.ndarray, feet: Seq[int], threshold: float, first_frame: str = "zero") -> np.ndarray:
    """1 where the foot moves less than ``threshold`` per frame. The first frame has no velocity: ``"zero"`` labels it
    0 (the authors' ``foot_contact``), ``"copy"`` gives it the second frame's label."""
    if first_frame not in ("zero", "copy"):
        raise ValueError(f"first_frame must be 'zero' or 'copy', got {first_frame!r}")
    if not feet:
        return np.zeros((positions.shape[0], 0), dtype=np.float32)
    p = positions[:, list(feet)]
    speed = np.linalg.norm(p[1:] - p[:-1], axis=-1)
    labels = (speed < threshold).astype(np.float32)
    first = labels[:1] if first_frame == "copy" else np.zeros_like(labels[:1])
    if labels.shape[0] == 0:  # a single frame
        first = np.zeros((1, len(feet)), dtype=np.float32)
    return np.concatenate([first, labels], axis=0)


# ------------------------------------------------------------------------------------------- features


def motion_to_features(rotations: Tensor, root_positions: Tensor, contacts: Tensor | None = None,
                       sixd: str = "rows") -> Tensor:
    """``rotations (T,J,4)`` unit quats, ``root_positions (T,3)``, ``contacts (T,C)`` -> ``(6, J+1+C, T)``;
    ``sixd``: 6D from the first two ``"rows"`` or ``"columns"`` of each rotation matrix."""
    T, J = rotations.shape[:2]
    rot6 = quat_to_6d(rotations.to(torch.float32), layout=sixd)  # (T, J, 6)
    root = root_positions.to(torch.float32)
    vel = torch.zeros(T, K)
    if T > 1:
        d = root[1:] - root[:-1]
        vel[1:, 0], vel[1:, 2] = d[:, 0], d[:, 2]
        vel[0, 0], vel[0, 2] = d[0, 0], d[0, 2]
    vel[:, 1] = root[:, 1]
    parts = [rot6, vel[:, None]]
    if contacts is not None and contacts.shape[1] > 0:
        c = torch.zeros(T, contacts.shape[1], K)
        c[..., 0] = contacts.to(torch.float32)
        parts.append(c)
    return torch.cat(parts, dim=1).permute(2, 1, 0).contiguous()


def integrate_root(features: Tensor, n_joints: int, root_start: Tensor | None = None) -> Tensor:
    """Root positions ``(..., T, 3)`` from the root-motion entity (cumulative horizontal displacement)."""
    rm = features[..., :, n_joints, :]  # (..., 6, T)
    dx, y, dz = rm[..., 0, :], rm[..., 1, :], rm[..., 2, :]
    sx = torch.cumsum(dx, dim=-1) - dx[..., :1]
    sz = torch.cumsum(dz, dim=-1) - dz[..., :1]
    if root_start is not None:
        sx = sx + root_start[0]
        sz = sz + root_start[2]
    return torch.stack([sx, y, sz], dim=-1)


def features_to_motion(features: Tensor, n_joints: int, root_start: Tensor | None = None, sixd: str = "rows"
                       ) -> tuple[Tensor, Tensor, Tensor]:
    """``(..., 6, E, T)`` -> local quats ``(..., T, J, 4)``, root positions ``(..., T, 3)``, contact logits
    ``(..., T, C)`` (raw label channel). ``sixd``: the features' 6D layout (``Sequence.sixd``)."""
    rot6 = features[..., :, :n_joints, :]  # (..., 6, J, T)
    rot6 = rot6.movedim(-3, -1).movedim(-3, -2)  # (..., T, J, 6)
    quats = sixd_to_quat(rot6, layout=sixd)
    root = integrate_root(features, n_joints, root_start)
    contacts = features[..., 0, n_joints + 1:, :].transpose(-1, -2)
    return quats, root, contacts


# ------------------------------------------------------------------------------------------- resampling


def resample(x: Tensor, length: int, ratio: float) -> Tensor:
    """Linear resampling along the last axis on a *fixed* grid: output frame ``i`` reads input position
    ``(i + 0.5) * ratio - 0.5`` (clamped to the input), where ``ratio`` = input rate / output rate.

    With ``ratio = L_in / L_out`` this is ``F.interpolate(mode='linear', align_corners=False)``; with a ratio that
    does not depend on the lengths, a prefix of the input always maps to the same prefix of the output.
    """
    L_in = x.shape[-1]
    if L_in == 0:
        raise ValueError("resample: empty input")
    if type(x) is not torch.Tensor or torch.compiler.is_compiling():
        # traced (ONNX export, torch.compile): built afresh as ops of the trace, its sizes left symbolic -- a grid
        # made under a fake mode must never reach the cache, nor a cached one a trace
        lo, hi, w, w1 = _resample_grid.__wrapped__(length, ratio, L_in, x.dtype, x.device)
    else:
        lo, hi, w, w1 = _resample_grid(int(length), float(ratio), int(L_in), x.dtype, x.device)
    return x.index_select(-1, lo) * w1 + x.index_select(-1, hi) * w


@functools.lru_cache(maxsize=256)
def _resample_grid(length: int, ratio: float, L_in: int, dtype: torch.dtype, device: torch.device
                   ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """resample's source frames and weights (lo, hi, w, 1 - w) for one (length, ratio, input length): a training
    run asks for the same few grids thousands of times (every level of every forward), and building one took a
    dozen small tensor ops, more than the resampling itself. Callers only read them. Made outside inference mode,
    so that a grid first built while sampling can be saved for a backward later."""
    with torch.inference_mode(False):
        pos = (torch.arange(length, dtype=torch.float64) + 0.5) * ratio - 0.5
        pos = pos.clamp(0.0, L_in - 1)
        lo = pos.floor().long()
        hi = (lo + 1).clamp(max=L_in - 1)
        w = (pos - lo.to(torch.float64)).to(dtype).to(device)
        return lo.to(device), hi.to(device), w, 1 - w


def resample_support(i: int, ratio: float, L_in: int | None = None) -> tuple[int, int]:
    """Input frames ``[lo, hi]`` that output frame ``i`` of :func:`resample` reads."""
    pos = max(0.0, (i + 0.5) * ratio - 0.5)
    lo = int(math.floor(pos))
    hi = lo + 1
    if L_in is not None:
        lo, hi = min(lo, L_in - 1), min(hi, L_in - 1)
    return lo, hi


def pyramid_lengths(n_frames: int, coarse_ratio: float = 0.2, scale_factor: float = 1.0 / 0.75) -> list[int]:
    """Frame counts of the levels, coarsest first (the authors' rule: ``int(n * ratio)``, then ``x scale`` until
    the sequence length, which is the last level)."""
    if n_frames < 2:
        raise UserError(f"a sequence needs at least 2 frames, got {n_frames}")
    lengths = [max(2, int(n_frames * coarse_ratio))]
    while lengths[-1] < n_frames:
        nxt = int(lengths[-1] * scale_factor)
        if nxt <= lengths[-1]:
            nxt = lengths[-1] + 1
        lengths.append(nxt)
    lengths[-1] = n_frames
    if len(lengths) > 1 and lengths[-2] >= n_frames:
        lengths.pop(-2)
    return lengths


MAX_FRAMES = 100_000  # the longest sequence a length search below looks at (the CLI's bound too)


def coarsest_needed(cfg) -> int:
    """Frames the coarsest pyramid level needs: its convolutions reflect-pad ``kernel_size // 2`` frames on each
    side, and reflect padding of p frames needs more than p frames."""
    return cfg.kernel_size // 2 + 1 if cfg.padding_mode == "reflect" else 1


def min_frames(cfg, coarsest_length) -> int:
    """The shortest sequence (training clip or output) whose coarsest pyramid level, ``coarsest_length(n)`` frames
    for ``n`` frames, is long enough for the convolutions of ``cfg``."""
    need = coarsest_needed(cfg)
    for n in range(2, MAX_FRAMES):
        if coarsest_length(n) >= need:
            return n
    return MAX_FRAMES


def min_training_frames(cfg) -> int:
    """The shortest training clip (after resampling) a run of ``cfg`` can learn from."""
    return min_frames(cfg, lambda n: pyramid_lengths(n, cfg.coarse_ratio, cfg.scale_factor)[0])


def check_training_length(clips: Seq["Sequence"], cfg) -> None:
    """``UserError`` naming the first clip too short for the pyramid of ``cfg``, and why."""
    need = coarsest_needed(cfg)
    n_min = min_training_frames(cfg)
    for c in clips:
        if c.n_frames < n_min:
            raise UserError(
                f"{c.name}: {c.n_frames} frames at {c.fps:g} fps (after resampling) is too short for GANimator: "
                f"it needs at least {n_min} frames, because the coarsest pyramid level (--coarse-ratio "
                f"{cfg.coarse_ratio:g} of the clip) must have {need} frames or more for the {cfg.kernel_size}-frame "
                f"convolutions' reflect padding of {need - 1} frames")


def level_lengths(n_frames: int, rates: Seq[float]) -> list[int]:
    """Lengths of every level for an ``n_frames`` output, given each level's rate relative to the finest."""
    return [max(1, math.ceil(n_frames * r - 1e-6)) for r in rates]


# ------------------------------------------------------------------------------------------- sequences


@dataclass
class Sequence:
    """One training clip in GANimator form (everything the model and the metrics need about it)."""

    name: str
    skeleton: Skeleton          # reduced, in working units
    feet: list[int]             # contact joints (indices into ``skeleton``)
    features: Tensor            # (6, E, T) float32
    root_start: Tensor          # (3,) root position of frame 0
    fps: float
    scale: float                # working units = file units * scale
    contact_threshold: float    # per-frame foot displacement counted as contact
    size: float                 # body size in working units (for scale-free comparisons)
    kept_joints: list[int] = field(default_factory=list)   # indices in the file's skeleton
    sixd: str = "rows"          # 6D layout of ``features`` ("rows" or "columns" of the rotation matrix)
    # the clip's own local rotations (T, J, 4) and root track (T, 3, working units) before the 6-D features round
    # them: constrained generation pastes these back so a kept joint is unchanged bit for bit (not checkpointed)
    source_rotations: Tensor | None = field(default=None, repr=False)
    source_root: Tensor | None = field(default=None, repr=False)

    @property
    def n_frames(self) -> int:
        return int(self.features.shape[-1])

    @property
    def n_joints(self) -> int:
        return self.skeleton.n_joints

    @property
    def n_entities(self) -> int:
        return int(self.features.shape[1])

    def rotations(self) -> Tensor:
        return features_to_motion(self.features, self.n_joints, sixd=self.sixd)[0]


@dataclass
class RawClip:
    """A BVH as rotations + root track (what GANimator needs of it)."""

    skeleton: Skeleton
    rotations: Tensor       # (T, J, 4) local unit quats
    root_positions: Tensor  # (T, 3)
    fps: float


def read_clip(path: str | Path, fold_root: bool = True) -> RawClip:
    """Parse a BVH into local quaternions and the root track through modi's one reader,
    :meth:`modi.data.motion.Motion.from_bvh` (one frame rate: ``Frame Time: 0.008333`` is 120 fps), keeping the
    declared OFFSETs of non-root joints (``translations="offsets"``: position channels of other joints are not
    used, as in the authors' loader), except Bandai's pattern, see :func:`modi.data.motion.fold_dummy_root`.
    ``fold_root=False`` reads that pattern as the authors' loader did: the static floor root's channels are the root
    track and its child stays at its OFFSET."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"BVH file not found: {p}")
    b = bvh_io.load(str(p))
    if b.n_frames < 1:
        raise UserError(f"{p}: the BVH has no frames")
    m = Motion.from_bvh(b, translations="offsets")
    if fold_root:
        return RawClip(m.skeleton, m.rotations, m.root_positions, m.fps)
    root = torch.from_numpy(np.ascontiguousarray(b.local_translations()[:, 0]))  # joint 0's own channels
    return RawClip(b.skeleton(), m.rotations, root.to(m.rotations.dtype), m.fps)


def subset_clip(clip: RawClip, keep: list[int]) -> RawClip:
    """Keep joints ``keep`` (sorted). Dropping whole subtrees is a selection; dropping inner joints needs
    rotations composed into their kept children (``modi.data.motion.Motion.subset``)."""
    keep = sorted(keep)
    kept = set(keep)
    s = clip.skeleton
    if all(s.parents[j] in kept for j in keep if j > 0):
        remap = {old: new for new, old in enumerate(keep)}
        sk = Skeleton([s.names[j] for j in keep], [-1 if j == 0 else remap[s.parents[j]] for j in keep],
                      s.offsets[keep], {remap[k]: v for k, v in s.end_sites.items() if k in remap},
                      [s.rotation_orders[j] for j in keep] if s.rotation_orders else None)
        return RawClip(sk, clip.rotations[:, keep], clip.root_positions, clip.fps)

    m = Motion(s, clip.rotations, clip.root_positions, clip.fps).subset(keep)
    return RawClip(m.skeleton, m.rotations, m.root_positions, m.fps)


def _fps_stride(fps: float, target: float | None) -> int:
    if not target:
        return 1
    return max(1, int(round(fps / target)))


def _scale_for(size: float) -> float:
    """A power of ten that brings the body to about a metre or two (cm and inch rigs become metre-like), so the
    root track and the 6D rotations have comparable magnitudes (the authors scaled centimetre rigs by 1/100)."""
    if size <= 0:
        return 1.0
    return float(10.0 ** (-round(math.log10(size / 1.5))))


def load_sequence(path: str | Path, cfg=None, *, keep_joints: Seq[str] | None = None, feet: Seq[str] | None = None,
                  like: Sequence | None = None) -> Sequence:
    """Load a BVH as a GANimator :class:`Sequence`.

    ``like``: another sequence whose joints, feet, units and contact threshold are reused (mixing several clips
    of one character, or reading a content / key-frame / trajectory file for a trained model). Joints are then
    matched by name (namespaces ignored), so a reduced export of the same rig also works.
    """
    return sequence_from_clip(read_clip(path), Path(path).stem, cfg, keep_joints=keep_joints, feet=feet, like=like,
                              where=str(path))


def sequence_from_clip(motion: RawClip, name: str, cfg=None, *, keep_joints: Seq[str] | None = None,
                       feet: Seq[str] | None = None, like: Sequence | None = None, where: str = "") -> Sequence:
    """:func:`load_sequence` for a clip already in memory (rotations + root track)."""
    cfg = cfg or GanimatorConfig()
    path = where or name
    skel = motion.skeleton
    names = [strip_namespace(n) for n in skel.names]
    if like is not None:
        want = [strip_namespace(n) for n in like.skeleton.names]
        missing = [n for n in want if n not in names]
        if missing:
            raise UserError(f"{path}: joints {', '.join(missing[:5])} of the model's skeleton are missing")
        kept = [names.index(n) for n in want]
    else:
        keep = keep_joints if keep_joints is not None else cfg.keep_joints
        if keep is not None:
            kept = reduce_joints(skel, keep)
        elif cfg.joint_reduction:
            kept = reduce_joints(skel)
        else:
            kept = list(range(skel.n_joints))
    order = sorted(kept)
    if order != list(range(skel.n_joints)):
        motion = subset_clip(motion, order)
    if like is not None and order != kept:
        motion = _permute_clip(motion, [order.index(k) for k in kept])
    stride = _fps_stride(motion.fps, cfg.fps)
    rot_source = motion.rotations[::stride]
    rot = rot_source.to(torch.float32)
    root = motion.root_positions[::stride].to(torch.float64)
    fps = motion.fps / stride
    skel = motion.skeleton
    skel = Skeleton([strip_namespace(n) for n in skel.names], list(skel.parents), np.array(skel.offsets),
                    dict(skel.end_sites), list(skel.rotation_orders) if skel.rotation_orders else None)
    if like is not None:
        # bring this file to the model's units by comparing rest-pose bone lengths
        mine = np.linalg.norm(skel.offsets[1:], axis=1).sum()
        theirs = np.linalg.norm(like.skeleton.offsets[1:], axis=1).sum()
        scale = float(theirs / mine) if mine > 0 else 1.0
        skel = Skeleton(skel.names, skel.parents, like.skeleton.offsets.copy(), dict(like.skeleton.end_sites),
                        list(like.skeleton.rotation_orders))
    else:
        with torch.no_grad():
            raw_pos, _ = forward_kinematics(rot, torch.as_tensor(skel.offsets, dtype=torch.float32), skel.parents,
                                            root.to(torch.float32))
        scale = _scale_for(body_height(raw_pos.numpy()))
        skel = Skeleton(skel.names, skel.parents, skel.offsets * scale,
                        {k: np.asarray(v) * scale for k, v in skel.end_sites.items()}, skel.rotation_orders)
    root_source = root * scale
    root = root_source.to(torch.float32)
    with torch.no_grad():
        pos, _ = forward_kinematics(rot, torch.as_tensor(skel.offsets, dtype=torch.float32), skel.parents, root)
    pos_np = pos.numpy().astype(np.float64)
    if like is not None:
        foot_idx = list(like.feet)
        size = like.size
        threshold = like.contact_threshold
    else:
        size = body_height(pos_np)
        feet_names = feet if feet is not None else cfg.feet
        if feet_names is not None:
            foot_idx = []
            for f in feet_names:
                f = strip_namespace(f)
                if f not in skel.names:
                    raise UserError(f"feet: no joint named {f!r}; joints are {', '.join(skel.names)}")
                foot_idx.append(skel.names.index(f))
        elif cfg.contacts:
            foot_idx = detect_feet(skel, pos_np)
        else:
            foot_idx = []
        if not cfg.contacts:
            foot_idx = []
        threshold = cfg.contact_velocity * size * (30.0 / fps)
    labels = torch.from_numpy(contact_labels(pos_np, foot_idx, threshold, cfg.contact_first_frame))
    sixd = like.sixd if like is not None else cfg.sixd
    features = motion_to_features(rot, root, labels if foot_idx else None, sixd=sixd)
    return Sequence(name=name, skeleton=skel, feet=foot_idx, features=features, root_start=root[0].clone(),
                    fps=fps, scale=scale, contact_threshold=threshold, size=size, kept_joints=kept, sixd=sixd,
                    source_rotations=rot_source, source_root=root_source)


def _permute_clip(clip: RawClip, perm: list[int]) -> RawClip:
    """Reorder joints (a file listing the model's joints in another topological order)."""
    skel = clip.skeleton
    inv = {old: new for new, old in enumerate(perm)}
    parents = [-1 if skel.parents[o] < 0 else inv[skel.parents[o]] for o in perm]
    if perm[0] != 0 or any(p >= j for j, p in enumerate(parents) if p >= 0):
        raise UserError("the joint order of the file cannot be matched to the model's skeleton")
    s = Skeleton([skel.names[o] for o in perm], parents, skel.offsets[perm],
                 {inv[k]: v for k, v in skel.end_sites.items() if k in inv},
                 [skel.rotation_orders[o] for o in perm] if skel.rotation_orders else None)
    return RawClip(s, clip.rotations[:, perm], clip.root_positions, clip.fps)


def check_compatible(seqs: Seq[Sequence]) -> None:
    """Mixing needs one skeleton: same joint names, parents and feet."""
    a = seqs[0]
    for b in seqs[1:]:
        if b.skeleton.names != a.skeleton.names or b.skeleton.parents != a.skeleton.parents or b.feet != a.feet:
            raise UserError(f"cannot mix {a.name} and {b.name}: different skeletons or feet")


def load_sequences(paths: Seq[str | Path], cfg=None) -> list[Sequence]:
    """Several clips of one character (motion mixing): the first defines joints, feet and units."""
    if not paths:
        raise UserError("no BVH files given")
    first = load_sequence(paths[0], cfg)
    out = [first]
    for p in paths[1:]:
        out.append(load_sequence(p, cfg, like=first))
    check_compatible(out)
    return out


def sequence_pyramid(seqs: Seq[Sequence], cfg) -> tuple[list[list[int]], list[list[float]]]:
    """Per-sequence level lengths (coarsest first), all with the same number of levels (the shortest sequence's;
    longer ones drop their coarsest levels, as the authors do), and each level's rate relative to its finest."""
    all_lengths = [pyramid_lengths(s.n_frames, cfg.coarse_ratio, cfg.scale_factor) for s in seqs]
    n = min(len(l) for l in all_lengths)
    if cfg.max_levels is not None:
        n = min(n, int(cfg.max_levels))
    n_common = min(len(l) for l in all_lengths)
    all_lengths = [l[len(l) - n_common:][:n] for l in all_lengths]
    rates = [[x / l[-1] for x in l] for l in all_lengths]
    return all_lengths, rates


def real_pyramid(seq: Sequence, lengths: Seq[int]) -> list[Tensor]:
    """The training clip at every level (linear downsampling on the fixed grid)."""
    T = seq.n_frames
    return [resample(seq.features, L, T / L) if L != T else seq.features.clone() for L in lengths]
