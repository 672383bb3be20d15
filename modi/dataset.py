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
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from modi import bvh as bvh_io
from modi.contacts import DEFAULT_HEIGHT_FACTOR, DEFAULT_VELOCITY_FACTOR, foot_contacts
from modi.errors import UserError
from modi.normalization import Normalizer
from modi.representation import MotionRepresentation
from modi.skeleton import Skeleton
from modi.topology import EntityLayout, PoolingHierarchy, build_hierarchy

CACHE_VERSION = 1


def default_cache_dir() -> Path:
    """``$MODI_CACHE`` if set, else ``~/.cache/modi``."""
    env = os.environ.get("MODI_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "modi"


@dataclass
class DatasetConfig:
    """Everything that changes the tensors (and so the cache key).

    ``drop_patterns=None`` uses the default reduction; ``keep_all_joints`` disables reduction entirely.
    ``feet`` are joint names (``None``: ``Skeleton.detect_feet()``).
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


def _translating_joints(b: bvh_io.Bvh, tol: float) -> list[int]:
    """Non-root joints whose position channels move away from their OFFSET by more than ``tol``."""
    trans = b.local_translations()
    dev = np.abs(trans[:, 1:] - b.offsets[None, 1:]).max(axis=(0, 2)) if b.n_joints > 1 else np.zeros(0)
    return [j + 1 for j in np.nonzero(dev > tol)[0].tolist()]


def motion_from_bvh(b: bvh_io.Bvh, path: str | None = None) -> Any:
    """A ``Motion`` that reproduces the file's joint positions.

    ``Motion`` carries one translation (the root's). Rigs such as Bandai's put a static anchor at the root and
    move its only child (``joint_Root`` -> ``Hips`` with position channels); those are *promoted*: the anchor is
    dropped and the child becomes the root with its global rotation and position from FK. Any other joint
    whose position channels move is fixed to its OFFSET, with a warning.
    """
    from modi.kinematics import bvh_global_quats_and_positions
    from modi.motion import Motion
    from modi.rotations import quat_inverse, quat_mul

    sk = b.skeleton()
    tol = 1e-4 * max(sk.height(), 1e-9)
    moving = _translating_joints(b, tol)
    promote = bool(moving) and moving[0] == 1 and sk.children(0) == [1]
    if not promote:
        if moving:
            warnings.warn(f"{path or 'bvh'}: joints {[sk.names[j] for j in moving]} have moving position channels; "
                          "only the root's translation is kept", stacklevel=2)
        return Motion.from_bvh(b)
    if len(moving) > 1:
        warnings.warn(f"{path or 'bvh'}: joints {[sk.names[j] for j in moving[1:]]} have moving position channels; "
                      "only the root's translation is kept", stacklevel=2)
    pos, gq = bvh_global_quats_and_positions(b, dtype=torch.float64)
    parents = b.parents
    local = torch.empty_like(gq)
    local[:, 0] = gq[:, 0]
    for j in range(1, b.n_joints):
        local[:, j] = quat_mul(quat_inverse(gq[:, parents[j]]), gq[:, j])
    # Skeleton.subset() must keep joint 0, so build the promoted skeleton here: joint 1 becomes the root.
    names = sk.names[1:]
    new_parents = [-1] + [p - 1 for p in sk.parents[2:]]
    offsets = sk.offsets[1:].copy()
    end_sites = {j - 1: v for j, v in sk.end_sites.items() if j >= 1}
    orders = sk.rotation_orders[1:] if sk.rotation_orders is not None else None
    new_sk = Skeleton(names, new_parents, offsets, end_sites, orders)
    return Motion(new_sk, local[:, 1:].contiguous(), pos[:, 1].contiguous(), float(b.fps))


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
        try:
            return _from_state(torch.load(cache_file, map_location="cpu", weights_only=True), from_cache=True)
        except Exception as exc:  # a corrupt or foreign cache file: rebuild it
            warnings.warn(f"ignoring unreadable dataset cache {cache_file}: {exc}", stacklevel=2)
    ds = _build(files, rels, shas, config, progress)
    if cache:
        _atomic_save(_to_state(ds), cache_file)
    return ds


def _build(files: list[Path], rels: list[str], shas: list[str], config: DatasetConfig, progress: bool) -> MotionDataset:
    dtype = getattr(torch, config.dtype)
    splits = split_files(len(files), config.test_fraction, config.seed)
    iterator: Any = zip(files, rels, shas, splits)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(list(iterator), desc="loading BVH", unit="clip")

    source_skeleton: Skeleton | None = None
    skeleton: Skeleton | None = None
    kept: list[int] = []
    feet: list[int] = []
    rep: MotionRepresentation | None = None
    height = 1.0
    clips: list[ClipInfo] = []
    chunks: dict[str, list[Tensor]] = {"train": [], "test": []}
    clip_idx: dict[str, list[Tensor]] = {"train": [], "test": []}
    starts_all: dict[str, list[Tensor]] = {"train": [], "test": []}
    for ci, (path, rel, sha, split) in enumerate(iterator):
        try:
            b = bvh_io.load(path)
        except UserError as exc:
            raise UserError(f"{rel}: {exc}") from None
        motion = motion_from_bvh(b, rel)
        if source_skeleton is None:
            source_skeleton = motion.skeleton
            if config.keep_all_joints:
                skeleton, kept = source_skeleton, list(range(source_skeleton.n_joints))
            else:
                try:
                    skeleton, kept = source_skeleton.reduce(config.drop_patterns, config.keep_joints)
                except (KeyError, ValueError) as exc:
                    raise UserError(f"joint reduction: {exc}") from None
            try:
                feet = skeleton.detect_feet(config.feet) if config.feet is not None else skeleton.detect_feet()
            except KeyError as exc:
                raise UserError(f"feet: {exc}") from None
            height = skeleton.height()
            rep = MotionRepresentation(skeleton, feet, rotation=config.rotation, root=config.root,
                                       velocity_factor=config.velocity_factor, height_factor=config.height_factor)
        else:
            _check_same_skeleton(source_skeleton, motion.skeleton, rel, height)
        assert skeleton is not None and rep is not None
        if kept != list(range(motion.skeleton.n_joints)):
            motion = motion.subset(kept)
        source_fps, source_frames = float(motion.fps), motion.n_frames
        if abs(source_fps - config.fps) > 1e-3 * config.fps:
            motion = motion.resample(config.fps)
        rot = motion.rotations.to(torch.float64)
        rootp = motion.root_positions.to(torch.float64)
        T = rot.shape[0]
        starts = _windows(T, config.window, config.stride)
        clips.append(ClipInfo(rel, source_frames, source_fps, T, len(starts), split, sha))
        if not starts:
            continue
        offsets = torch.as_tensor(skeleton.offsets, dtype=torch.float64)
        from modi.kinematics import forward_kinematics

        pos = forward_kinematics(rot, offsets, skeleton.parents, rootp)[0]
        contacts = foot_contacts(pos, feet, height, config.fps, config.velocity_factor, config.height_factor)
        idx = torch.tensor(starts)[:, None] + torch.arange(config.window)[None]  # (N, W)
        w_rot, w_root, w_con = rot[idx], rootp[idx].clone(), contacts[idx]
        if config.center:
            w_root[..., [0, 2]] -= w_root[:, :1, [0, 2]]
        chunks[split].append(rep.encode_parts(w_rot, w_root, w_con).to(dtype))
        clip_idx[split].append(torch.full((len(starts),), ci, dtype=torch.int64))
        starts_all[split].append(torch.tensor(starts, dtype=torch.int64))

    assert rep is not None and skeleton is not None and source_skeleton is not None
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


def _check_same_skeleton(ref: Skeleton, sk: Skeleton, rel: str, height: float) -> None:
    if sk.names != ref.names or sk.parents != ref.parents:
        raise UserError(f"{rel}: skeleton differs from the first file's ({sk.n_joints} vs {ref.n_joints} joints "
                        "or different names/hierarchy); a dataset needs one skeleton")
    diff = np.abs(sk.offsets[1:] - ref.offsets[1:]).max() if sk.n_joints > 1 else 0.0
    if diff > 0.01 * height:
        warnings.warn(f"{rel}: bone offsets differ from the first file's by up to {diff:.3g}; "
                      "using the first file's", stacklevel=3)


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
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".pt")
        os.close(fd)
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except OSError as exc:  # an unwritable cache must not stop training
        warnings.warn(f"could not write dataset cache {path}: {exc}", stacklevel=3)
