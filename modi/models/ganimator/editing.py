"""Constrained generation from a trained GANimator: loops, in-betweens, expansion, body-part editing (the
applications of docs/single_clip.md; harmonisation is style transfer at a finer level, in ``generate.py``).

**Known content, blended at every level.** In-betweens, expansion and body-part editing all give some of the output
(frames, or joints) and ask the model for the rest. They share one mechanism: a *known* feature tensor and a mask
over (entity, frame). Every level of the pyramid is generated as usual and then blended with the known content
brought to that level's grid (the mask resampled the same way), so each finer generator sees the constraint in its
input and fills in around it. The finest level takes the known frames exactly, and the generated frames beside a
given span are moved by the span's edge offset, fading over a few frames, so the generated side eases into it. The decoded motion then gets the given
rotations pasted back, because the 6-D round trip is not exact to the bit.
Why not key-frame editing's coarse-level replacement: it pins only the coarsest grid, and the finer residuals then
move every frame again. Why not optimising the noise: that costs an optimisation per motion and still pins no frame
exactly.

**The loop runs every level on a circle.** Each level's input is padded with its own other end, by the generator's
receptive radius, and levels are upsampled circularly. So the last frame is followed by the first exactly as any
frame by its neighbour: no frame is blended or cut, and the seam is as smooth as the model's motion anywhere else.
One detail makes that true: linear upsampling makes a frame's step larger or smaller by where it falls between
the coarser level's frames, and on the fixed grids every level's frame 0 falls at the same place, which would put
the roughest step of all at the seam (1.9x the mean step, measured on white noise through a 6-level pyramid). The
circular grids are moved by half a coarse frame (``LOOP_PHASE``), which spreads that alignment around the circle
(the seam then 0.9x the mean step, and no place above 1.5x).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence as Seq

import torch
from torch import Tensor

from modi.errors import UserError
from modi.models.ganimator.data import K, load_sequence, min_frames, resample
from modi.models.ganimator.data import Sequence as Clip
from modi.models.ganimator.networks import GanimatorModel

LOOP_ROOT = ("travel", "return")
FEATHER = 8  # finest-level frames over which a generated side eases into given frames
LOOP_PHASE = 0.5  # coarse frames by which a loop's circular upsampling grids are moved (see the module docstring)


# ------------------------------------------------------------------------------------------- inputs


def load_clip(model: GanimatorModel, spec: str | Path, what: str) -> Clip:
    """A BVH on the run's rig; ``PATH@F`` takes frame ``F`` of it as a pose (``@-1``: the last frame).

    ``what`` names the option in errors (``--inbetween``...)."""
    path, frame = Path(spec), None
    if not path.is_file() and "@" in str(spec):
        head, _, tail = str(spec).rpartition("@")
        try:
            frame = int(tail)
        except ValueError:
            frame = None
        else:
            path = Path(head)
    if not path.is_file():
        raise UserError(f"{what} {spec}: no such BVH file")
    clip = load_sequence(path, model.cfg, like=model.seqs[0])
    if frame is None:
        return clip
    T = clip.n_frames
    if not -T <= frame < T:
        raise UserError(f"{what} {spec}: frame {frame} is outside the clip (frames 0..{T - 1} at {clip.fps:g} fps, "
                        "after resampling)")
    return take_frames(clip, frame % T, frame % T + 1)


def take_frames(clip: Clip, a: int, b: int) -> Clip:
    """Frames ``[a, b)`` of a clip as a clip of its own."""
    out = Clip(**{**clip.__dict__})
    out.features = clip.features[..., a:b].clone()
    out.source_rotations = clip.source_rotations[a:b] if clip.source_rotations is not None else None
    out.source_root = clip.source_root[a:b] if clip.source_root is not None else None
    out.root_start = (clip.source_root[a] if clip.source_root is not None else clip.root_start).to(torch.float32)
    return out


def _unconditional(model: GanimatorModel, what: str) -> None:
    if model.cond_entities:
        raise UserError(f"{what} needs an unconditional run; this one is trajectory-conditioned")


def min_output_frames(model: GanimatorModel) -> int:
    """Shortest output length whose coarsest level is long enough for the model's convolutions."""
    return min_frames(model.cfg, lambda n: model.level_lengths(n)[0])


