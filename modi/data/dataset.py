"""A windowed motion dataset from a folder of BVH files (MoDi-style training data).

Pipeline per clip: load BVH -> ``Motion`` (promoting a translation-carrying child of an anchor root, see
``motion_from_bvh``) -> joint reduction (``Skeleton.reduce``; default drops fingers and face joints) ->
resample to ``fps`` -> contact labels on the full clip -> windows of ``window`` frames every ``stride`` frames,
each re-centred so its first frame stands at x = z = 0 -> one ``(K, E, T)`` tensor per window.

The split is 80/20 **by file** (a seeded permutation of the sorted relative paths), never by window, so no test
window overlaps a training clip. Normalisation stats are fitted on the training windows only (contacts left
raw). The result is cached on disk under a key made of the files' content hashes and every setting that changes
the tensors, in ``$MODI_CACHE`` or ``~/.cache/modi``.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from modi.core.contacts import DEFAULT_HEIGHT_FACTOR, DEFAULT_VELOCITY_FACTOR, foot_contacts
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import euler_to_quat, quat_apply, quat_mul, quat_to_euler
from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import EntityLayout, PoolingHierarchy, build_hierarchy
from modi.data.motion import Motion
from modi.data.normalization import Normalizer
from modi.data.representation import LEAF_ROTATIONS, MotionRepresentation
from modi.errors import UserError
from modi.faults import OutputError, atomic_torch_save
from modi.io import bvh as bvh_io
from modi.io.safe_load import UnsafeFileError, load_data

CACHE_VERSION = 2  # 2: skeleton offsets from the clip nearest the median, not the first file


def default_cache_dir() -> Path:
    """``$MODI_CACHE`` if set, else ``~/.cache/modi``."""
    env = os.environ.get("MODI_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "modi"


@dataclass
class DatasetConfig:
    """Everything that changes the tensors (and so the cache key).

    ``drop_patterns=None`` uses the default reduction; ``keep_all_joints`` disables reduction entirely.
    ``feet`` are joint names (``None``: ``Skeleton.detect_feet()``). ``drop_root_anchor`` removes a root that only
    carries its single child at its own place (Bandai's ``joint_Root`` above ``Hips``; exact, see
    ``root_anchor``); ``leaf_rotations="drop"`` stores no rotation for joints without children
    (``modi.data.representation``). Both are MoDi's released preprocessing; the defaults here keep every joint.
    """

    fps: float = 30.0
    window: int = 64
    stride: int = 16
    test_fraction: float = 0.2
    seed: int = 0
    drop_patterns: list[str] | None = None
    keep_joints: list[str] | None = None
    keep_all_joints: bool = False
    feet: list[str] | None = None
    rotation: str = "quat"
    root: str = "velocity"
    center: bool = True
    velocity_factor: float = DEFAULT_VELOCITY_FACTOR
    height_factor: float | None = DEFAULT_HEIGHT_FACTOR
    min_std: float = 1e-3
    dtype: str = "float32"
    drop_root_anchor: bool = False
    leaf_rotations: str = "keep"

    def validate(self) -> None:
        if self.fps <= 0:
            raise UserError(f"--fps must be positive, got {self.fps}")
        if self.window < 1:
            raise UserError(f"--window must be at least 1 frame, got {self.window}")
        if self.stride < 1:
            raise UserError(f"--stride must be at least 1 frame, got {self.stride}")
        if not 0.0 <= self.test_fraction < 1.0:
            raise UserError(f"--test-fraction must be in [0, 1), got {self.test_fraction}")
        if self.dtype not in ("float32", "float64"):
            raise UserError(f"dtype must be float32 or float64, got {self.dtype!r}")
        if self.leaf_rotations not in LEAF_ROTATIONS:
            raise UserError(f"leaf_rotations must be one of {LEAF_ROTATIONS}, got {self.leaf_rotations!r}")


@dataclass
class ClipInfo:
    """One source file: frames and rate before resampling, frames after, windows, and its split."""

    path: str
    source_frames: int
    source_fps: float
    frames: int
    n_windows: int
    split: str
    sha: str


@dataclass
class MotionDataset:
    """Windows as raw (un-normalised) ``(N, K, E, T)`` tensors plus everything needed to use them.

    ``train``/``test`` are raw; ``normalized(split)`` applies ``normalizer``. ``clip_index_*`` give each window's
    clip (index into ``clips``) and ``window_start_*`` its first frame in the resampled clip.
    """

    config: DatasetConfig
    skeleton: Skeleton
    source_skeleton: Skeleton
    kept_joints: list[int]
    feet: list[int]
    representation: MotionRepresentation
    normalizer: Normalizer
    train: Tensor
    test: Tensor
    clips: list[ClipInfo]
    clip_index_train: Tensor
    clip_index_test: Tensor
    window_start_train: Tensor
    window_start_test: Tensor
    from_cache: bool = False
    layout: EntityLayout = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.layout = self.representation.layout

    def hierarchy(self, neighbor_distance: int = 1) -> PoolingHierarchy:
        """The skeletal pooling hierarchy of this dataset's skeleton and contact joints."""
        return build_hierarchy(self.skeleton, self.feet, neighbor_distance=neighbor_distance)

    def normalized(self, split: str = "train") -> Tensor:
        return self.normalizer.normalize(self._split(split))

    def _split(self, split: str) -> Tensor:
        if split == "train":
            return self.train
        if split == "test":
            return self.test
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")

    def torch_dataset(self, split: str = "train", normalized: bool = True) -> torch.utils.data.TensorDataset:
        x = self.normalized(split) if normalized else self._split(split)
        return torch.utils.data.TensorDataset(x)

    @property
    def n_frames(self) -> int:
        return sum(c.frames for c in self.clips)

    def summary(self) -> dict[str, Any]:
        h = self.hierarchy()
        return {
            "clips": len(self.clips),
            "train_clips": sum(c.split == "train" for c in self.clips),
            "test_clips": sum(c.split == "test" for c in self.clips),
            "source_frames": sum(c.source_frames for c in self.clips),
            "frames": self.n_frames,
            "fps": self.config.fps,
            "source_fps": sorted({round(c.source_fps, 3) for c in self.clips}),
            "joints_source": self.source_skeleton.n_joints,
            "joints": self.skeleton.n_joints,
            "feet": [self.skeleton.names[f] for f in self.feet],
            "height": self.skeleton.height(),
            "entities": self.representation.n_entities,
            "hierarchy_entities": h.entity_counts,
            "hierarchy_edges": h.edge_counts,
            "train_windows": int(self.train.shape[0]),
            "test_windows": int(self.test.shape[0]),
            "window": self.config.window,
            "stride": self.config.stride,
            "tensor_shape": list(self.train.shape[1:]),
            "from_cache": self.from_cache,
        }


