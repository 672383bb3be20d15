"""The feature extractor behind FID/KID/precision/recall/diversity: an ST-GCN-style action recogniser.

MoDi (Appendix D.3) measures generated motion with the penultimate features of an ST-GCN action recogniser
(Yan et al. 2018) trained on real labels. This module holds that recogniser over global joint *positions*,
so any generator of the same skeleton (rotations, positions, whatever representation) is judged alike.

Input pipeline (one place, used for training and evaluation alike, parameters stored in the file):
joints selected by name -> resampled to ``fps`` -> windows of ``window`` frames -> each window put in a
canonical frame (up axis to Y, root's mean ground position to the origin, mean facing -- from the left/right
hip-level joint pair -- turned to +Z) -> divided by the body height -> positions and per-second velocities
(6 channels) -> per-channel standardisation with training-set statistics.

Network: blocks of [spatial graph conv with the ST-GCN "spatial" partition (self / towards root / away from
root) and a learnable edge importance] x [temporal conv], BatchNorm, ReLU, residual; by default three blocks
(32, 64, 128 channels), each halving time -- sized to train in a few CPU minutes. Global average pooling gives
the ``feature_dim`` features the metrics use; a linear head classifies.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from tqdm import tqdm

from modi._version import __version__ as modi_version
from modi.core.kinematics import bvh_positions
from modi.errors import CheckpointError, UserError
from modi.faults import atomic_torch_save
from modi.io import bvh as bvh_io
from modi.io.safe_load import load_data

__all__ = [
    "FeatureConfig",
    "STGCN",
    "FeatureExtractor",
    "LabelledClip",
    "load_labelled_folder",
    "split_by_file",
    "make_windows",
    "canonicalize",
    "lr_pairs",
    "train_feature_extractor",
    "load_extractor",
    "windows_and_labels",
    "select_joints",
    "resample_positions",
]

FORMAT = "modi-features-v1"


# ----------------------------------------------------------------------------------------------------------------
# Configuration


@dataclass
class FeatureConfig:
    """Everything needed to rebuild the extractor and its input pipeline (saved inside the file)."""

    joint_names: list[str]
    parents: list[int]
    class_names: list[str]
    window: int = 64
    fps: float = 30.0
    up_axis: int = 1
    body_height: float = 1.0
    pairs: list[tuple[int, int]] = field(default_factory=list)  # (left, right) joints giving the facing
    channels: list[int] = field(default_factory=lambda: [32, 64, 128])
    strides: list[int] = field(default_factory=lambda: [2, 2, 2])
    temporal_kernel: int = 9
    dropout: float = 0.1
    joint_norm: bool = False  # standardise per (channel, joint) instead of per channel (erases where joints are)

    @property
    def n_classes(self) -> int:
        return len(self.class_names)

    @property
    def feature_dim(self) -> int:
        return self.channels[-1]

    def __post_init__(self) -> None:
        if len(self.joint_names) != len(self.parents):
            raise ValueError("joint_names and parents differ in length")
        if len(self.channels) != len(self.strides):
            raise ValueError("channels and strides differ in length")
        if self.window < 8:
            raise ValueError(f"window must be >= 8 frames, got {self.window}")
        if self.temporal_kernel % 2 != 1:
            raise ValueError(f"temporal_kernel must be odd, got {self.temporal_kernel}")
        self.pairs = [tuple(int(i) for i in p) for p in self.pairs]


# ----------------------------------------------------------------------------------------------------------------
# Skeleton helpers

_SIDE_WORDS = re.compile(r"left|right", re.IGNORECASE)


def _side_key(name: str) -> tuple[str | None, str]:
    """('L' | 'R' | None, name with the side marker removed) -- LeftUpLeg, UpperLeg_L, L_Hip, LHipJoint, Bip01 L Foot."""
    base = name.split(":")[-1]
    m = _SIDE_WORDS.search(base)
    if m:
        return m.group(0)[0].upper(), (base[: m.start()] + "*" + base[m.end() :]).lower()
    tokens = re.split(r"([^A-Za-z0-9]+)", base)
    for i, t in enumerate(tokens):
        if t.lower() in ("l", "r"):
            return t.upper(), "".join(tokens[:i] + ["*"] + tokens[i + 1 :]).lower()
    m = re.match(r"([LR])(?=[A-Z])", base)
    if m:
        return m.group(1), "*" + base[1:].lower()
    return None, base.lower()


def _depths(parents: Sequence[int]) -> list[int]:
    d: list[int] = []
    for p in parents:
        d.append(0 if p < 0 else d[p] + 1)
    return d


def lr_pairs(names: Sequence[str], parents: Sequence[int]) -> list[tuple[int, int]]:
    """The left/right joint pairs closest to the root (hips for most rigs): their across vector gives the facing."""
    left: dict[str, int] = {}
    right: dict[str, int] = {}
    for j, n in enumerate(names):
        side, key = _side_key(n)
        if side == "L":
            left.setdefault(key, j)
        elif side == "R":
            right.setdefault(key, j)
    pairs = [(left[k], right[k]) for k in left if k in right]
    if not pairs:
        return []
    depth = _depths(parents)
    best = min(depth[a] for a, _ in pairs)
    return sorted(p for p in pairs if depth[p[0]] == best)


def select_joints(names: Sequence[str], wanted: Sequence[str]) -> list[int]:
    """Indices of ``wanted`` joints in ``names``; a UserError lists any that are missing."""
    index = {n: i for i, n in enumerate(names)}
    missing = [n for n in wanted if n not in index]
    if missing:
        raise UserError(
            f"motion lacks {len(missing)} joint(s) the feature extractor was trained on: {', '.join(missing[:8])}"
            + (" ..." if len(missing) > 8 else "")
        )
    return [index[n] for n in wanted]


def _reindex_parents(parents: Sequence[int], keep: Sequence[int]) -> list[int]:
    """Parents of the kept joints, re-pointed to their nearest kept ancestor."""
    pos = {j: i for i, j in enumerate(keep)}
    out = []
    for j in keep:
        p = parents[j]
        while p >= 0 and p not in pos:
            p = parents[p]
        out.append(pos[p] if p >= 0 else -1)
    return out


# ----------------------------------------------------------------------------------------------------------------
# Input pipeline


def resample_positions(positions: np.ndarray, fps: float, target_fps: float) -> np.ndarray:
    """Linear resampling of ``(F, J, 3)`` positions in time (positions interpolate linearly without artefacts)."""
    if fps <= 0 or target_fps <= 0:
        raise ValueError(f"fps must be positive (got {fps} -> {target_fps})")
    if abs(fps - target_fps) < 1e-3 * target_fps or positions.shape[0] < 2:
        return positions
    n = positions.shape[0]
    duration = (n - 1) / fps
    m = int(math.floor(duration * target_fps + 1e-6)) + 1
    t = np.arange(m) / target_fps * fps
    i0 = np.clip(np.floor(t).astype(int), 0, n - 1)
    i1 = np.clip(i0 + 1, 0, n - 1)
    w = (t - i0)[:, None, None]
    return positions[i0] * (1 - w) + positions[i1] * w


def make_windows(positions: np.ndarray, window: int, stride: int, tail: bool = True) -> np.ndarray:
    """``(n, window, J, 3)`` windows every ``stride`` frames; with ``tail`` one more aligned to the clip's end so the
    tail is covered; a clip shorter than ``window`` gives one window padded by holding its last pose."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    n = positions.shape[0]
    if n == 0:
        raise ValueError("empty clip")
    if n < window:
        pad = np.repeat(positions[-1:], window - n, axis=0)
        return np.concatenate([positions, pad], axis=0)[None]
    starts = list(range(0, n - window + 1, stride))
    if tail and starts[-1] != n - window:
        starts.append(n - window)
    return np.stack([positions[s : s + window] for s in starts])