# ------------------------------------------------------------------------------------------- the loop


def circular_resample(x: Tensor, length: int, phase: float = 0.0) -> Tensor:
    """Linear resampling of a periodic signal along the last axis (the grid of :func:`resample` with
    ``ratio = L_in / length``, read modulo ``L_in``), its samples moved by ``phase`` input frames."""
    L_in = x.shape[-1]
    pos = (torch.arange(length, dtype=torch.float64) + 0.5) * (L_in / length) - 0.5 + phase
    lo = pos.floor()
    w = (pos - lo).to(x.dtype).to(x.device)
    lo = lo.long() % L_in
    hi = (lo + 1) % L_in
    return x.index_select(-1, lo.to(x.device)) * (1 - w) + x.index_select(-1, hi.to(x.device)) * w


def wrap_pad(x: Tensor, r: int) -> Tensor:
    """``x`` with ``r`` frames of its other end on each side (any ``r``, also beyond one period)."""
    L = x.shape[-1]
    idx = torch.arange(-r, L + r, device=x.device) % L
    return x.index_select(-1, idx)


@torch.no_grad()
def loop_features(model: GanimatorModel, n_frames: int, *, root: str = "travel",
                  generator: torch.Generator | None = None, fine_noise: bool = False) -> Tensor:
    """A motion ``(1, 6, E, n_frames)`` whose frame ``n_frames - 1`` leads into frame 0 as any frame into the next.

    ``root="travel"``: each repetition moves on by the loop's own displacement (a walk cycle walks on);
    ``"return"``: the horizontal displacement is evened out to sum to zero, so the root returns to its start."""
    _unconditional(model, "--loop")
    if root not in LOOP_ROOT:
        raise UserError(f"loop root must be one of {', '.join(LOOP_ROOT)}, got {root!r}")
    n_min = min_output_frames(model)
    if n_frames < n_min:
        raise UserError(f"--loop with --frames {n_frames}: a loop needs at least {n_min} frames on this run (its "
                        "coarsest level must hold the convolutions' support)")
    lengths = model.level_lengths(n_frames)
    noises = model.random_noises(lengths, 1, 0, fine_noise, generator)
    R = model.gens[0].receptive_radius
    E = model.n_entities
    prev = None
    for l, L in enumerate(lengths):
        base = torch.zeros(1, K, E, L, device=model.device) if l == 0 else circular_resample(prev, L, LOOP_PHASE)
        z = noises[l]
        x = base if z is None else base + z
        prev = model.gens[l](wrap_pad(x, R), wrap_pad(base, R), None)[..., R:R + L] + base
    if root == "return":
        J = model.n_joints
        prev = prev.clone()
        for c in (0, 2):  # dx, dz of the root-motion entity
            prev[:, c, J] -= prev[:, c, J].mean(dim=-1, keepdim=True)
    return prev


# ------------------------------------------------------------------------------------------- known content


@dataclass
class Constraint:
    """What a constrained motion must contain: features ``(6, E, T)`` and a mask ``(E, T)`` in [0, 1] on the
    model's grid, plus the exact rotations and root positions to paste into the decoded motion."""

    known: Tensor
    mask: Tensor
    pieces: list[tuple[int, Clip]]  # (first output frame, clip) for every given frame span
    joints: list[int]               # the joints whose rotations are given (all joints for a frame span)
    root_given: bool                # whether the root track is given where the pieces lie

    @property
    def n_frames(self) -> int:
        return int(self.known.shape[-1])