# ================================================================================================= loading


def find_bvh_files(root: str | os.PathLike) -> list[Path]:
    """All ``*.bvh`` under ``root`` (recursive, case-insensitive suffix), sorted by relative path."""
    root = Path(root)
    if not root.exists():
        raise UserError(f"no such directory: {root}")
    if root.is_file():
        return [root]
    files = sorted((p for p in root.rglob("*") if p.is_file() and p.suffix.lower() == ".bvh"),
                   key=lambda p: p.relative_to(root).as_posix())
    if not files:
        raise UserError(f"no .bvh files under {root}")
    return files


def _channel_columns(b: bvh_io.Bvh) -> tuple[np.ndarray, np.ndarray]:
    """(J,3) motion columns of each joint's rotation channels (in its Euler order) and X/Y/Z position channels;
    -1 where a joint lacks the channel."""
    rot = np.full((b.n_joints, 3), -1, dtype=np.int64)
    pos = np.full((b.n_joints, 3), -1, dtype=np.int64)
    col = 0
    for j, chans in enumerate(b.channels):
        r = 0
        for c in chans:
            axis = "XYZ".index(c[0].upper())
            if c.lower().endswith("rotation"):
                rot[j, r] = col
                r += 1
            else:
                pos[j, axis] = col
            col += 1
    return rot, pos


