"""A run of the authors' released GANimator as a modi GANimator run (``modi import ganimator-released``).

What a user of the released code holds is its run folder: ``args.txt`` (the command line of their ``train.py``),
``gen000.pt`` ... (one generator ``state_dict`` per level: dense weights with their 0/1 skeleton masks),
``z_star.pt`` (the reconstruction noise, a list of tensors) and ``amps.pt`` (the noise amplitudes). Their
discriminators are not saved. The skeleton is not in those files either: it comes from the training BVH.

How the released code picks and orders the joints, and which joints carry contacts, is read back from the
checkpoint itself instead of from a table: the first layer's mask is the entity adjacency, so the joint order
is the depth-first order of the file's (reduced) skeleton whose neighbourhoods reproduce it, and each contact
entity is wired to exactly one joint, its foot. Units, frame stride and contact threshold are the candidates
whose data pyramid reproduces ``amps.pt`` (the amplitudes are a fingerprint of the training tensor). Anything that
does not match is refused with one line, never converted into a silently different model.

Layouts: the released tensor is ``(B, E*6, T)``, entities ``[joints, contacts, root motion]``, channel
``entity*C + c``; modi's is ``(B, 6, E, T)`` with entities ``[joints, root motion, contacts]``. ``perm[e]`` is the
released entity of modi entity ``e``; weights, biases, ``z*`` and features move with it.

Files are read with ``torch.load(weights_only=True)`` (``modi.io.safe_load``): data, never code.
"""
from __future__ import annotations

import dataclasses
import itertools
import re
import shlex
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor

from modi.core.joint_reduction import reduce_joints
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import quat_apply, quat_mul
from modi.core.skeleton import Skeleton, strip_namespace
from modi.errors import CheckpointError, UserError
from modi.interop.provenance import file_record, folder_record, record
from modi.io import bvh as bvh_io
from modi.io.safe_load import load_data
from modi.models.ganimator.config import GanimatorConfig
from modi.models.ganimator.data import (
    RawClip,
    _permute_clip,
    body_height,
    contact_labels,
    motion_to_features,
    pyramid_lengths,
    read_clip,
    real_pyramid,
    resample,
    sequence_pyramid,
    subset_clip,
)
from modi.models.ganimator.data import Sequence as Clip
from modi.models.ganimator.networks import EntityBias, ganimator_neighbors
from modi.models.ganimator.training import Trainer, blocks_of, checkpoint_path

ARGS_FILE = "args.txt"

# the released option defaults this import depends on (their option.py); args.txt overrides them
_DEFAULTS: dict[str, Any] = {
    "skeleton_aware": 1, "neighbour_dist": 2, "kernel_size": 5, "padding_mode": "reflect", "batch_norm": 0,
    "last_gen_active": "None", "use_velo": 1, "keep_y_pos": 1, "repr": "repr6d", "contact": 1,
    "enforce_contact": 1, "joint_reduction": 1, "ratio": "1./5", "scaling_rate": 1 / 0.75, "base_channel": -1,
    "n_layers": -1, "use_factor_channel_list": 0, "conditional_generator": 0, "full_noise": 0,
    "nearest_interpolation": 0, "multiple_sequences": 0, "num_stages_limit": -1, "full_zstar": 1,
    "bvh_prefix": "./data/", "bvh_name": "dance", "D_fact": 5, "G_fact": 1, "lr_g": 1e-4, "shared_lr": 1e-4,
    "num_iters": 15000, "lambda_gp": 1.0, "lambda_rec": 50.0, "lambda_consistency": 5.0, "group_size": 2,
    "gan_mode": "wgan-gp", "rec_loss_type": "L1", "no_noise": 0, "slerp": 0, "requires_noise_amp": 1,
    "correct_zstar_gen": 0,
}

# options whose other values give a model modi does not reproduce: (name, required value, what it is)
_REQUIRED = [("skeleton_aware", 1, "skeleton-aware convolutions"), ("repr", "repr6d", "6D rotations"),
             ("use_velo", 1, "root velocity"), ("keep_y_pos", 1, "absolute root height"),
             ("batch_norm", 0, "no batch norm"), ("last_gen_active", "None", "no output activation"),
             ("use_factor_channel_list", 0, "the default channel widths"), ("full_noise", 0, "shared noise"),
             ("nearest_interpolation", 0, "linear upsampling"), ("multiple_sequences", 0, "one training clip"),
             ("conditional_generator", 0, "an unconditional generator"), ("full_zstar", 1, "per-channel z*"),
             ("no_noise", 0, "noise"), ("slerp", 0, "linear resampling"),
             ("requires_noise_amp", 1, "data-derived noise amplitudes"),
             ("correct_zstar_gen", 0, "z* as saved (theirs rescales it after saving)")]


# ------------------------------------------------------------------------------------------- the run folder


def find_run(ckpt: str | Path) -> Path:
    """The released run folder: ``ckpt`` itself, or the folder of a file in it (``gen000.pt``, ``args.txt``)."""
    p = Path(ckpt)
    if not p.exists():
        raise UserError(f"{p}: no such released GANimator run or checkpoint file")
    run = p if p.is_dir() else p.parent
    missing = [n for n in (ARGS_FILE, "gen000.pt", "z_star.pt", "amps.pt") if not (run / n).is_file()]
    if missing:
        raise UserError(f"{run}: not a released GANimator run (missing {', '.join(missing)}; their train.py "
                        "writes args.txt, gen000.pt..., z_star.pt and amps.pt into --save_path)")
    return run