def ease_in(out: Tensor, c: Constraint, frames: int) -> Tensor:
    """The finest level: given frames exact, and the generated frames next to a given span moved towards it by
    the span's edge offset (given - generated), fading out linearly over ``frames`` frames. An offset keeps the
    generated velocity where a cross-fade towards the edge pose would hold the pose still."""
    m = c.mask.to(out.device, out.dtype)
    k = c.known.to(out.device, out.dtype).unsqueeze(0)
    res = out * (1 - m) + k * m
    T = out.shape[-1]
    for at, clip in c.pieces:
        a, b = at, at + clip.n_frames  # the span [a, b)
        for edge, step in ((a, -1), (b - 1, 1)):
            off = (k[..., edge] - out[..., edge]) * m[:, edge]  # (1, 6, E): only the given entities
            for d in range(1, frames + 1):
                t = edge + step * d
                if not 0 <= t < T or bool(m[:, t].any() and (m[:, t] == m[:, edge]).all()):
                    break
                res[..., t] = res[..., t] + off * (1.0 - d / (frames + 1)) * (1 - m[:, t])
    return res


@torch.no_grad()
def constrained_features(model: GanimatorModel, c: Constraint, *, generator: torch.Generator | None = None,
                         fine_noise: bool = False, feather_frames: int = FEATHER) -> Tensor:
    """A motion ``(1, 6, E, T)`` holding ``c.known`` where ``c.mask`` is 1 and the model's motion elsewhere (see
    the module's docstring). At a coarser level a frame partly inside a given span mixes the two by the share
    of it that is given (the resampled mask)."""
    T = c.n_frames
    lengths = model.level_lengths(T)
    rates = model.rates[0]
    noises = model.random_noises(lengths, 1, 0, fine_noise, generator)
    known = c.known.to(model.device, torch.float32).unsqueeze(0)
    mask = c.mask.to(model.device, torch.float32)
    E = model.n_entities
    prev = None
    for l, L in enumerate(lengths):
        base = torch.zeros(1, K, E, L, device=model.device) if l == 0 else resample(prev, L, rates[l - 1] / rates[l])
        z = noises[l]
        x = base if z is None else base + z
        out = model.gens[l](x, base, None) + base
        if L == T:
            prev = ease_in(out, c, feather_frames)
        else:  # known is 0 outside the mask, so its resampling is already the mask-weighted given part
            prev = resample(known, L, T / L) + (1 - resample(mask, L, T / L)) * out
    return prev


def paste(c: Constraint, quats: Tensor, root: Tensor) -> tuple[Tensor, Tensor]:
    """The decoded motion (working units) with the given rotations (bit for bit) and root track put back; the root
    comes back in float64.

    Where the root is given, the generated frames between two given spans are moved by an offset that goes
    linearly from the one span's end to the other's start, so both join exactly; before the first span and after
    the last, by the constant offset that joins them."""
    q, r = quats.clone(), root.clone().to(torch.float64)
    g = r.clone()
    spans = []
    for at, clip in c.pieces:
        n = clip.n_frames
        q[at:at + n, c.joints] = clip.source_rotations[:, c.joints].to(q.dtype)
        if c.root_given:
            r[at:at + n] = clip.source_root.to(torch.float64)
            spans.append((at, at + n))
    if not spans:
        return q, r
    spans.sort()
    T = r.shape[0]
    a0 = spans[0][0]
    r[:a0] = g[:a0] + (r[a0] - g[a0])
    for (_, e), (b, _) in zip(spans, spans[1:]):
        if b > e:
            off_a, off_b = r[e - 1] - g[e - 1], r[b] - g[b]
            s = torch.arange(1, b - e + 1, dtype=torch.float64)[:, None] / (b - e + 1)
            r[e:b] = g[e:b] + off_a * (1 - s) + off_b * s
    e_last = spans[-1][1]
    if e_last < T:
        r[e_last:] = g[e_last:] + (r[e_last - 1] - g[e_last - 1])
    return q, r


def _frames_constraint(model: GanimatorModel, T: int, pieces: list[tuple[int, Clip]]) -> Constraint:
    E = model.n_entities
    known = torch.zeros(K, E, T)
    mask = torch.zeros(E, T)
    for at, clip in pieces:
        n = clip.n_frames
        known[..., at:at + n] = clip.features
        mask[:, at:at + n] = 1.0
    return Constraint(known, mask, pieces, list(range(model.n_joints)), True)