def canonicalize(windows: np.ndarray, up_axis: int, pairs: Sequence[tuple[int, int]], body_height: float) -> np.ndarray:
    """Windows ``(n, T, J, 3)`` in a canonical frame: Y up, root's mean ground point at the origin, mean facing
    along +Z (left along +X), lengths in body heights. Joint 0 is the root. Without ``pairs`` the heading is left
    as is (the classifier then has to learn every heading)."""
    w = np.asarray(windows, dtype=np.float64)
    if w.ndim != 4 or w.shape[-1] != 3:
        raise ValueError(f"windows: expected (n, T, J, 3), got {w.shape}")
    perm = {0: [1, 0, 2], 1: [0, 1, 2], 2: [0, 2, 1]}[up_axis]  # put the up axis at index 1 (Y)
    w = w[..., perm]
    if up_axis != 1:
        w[..., 2] *= -1.0  # keep the frame right-handed after swapping axes
    origin = w[:, :, 0].mean(axis=1)  # (n, 3)
    origin[:, 1] = 0.0
    w = w - origin[:, None, None, :]
    if pairs:
        across = sum(w[:, :, a] - w[:, :, b] for a, b in pairs).mean(axis=1)  # (n, 3), points to the left
        # forward = across x up; rotate about Y so that forward -> +Z (equivalently left -> +X)
        ang = np.arctan2(across[:, 2], across[:, 0])  # angle of the left vector from +X towards +Z
        c, s = np.cos(ang), np.sin(ang)
        x, z = w[..., 0].copy(), w[..., 2].copy()
        w[..., 0] = c[:, None, None] * x + s[:, None, None] * z
        w[..., 2] = -s[:, None, None] * x + c[:, None, None] * z
    return w / body_height