def _bake_moving_anchor(b: bvh_io.Bvh) -> bvh_io.Bvh | None:
    """For a root 'anchor' with one child that carries the translation (Bandai: ``joint_Root`` -> ``Hips``) and
    an anchor that itself moves (4 Bandai clips translate ``joint_Root`` too), return a copy with the anchor's
    motion composed into the child and the anchor frozen at the identity, else ``None``.

    ``Motion.from_bvh`` handles a *static* anchor exactly (the child's translation becomes the root
    trajectory) but can only average a moving one; after baking every such file takes that exact path.
    """
    if b.n_joints < 2 or [j for j, p in enumerate(b.parents) if p == 0] != [1]:
        return None
    rot_cols, pos_cols = _channel_columns(b)
    if (pos_cols[1] < 0).any():
        return None  # the child has no position channels to carry the trajectory
    trans = b.local_translations()
    euler = b.euler_degrees()
    scale = max(float(np.abs(trans[:, 1]).max()), 1e-9)
    anchor_moves = np.ptp(trans[:, 0], axis=0).max() > 1e-9 * scale or np.ptp(euler[:, 0], axis=0).max() > 1e-9
    child_moves = np.ptp(trans[:, 1], axis=0).max() > 1e-6 * scale
    if not (anchor_moves and child_moves):
        return None
    orders = b.rotation_orders
    e = torch.from_numpy(euler[:, :2])
    q0, q1 = euler_to_quat(e[:, 0], orders[0]), euler_to_quat(e[:, 1], orders[1])
    t = torch.from_numpy(trans[:, :2])
    anchor_pos = torch.zeros(3, dtype=torch.float64) if (pos_cols[0] >= 0).all() else torch.from_numpy(b.offsets[0])
    child_pos = t[:, 0] + quat_apply(q0, t[:, 1]) - anchor_pos
    child_euler = quat_to_euler(quat_mul(q0, q1), orders[1]).numpy()
    out = b.copy()
    for axis in range(3):
        if pos_cols[0, axis] >= 0:
            out.motion[:, pos_cols[0, axis]] = 0.0
        if rot_cols[0, axis] >= 0:
            out.motion[:, rot_cols[0, axis]] = 0.0
        out.motion[:, pos_cols[1, axis]] = child_pos[:, axis].numpy()
        if rot_cols[1, axis] >= 0:
            out.motion[:, rot_cols[1, axis]] = child_euler[:, axis]
        elif np.abs(child_euler[:, axis]).max() > 1e-9:
            return None  # the child cannot hold the anchor's rotation about this axis
    return out


def root_anchor(skeleton: Skeleton) -> bool:
    """Whether joint 0 is an anchor that only repeats its one child: the child sits at the root (zero offset,
    which is what ``Motion.from_bvh`` leaves when it moves the child's animated translation into the root
    trajectory, as for Bandai's ``joint_Root`` -> ``Hips``). Dropping such a root with ``Motion.subset`` is
    exact: the child becomes the root with its global trajectory and orientation."""
    kids = skeleton.children(0) if skeleton.n_joints > 1 else []
    if len(kids) != 1:
        return False
    scale = max(float(np.abs(skeleton.offsets).max()), 1e-12)
    return bool(np.abs(skeleton.offsets[kids[0]]).max() <= 1e-9 * scale)


def motion_from_bvh(b: bvh_io.Bvh, path: str | None = None) -> Any:
    """``Motion.from_bvh`` that also keeps the trajectory of rigs whose root anchor moves.

    Bandai puts a ``joint_Root`` anchor above ``Hips`` and translates ``Hips``; ``Motion.from_bvh`` turns that
    into an exact motion (Hips' translation becomes the root trajectory, all 22 joints kept) when the anchor
    is static. When the anchor moves as well, its motion is first composed into ``Hips``
    (``_bake_moving_anchor``) so the same exact conversion applies.
    """
    baked = _bake_moving_anchor(b)
    return Motion.from_bvh(baked if baked is not None else b)


def feet_positions(rotations: Tensor, root_positions: Tensor, skeleton: Skeleton, feet: Sequence[int]) -> Tensor:
    """Global positions (..., T, F, 3) of the ``feet`` only: FK restricted to their ancestor chains (cheap)."""
    needed = sorted({a for f in feet for a in [f, *skeleton.ancestors(f)]} | {0})
    where = {j: i for i, j in enumerate(needed)}
    parents = [-1 if skeleton.parents[j] < 0 else where[skeleton.parents[j]] for j in needed]
    offsets = torch.as_tensor(skeleton.offsets[needed], dtype=rotations.dtype)
    pos = forward_kinematics(rotations[..., needed, :], offsets, parents, root_positions)[0]
    return pos[..., [where[f] for f in feet], :]