# their other options (option.py) that are numbers, typed as their parser types them (the rest are text)
_OTHER_TYPES: dict[str, Any] = {"debug": 0, "silent": 0, "no_gan": 0, "num_conditional_generator": 0, "lr_d": 0.0,
                                "detach_label": 0, "use_sigmoid": 0, "save_freq": 0, "use_6d_fk": 0}


def _typed(name: str, text: str) -> Any:
    d = _DEFAULTS.get(name, _OTHER_TYPES.get(name))
    try:
        if isinstance(d, bool) or isinstance(d, int):
            return int(text)
        if isinstance(d, float):
            return float(text)
    except ValueError:
        raise UserError(f"{ARGS_FILE}: --{name} {text!r} is not a number") from None
    return text


def stated_args(run: Path) -> dict[str, Any]:
    """The options ``args.txt`` states (its first line, as their loader reads it), typed as their parser types
    them; their defaults are not added."""
    try:
        line = (run / ARGS_FILE).read_text(encoding="utf-8", errors="replace").splitlines()[:1]
    except OSError as exc:
        raise UserError(f"{run / ARGS_FILE}: cannot read ({exc.strerror})") from None
    try:
        tokens = shlex.split(line[0]) if line else []
    except ValueError:
        tokens = line[0].split()
    args: dict[str, Any] = {}
    i = 0
    while i < len(tokens):
        tok = tokens[i]
        if not tok.startswith("--"):
            raise UserError(f"{run / ARGS_FILE}: unexpected {tok!r} (expected --option value)")
        if "=" in tok:
            name, value = tok[2:].split("=", 1)
            i += 1
        else:
            name = tok[2:]
            if i + 1 >= len(tokens):
                raise UserError(f"{run / ARGS_FILE}: --{name} has no value")
            value = tokens[i + 1]
            i += 2
        args[name] = _typed(name, value)
    return args


def read_args(run: Path) -> dict[str, Any]:
    """The options of their ``train.py``: ``args.txt`` over their defaults, checked for what modi imports."""
    args = {**_DEFAULTS, **stated_args(run)}
    for name, want, what in _REQUIRED:
        if args[name] != want:
            raise UserError(f"{run}: trained with --{name}={args[name]}; modi imports released runs with {what} "
                            f"(--{name}={want}) only")
    if args["shared_lr"] != 0:  # their option checker: a shared rate overrides both
        args["lr_g"] = args["shared_lr"]
    return args


def _fraction(text: str) -> float:
    """``--ratio`` as their option writes it (``1./5``), without evaluating it."""
    m = re.fullmatch(r"\s*([0-9.eE+-]+)\s*(?:/\s*([0-9.eE+-]+)\s*)?", str(text))
    if not m:
        raise UserError(f"{ARGS_FILE}: --ratio {text!r} is not a number or a fraction")
    num = float(m.group(1))
    den = float(m.group(2)) if m.group(2) else 1.0
    return num / den


def _load(path: Path, what: str) -> Any:
    return load_data(path, what, hint="; a released GANimator file holds tensors only")


def generator_files(run: Path) -> list[Path]:
    """``gen000.pt``, ``gen001.pt``, ... of the run (their loader also accepts ``gen0.pt``), coarsest first."""
    out = []
    for level in itertools.count():
        path = run / f"gen{level:03d}.pt"
        if not path.is_file():
            path = run / f"gen{level}.pt"
        if not path.is_file():
            return out
        out.append(path)
    return out


def read_generators(run: Path) -> list[dict[str, Tensor]]:
    """``gen000.pt``, ``gen001.pt``, ... (their loader also accepts ``gen0.pt``) as state dicts of tensors."""
    out = []
    for path in generator_files(run):
        sd = _load(path, "released GANimator generator")
        if not isinstance(sd, dict) or not all(isinstance(v, Tensor) for v in sd.values()):
            raise UserError(f"{path}: not a generator state_dict (expected a dict of tensors)")
        out.append(sd)
    return out


# ------------------------------------------------------------------------------------------- layouts


def entity_perm(n_joints: int, n_contacts: int) -> list[int]:
    """``perm[e]``: the released entity of modi entity ``e`` ([joints, root motion, contacts] -> [joints,
    contacts, root motion])."""
    J, C = n_joints, n_contacts
    return list(range(J)) + [J + C] + [J + k for k in range(C)]