def window_inputs(canon: np.ndarray, fps: float) -> np.ndarray:
    """``(n, 6, T, J)`` network input: canonical positions and their per-second velocities."""
    vel = np.diff(canon, axis=1, prepend=canon[:, :1]) * fps
    vel[:, 0] = vel[:, 1] if canon.shape[1] > 1 else 0.0
    x = np.concatenate([canon, vel], axis=-1)  # (n, T, J, 6)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2)).astype(np.float32)


# ----------------------------------------------------------------------------------------------------------------
# Network


def spatial_partitions(parents: Sequence[int]) -> Tensor:
    """ST-GCN's spatial partition ``(3, J, J)``: self, neighbours nearer the root, neighbours farther from it.
    ``A[k, i, j]`` is the weight with which joint i's features flow into joint j; columns are normalised by
    the total degree (self included) so every joint averages over its neighbourhood."""
    J = len(parents)
    A = torch.zeros(3, J, J)
    for j in range(J):
        A[0, j, j] = 1.0
        p = parents[j]
        if p >= 0:
            A[1, p, j] = 1.0  # parent -> child: the neighbour nearer the root
            A[2, j, p] = 1.0  # child -> parent: the neighbour farther from the root
    deg = A.sum(dim=(0, 1))
    return A / deg.clamp_min(1.0)