class _torch_threads:
    """Run a block with a given torch intra-op thread count (small tensors gain nothing from threads, and on a
    busy machine the spinning costs several times the work)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.saved = torch.get_num_threads()

    def __enter__(self) -> None:
        torch.set_num_threads(self.n)

    def __exit__(self, *exc: Any) -> None:
        torch.set_num_threads(self.saved)


def _file_sha(path: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _cache_key(config: DatasetConfig, rel_and_sha: list[tuple[str, str]]) -> str:
    payload = json.dumps({"v": CACHE_VERSION, "config": dataclasses.asdict(config), "files": rel_and_sha},
                         sort_keys=True)
    return hashlib.blake2b(payload.encode(), digest_size=16).hexdigest()


def split_files(n: int, test_fraction: float, seed: int) -> list[str]:
    """'train'/'test' per file index: a seeded permutation, ``round(n * test_fraction)`` test files
    (at least one when ``n >= 2`` and ``test_fraction > 0``)."""
    n_test = int(round(n * test_fraction))
    if test_fraction > 0 and n >= 2:
        n_test = max(1, min(n_test, n - 1))
    else:
        n_test = 0
    perm = np.random.default_rng(seed).permutation(n)
    split = ["train"] * n
    for i in perm[:n_test]:
        split[int(i)] = "test"
    return split


def _windows(n_frames: int, window: int, stride: int) -> list[int]:
    return list(range(0, n_frames - window + 1, stride)) if n_frames >= window else []


def build_dataset(
    root: str | os.PathLike,
    config: DatasetConfig | None = None,
    cache: bool = True,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = False,
) -> MotionDataset:
    """Load every BVH under ``root`` into a windowed, split, normalised dataset (cached; see module docstring)."""
    config = config or DatasetConfig()
    config.validate()
    root = Path(root)
    files = find_bvh_files(root)
    rels = [f.relative_to(root).as_posix() if root.is_dir() else f.name for f in files]
    shas = [_file_sha(f) for f in files]
    key = _cache_key(config, list(zip(rels, shas)))
    cdir = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    cache_file = cdir / f"dataset-{key}.pt"
    if cache and cache_file.is_file():
        try:  # as data only: a cache file naming code was put there by someone else, so say so (exit 2)
            return _from_state(load_data(cache_file, "dataset cache file",
                                         hint="; delete it (or pass --no-cache) to rebuild the cache"),
                               from_cache=True)
        except UnsafeFileError:
            raise
        except Exception as exc:  # a corrupt or stale cache file: rebuild it
            warnings.warn(f"ignoring unreadable dataset cache {cache_file}: {exc}", stacklevel=2)
    with _torch_threads(1):
        ds = _build(files, rels, shas, config, progress)
    if cache:
        _atomic_save(_to_state(ds), cache_file)
    return ds


def _build(files: list[Path], rels: list[str], shas: list[str], config: DatasetConfig, progress: bool) -> MotionDataset:
    dtype = getattr(torch, config.dtype)
    splits = split_files(len(files), config.test_fraction, config.seed)
    iterator: Any = zip(files, rels, shas, splits)
    if progress:
        iterator = tqdm(list(iterator), desc="loading BVH", unit="clip")

    # Pass 1: every clip on the reduced skeleton at the dataset rate. Joint reduction depends only on names and
    # hierarchy, which every file must share, so the first file may decide it.
    kept: list[int] | None = None
    first: Skeleton | None = None
    loaded: list[tuple[str, str, str, float, int, Skeleton, Any]] = []
    for path, rel, sha, split in iterator:
        try:
            b = bvh_io.load(path)
        except UserError as exc:
            raise UserError(f"{rel}: {exc}") from None
        motion = motion_from_bvh(b, rel)
        if first is None:
            first = motion.skeleton
            if config.keep_all_joints:
                reduced, kept = first, list(range(first.n_joints))
            else:
                try:
                    reduced, kept = first.reduce(config.drop_patterns, config.keep_joints)
                except (KeyError, ValueError) as exc:
                    raise UserError(f"joint reduction: {exc}") from None
            if config.drop_root_anchor and kept[0] == 0 and root_anchor(reduced):
                kept = kept[1:]
        elif motion.skeleton.names != first.names or motion.skeleton.parents != first.parents:
            raise UserError(f"{rel}: skeleton differs from the first file's ({motion.skeleton.n_joints} vs "
                            f"{first.n_joints} joints or different names/hierarchy); a dataset needs one skeleton")
        assert kept is not None
        source = motion.skeleton
        if kept != list(range(motion.skeleton.n_joints)):
            motion = motion.subset(kept)
        source_fps, source_frames = float(motion.fps), motion.n_frames
        if abs(source_fps - config.fps) > 1e-3 * config.fps:
            motion = motion.resample(config.fps)
        loaded.append((rel, sha, split, source_fps, source_frames, source, motion))

    # The dataset's skeleton is the clip whose bone offsets are closest to the per-joint median over all clips
    # (its file's rest definition, end sites included). Offsets then depend neither on file order nor on one
    # odd clip: a 1-frame bind pose whose root OFFSET is a world position, or a clip with stretched bones, is
    # outvoted by the others instead of setting the bones of every generated motion.
    offs = np.stack([m.skeleton.offsets for *_, m in loaded])  # (N, J, 3)
    median = np.median(offs, axis=0)
    far = np.abs(offs - median[None]).max(axis=(1, 2))
    pick = int(np.lexsort((np.arange(len(loaded)), far))[0])  # nearest the median; ties: the first sorted path
    skeleton = loaded[pick][-1].skeleton
    source_skeleton = loaded[pick][5]
    height = skeleton.height()
    try:
        feet = skeleton.detect_feet(config.feet) if config.feet is not None else skeleton.detect_feet()
    except KeyError as exc:
        raise UserError(f"feet: {exc}") from None
    if config.feet is None:
        feet = [f for f in feet if f != 0]  # a single-joint rig's only leaf is its root: it has no feet
    if len(set(feet)) != len(feet):
        dup = sorted({skeleton.names[f] for f in feet if feet.count(f) > 1})
        raise UserError(f"--feet: joint {', '.join(dup)} is given twice")
    if 0 in feet:
        raise UserError(f"--feet: the root joint {skeleton.names[0]} cannot be a foot (contacts are measured on "
                        "the feet relative to the ground while the root carries the trajectory)")
    rep = MotionRepresentation(skeleton, feet, rotation=config.rotation, root=config.root,
                               velocity_factor=config.velocity_factor, height_factor=config.height_factor,
                               leaf_rotations=config.leaf_rotations)

    # Pass 2: contacts and windows on that one skeleton.
    clips: list[ClipInfo] = []
    chunks: dict[str, list[Tensor]] = {"train": [], "test": []}
    clip_idx: dict[str, list[Tensor]] = {"train": [], "test": []}
    starts_all: dict[str, list[Tensor]] = {"train": [], "test": []}
    for ci, (rel, sha, split, source_fps, source_frames, _, motion) in enumerate(loaded):
        if ci != pick:
            _check_same_skeleton(skeleton, motion.skeleton, rel, height)
        rot = motion.rotations.to(torch.float64)
        rootp = motion.root_positions.to(torch.float64)
        T = rot.shape[0]
        starts = _windows(T, config.window, config.stride)
        clips.append(ClipInfo(rel, source_frames, source_fps, T, len(starts), split, sha))
        if not starts:
            continue
        fpos = feet_positions(rot, rootp, skeleton, feet)
        contacts = foot_contacts(fpos, list(range(len(feet))), height, config.fps, config.velocity_factor,
                                 config.height_factor)
        # Encode the clip once (quaternion signs continuous over the clip), then cut overlapping windows.
        x = rep.encode_parts(rot, rootp, contacts)  # (K, E, T)
        win = x.unfold(-1, config.window, config.stride)[:, :, : len(starts)].permute(2, 0, 1, 3).contiguous()
        if config.center:
            _recenter(win, rep, rootp, starts)
        chunks[split].append(win.to(dtype))
        clip_idx[split].append(torch.full((len(starts),), ci, dtype=torch.int64))
        starts_all[split].append(torch.tensor(starts, dtype=torch.int64))
    del loaded

    K, E, W = rep.K, rep.n_entities, config.window

    def cat(split: str) -> tuple[Tensor, Tensor, Tensor]:
        if not chunks[split]:
            return torch.zeros((0, K, E, W), dtype=dtype), torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64)
        return torch.cat(chunks[split]), torch.cat(clip_idx[split]), torch.cat(starts_all[split])

    train, ci_train, st_train = cat("train")
    test, ci_test, st_test = cat("test")
    if train.shape[0] == 0:
        raise UserError(f"no training windows: every training clip is shorter than --window {config.window} frames "
                        f"at {config.fps:g} fps")
    normalizer = Normalizer.fit(train, min_std=config.min_std, skip_entities=rep.contacts)
    return MotionDataset(config, skeleton, source_skeleton, kept, feet, rep, normalizer, train, test, clips,
                         ci_train, ci_test, st_train, st_test)


def _recenter(win: Tensor, rep: MotionRepresentation, rootp: Tensor, starts: list[int]) -> None:
    """Move each window (N, K, E, W) so that its first frame stands at x = z = 0 (in place)."""
    J = rep.n_joints
    if rep.root == "velocity":
        win[:, 0, J, 0] = 0.0  # the displacement into the first frame
        win[:, 2, J, 0] = 0.0
    else:
        first = rootp[starts][:, [0, 2]].to(win.dtype)  # (N, 2)
        win[:, 0, J, :] -= first[:, :1]
        win[:, 2, J, :] -= first[:, 1:]


def _check_same_skeleton(ref: Skeleton, sk: Skeleton, rel: str, height: float) -> None:
    if sk.names != ref.names or sk.parents != ref.parents:
        raise UserError(f"{rel}: skeleton differs from the first file's ({sk.n_joints} vs {ref.n_joints} joints "
                        "or different names/hierarchy); a dataset needs one skeleton")
    diff = np.abs(sk.offsets[1:] - ref.offsets[1:]).max() if sk.n_joints > 1 else 0.0
    if diff > 0.01 * height:
        warnings.warn(f"{rel}: bone offsets differ from the dataset's (the clip nearest the median of all clips) "
                      f"by up to {diff:.3g}; using the dataset's", stacklevel=3)


# ================================================================================================= cache


def _to_state(ds: MotionDataset) -> dict[str, Any]:
    return {
        "version": CACHE_VERSION,
        "config": dataclasses.asdict(ds.config),
        "skeleton": ds.skeleton.to_dict(),
        "source_skeleton": ds.source_skeleton.to_dict(),
        "kept_joints": list(ds.kept_joints),
        "feet": list(ds.feet),
        "representation": {k: v for k, v in ds.representation.to_dict().items() if k != "skeleton"},
        "normalizer": ds.normalizer.state_dict(),
        "train": ds.train,
        "test": ds.test,
        "clips": [dataclasses.asdict(c) for c in ds.clips],
        "clip_index_train": ds.clip_index_train,
        "clip_index_test": ds.clip_index_test,
        "window_start_train": ds.window_start_train,
        "window_start_test": ds.window_start_test,
    }


def _from_state(s: dict[str, Any], from_cache: bool = False) -> MotionDataset:
    if s.get("version") != CACHE_VERSION:
        raise ValueError(f"cache version {s.get('version')} != {CACHE_VERSION}")
    skeleton = Skeleton.from_dict(s["skeleton"])
    rep = MotionRepresentation(skeleton=skeleton, **s["representation"])
    return MotionDataset(
        config=DatasetConfig(**s["config"]),
        skeleton=skeleton,
        source_skeleton=Skeleton.from_dict(s["source_skeleton"]),
        kept_joints=list(s["kept_joints"]),
        feet=list(s["feet"]),
        representation=rep,
        normalizer=Normalizer.from_state_dict(s["normalizer"]),
        train=s["train"],
        test=s["test"],
        clips=[ClipInfo(**c) for c in s["clips"]],
        clip_index_train=s["clip_index_train"],
        clip_index_test=s["clip_index_test"],
        window_start_train=s["window_start_train"],
        window_start_test=s["window_start_test"],
        from_cache=from_cache,
    )


def _atomic_save(obj: Any, path: Path) -> None:
    try:
        atomic_torch_save(obj, path)  # temp + fsync + rename: a killed run never leaves half a cache file
    except OutputError as exc:  # an unwritable cache (full disk, read-only) must not stop training
        warnings.warn(f"could not write dataset cache {path}: {exc}", stacklevel=3)