def inbetween_constraint(model: GanimatorModel, start: Clip, end: Clip, frames: int) -> Constraint:
    """``start``, then ``frames`` generated frames, then ``end``; both clips keep their positions in the scene."""
    _unconditional(model, "--inbetween")
    if frames < 1:
        raise UserError(f"--inbetween needs --frames of at least 1 (the frames to generate between the two), got "
                        f"{frames}")
    T = start.n_frames + frames + end.n_frames
    n_min = min_output_frames(model)
    if T < n_min:
        raise UserError(f"--inbetween: {start.n_frames} + {frames} + {end.n_frames} frames is too short for this run: "
                        f"the whole motion needs at least {n_min} frames; ask for at least "
                        f"{n_min - start.n_frames - end.n_frames} frames between")
    return _frames_constraint(model, T, [(0, start), (start.n_frames + frames, end)])


def expand_constraint(model: GanimatorModel, clip: Clip, frames: int, at: int | None = None) -> Constraint:
    """A ``frames``-frame motion holding ``clip`` unchanged from frame ``at`` (default: centred)."""
    _unconditional(model, "--expand")
    S = clip.n_frames
    if frames <= S:
        raise UserError(f"--expand: --frames {frames} must be longer than the clip ({S} frames at {clip.fps:g} fps)")
    n_min = min_output_frames(model)
    if frames < n_min:
        raise UserError(f"--expand: --frames {frames} is too short for this run: at least {n_min} frames")
    at = (frames - S) // 2 if at is None else int(at)
    if not 0 <= at <= frames - S:
        raise UserError(f"--at {at}: the clip's {S} frames must fit in the {frames} output frames (0 <= --at <= "
                        f"{frames - S})")
    return _frames_constraint(model, frames, [(at, clip)])


# ------------------------------------------------------------------------------------------- body parts


def _children(parents: Seq[int]) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[p].append(j)
    return kids


def _subtree(kids: list[list[int]], j: int) -> list[int]:
    out, stack = [], [j]
    while stack:
        k = stack.pop()
        out.append(k)
        stack.extend(kids[k])
    return sorted(out)


def body_halves(parents: Seq[int], feet: Seq[int], names: Seq[str]) -> tuple[list[int], list[int]]:
    """``(lower, upper)`` joints of a humanoid, found from the tree: from the root down its single-child chain to
    the first joint that branches (the hips); the branches holding a foot are the legs, the others the upper body.
    Lower = that chain + the legs. A tree with no such split (no feet, or every branch a leg) is refused."""
    kids = _children(parents)
    chain = [0]
    while len(kids[chain[-1]]) == 1:
        chain.append(kids[chain[-1]][0])
    foot = set(feet)
    legs, upper = [], []
    for c in kids[chain[-1]]:
        part = _subtree(kids, c)
        (legs if foot & set(part) else upper).extend(part)
    if not legs or not upper:
        raise UserError("'upper'/'lower' needs a humanoid (legs with feet and an upper body branching from the hips); "
                        f"name the joints to keep instead: {', '.join(names)}")
    return sorted(chain + legs), sorted(upper)


def kept_joints(model: GanimatorModel, keep: str | Seq[str]) -> list[int]:
    """Joint indices from ``upper``/``lower`` or joint names, checked against the rig."""
    seq = model.seqs[0]
    names = list(seq.skeleton.names)
    items = [k.strip() for k in (keep.split(",") if isinstance(keep, str) else keep) if k and k.strip()]
    if not items:
        raise UserError("--keep: give at least one joint to keep (a name, or upper / lower)")
    out: set[int] = set()
    for k in items:
        if k in ("upper", "lower"):
            lower, upper = body_halves(seq.skeleton.parents, seq.feet, names)
            out.update(lower if k == "lower" else upper)
        elif k in names:
            out.add(names.index(k))
        else:
            raise UserError(f"--keep: no joint named {k!r} on this run's rig; joints are {', '.join(names)} "
                            "(or upper / lower)")
    if len(out) == len(names):
        raise UserError("--keep: every joint is kept, so nothing is left to generate")
    return sorted(out)