def to_modi_layout(x: Tensor, perm: Sequence[int]) -> Tensor:
    """A released tensor ``(B, E*6, T)`` as modi's ``(B, 6, E, T)``."""
    B, CE, T = x.shape
    E = len(perm)
    return x.reshape(B, E, CE // E, T)[:, list(perm)].permute(0, 2, 1, 3).contiguous()


def to_released_layout(x: Tensor, perm: Sequence[int]) -> Tensor:
    """modi's ``(B, 6, E, T)`` as the released ``(B, E*6, T)``."""
    B, C, E, T = x.shape
    inv = [0] * E
    for e, r in enumerate(perm):
        inv[r] = e
    return x.permute(0, 2, 1, 3)[:, inv].reshape(B, E * C, T).contiguous()


def entity_adjacency(mask: Tensor, n_entities: int, where: str = "", binary: bool = True) -> np.ndarray:
    """``adj[out, in]`` of a released skeleton-conv mask ``(E*Co, E*Ci, U)``; each block must be all 0 or all 1
    (``binary=False``: all 0 or all non-zero; their discriminators' masks drift off 1 in training, see
    ``benchmarks/peers/released_ganimator.py``)."""
    E = n_entities
    Co, Ci, U = mask.shape[0] // E, mask.shape[1] // E, mask.shape[2]
    if Co * E != mask.shape[0] or Ci * E != mask.shape[1]:
        raise UserError(f"{where}: mask {tuple(mask.shape)} is not split over {E} entities")
    blocks = mask.detach().to(torch.float64).reshape(E, Co, E, Ci, U)
    if not binary:
        blocks = (blocks != 0).to(torch.float64)
    lo, hi = blocks.amin(dim=(1, 3, 4)), blocks.amax(dim=(1, 3, 4))
    bad = (lo != hi) | ((hi != 0) & (hi != 1))
    if bool(bad.any()):
        r, c = [int(v) for v in bad.nonzero()[0]]
        raise UserError(f"{where}: mask block (entity {r}, entity {c}) is not a 0/1 skeleton mask")
    return (hi == 1).numpy()


# ------------------------------------------------------------------------------------------- skeleton


def _preorders(parents: Sequence[int], subset: Sequence[int], limit: int = 720) -> list[list[int]]:
    """Depth-first orders of the ``subset`` tree: the file's order first, then its root's children permuted
    (their rig tables list e.g. a Mixamo character's legs before its spine)."""
    kept = set(subset)
    children: dict[int, list[int]] = {j: [] for j in subset}
    for j in subset:
        if j != subset[0]:
            children[parents[j]].append(j)

    def walk(j: int, first: list[int] | None = None) -> list[int]:
        out = [j]
        for c in (first if first is not None else children[j]):
            out += walk(c)
        return out

    root = subset[0]
    if any(parents[j] not in kept for j in subset if j != root):
        return []
    orders = []
    for perm in itertools.islice(itertools.permutations(children[root]), limit):
        orders.append(walk(root, list(perm)))
    return orders


def _released_neighbours(parents: Sequence[int], feet: Sequence[int], distance: int) -> list[set[int]]:
    """The neighbourhoods modi builds (``ganimator_neighbors``) in the released entity order."""
    J, C = len(parents), len(feet)
    perm = entity_perm(J, C)
    nb = ganimator_neighbors(list(parents), list(feet), distance)
    out: list[set[int]] = [set() for _ in perm]
    for e, n in enumerate(nb):
        out[perm[e]] = {perm[x] for x in n}
    return out


def joint_subsets(parents: Sequence[int], bases: Sequence[Sequence[int]], max_drop: int = 3
                  ) -> Iterator[list[int]]:
    """Candidate joint sets: each base (modi's reduction, every joint), then each base without 1..``max_drop`` of
    its leaves (their rig tables also leave out e.g. a Mixamo character's eyes)."""
    for base in bases:
        yield sorted(base)
    for k in range(1, max_drop + 1):
        for base in bases:
            kept = set(base)
            leaves = [j for j in sorted(base) if j != min(base) and not any(parents[c] == j for c in kept)]
            for drop in itertools.combinations(leaves, k):
                yield sorted(kept - set(drop))


def match_skeleton(parents: Sequence[int], adj: np.ndarray, distance: int, candidates: Iterable[Sequence[int]]
                   ) -> tuple[list[int], list[int]]:
    """(joint order as file indices, feet as indices into that order) reproducing the mask adjacency ``adj``."""
    E = adj.shape[0]
    tried = set()
    for subset in candidates:
        J = len(subset)
        C = E - 1 - J
        tried.add(J)
        if C < 0 or not all(int(adj[:J, J + k].sum()) == 1 for k in range(C)):
            continue
        for order in _preorders(parents, sorted(subset)):
            pos = {j: i for i, j in enumerate(order)}
            par = [-1] + [pos[parents[j]] for j in order[1:]]
            feet = []
            for k in range(C):
                rows = [j for j in range(J) if adj[j, J + k]]
                if len(rows) != 1:
                    break
                feet.append(rows[0])
            if len(feet) != C:
                continue
            want = _released_neighbours(par, feet, distance)
            if all(set(np.nonzero(adj[e])[0].tolist()) == want[e] for e in range(E)):
                return list(order), feet
    raise UserError(f"the BVH's skeleton does not match the checkpoint: its masks connect {E} entities (joints, "
                    f"contacts, root motion), and no depth-first order of the BVH's joints (sets of "
                    f"{', '.join(map(str, sorted(tried)))} joints) reproduces them; pass the BVH the model was "
                    "trained on")


# ------------------------------------------------------------------------------------------- data


def released_stride(fps: float) -> int:
    """Their loader halves the frame rate while a frame lasts under ~1/120 s, then ~1/60 s: 120 fps -> 30."""
    ft, stride = 1.0 / fps, 1
    for limit in (0.0084, 0.017):
        if ft < limit:
            ft, stride = ft * 2, stride * 2
    return stride


def _amplitudes(clip: Any, lengths: Sequence[int]) -> list[float]:
    """Each level's noise amplitude as their ``train.py`` sets it: the RMS of what upsampling the coarser real
    level misses (of the whole level at level 0)."""
    reals = real_pyramid(clip, lengths)
    out = []
    for i, r in enumerate(reals):
        prev = torch.zeros_like(r) if i == 0 else resample(reals[i - 1], lengths[i], lengths[i - 1] / lengths[i])
        out.append(float(((r - prev) ** 2).mean().sqrt()))
    return out


def floor_root(raw: Any) -> bool:
    """Whether the file's joint 0 is a static floor root above one joint (Bandai's ``joint_Root`` above ``Hips``):
    constant position channels and rotation, one child."""
    s = raw.skeleton
    if sum(1 for p in s.parents if p == 0) != 1 or raw.rotations.shape[0] < 2:
        return False
    root, rot = raw.root_positions.to(torch.float64), raw.rotations[:, 0].to(torch.float64)
    size = float(np.ptp(s.rest_positions(), axis=0).max()) or 1.0
    return bool((root - root[0]).abs().max() <= 1e-9 * size and (rot - rot[0]).abs().max() <= 1e-9)


def their_reading(raw: Any, order: Sequence[int]) -> Any:
    """The clip of ``raw`` (read with ``fold_root=False``) on the joints ``order`` (file indices) as their loader
    (``BVH_file``) makes it: the root track is always the file's joint-0 position channels, every other joint sits
    at its OFFSET. Where the order keeps joint 0 that is modi's subset; where it starts below it (a table that
    leaves out a static floor root such as Bandai's ``joint_Root``), the first kept joint is placed on that track
    with its own local rotation, as their forward kinematics does."""
    if order[0] == 0:
        srt = sorted(order)
        return _permute_clip(subset_clip(raw, srt), [srt.index(j) for j in order])
    s = raw.skeleton
    pos = {j: i for i, j in enumerate(order)}
    if any(s.parents[j] not in pos for j in order[1:]):
        raise UserError("the joint order of the file cannot be matched to the model's skeleton")
    sk = Skeleton([s.names[j] for j in order], [-1] + [pos[s.parents[j]] for j in order[1:]], s.offsets[list(order)],
                  {pos[k]: v for k, v in s.end_sites.items() if k in pos},
                  [s.rotation_orders[j] for j in order] if s.rotation_orders else None)
    return RawClip(sk, raw.rotations[:, list(order)], raw.root_positions, raw.fps)


def _build(bvh: Path, order: Sequence[int], feet: Sequence[int], scale: float, threshold: float, raw: Any
           ) -> tuple[Any, np.ndarray, float]:
    """(clip, each contact label's foot speed ``(T-1, C)``, the largest coordinate) of :func:`build_clip`."""
    clip = their_reading(raw, order)
    stride = released_stride(raw.fps)
    rot = clip.rotations[::stride].to(torch.float32)
    root = (clip.root_positions[::stride].to(torch.float64) * scale).to(torch.float32)
    sk = clip.skeleton
    skel = Skeleton([strip_namespace(n) for n in sk.names], list(sk.parents), np.asarray(sk.offsets) * scale,
                    {k: np.asarray(v) * scale for k, v in sk.end_sites.items()},
                    list(sk.rotation_orders) if sk.rotation_orders else None)
    offsets = torch.as_tensor(skel.offsets, dtype=torch.float32)
    with torch.no_grad():
        pos, _ = forward_kinematics(rot, offsets, skel.parents, root)
        if order[0] != 0:
            # their table's first joint keeps the left-out floor root as its parent, and their forward kinematics
            # then takes it for its own parent: its rotation applies twice and it sits at twice its rotated OFFSET
            # (not on the root track). Their contact labels come from those positions.
            twice = rot.clone()
            twice[:, 0] = quat_mul(rot[:, 0], rot[:, 0])
            lab_pos, _ = forward_kinematics(twice, offsets, skel.parents, 2 * quat_apply(rot[:, 0], offsets[0]))
        else:
            lab_pos = pos
    pos_np = pos.numpy().astype(np.float64)
    lab_np = lab_pos.numpy().astype(np.float64)
    labels = torch.from_numpy(contact_labels(lab_np, list(feet), threshold, "zero"))
    features = motion_to_features(rot, root, labels if feet else None, sixd="rows")
    p = lab_np[:, list(feet)]
    speed = np.linalg.norm(p[1:] - p[:-1], axis=-1)
    out = Clip(name=bvh.stem, skeleton=skel, feet=list(feet), features=features, root_start=root[0].clone(),
               fps=raw.fps / stride, scale=float(scale), contact_threshold=float(threshold),
               size=body_height(pos_np), kept_joints=list(order), sixd="rows")
    return out, speed, float(np.abs(lab_np).max())


def build_clip(bvh: Path, order: Sequence[int], feet: Sequence[int], scale: float, threshold: float,
               raw: Any = None) -> Any:
    """The training clip as the released loader makes it (joints in ``order``, stride, ``scale``, labels);
    ``raw``: the BVH already read (``read_clip(bvh, fold_root=False)``)."""
    return _build(bvh, order, feet, scale, threshold, read_clip(bvh, fold_root=False) if raw is None else raw)[0]


# units and per-frame contact thresholds their loader can produce (centimetre rigs / 100, one data set x 0.14)
SCALES = (1.0, 0.01, 0.14, 0.0014)
THRESHOLDS = (0.018, 0.006)
EXACT = 1e-5      # amplitudes this close: the same tensor (float32 sums in another order)
ACCEPT = 1e-3     # the most an import tolerates
ROUNDING = 8.0    # a label is rounding-ambiguous within this many float32 ulps of the largest coordinate
MAX_FLIPS = 10    # the most rounding-ambiguous labels searched (2**MAX_FLIPS label sets at most)


def _amp_error(mine: Sequence[float], amps: Sequence[float]) -> tuple[float, int]:
    """(largest relative difference, its level)."""
    errs = [abs(a - b) / max(abs(b), 1e-12) for a, b in zip(mine, amps)]
    level = int(np.argmax(errs))
    return errs[level], level


def ambiguous_labels(speed: np.ndarray, threshold: float, magnitude: float) -> list[tuple[int, int]]:
    """(frame, contact) of every label whose foot speed is within float32 rounding of ``threshold`` (their loader
    computes positions in float32: a speed this close to the threshold may fall on either side of it there),
    closest first. ``magnitude``: the largest coordinate (rounding scales with it)."""
    band = ROUNDING * float(np.finfo(np.float32).eps) * magnitude
    near = np.argwhere(np.abs(speed - threshold) <= band)
    order = np.argsort(np.abs(speed[near[:, 0], near[:, 1]] - threshold), kind="stable")
    return [(int(near[i, 0]) + 1, int(near[i, 1])) for i in order]  # label t+1 is the speed from t to t+1


def _flipped(clip: Any, flips: Sequence[tuple[int, int]]) -> Any:
    f = clip.features.clone()
    base = clip.n_joints + 1
    for t, k in flips:
        f[0, base + k, t] = 1.0 - f[0, base + k, t]
    return dataclasses.replace(clip, features=f)


def settle_labels(clip: Any, speed: np.ndarray, magnitude: float, lengths: Sequence[int], amps: Sequence[float]
                  ) -> tuple[Any, list[tuple[int, int]], float, int]:
    """The labels their loader computed where rounding could put a foot speed on either side of the threshold:
    the set of flips of those labels (fewest first) whose pyramid reproduces ``amps`` exactly. Returns (clip,
    flips, amplitude error, number of ambiguous labels); the clip unchanged when no flip set does better."""
    near = ambiguous_labels(speed, clip.contact_threshold, magnitude)
    best = (clip, [], _amp_error(_amplitudes(clip, lengths), amps)[0])
    for n in range(1, min(len(near), MAX_FLIPS) + 1):
        for flips in itertools.combinations(near[:MAX_FLIPS], n):
            cand = _flipped(clip, flips)
            err = _amp_error(_amplitudes(cand, lengths), amps)[0]
            if err < best[2]:
                best = (cand, list(flips), err)
            if err <= EXACT:
                return cand, list(flips), err, len(near)
    return best[0], best[1], best[2], len(near)


def match_clip(bvh: Path, order: Sequence[int], feet: Sequence[int], lengths: Sequence[int],
               amps: Sequence[float], raw: Any = None, notes: dict | None = None) -> Any:
    """The clip whose pyramid reproduces the checkpoint's amplitudes (units, contact threshold, and the contact
    labels that float32 rounding decides); ``notes`` receives what was settled (``scale``, ``threshold``,
    ``flipped_labels``, ``amplitude_error``)."""
    raw = read_clip(bvh, fold_root=False) if raw is None else raw
    tried = []
    for scale in SCALES:
        for th in (THRESHOLDS if feet else THRESHOLDS[:1]):
            clip, speed, mag = _build(bvh, order, feet, scale, th, raw)
            if clip.n_frames != lengths[-1]:
                raise UserError(f"{bvh}: {clip.n_frames} frames at {clip.fps:g} fps, but the checkpoint's finest "
                                f"level has {lengths[-1]}; pass the BVH the model was trained on")
            mine = _amplitudes(clip, lengths)
            err, level = _amp_error(mine, amps)
            tried.append((err, level, mine, clip, speed, mag))
    tried.sort(key=lambda r: r[0])
    flips: list[tuple[int, int]] = []
    n_near = 0
    clip, err = tried[0][3], tried[0][0]
    if err > EXACT and feet:  # a contact label that rounding put on the other side of the threshold?
        for e0, _, _, c0, speed, mag in tried[:2]:
            c1, f1, e1, near = settle_labels(c0, speed, mag, lengths, amps)
            n_near = max(n_near, near)
            if e1 < err:
                clip, flips, err = c1, f1, e1
            if err <= EXACT:
                break
    if err > ACCEPT:
        e0, level, mine, c0 = tried[0][:4]
        if n_near > MAX_FLIPS:
            cause = (f"{n_near} of its contact labels lie within float32 rounding of the threshold, more than the "
                     f"{MAX_FLIPS} this import tries both ways, so their labels cannot be settled")
        else:
            cause = "the skeleton and length match, the motion is not the one this run was trained on"
        raise UserError(
            f"{bvh}: read as their loader reads it (root track from {raw.skeleton.names[0]}'s channels, joints at "
            f"their OFFSETs, units x{c0.scale:g}, contact threshold {c0.contact_threshold:g}), this BVH gives level "
            f"{level}'s noise amplitude {mine[level]:.6g} where amps.pt holds {amps[level]:.6g} (the noise "
            f"amplitudes are off by {e0:.1%}): {cause}")
    if notes is not None:
        notes.update(scale=clip.scale, threshold=clip.contact_threshold, amplitude_error=err,
                     flipped_labels=[{"frame": t, "joint": clip.skeleton.names[clip.feet[k]]} for t, k in flips])
    return clip


def find_bvh(data: Path | None, run: Path, args: dict) -> Path:
    """``--data`` (a BVH, or a folder holding ``{bvh_name}.bvh``), else their ``--bvh_prefix/--bvh_name``."""
    name = f"{args['bvh_name']}.bvh"
    if data is not None:
        data = Path(data)
        if data.is_dir():
            if (data / name).is_file():
                return data / name
            raise UserError(f"{data}: no {name} in this folder (the run was trained on {args['bvh_name']})")
        if not data.is_file():
            raise UserError(f"{data}: no such BVH file")
        return data
    prefix = Path(str(args["bvh_prefix"]))
    for base in ([prefix] if prefix.is_absolute() else [Path.cwd() / prefix, run.parent / prefix, run / prefix]):
        if (base / name).is_file():
            return base / name
    raise UserError(f"{run}: its training BVH {prefix / name} was not found; pass it with --data BVH")


# ------------------------------------------------------------------------------------------- weights


def _pairs(mod: Any) -> tuple[list[int], list[int]]:
    """(output entity, input entity) of every stored pair of a modi skeletal conv, in storage order."""
    offsets = mod.offsets.tolist()
    rows = [r for r in range(len(offsets) - 1) for _ in range(offsets[r], offsets[r + 1])]
    return rows, mod.index.tolist()


def _convs(body: Any) -> list[tuple[str, Any, str]]:
    """(conv name, conv module, bias name) of a modi ``SkeletalStack`` in order."""
    mods = list(body.net.named_children())
    out = []
    for i, (name, m) in enumerate(mods):
        if hasattr(m, "index") and hasattr(m, "offsets"):
            bname = mods[i + 1][0] if i + 1 < len(mods) and isinstance(mods[i + 1][1], EntityBias) else None
            out.append((name, m, bname))
    return out


def stack_state(sd: dict[str, Tensor], body: Any, perm: Sequence[int], prefix: str, where: str,
                first: int = 0, binary: bool = True) -> dict[str, Tensor]:
    """modi ``SkeletalStack`` tensors (keys under ``prefix``) for released layers ``layers.{first+i}.0``."""
    out: dict[str, Tensor] = {}
    E = len(perm)
    p = torch.as_tensor(list(perm))
    for i, (cname, conv, bname) in enumerate(_convs(body)):
        key = f"layers.{first + i}.0"
        try:
            w, mask, b = sd[f"{key}.weight"], sd[f"{key}.mask"], sd[f"{key}.bias"]
        except KeyError as exc:
            raise UserError(f"{where}: no tensor {exc.args[0]} (not a released skeleton-aware generator)") from None
        co, ci, U = conv.out_ch, conv.in_ch, conv.kernel_size
        if tuple(w.shape) != (E * co, E * ci, U) or w.shape != mask.shape:
            raise UserError(f"{where}: {key}.weight is {tuple(w.shape)}, expected {(E * co, E * ci, U)} for this "
                            "skeleton and these options")
        adj = entity_adjacency(mask, E, f"{where}: {key}.mask", binary)
        rows, cols = _pairs(conv)
        mine = np.zeros((E, E), dtype=bool)
        mine[p[rows].numpy(), p[cols].numpy()] = True
        if not np.array_equal(mine, adj):
            raise UserError(f"{where}: {key}.mask connects other entities than this skeleton's neighbourhoods")
        # their forward multiplies by the mask, so a weight outside it never acted: the product is the weight
        wr = (w.detach() * mask.detach()).reshape(E, co, E, ci, U)
        blocks = wr[p[rows], :, p[cols]]  # (nnz, co, ci, U)
        out[f"{prefix}{cname}.weight"] = blocks.permute(1, 0, 2, 3).contiguous().to(conv.weight.dtype)
        if bname is not None:
            out[f"{prefix}{bname}.bias"] = b.detach().reshape(E, co)[p].t().reshape(co, E, 1).contiguous()
    return out


def generator_state(sd: dict[str, Tensor], gen: Any, perm: Sequence[int], where: str = "generator"
                    ) -> dict[str, Tensor]:
    """The state dict of modi ``LevelGenerator`` ``gen`` for a released level generator's ``state_dict``
    (linear in the tensors: their gradients, with the masks, map to modi's gradients the same way)."""
    n = len(_convs(gen.body))
    extra = sorted(k for k in sd if not re.fullmatch(rf"layers\.[0-{n - 1}]\.0\.(weight|mask|bias)", k))
    if extra:
        raise UserError(f"{where}: unexpected tensors {', '.join(extra[:3])} (not a {n}-layer released generator)")
    return stack_state(sd, gen.body, perm, "body.net.", where)


def discriminator_state(sd: dict[str, Tensor], disc: Any, perm: Sequence[int], where: str = "discriminator",
                        binary: bool = True) -> dict[str, Tensor]:
    """The state dict of modi ``PatchDiscriminator`` ``disc`` for a released discriminator (skeleton-aware
    layers, then a plain temporal conv over ``entity*C + c`` channels; modi's head reads ``c*E + entity``).
    ``binary=False`` accepts masks that training moved off 1 (the effective weight ``weight * mask`` is kept)."""
    out = stack_state(sd, disc.body, perm, "body.net.", where, binary=binary)
    n = len(_convs(disc.body))
    w, b = sd[f"layers.{n}.0.weight"], sd[f"layers.{n}.0.bias"]
    E = len(perm)
    C = w.shape[1] // E
    out["head.weight"] = w.detach().reshape(1, E, C, -1)[:, list(perm)].permute(0, 2, 1, 3).reshape(1, C * E, -1)
    out["head.bias"] = b.detach().clone()
    return out


# ------------------------------------------------------------------------------------------- the import


def config_for(args: dict, clip: Any, n_levels: int) -> Any:
    """modi's config for the released options (the released forms of every loss-level option)."""
    limit = int(args["num_stages_limit"])
    return GanimatorConfig(
        fps=clip.fps, keep_joints=list(clip.skeleton.names), feet=[clip.skeleton.names[f] for f in clip.feet],
        contacts=bool(clip.feet), contact_velocity=clip.contact_threshold / clip.size * (clip.fps / 30.0),
        contact_first_frame="zero", sixd="rows", coarse_ratio=_fraction(args["ratio"]),
        scale_factor=float(args["scaling_rate"]), max_levels=limit if limit != -1 else None,
        neighbor_distance=int(args["neighbour_dist"]), kernel_size=int(args["kernel_size"]),
        padding_mode=str(args["padding_mode"]),
        base_channels=int(args["base_channel"]) if int(args["base_channel"]) != -1 else 128,
        n_layers=int(args["n_layers"]) if int(args["n_layers"]) != -1 else 4, bias_init="uniform",
        lambda_gp=float(args["lambda_gp"]), lambda_rec=float(args["lambda_rec"]),
        lambda_contact=float(args["lambda_consistency"]) if args["contact"] else 0.0, contact_rescale=False,
        lr=float(args["lr_g"]), iterations=int(args["num_iters"]), group_size=int(args["group_size"]),
        d_steps=int(args["D_fact"]), g_steps=int(args["G_fact"]), fake_pool=50, preset="paper")


def read_released(ckpt: Path | str, data: Path | str | None = None) -> dict[str, Any]:
    """Everything of a released run, matched to its BVH: options, clip, entity order, tensors (no model yet)."""
    run = find_run(ckpt)
    args = read_args(run)
    try:
        sds = read_generators(run)
        z_star = _load(run / "z_star.pt", "released GANimator z_star")
        amps = _load(run / "amps.pt", "released GANimator amps")
    except CheckpointError as exc:
        raise UserError(str(exc)) from None
    if isinstance(z_star, (list, tuple)):
        if len(z_star) != 1:
            raise UserError(f"{run / 'z_star.pt'}: {len(z_star)} clips; modi imports single-clip runs")
        z_star = z_star[0]
    if not isinstance(z_star, Tensor) or z_star.ndim != 3 or not isinstance(amps, Tensor):
        raise UserError(f"{run}: z_star.pt / amps.pt do not hold the tensors their train.py writes")
    amps_row = [float(a) for a in (amps[0] if amps.ndim == 2 else amps)]
    if len(amps_row) != len(sds):
        raise UserError(f"{run}: {len(sds)} generator files but {len(amps_row)} amplitudes in amps.pt")
    first = sds[0].get("layers.0.0.mask")
    if first is None:
        raise UserError(f"{run / 'gen000.pt'}: no layers.0.0.mask (not a skeleton-aware released generator)")
    E = z_star.shape[1] // 6
    if E * 6 != z_star.shape[1] or first.shape[1] != z_star.shape[1]:
        raise UserError(f"{run}: z_star has {z_star.shape[1]} channels, the first layer {first.shape[1]}")
    adj = entity_adjacency(first, E, f"{run / 'gen000.pt'}: layers.0.0.mask")
    bvh = find_bvh(Path(data) if data is not None else None, run, args)
    raw = read_clip(bvh, fold_root=False)  # their loader's reading: see their_reading
    sk = raw.skeleton
    cands = [reduce_joints(sk)] if args["joint_reduction"] else []
    cands.append(list(range(sk.n_joints)))
    if floor_root(raw):  # a table may list the static floor root (Bandai's joint_Root) or start below it
        cands += [[j for j in c if j != 0] for c in cands]
    order, feet = match_skeleton(sk.parents, adj, int(args["neighbour_dist"]), joint_subsets(sk.parents, cands))
    return {"run": run, "args": args, "sds": sds, "z_star": z_star.detach(), "amps": amps_row, "bvh": bvh,
            "order": order, "feet": feet, "E": E, "raw": raw}


def import_checkpoint(ckpt: Path | str, data: Path | str | None, out: Path | str) -> Path:
    """Convert the released run at ``ckpt`` (its folder, or a file in it) trained on the BVH ``data`` (None: the
    path in its ``args.txt``) into the modi GANimator run folder ``out``; returns ``out``.

    The run is written by modi's own trainer (``Trainer.save``), marked fully trained, with the released
    generators, ``z*`` and amplitudes; its discriminators are freshly initialised (the released code does not save
    them). Raises ``UserError`` (one line) on anything that does not match."""
    r = read_released(ckpt, data)
    run, args, sds = r["run"], r["args"], r["sds"]
    J = len(r["order"])
    perm = entity_perm(J, len(r["feet"]))
    # level lengths: the released pyramid of the clip (checked against z* and the number of generator files)

    raw = r["raw"]
    n_frames = len(range(0, raw.rotations.shape[0], released_stride(raw.fps)))
    lengths = pyramid_lengths(n_frames, _fraction(args["ratio"]), float(args["scaling_rate"]))
    if int(args["num_stages_limit"]) != -1:
        lengths = lengths[: int(args["num_stages_limit"])]
    if len(lengths) != len(sds) or lengths[0] != r["z_star"].shape[-1]:
        raise UserError(f"{run}: {len(sds)} levels with a coarsest of {r['z_star'].shape[-1]} frames, but the BVH "
                        f"{r['bvh']} gives levels {lengths}; pass the BVH the model was trained on")
    notes: dict[str, Any] = {}
    clip = match_clip(r["bvh"], r["order"], r["feet"], lengths, r["amps"], raw, notes)
    cfg = config_for(args, clip, len(sds))
    got, _ = sequence_pyramid([clip], cfg)
    if got[0] != lengths:
        raise UserError(f"{run}: modi's pyramid {got[0]} differs from the released one {lengths} for this clip")
    out = Path(out)
    if checkpoint_path(out).exists():
        raise UserError(f"{out} already holds a modi run; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    with torch.random.fork_rng(devices=[]):  # the trainer seeds torch; leave the caller's generator alone
        trainer = Trainer([clip], cfg, out)
    model = trainer.model
    for level, (g, sd) in enumerate(zip(model.gens, sds)):
        g.load_state_dict(generator_state(sd, g, perm, f"{run / f'gen{level:03d}.pt'}"))
    model.z_stars[0].data.copy_(to_modi_layout(r["z_star"].to(torch.float32), perm))
    model.amps = [list(r["amps"])]
    n_blocks = len(blocks_of(model.n_levels, cfg.group_size))
    trainer.state.update(block=n_blocks, iteration=0, levels_done=model.n_levels,
                         imported_from=provenance(r, clip, lengths, n_blocks, notes))
    trainer.save()
    return out


def provenance(r: dict[str, Any], clip: Any, lengths: Sequence[int], n_blocks: int, notes: dict[str, Any]
               ) -> dict[str, Any]:
    """What the run folder and its BVH say (``imported_from`` of the modi run): their options as ``args.txt``
    states them, their iterations (``--num_iters`` per block of levels; their ``train.py`` writes the generators
    when a block is done), the clip as their loader read it (the rate its Frame Time states, their frame stride,
    units, contact threshold and the labels the amplitudes settled) and every file's SHA-256."""
    run, args, raw = r["run"], r["args"], r["raw"]
    stride = released_stride(raw.fps)
    files = [run / ARGS_FILE, *generator_files(run), run / "z_star.pt", run / "amps.pt"]
    line = (run / ARGS_FILE).read_text(encoding="utf-8", errors="replace").splitlines()[:1]
    frame_time = bvh_io.load(str(r["bvh"])).frame_time  # as the file states it; modi's rate is the one reader's
    data = {**file_record(r["bvh"]), "frame_time": frame_time, "fps": 1.0 / frame_time, "stride": stride,
            "clip_fps": clip.fps, "frames": int(raw.rotations.shape[0]), "clip_frames": clip.n_frames,
            "window": clip.n_frames, "pyramid": list(lengths), "joints": list(clip.skeleton.names),
            "contacts": [clip.skeleton.names[f] for f in clip.feet], "floor_root": floor_root(raw),
            **notes}
    return record("ganimator-released", folder_record(run, files), iterations=int(args["num_iters"]) * n_blocks,
                  iterations_from=f"from args.txt (--num_iters {int(args['num_iters'])} per block, {n_blocks} blocks; "
                                  "their train.py writes the generators when a block is done)",
                  args=stated_args(run), command=line[0] if line else "", data=data,
                  seed=args.get("seed"))


__all__ = ["import_checkpoint", "read_released", "find_run", "read_args", "read_generators", "entity_perm",
           "to_modi_layout", "to_released_layout", "entity_adjacency", "joint_subsets", "match_skeleton",
           "build_clip", "match_clip", "released_stride", "their_reading", "floor_root", "ambiguous_labels",
           "settle_labels", "stated_args", "generator_files", "provenance", "generator_state", "discriminator_state", "config_for"]