class _Block(nn.Module):
    def __init__(self, cin: int, cout: int, A: Tensor, stride: int, kernel: int, dropout: float, residual: bool):
        super().__init__()
        self.register_buffer("A", A.clone())
        self.importance = nn.Parameter(torch.ones_like(A))
        self.k = A.shape[0]
        self.gcn = nn.Conv2d(cin, cout * self.k, 1)
        self.tcn = nn.Sequential(
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, (kernel, 1), (stride, 1), ((kernel - 1) // 2, 0)),
            nn.BatchNorm2d(cout),
            nn.Dropout(dropout, inplace=True),
        )
        if not residual:
            self.res = None
        elif cin == cout and stride == 1:
            self.res = nn.Identity()
        else:
            self.res = nn.Sequential(nn.Conv2d(cin, cout, 1, (stride, 1)), nn.BatchNorm2d(cout))
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        n, _, t, v = x.shape
        y = self.gcn(x).view(n, self.k, -1, t, v)
        y = torch.einsum("nkctv,kvw->nctw", y, self.A * self.importance)
        y = self.tcn(y)
        if self.res is not None:
            y = y + self.res(x)
        return self.relu(y)


class STGCN(nn.Module):
    """ST-GCN classifier over ``(N, 6, T, J)`` inputs. ``features(x)`` is the pooled penultimate layer."""

    def __init__(self, config: FeatureConfig):
        super().__init__()
        A = spatial_partitions(config.parents)
        J = len(config.parents)
        self.joint_norm = config.joint_norm
        self.data_bn = nn.BatchNorm1d(6 * J) if config.joint_norm else nn.BatchNorm2d(6)
        blocks = []
        cin = 6
        for i, (c, s) in enumerate(zip(config.channels, config.strides)):
            blocks.append(_Block(cin, c, A, s, config.temporal_kernel, 0.0 if i == 0 else config.dropout, i > 0))
            cin = c
        self.blocks = nn.ModuleList(blocks)
        self.head = nn.Linear(cin, config.n_classes)

    def _feature_map(self, x: Tensor) -> Tensor:
        n, c, t, v = x.shape
        if self.joint_norm:
            x = self.data_bn(x.permute(0, 1, 3, 2).reshape(n, c * v, t)).view(n, c, v, t).permute(0, 1, 3, 2)
        else:
            x = self.data_bn(x)
        for b in self.blocks:
            x = b(x)
        return x

    def features(self, x: Tensor) -> Tensor:
        return self._feature_map(x).mean(dim=(2, 3))

    def temporal_features(self, x: Tensor) -> Tensor:
        """The last block's map averaged over joints, before the temporal pooling: ``(N, T', feature_dim)``, one
        vector per output time step (``T' = T / prod(strides)``) -- the samples SIFID's Gaussians are fitted to."""
        return self._feature_map(x).mean(dim=3).transpose(1, 2)

    def forward(self, x: Tensor) -> Tensor:
        return self.head(self.features(x))


# ----------------------------------------------------------------------------------------------------------------
# Extractor = config + normalisation + network


class FeatureExtractor:
    """A trained recogniser with its input pipeline. Feed it joint positions; get features or class scores."""

    def __init__(self, config: FeatureConfig, model: STGCN, mean: np.ndarray, std: np.ndarray,
                 info: dict[str, Any] | None = None):
        self.config = config
        self.model = model.eval()
        self.mean = np.asarray(mean, dtype=np.float32)
        self.std = np.asarray(std, dtype=np.float32)
        self.info = dict(info or {})

    # -- input ---------------------------------------------------------------------------------------------------
    def clip_positions(self, positions: Any, names: Sequence[str], fps: float) -> np.ndarray:
        """The extractor's joints (by name) of one clip ``(F, J_any, 3)``, resampled to its fps."""
        if isinstance(positions, Tensor):
            positions = positions.detach().cpu().numpy()
        p = np.asarray(positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[-1] != 3 or p.shape[1] != len(names):
            raise ValueError(f"positions: expected (frames, {len(names)} joints, 3), got {p.shape}")
        p = p[:, select_joints(names, self.config.joint_names)]
        return resample_positions(p, fps, self.config.fps)

    def windows(self, clips: Sequence[np.ndarray], stride: int | None = None, tail: bool = True) -> np.ndarray:
        """All windows of clips already in the extractor's joints and fps (``clip_positions``). The default stride
        (= window) without ``tail`` gives each clip ``max(1, frames // window)`` disjoint windows."""
        stride = self.config.window if stride is None else stride
        if not clips:
            raise ValueError("no clips given")
        return np.concatenate([make_windows(c, self.config.window, stride, tail) for c in clips])

    def inputs(self, windows: np.ndarray) -> Tensor:
        """Normalised network input ``(n, 6, T, J)`` of raw windows ``(n, T, J, 3)`` in skeleton units."""
        c = self.config
        if windows.ndim != 4 or windows.shape[1] != c.window or windows.shape[2] != len(c.joint_names):
            raise ValueError(f"windows: expected (n, {c.window}, {len(c.joint_names)}, 3), got {windows.shape}")
        x = window_inputs(canonicalize(windows, c.up_axis, c.pairs, c.body_height), c.fps)
        return torch.from_numpy((x - self.mean) / self.std)

    # -- output --------------------------------------------------------------------------------------------------
    @torch.no_grad()
    def _run(self, windows: np.ndarray, fn: str, batch: int) -> np.ndarray:
        self.model.eval()
        out = []
        for s in range(0, windows.shape[0], batch):
            x = self.inputs(windows[s : s + batch])
            out.append(getattr(self.model, fn)(x).double().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.config.feature_dim))

    def features(self, windows: np.ndarray, batch: int = 256) -> np.ndarray:
        """Penultimate-layer features ``(n, feature_dim)`` float64 of raw windows ``(n, T, J, 3)``."""
        return self._run(windows, "features", batch)

    def temporal_features(self, windows: np.ndarray, batch: int = 256) -> np.ndarray:
        """Per-time-step features ``(n, T', feature_dim)`` float64 of raw windows (``features`` is their mean)."""
        if windows.shape[0] == 0:
            return np.zeros((0, 0, self.config.feature_dim))
        return self._run(windows, "temporal_features", batch)

    def logits(self, windows: np.ndarray, batch: int = 256) -> np.ndarray:
        return self._run(windows, "forward", batch)

    def predict(self, windows: np.ndarray, batch: int = 256) -> np.ndarray:
        return self.logits(windows, batch).argmax(axis=1)

    # -- persistence ---------------------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "config": dataclasses.asdict(self.config),
            "model": self.model.state_dict(),
            "mean": torch.from_numpy(self.mean),
            "std": torch.from_numpy(self.std),
            "info": json.loads(json.dumps(self.info)),
            "modi_version": modi_version,
        }

    def save(self, path: str | os.PathLike) -> None:
        """One file with config, skeleton (joint names + parents), normalisation, weights and training info;
        written atomically (``modi.faults``: a full disk is one line, an earlier file stays intact)."""
        atomic_torch_save(self.state(), path)