def parts_constraint(model: GanimatorModel, clip: Clip, keep: str | Seq[str]) -> Constraint:
    """``clip``'s length, with the kept joints' rotations (and the root track, when the root joint is kept) as given
    and the other joints generated to go with them. Contact labels are always generated."""
    _unconditional(model, "--edit")
    joints = kept_joints(model, keep)
    T = clip.n_frames
    n_min = min_output_frames(model)
    if T < n_min:
        raise UserError(f"--edit: the clip's {T} frames are too short for this run: at least {n_min} frames")
    J, E = model.n_joints, model.n_entities
    ents = list(joints) + ([J] if 0 in joints else [])
    known = torch.zeros(K, E, T)
    mask = torch.zeros(E, T)
    known[:, ents] = clip.features[:, ents]
    mask[ents] = 1.0
    return Constraint(known, mask, [(0, clip)], joints, 0 in joints)


# ------------------------------------------------------------------------------------------- the command


def edit_features(model: GanimatorModel, n: int = 1, frames: int | None = None, seed: int = 0, *,
                  loop: bool = False, loop_root: str = "travel", inbetween: tuple | None = None,
                  expand: str | Path | None = None, at: int | None = None, edit: str | Path | None = None,
                  keep: str | Seq[str] | None = None, fine_noise: bool = False
                  ) -> tuple[list[Tensor], list[Constraint | None], Tensor | None, str]:
    """What ``modi ganimator generate --loop | --inbetween | --expand | --edit`` samples: ``(features (6, E, T) per
    motion, the constraint to paste per motion (None for a loop), root start or None, mode)``.

    Every input is read and checked before anything is generated. Motion ``i`` uses seed ``seed + i``.
    ``frames``: the loop's length, the frames between the two in-between clips, or the expanded length."""
    if n < 1:
        raise UserError("--n must be at least 1")
    if sum(bool(x) for x in (loop, inbetween, expand, edit)) != 1:
        raise UserError("use exactly one of --loop, --inbetween, --expand, --edit")
    if keep is not None and not edit:
        raise UserError("--keep goes with --edit CLIP")
    if at is not None and not expand:
        raise UserError("--at goes with --expand CLIP")
    seq = model.seqs[0]
    c: Constraint | None = None
    start = None
    if loop:
        T = frames or seq.n_frames
        out = [loop_features(model, T, root=loop_root, generator=torch.Generator().manual_seed(seed + i),
                             fine_noise=fine_noise)[0] for i in range(n)]
        return out, [None] * n, None, f"loop ({loop_root})"
    if inbetween:
        if len(inbetween) != 2:
            raise UserError("--inbetween takes two clips or poses: START END")
        if frames is None:
            raise UserError("--inbetween needs --frames: how many frames to generate between START and END")
        a, b = load_clip(model, inbetween[0], "--inbetween"), load_clip(model, inbetween[1], "--inbetween")
        c, mode = inbetween_constraint(model, a, b, frames), "in-between"
        start = a.root_start
    elif expand:
        clip = load_clip(model, expand, "--expand")
        if frames is None:
            raise UserError("--expand needs --frames: the length of the expanded motion")
        c, mode = expand_constraint(model, clip, frames, at), "expansion"
    else:
        if keep is None:
            raise UserError("--edit needs --keep: the joints to keep (names, or upper / lower)")
        clip = load_clip(model, edit, "--edit")
        c, mode = parts_constraint(model, clip, keep), "body-part editing"
        start = clip.root_start
    out = [constrained_features(model, c, generator=torch.Generator().manual_seed(seed + i),
                                fine_noise=fine_noise)[0] for i in range(n)]
    return out, [c] * n, start, mode


__all__ = ["edit_features", "LOOP_ROOT", "FEATHER", "min_output_frames", "load_clip", "take_frames", "circular_resample", "wrap_pad", "loop_features",
           "Constraint", "ease_in", "constrained_features", "paste", "inbetween_constraint", "expand_constraint",
           "body_halves", "kept_joints", "parts_constraint"]
