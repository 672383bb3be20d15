"""``Motion``: a clip as local joint rotations + root trajectory on a fixed-offset skeleton.

This is the form every representation, model and metric works on, and the one motion type the public API
(:mod:`modi`) returns: MoDi samples, GANimator outputs, encoder reconstructions and BVH files all come back as a
``Motion``, with its frame rate and length unit always known (``positions(unit="m")`` gives metres).

It deliberately has no per-joint translations: bones keep their length. ``Motion.from_bvh`` therefore has to
decide what to do with BVH files that animate non-root translations (see its docstring); everything else
round-trips exactly through ``to_bvh``, Bandai's static ``joint_Root`` included (``static_root``).
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from modi.core.body import UNIT_SCALES, guess_unit, unit_name
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import (
    euler_to_quat,
    matrix_to_quat,
    quat_apply,
    quat_canonical,
    quat_inverse,
    quat_mul,
    quat_slerp,
    quat_to_euler,
    quat_unflip,
)
from modi.core.skeleton import Skeleton
from modi.io import bvh as bvh_io
from modi.io import gltf

__all__ = ["Motion"]


def _snap_fps(fps: float) -> float:
    """BVH frame times are printed rounded (0.0333333, 0.016667): recover the integer rate they stand for."""
    r = round(fps)
    return float(r) if r > 0 and abs(fps - r) <= 1e-4 * fps else float(fps)


def _guessed_unit(skeleton: Skeleton) -> str:
    """:func:`modi.core.body.guess_unit` of the skeleton's size, remembered on the skeleton object (many motions
    share one skeleton: a codec's samples, a dataset's clips) and recomputed when its offsets change."""
    key = (skeleton.offsets.tobytes(), tuple(skeleton.names))
    memo = skeleton.__dict__.get("_unit_memo")
    if memo is None or memo[0] != key:
        memo = (key, guess_unit(skeleton.height()).unit)
        skeleton.__dict__["_unit_memo"] = memo
    return memo[1]


def _same_tensor(a: Tensor, b: Tensor) -> bool:
    """Exactly equal values, dtype and device (``torch.equal`` refuses to compare across devices)."""
    return a.shape == b.shape and a.dtype == b.dtype and a.device == b.device and bool(torch.equal(a, b))


def _rest_positions(parents: list[int], offsets: np.ndarray) -> np.ndarray:
    pos = np.zeros_like(offsets)
    for j, p in enumerate(parents):
        if p >= 0:
            pos[j] = pos[p] + offsets[j]
    return pos


def _euler_quats(euler: np.ndarray, orders: list[str], dtype: torch.dtype) -> Tensor:
    """(F, J, 3) degrees, per-joint order -> (F, J, 4), one batched call per distinct order."""
    e = torch.from_numpy(np.ascontiguousarray(euler)).to(dtype)
    out = torch.empty(e.shape[:-1] + (4,), dtype=dtype)
    for order in sorted(set(orders)):
        idx = [j for j, o in enumerate(orders) if o == order]
        out[:, idx] = euler_to_quat(e[:, idx], order)
    return out


def fold_dummy_root(parents, trans: np.ndarray, euler: np.ndarray, quat0: torch.Tensor, scale: float):
    """Bandai's pattern: a *static* joint 0 (constant channels) whose only child carries the animated
    translation (``joint_Root`` above ``Hips``). Joint 0 is rigid, so ``pos[a](t) = root + R0 @ t_a(t)``: returns
    ``(root track with all of t_a moved in, a)`` (the child's offset is then zero), or None for any other file.
    ``trans`` (F, J, 3) local translations, ``euler`` (F, J, 3) channel angles, ``quat0`` joint 0's rotation."""
    children0 = [j for j, p in enumerate(parents) if p == 0]
    if len(children0) != 1:
        return None
    a = children0[0]
    root_static = np.ptp(trans[:, 0], axis=0).max() <= 1e-9 * scale and np.ptp(euler[:, 0], axis=0).max() <= 1e-9
    child_moves = np.abs(trans[:, a] - trans[:, a].mean(axis=0)).max() > 1e-6 * scale
    if not (root_static and child_moves):
        return None
    r0 = quat0.to(torch.float64).expand(trans.shape[0], 4)
    return trans[:, 0] + quat_apply(r0, torch.from_numpy(trans[:, a])).numpy(), a


@dataclass(eq=False, repr=False)
class Motion:
    """A clip: local unit quaternions ``rotations (T, J, 4)`` (w,x,y,z, parent frame), ``root_positions (T, 3)``
    (joint 0's global position), on ``skeleton`` (fixed offsets), sampled at ``fps``.

    ``unit`` is the length unit of the offsets and root positions (``"metres"``, ``"centimetres"``, ``"inches"``,
    ``"millimetres"``): given, or guessed from the body size (:func:`modi.core.body.guess_unit`) when None, so it is
    always known. ``static_root`` (3,) is set by :meth:`from_bvh` for files whose joint 0 is a static anchor above
    the animated child (Bandai's ``joint_Root`` over ``Hips``): the child's motion is the root track, and joint 0
    stays where the file has it in :meth:`positions` and :meth:`to_bvh`. ``contacts`` maps foot joint names to
    ``(T,)`` bool ground-contact labels where a model predicted them (MoDi, GANimator): :meth:`to_gltf` writes them
    into the file and :func:`modi.show` draws them.

    ``==`` compares every field exactly (``torch.equal``); ``repr`` is one line.
    """

    skeleton: Skeleton
    rotations: Tensor
    root_positions: Tensor
    fps: float
    unit: str | None = None
    static_root: Tensor | None = None
    contacts: dict[str, Tensor] | None = None

    def __post_init__(self) -> None:
        self.rotations = torch.as_tensor(self.rotations)
        if not self.rotations.is_floating_point():
            self.rotations = self.rotations.to(torch.get_default_dtype())
        self.root_positions = torch.as_tensor(self.root_positions, dtype=self.rotations.dtype,
                                              device=self.rotations.device)
        j = self.skeleton.n_joints
        if self.rotations.ndim != 3 or self.rotations.shape[1:] != (j, 4):
            raise ValueError(f"Motion: rotations must be (T, {j}, 4), got {tuple(self.rotations.shape)}")
        t = self.rotations.shape[0]
        if t < 1:
            raise ValueError("Motion: needs at least one frame")
        if self.root_positions.shape != (t, 3):
            raise ValueError(f"Motion: root_positions must be ({t}, 3), got {tuple(self.root_positions.shape)}")
        self.fps = float(self.fps)
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"Motion: fps must be positive, got {self.fps}")
        self.unit = _guessed_unit(self.skeleton) if self.unit is None else unit_name(self.unit)
        if self.static_root is not None:
            self.static_root = torch.as_tensor(self.static_root, dtype=self.rotations.dtype,
                                               device=self.rotations.device).reshape(3)
        if self.contacts is not None:
            labels = {}
            for name, c in self.contacts.items():
                if name not in self.skeleton.names:
                    raise ValueError(f"Motion: contact labels for {name!r}, which is not a joint of the skeleton")
                c = torch.as_tensor(np.asarray(c) if not isinstance(c, Tensor) else c).to(torch.bool).cpu()
                if c.shape != (t,):
                    raise ValueError(f"Motion: contact labels of {name!r} must be ({t},), got {tuple(c.shape)}")
                labels[name] = c
            self.contacts = labels

    def _like(self, rotations: Tensor, root_positions: Tensor, fps: float | None = None,
              skeleton: Skeleton | None = None, static_root: Tensor | None | bool = True,
              frames: Sequence[int] | slice | None = None) -> "Motion":
        """A Motion with this one's unit (and static root, unless told otherwise); contact labels follow ``frames``
        (the source frame of each new frame), kept for the joints ``skeleton`` still has."""
        keep = self.static_root if static_root is True else static_root
        if keep is not None:
            keep = keep.to(dtype=rotations.dtype, device=rotations.device)
        sk = self.skeleton if skeleton is None else skeleton
        contacts = None
        if self.contacts is not None:
            pick = slice(None) if frames is None else frames
            contacts = {k: v[pick] for k, v in self.contacts.items() if k in sk.names}
        return Motion(sk, rotations, root_positions, self.fps if fps is None else fps, self.unit, keep, contacts)

    # ------------------------------------------------------------------ basics
    @property
    def n_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def n_joints(self) -> int:
        return self.skeleton.n_joints

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the one after the last (``n_frames / fps``)."""
        return self.n_frames / self.fps

    def __repr__(self) -> str:
        sk = self.skeleton
        anchor = f", static root {sk.names[0]}" if self.static_root is not None else ""
        return (f"Motion({self.n_frames} frames at {self.fps:g} fps, {self.n_joints} joints (root {sk.names[0]!r}"
                f"{anchor}), {self.unit}, {str(self.rotations.dtype).replace('torch.', '')} on "
                f"{self.rotations.device})")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Motion):
            return NotImplemented
        sr_a, sr_b = self.static_root, other.static_root
        ca, cb = self.contacts or {}, other.contacts or {}
        same_contacts = ca.keys() == cb.keys() and all(torch.equal(ca[k], cb[k]) for k in ca)
        return (self.skeleton == other.skeleton and self.fps == other.fps and self.unit == other.unit
                and same_contacts
                and _same_tensor(self.rotations, other.rotations)
                and _same_tensor(self.root_positions, other.root_positions)
                and ((sr_a is None and sr_b is None) or (sr_a is not None and sr_b is not None
                                                         and _same_tensor(sr_a, sr_b))))

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by value

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> "Motion":
        return self._like(self.rotations.to(dtype=dtype, device=device),
                          self.root_positions.to(dtype=dtype, device=device))

    def crop(self, start: int, stop: int | None = None) -> "Motion":
        """Frames ``[start, stop)``."""
        sl = slice(start, stop)
        return self._like(self.rotations[sl], self.root_positions[sl], frames=sl)

    def forward_kinematics(self) -> tuple[Tensor, Tensor]:
        """(global positions (T, J, 3), global rotations (T, J, 4)) by the reference FK, in the motion's unit
        (joint 0 rides on the root track: see :meth:`positions` for the file's static anchor)."""
        return forward_kinematics(self.rotations, self.skeleton.offsets, self.skeleton.parents, self.root_positions)

    def positions(self, unit: str | None = None) -> Tensor:
        """Global joint positions ``(T, J, 3)`` (the reference FK; cost: one FK pass).

        ``unit``: None keeps the motion's own :attr:`unit`; ``"m"`` / ``"metres"`` (also ``"cm"``, ``"mm"``,
        ``"in"`` and their long names) converts. A static anchor (``static_root``) stays where the file put it."""
        pos = self.forward_kinematics()[0]
        if self.static_root is not None:
            pos = pos.clone()
            pos[:, 0] = self.static_root
        if unit is not None:
            pos = pos * (UNIT_SCALES[self.unit] / UNIT_SCALES[unit_name(unit)])
        return pos

    def metres_per_unit(self) -> float:
        """The factor from the motion's unit to metres."""
        return UNIT_SCALES[self.unit]

    # ------------------------------------------------------------------ BVH
    @classmethod
    def from_bvh(cls, bvh_or_path: "bvh_io.Bvh | str | os.PathLike", dtype: torch.dtype = torch.float64, *,
                 translations: str = "mean", unit: str | None = None) -> "Motion":
        """Convert a :class:`modi.io.bvh.Bvh` (or a path to one) into a Motion: the one BVH reader of modi (MoDi's
        data, GANimator's clips, the metrics and :func:`modi.load` all read through it). Cost: parsing the file and
        one Euler-to-quaternion pass.

        * rotations: each joint's Euler channels in its own order, made sign-continuous over time
          (first frame with w >= 0); joints without rotation channels get the identity.
        * root_positions: joint 0's position channels (its OFFSET where it has none).
        * offsets: a non-root joint's translation (position channels where present, else OFFSET).
        * fps: ``1 / frame_time``, snapped to an integer when the file's frame time is a rounded 1/n
          (``Frame Time: 0.008333`` is 120 fps, not 120.0048).
        * unit: given, or guessed from the body size (see :class:`Motion`).

        Files that animate the translation of non-root joints cannot be represented exactly by
        fixed bones. Two cases are handled:

        * a *static* joint 0 (constant channels) whose only child carries the translation — e.g.
          Bandai's ``joint_Root`` above ``Hips``: that child gets a zero offset and its animated
          translation moves into ``root_positions``; joint 0's fixed position is kept as ``static_root``, so
          :meth:`positions` and :meth:`to_bvh` reproduce the file's poses exactly (every joint, the anchor
          included). :meth:`subset` without joint 0 gives an exact child-rooted motion;
        * anything else (e.g. a few stretchy bones in the Elephant rig): with ``translations="mean"`` (the
          default) the translation's temporal mean becomes the fixed offset, and a warning says how large the
          discarded stretch was; ``translations="offsets"`` keeps the declared OFFSETs silently (GANimator's
          loader, as the authors' code).
        """
        if translations not in ("mean", "offsets"):
            raise ValueError(f"from_bvh: translations must be 'mean' or 'offsets', got {translations!r}")
        b = bvh_or_path if isinstance(bvh_or_path, bvh_io.Bvh) else bvh_io.load(bvh_or_path)
        where = "" if isinstance(bvh_or_path, bvh_io.Bvh) else f"{os.fspath(bvh_or_path)}: "
        orders = b.rotation_orders
        euler = b.euler_degrees()
        trans = b.local_translations()  # (F, J, 3)
        quats = _euler_quats(euler, orders, torch.float64)
        offsets = trans.mean(axis=0) if translations == "mean" else b.offsets.copy()
        offsets[0] = b.offsets[0]
        root = trans[:, 0].copy()

        scale = float(np.ptp(_rest_positions(b.parents, offsets), axis=0).max())
        scale = scale if scale > 0 else max(float(np.abs(trans).max()), 1.0)
        dev = np.abs(trans - offsets[None]).max(axis=(0, 2))  # (J,) max deviation from the fixed offset
        animated = dev > 1e-6 * scale
        animated[0] = False

        static_root = None
        folded = fold_dummy_root(b.parents, trans, euler, quats[0, 0], scale)
        if folded is not None:
            static_root = torch.from_numpy(trans[0, 0].copy())
            root, a = folded
            offsets[a] = 0.0
            animated[a] = False
        if animated.any() and translations == "mean":
            names = [b.names[j] for j in np.nonzero(animated)[0]]
            warnings.warn(
                f"{where}Motion keeps bones rigid: the animated translations of {len(names)} joint(s) "
                f"({', '.join(names[:5])}{', ...' if len(names) > 5 else ''}; up to {dev[animated].max() / scale:.2%} "
                f"of the skeleton's size) are replaced by their mean",
                stacklevel=2,
            )
        skeleton = Skeleton(
            names=list(b.names),
            parents=list(b.parents),
            offsets=offsets,
            end_sites={k: v.copy() for k, v in b.end_sites.items()},
            rotation_orders=list(orders),
        )
        rotations = quat_unflip(torch.cat((quat_canonical(quats[:1]), quats[1:])), dim=0)
        return cls(skeleton, rotations.to(dtype), torch.from_numpy(root).to(dtype), _snap_fps(b.fps), unit,
                   None if static_root is None else static_root.to(dtype))

    def to_bvh(self, path: str | os.PathLike | None = None, precision: int = 6) -> bvh_io.Bvh:
        """The motion as a :class:`modi.io.bvh.Bvh` (root: 6 channels, XYZ position + rotation; the others 3
        rotation channels, each in ``skeleton.rotation_orders``), written to ``path`` too when given (atomically,
        ``precision`` decimals). A static anchor (``static_root``) is written where the file had it, its child with
        position channels, so a write-back of what :meth:`from_bvh` read reproduces the file's poses."""
        sk = self.skeleton
        orders = sk.rotation_orders or ["ZYX"] * sk.n_joints
        rot = self.rotations.detach().to("cpu", torch.float64)
        euler = torch.empty(rot.shape[:-1] + (3,), dtype=torch.float64)
        for order in sorted(set(orders)):
            idx = [j for j, o in enumerate(orders) if o == order]
            euler[:, idx] = quat_to_euler(rot[:, idx], order)
        root = self.root_positions.detach().to("cpu", torch.float64)
        channels = [[f"{c}rotation" for c in o] for o in orders]
        channels[0] = ["Xposition", "Yposition", "Zposition"] + channels[0]
        offsets = sk.offsets.copy()
        children0 = sk.children(0)
        if self.static_root is not None and len(children0) == 1:
            a = children0[0]
            anchor = self.static_root.detach().to("cpu", torch.float64).expand(self.n_frames, 3)
            local = quat_apply(quat_inverse(rot[:, 0]), root - anchor)  # the child's translation under joint 0
            channels[a] = ["Xposition", "Yposition", "Zposition"] + channels[a]
            offsets[a] = local[0].numpy()
            cols = [anchor, euler[:, 0]]
            for j in range(1, sk.n_joints):
                cols += [local, euler[:, j]] if j == a else [euler[:, j]]
            motion = torch.cat(cols, dim=1).numpy()
        else:
            motion = torch.cat((root, euler.reshape(self.n_frames, -1)), dim=1).numpy()
        out = bvh_io.Bvh(
            names=list(sk.names),
            parents=list(sk.parents),
            offsets=offsets,
            channels=channels,
            end_sites={k: np.asarray(v, dtype=np.float64).copy() for k, v in sk.end_sites.items()},
            frame_time=1.0 / self.fps,
            motion=motion,
        )
        if path is not None:
            bvh_io.save(out, path, precision)
        return out

    def save(self, path: str | os.PathLike, precision: int = 6) -> None:
        """Write the motion as a BVH file (:meth:`to_bvh` with a path)."""
        self.to_bvh(path, precision)

    def contact_arrays(self) -> dict[str, np.ndarray] | None:
        """The contact labels as numpy arrays ({joint name: (T,) bool}), or None: what the file writers take."""
        return None if self.contacts is None else {k: v.numpy() for k, v in self.contacts.items()}

    @classmethod
    def from_gltf(cls, path: str | os.PathLike) -> "Motion":
        """A glTF file's skeleton animation as a Motion in metres (bones rigid: a non-root joint's offset is the mean
        of its translation track; the transform above the skeleton is folded into the root); contact labels come
        back from the animation's extras, as :meth:`to_gltf` writes them."""
        tr = gltf.read_tracks(path)
        above = np.asarray(tr.above, dtype=np.float64)
        s = float(np.linalg.norm(above[:3, 0])) or 1.0
        rot = torch.from_numpy(above[:3, :3] / s)
        q_above = matrix_to_quat(rot).to(torch.float64)
        trans = tr.translations.to(torch.float64)
        root = s * trans[:, 0] @ rot.T + torch.from_numpy(above[:3, 3])
        rotations = tr.rotations.to(torch.float64).clone()
        rotations[:, 0] = quat_mul(q_above.expand_as(rotations[:, 0]), rotations[:, 0])
        offsets = s * trans.mean(0).numpy()
        offsets[0] = root[0].numpy()
        skeleton = Skeleton(list(tr.names), list(tr.parents), offsets)
        contacts = None
        if tr.contacts is not None and tr.contacts.any():
            contacts = {tr.names[j]: tr.contacts[:, j] for j in range(len(tr.names)) if tr.contacts[:, j].any()}
        return cls(skeleton, rotations, root, tr.fps, "metres", contacts=contacts)

    def to_gltf(self, path: str | os.PathLike, *, scale: float | None = None, mesh: bool = False) -> Path:
        """Write the motion as glTF 2.0 (``.glb`` binary or ``.gltf`` JSON, by the suffix), Y up in metres, with its
        contact labels (if any) in the animation's extras; returns the path. ``scale`` (metres per unit) defaults to
        the motion's :attr:`unit`; ``mesh`` adds a skinned stick mesh for viewers that draw no skeleton."""
        gltf.save(self.to_bvh(), path, scale=self.metres_per_unit() if scale is None else scale,
                  contacts=self.contact_arrays(), mesh=mesh)
        return Path(path)

    # ------------------------------------------------------------------ resampling
    def resample(self, fps: float) -> "Motion":
        """Resample in time to ``fps``: slerp for rotations, linear for the root.

        Frame ``i`` of the result is at source time ``i * old/new`` (frames), so the first frame is
        kept and the result has ``floor((T - 1) * new / old) + 1`` frames (never past the clip's end).
        """
        fps = float(fps)
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"resample: fps must be positive, got {fps}")
        if abs(fps - self.fps) <= 1e-9 * self.fps:
            return self._like(self.rotations.clone(), self.root_positions.clone())
        ratio = self.fps / fps  # source frames per target frame
        n = int(math.floor((self.n_frames - 1) / ratio + 1e-9)) + 1
        t = torch.arange(n, dtype=torch.float64) * ratio
        i0 = torch.clamp(torch.floor(t).long(), 0, self.n_frames - 1)
        i1 = torch.clamp(i0 + 1, max=self.n_frames - 1)
        frac = (t - i0.to(torch.float64)).clamp(0.0, 1.0).to(self.rotations.dtype).to(self.rotations.device)
        i0, i1 = i0.to(self.rotations.device), i1.to(self.rotations.device)
        rot = quat_slerp(self.rotations[i0], self.rotations[i1], frac[:, None, None])
        root = self.root_positions[i0] * (1 - frac[:, None]) + self.root_positions[i1] * frac[:, None]
        nearest = torch.where(frac.cpu() < 0.5, i0.cpu(), i1.cpu())
        return self._like(rot, root, fps, frames=nearest)

    # ------------------------------------------------------------------ joint subsets
    def subset(self, keep_indices) -> "Motion":
        """Keep only ``keep_indices`` (any order; result in ascending original order) and re-parent.

        Each kept joint hangs from its nearest kept ancestor. Its new local rotation is the exact
        product of the dropped intermediate joints' rotations with its own (``G_parent^-1 G_joint``),
        so every kept joint's *global orientation* is preserved. Its new offset is the plain sum of the
        offsets along the dropped chain (the rest pose, all rotations identity) — one skeleton for
        every clip, as in MoDi/GANimator. A fixed offset cannot follow a dropped joint that rotates:
        for parent P, dropped J, child C the true translation ``t_J + R_J t_C`` varies with ``R_J``.
        So kept *positions* are exact when each dropped intermediate joint has an identity rotation
        (or nothing below it to move); otherwise they drift by that rotation's effect on the chain.

        Dropping the root is exact: the kept joint with no kept ancestor becomes the root and takes
        its global trajectory and orientation. A kept joint whose children were all dropped gets an
        End Site at its first dropped child's offset (for viewers).
        """
        sk = self.skeleton
        try:
            keep = sorted({int(k) for k in keep_indices})
        except (TypeError, ValueError):
            raise ValueError(f"subset: keep_indices must be joint indices, got {keep_indices!r}") from None
        if not keep:
            raise ValueError("subset: keep_indices is empty")
        if keep[0] < 0 or keep[-1] >= sk.n_joints:
            raise ValueError(f"subset: joint indices must be in 0..{sk.n_joints - 1}, got {keep[0]}..{keep[-1]}")
        kept = set(keep)
        new_index = {j: i for i, j in enumerate(keep)}
        new_parents: list[int] = []
        new_offsets = np.zeros((len(keep), 3))
        for i, j in enumerate(keep):
            off = np.zeros(3)
            a = j
            while a >= 0 and (a == j or a not in kept):
                off += sk.offsets[a]
                a = sk.parents[a]
            if a < 0:
                if i != 0:
                    raise ValueError(
                        f"subset: kept joints {sk.names[keep[0]]!r} and {sk.names[j]!r} have no common kept "
                        "ancestor (the result must be one tree)")
                new_parents.append(-1)
                new_offsets[i] = off if j != 0 else sk.offsets[0]
            else:
                new_parents.append(new_index[a])
                new_offsets[i] = off
        gpos, grot = self.forward_kinematics()
        rots = torch.empty(self.n_frames, len(keep), 4, dtype=self.rotations.dtype, device=self.rotations.device)
        for i, j in enumerate(keep):
            p = new_parents[i]
            if p < 0:
                rots[:, i] = grot[:, j]
            elif keep[p] == sk.parents[j]:
                rots[:, i] = self.rotations[:, j]  # direct child: keep the exact local rotation
            else:
                rots[:, i] = quat_mul(quat_inverse(grot[:, keep[p]]), grot[:, j])
        end_sites = {}
        for i, j in enumerate(keep):
            if j in sk.end_sites:
                end_sites[i] = np.asarray(sk.end_sites[j]).copy()
            elif i not in new_parents:
                dropped = sk.children(j)
                if dropped:
                    end_sites[i] = sk.offsets[dropped[0]].copy()
        orders = sk.rotation_orders or ["ZYX"] * sk.n_joints
        skeleton = Skeleton(
            names=[sk.names[j] for j in keep],
            parents=new_parents,
            offsets=new_offsets,
            end_sites=end_sites,
            rotation_orders=[orders[j] for j in keep],
        )
        rots = quat_unflip(torch.cat((quat_canonical(rots[:1]), rots[1:])), dim=0)
        return self._like(rots, gpos[:, keep[0]].clone(), skeleton=skeleton,
                          static_root=self.static_root if keep[0] == 0 and all(c in kept for c in sk.children(0))
                          else None)