def load_extractor(path: str | os.PathLike) -> FeatureExtractor:
    """Load a file written by :meth:`FeatureExtractor.save`; a CheckpointError says what is wrong with it."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"feature extractor not found: {path}")
    st = load_data(path, "feature-extractor file")  # as data only: code in the file is refused unrun
    if not isinstance(st, dict) or st.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a modi feature-extractor file (expected format {FORMAT!r})")
    cfg = dict(st["config"])
    config = FeatureConfig(**cfg)
    model = STGCN(config)
    try:
        model.load_state_dict(st["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not match the stored config ({exc})") from None
    return FeatureExtractor(config, model, st["mean"].numpy(), st["std"].numpy(), st.get("info", {}))


# ----------------------------------------------------------------------------------------------------------------
# Labelled data


@dataclass
class LabelledClip:
    name: str  # path relative to the data root
    positions: np.ndarray  # (F, J, 3) in the extractor's joints, at the extractor's fps
    label: int


def _find_label_names(root: Path, key: str) -> list[str] | None:
    """Names from ``cfg/{key}_label.txt``, minus a prefix they all share (Bandai: ``dataset-1_walk`` -> ``walk``)."""
    for d in [root, *root.parents][:3]:
        f = d / "cfg" / f"{key}_label.txt"
        if f.is_file():
            names = [ln.strip() for ln in f.read_text().splitlines() if ln.strip()]
            prefix = os.path.commonprefix(names) if len(names) > 1 else ""
            cut = max(prefix.rfind("_"), prefix.rfind("-")) + 1
            return [n[cut:] for n in names] if cut and all(len(n) > cut for n in names) else names
    return None


def load_labelled_folder(
    root: str | os.PathLike,
    label_key: str = "content",
    fps: float = 30.0,
    progress: bool = True,
) -> tuple[list[LabelledClip], list[str], list[str], list[int], float]:
    """Read every BVH under ``root`` that has a JSON beside it holding an integer ``label_key``.

    Returns ``(clips, class_names, joint_names, parents, body_height)``. Class names come from
    ``cfg/{label_key}_label.txt`` (looked up in ``root`` and its two parents; Bandai-Namco's layout), else
    ``class_<i>``. An anchor root with a single child (Bandai's ``joint_Root`` above ``Hips``) is dropped, as
    ``modi.data.dataset.motion_from_bvh`` does, so generated motions of the promoted skeleton match by name. All clips must share the skeleton's joint names.
    """
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"data folder not found: {root}")
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() == ".bvh")
    labelled = []
    for f in files:
        js = f.with_suffix(".json")
        if not js.is_file():
            continue
        try:
            meta = json.loads(js.read_text())
            label = int(meta[label_key])
        except (ValueError, KeyError, TypeError) as exc:
            raise UserError(f"{js}: no integer {label_key!r} label ({exc})") from None
        labelled.append((f, label))
    if not labelled:
        raise UserError(f"no labelled BVH files under {root} (need a JSON with {label_key!r} beside each BVH)")
    names = _find_label_names(root, label_key)
    top = max(lab for _, lab in labelled)
    if names is None:
        names = [f"class_{i}" for i in range(top + 1)]
    if top >= len(names) or min(lab for _, lab in labelled) < 0:
        raise UserError(f"labels out of range: found {top}, but only {len(names)} class names")

    it = labelled if not progress else tqdm(labelled, desc="loading clips", unit="clip", leave=False)
    raw = []
    ref_names = None
    skeleton = None
    for f, label in it:
        b = bvh_io.load(f)
        if ref_names is None:
            ref_names, skeleton = list(b.names), b.skeleton()
        elif list(b.names) != ref_names:
            raise UserError(f"{f}: its joints differ from {labelled[0][0].name}; one skeleton per data folder")
        raw.append((str(f.relative_to(root)), bvh_positions(b), b.fps, label))
    anchor = len(ref_names) > 1 and skeleton.children(0) == [1]
    keep = list(range(1, len(ref_names))) if anchor else list(range(len(ref_names)))
    joint_names = [ref_names[j] for j in keep]
    parents = _reindex_parents(skeleton.parents, keep)
    clips = [LabelledClip(n, resample_positions(p[:, keep], r, fps), lab) for n, p, r, lab in raw]
    try:
        height = float(skeleton.height())
    except Exception:  # noqa: BLE001 -- fall back to the data's own vertical extent
        height = 0.0
    if not height > 0:
        all_p = np.concatenate([c.positions for c in clips])
        height = float(np.ptp(all_p[..., 1], axis=0).max()) or 1.0
    return clips, names, joint_names, parents, height


def split_by_file(clips: Sequence[LabelledClip], holdout: float = 0.2, seed: int = 0) -> tuple[list[int], list[int]]:
    """Class-stratified split by file: per class, ``round(holdout * n)`` files (at least 1 when the class has
    2+ files, none when it has 1 -- a lone clip cannot be both learned and tested) go to the held-out set."""
    if not 0 < holdout < 1:
        raise ValueError(f"holdout must be in (0, 1), got {holdout}")
    rng = np.random.default_rng(seed)
    train, held = [], []
    by_class: dict[int, list[int]] = {}
    for i, c in enumerate(clips):
        by_class.setdefault(c.label, []).append(i)
    for lab in sorted(by_class):
        idx = sorted(by_class[lab], key=lambda i: clips[i].name)
        n_hold = 0 if len(idx) == 1 else max(1, int(round(holdout * len(idx))))
        order = rng.permutation(len(idx))
        held += [idx[k] for k in order[:n_hold]]
        train += [idx[k] for k in order[n_hold:]]
    return sorted(train), sorted(held)


def windows_and_labels(clips: Sequence[LabelledClip], window: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    ws, ls = [], []
    for c in clips:
        w = make_windows(c.positions, window, stride)
        ws.append(w)
        ls.append(np.full(len(w), c.label))
    return np.concatenate(ws), np.concatenate(ls)


# ----------------------------------------------------------------------------------------------------------------
# Training


def _augment(canon: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """On canonical windows (Y up): small heading jitter (the facing estimate is not exact), body-size jitter."""
    n = canon.shape[0]
    ang = rng.uniform(-np.pi / 12, np.pi / 12, size=n)
    scale = rng.uniform(0.9, 1.1, size=n)
    out = canon.copy()
    x, z = out[..., 0].copy(), out[..., 2].copy()
    c, s = np.cos(ang)[:, None, None], np.sin(ang)[:, None, None]
    out[..., 0] = c * x + s * z
    out[..., 2] = -s * x + c * z
    return out * scale[:, None, None, None]


def train_feature_extractor(
    train_windows: np.ndarray,
    train_labels: np.ndarray,
    config: FeatureConfig,
    val_windows: np.ndarray | None = None,
    val_labels: np.ndarray | None = None,
    epochs: int = 30,
    batch_size: int = 64,
    lr: float = 2e-3,
    weight_decay: float = 1e-4,
    max_seconds: float | None = None,
    seed: int = 0,
    progress: bool = True,
    augment: bool = True,
) -> tuple[FeatureExtractor, dict[str, Any]]:
    """Train the recogniser on raw windows ``(n, T, J, 3)`` with integer labels.

    Classes are balanced by sampling (each class equally likely per batch) because real action sets are
    skewed (Bandai: 30 walk clips, 1 kick clip). AdamW with a cosine schedule; ``max_seconds`` stops early
    (the schedule is laid out for ``epochs``). Returns the extractor and a history with the held-out top-1.
    """
    if train_windows.ndim != 4 or train_windows.shape[0] != len(train_labels):
        raise ValueError(f"train_windows {train_windows.shape} and {len(train_labels)} labels do not match")
    if train_labels.min() < 0 or train_labels.max() >= config.n_classes:
        raise ValueError(f"labels must lie in [0, {config.n_classes})")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    x_all = window_inputs(canonicalize(train_windows, config.up_axis, config.pairs, config.body_height), config.fps)
    # per channel (6, 1, 1) by default: a joint's mean place (left hand on the left) is what tells it apart
    axes = (0, 2) if config.joint_norm else (0, 2, 3)
    mean = x_all.mean(axis=axes, keepdims=True)[0]
    std = x_all.std(axis=axes, keepdims=True)[0] + 1e-3
    std = std.astype(np.float32)
    model = STGCN(config)
    extractor = FeatureExtractor(config, model, mean, std)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    n = train_windows.shape[0]
    steps_per_epoch = max(1, n // batch_size)
    total = epochs * steps_per_epoch
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=total, pct_start=0.1)
    counts = np.bincount(train_labels, minlength=config.n_classes).astype(np.float64)
    p = 1.0 / counts[train_labels]
    p /= p.sum()
    loss_fn = nn.CrossEntropyLoss(label_smoothing=0.1)
    history: dict[str, Any] = {"epochs": [], "train_windows": int(n)}
    bar = tqdm(total=total, desc="train features", unit="step", disable=not progress)
    start = time.perf_counter()
    cpu_start = time.process_time()
    stopped_early = False
    for epoch in range(epochs):
        model.train()
        run_loss, run_correct, seen = 0.0, 0, 0
        for _ in range(steps_per_epoch):
            idx = rng.choice(n, size=batch_size, p=p)
            canon = canonicalize(train_windows[idx], config.up_axis, config.pairs, config.body_height)
            if augment:
                canon = _augment(canon, rng)
            x = torch.from_numpy((window_inputs(canon, config.fps) - mean) / std)
            y = torch.from_numpy(train_labels[idx]).long()
            logits = model(x)
            loss = loss_fn(logits, y)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            run_loss += loss.item() * len(idx)
            run_correct += int((logits.argmax(1) == y).sum())
            seen += len(idx)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{run_loss / seen:.3f}", acc=f"{run_correct / seen:.2f}")
            if max_seconds is not None and time.perf_counter() - start > max_seconds:
                stopped_early = True
                break
        entry = {"epoch": epoch + 1, "loss": run_loss / max(seen, 1), "train_acc": run_correct / max(seen, 1)}
        if val_windows is not None and val_labels is not None and len(val_labels):
            entry["val_top1"] = float((extractor.predict(val_windows) == val_labels).mean())
        history["epochs"].append(entry)
        if stopped_early:
            break
    if bar is not None:
        bar.close()
    model.eval()
    history["seconds"] = time.perf_counter() - start
    history["cpu_seconds"] = time.process_time() - cpu_start  # comparable when other jobs share the cores
    history["stopped_early"] = stopped_early
    if val_windows is not None and val_labels is not None and len(val_labels):
        pred = extractor.predict(val_windows)
        history["val_top1"] = float((pred == val_labels).mean())
        per_class = {}
        for c in np.unique(val_labels):
            m = val_labels == c
            per_class[config.class_names[int(c)]] = float((pred[m] == c).mean())
        history["val_per_class"] = per_class
        history["val_balanced_top1"] = float(np.mean(list(per_class.values())))
        history["val_windows"] = int(len(val_labels))
    extractor.info.update(history)
    return extractor, history
