"""Motion <-> model tensors, with exact round trips.

One layout serves both systems (see ``modi.core.skeleton_graph``): entities are the ``J`` edges (joint ``j``'s local
rotation lives on the edge pointing to it; the root's on its abstract edge), then one root-motion entity, then
one entity per contact joint. Every entity has ``K`` channels; the shorter ones are zero-padded.

* **MoDi** (``rotation="quat"``, K=4): unit quaternions (w, x, y, z). Their sign is made continuous in time
  (first frame w >= 0, then each frame takes the sign closer to the previous one) so convolutions see smooth
  signals; both signs decode to the same rotation.
* **GANimator** (``rotation="6d"``, K=6): the first two columns of the rotation matrix; contacts are wired as
  virtual joints to their foot *and* to the root-motion entity. ``to_flat``/``from_flat`` give the flat
  ``(E*K, T)`` view (entity-major: each entity's channels contiguous) for code that wants GANimator's 2-D tensor.

Root-motion entity channels: ``root="velocity"`` (default; MoDi's choice) stores ``[x[t]-x[t-1], y[t],
z[t]-z[t-1]]`` -- horizontal displacement per frame in world axes and the absolute height (height does not
drift and is meaningful on its own); ``x[-1] = z[-1] = 0``, so frame 0 carries the starting ground position and
a cumulative sum restores the trajectory exactly. ``root="position"`` stores ``[x, y, z]``. ``root="velocity3"``
(the released MoDi's ``--use_velocity``, for imported checkpoints) differences all three axes. Y is up.
Contact entities hold the label (0/1 in data, a logit or probability from a model) in channel 0.

``leaf_rotations="drop"`` (MoDi's released preprocessing): the local rotation of a joint without children moves no
joint, so it is not data: the leaf's entity (its bone, which stays in the topology) holds the identity rotation
in every frame, and decoding returns the identity there whatever a model wrote. Joint positions still round-trip
exactly; only those invisible rotations (and any End Site marker they would turn) are lost. ``"keep"`` stores them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import torch
from torch import Tensor

from modi.core.contacts import DEFAULT_HEIGHT_FACTOR, DEFAULT_VELOCITY_FACTOR, foot_contacts
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import quat_normalize, quat_to_6d, sixd_to_quat
from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import EntityLayout
from modi.data.motion import Motion

ROTATION_WIDTH = {"quat": 4, "6d": 6}
ROOT_MODES = ("velocity", "position", "velocity3")
LEAF_ROTATIONS = ("keep", "drop")


def continuous_quats(q: Tensor, dim: int = -3) -> Tensor:
    """Flip quaternion signs so consecutive frames (along ``dim`` of a (..., T, ..., 4) tensor) have a
    non-negative dot product and the first frame has w >= 0. Same rotations, smooth signal."""
    dim = dim % q.ndim
    T = q.shape[dim]
    if T == 0:
        return q
    first = q.narrow(dim, 0, 1)
    sign0 = torch.where(first[..., :1] < 0, -1.0, 1.0).to(q.dtype)
    if T == 1:
        return q * sign0
    dots = (q.narrow(dim, 1, T - 1) * q.narrow(dim, 0, T - 1)).sum(-1, keepdim=True)
    flips = (dots < 0).to(torch.int64)
    parity = torch.cat([torch.zeros_like(flips.narrow(dim, 0, 1)), flips.cumsum(dim)], dim=dim) % 2
    sign = (1 - 2 * parity).to(q.dtype) * sign0
    return q * sign


def _swap_te(x: Tensor) -> Tensor:
    """Reverse the last three dimensions: (..., A, B, C) -> (..., C, B, A)."""
    return x.permute(*range(x.ndim - 3), -1, -2, -3)


@dataclass
class MotionRepresentation:
    """Encoder/decoder between a :class:`modi.data.motion.Motion` (plus contact labels) and a ``(K, E, T)`` tensor.

    All ``*_parts`` methods are batched over leading dimensions and differentiable; ``encode``/``decode``
    handle one ``Motion``.
    """

    skeleton: Skeleton
    feet: list[int]
    rotation: str = "quat"
    root: str = "velocity"
    contacts_to_root_motion: bool = False
    velocity_factor: float = DEFAULT_VELOCITY_FACTOR
    height_factor: float | None = DEFAULT_HEIGHT_FACTOR
    leaf_rotations: str = "keep"
    layout: EntityLayout = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.rotation not in ROTATION_WIDTH:
            raise ValueError(f"rotation must be one of {sorted(ROTATION_WIDTH)}, got {self.rotation!r}")
        if self.root not in ROOT_MODES:
            raise ValueError(f"root must be one of {ROOT_MODES}, got {self.root!r}")
        if self.leaf_rotations not in LEAF_ROTATIONS:
            raise ValueError(f"leaf_rotations must be one of {LEAF_ROTATIONS}, got {self.leaf_rotations!r}")
        self.feet = [int(f) for f in self.feet]
        self.layout = EntityLayout(list(self.skeleton.parents), self.feet, self.contacts_to_root_motion)

    # -------------------------------------------------------------------------------------------- shape facts

    @property
    def K(self) -> int:
        return ROTATION_WIDTH[self.rotation]

    @property
    def n_joints(self) -> int:
        return self.skeleton.n_joints

    @property
    def n_entities(self) -> int:
        return self.layout.n_entities

    @property
    def dropped_rotations(self) -> list[int]:
        """Joints whose rotation is not stored (``leaf_rotations="drop"``): every non-root joint without children."""
        if self.leaf_rotations == "keep":
            return []
        parents = list(self.skeleton.parents)
        has_child = {p for p in parents if p >= 0}
        return [j for j in range(1, len(parents)) if j not in has_child]

    def _identity_at_dropped(self, quats: Tensor) -> Tensor:
        """``quats (..., J, 4)`` with the identity at ``dropped_rotations`` (differentiable elsewhere)."""
        dropped = self.dropped_rotations
        if not dropped:
            return quats
        mask = torch.zeros(quats.shape[-2], 1, dtype=torch.bool, device=quats.device)
        mask[dropped] = True
        ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
        return torch.where(mask, ident, quats)

    @property
    def root_motion(self) -> int:
        return self.layout.root_motion

    @property
    def contacts(self) -> list[int]:
        return self.layout.contacts

    def entity_names(self) -> list[str]:
        return self.layout.entity_names(self.skeleton.names)

    # -------------------------------------------------------------------------------------------- tensors

    def encode_parts(self, rotations: Tensor, root_positions: Tensor, contacts: Tensor | None = None) -> Tensor:
        """``rotations (..., T, J, 4)`` local unit quats, ``root_positions (..., T, 3)``, ``contacts (..., T, F)``
        (zeros when ``None``) -> ``(..., K, E, T)``."""
        J, F, K = self.n_joints, len(self.feet), self.K
        if rotations.ndim < 3 or rotations.shape[-2:] != (J, 4):
            raise ValueError(f"encode: rotations must be (..., T, {J}, 4), got {tuple(rotations.shape)}")
        lead, T = rotations.shape[:-3], rotations.shape[-3]
        if root_positions.shape != (*lead, T, 3):
            raise ValueError(f"encode: root_positions must be {(*lead, T, 3)}, got {tuple(root_positions.shape)}")
        if contacts is None:
            contacts = rotations.new_zeros((*lead, T, F))
        if contacts.shape != (*lead, T, F):
            raise ValueError(f"encode: contacts must be {(*lead, T, F)}, got {tuple(contacts.shape)}")
        q = continuous_quats(self._identity_at_dropped(quat_normalize(rotations)), dim=-3)
        rot = q if self.rotation == "quat" else quat_to_6d(q)  # (..., T, J, K)
        rp = root_positions.to(rot.dtype)
        if self.root == "velocity":
            prev = torch.cat([torch.zeros_like(rp[..., :1, :]), rp[..., :-1, :]], dim=-2)
            rm = torch.stack([rp[..., 0] - prev[..., 0], rp[..., 1], rp[..., 2] - prev[..., 2]], dim=-1)
        elif self.root == "velocity3":
            rm = rp - torch.cat([torch.zeros_like(rp[..., :1, :]), rp[..., :-1, :]], dim=-2)
        else:
            rm = rp
        out = rot.new_zeros((*lead, T, self.n_entities, K))
        out[..., :J, :] = rot
        out[..., J, :3] = rm
        if F:
            out[..., J + 1:, 0] = contacts.to(rot.dtype)
        return _swap_te(out).contiguous()  # (..., T, E, K) -> (..., K, E, T)

    def decode_parts(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(..., K, E, T)`` -> ``(rotations (..., T, J, 4) unit quats, root_positions (..., T, 3),
        contacts (..., T, F))``. Padding channels are ignored; contacts are returned as stored (label or logit)."""
        J, F, K, E = self.n_joints, len(self.feet), self.K, self.n_entities
        if x.ndim < 3 or x.shape[-3] != K or x.shape[-2] != E:
            raise ValueError(f"decode: expected (..., K={K}, E={E}, T), got {tuple(x.shape)}")
        t = _swap_te(x)  # (..., T, E, K)
        rot = t[..., :J, :]
        quats = self._identity_at_dropped(quat_normalize(rot) if self.rotation == "quat" else sixd_to_quat(rot))
        rm = t[..., J, :3]
        if self.root == "velocity":
            xz = torch.cumsum(rm[..., 0::2], dim=-2)  # x and z: a view (a list index is a host tensor)
            root = torch.stack([xz[..., 0], rm[..., 1], xz[..., 1]], dim=-1)
        elif self.root == "velocity3":
            root = torch.cumsum(rm, dim=-2)
        else:
            root = rm
        contacts = t[..., J + 1:J + 1 + F, 0]
        return quats, root, contacts

    def positions(self, x: Tensor) -> Tensor:
        """Global joint positions ``(..., T, J, 3)`` of a representation tensor (differentiable FK)."""
        quats, root, _ = self.decode_parts(x)
        offsets = torch.as_tensor(self.skeleton.offsets, dtype=quats.dtype, device=quats.device)
        return forward_kinematics(quats, offsets, self.skeleton.parents, root)[0]

    # -------------------------------------------------------------------------------------------- Motion

    def contacts_of(self, motion: Any) -> Tensor:
        """Contact labels (T, F) of a Motion from foot velocity and height (see ``modi.core.contacts``)."""
        pos = motion.positions()
        return foot_contacts(pos, self.feet, self.skeleton.height(), float(motion.fps),
                             self.velocity_factor, self.height_factor)

    def encode(self, motion: Any, contacts: Tensor | None = None) -> Tensor:
        """One Motion -> ``(K, E, T)``; contacts are computed from the motion when not given."""
        if motion.skeleton.n_joints != self.n_joints or list(motion.skeleton.parents) != list(self.skeleton.parents):
            raise ValueError("encode: the motion's skeleton does not match the representation's")
        if contacts is None:
            contacts = self.contacts_of(motion)
        return self.encode_parts(motion.rotations, motion.root_positions, contacts)

    def decode(self, x: Tensor, fps: float) -> Any:
        """``(K, E, T)`` -> Motion (contacts are dropped; use ``decode_parts`` to keep them)."""
        if x.ndim != 3:
            raise ValueError(f"decode: expected one motion (K, E, T), got {tuple(x.shape)}; use decode_batch")
        quats, root, _ = self.decode_parts(x)
        return Motion(self.skeleton, quats, root, float(fps))

    def decode_batch(self, x: Tensor, fps: float) -> list[Any]:
        return [self.decode(xi, fps) for xi in x]

    # -------------------------------------------------------------------------------------------- views

    def to_flat(self, x: Tensor) -> Tensor:
        """``(..., K, E, T)`` -> ``(..., E*K, T)``, entity-major (GANimator's per-joint channel groups)."""
        return x.transpose(-3, -2).reshape(*x.shape[:-3], x.shape[-2] * x.shape[-3], x.shape[-1])

    def from_flat(self, x: Tensor) -> Tensor:
        E, K = self.n_entities, self.K
        if x.ndim < 2 or x.shape[-2] != E * K:
            raise ValueError(f"from_flat: expected (..., {E * K}, T), got {tuple(x.shape)}")
        return x.reshape(*x.shape[:-2], E, K, x.shape[-1]).transpose(-3, -2)

    def to_dict(self) -> dict:
        return {
            "skeleton": self.skeleton.to_dict(),
            "feet": list(self.feet),
            "rotation": self.rotation,
            "root": self.root,
            "contacts_to_root_motion": self.contacts_to_root_motion,
            "velocity_factor": self.velocity_factor,
            "height_factor": self.height_factor,
            "leaf_rotations": self.leaf_rotations,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "MotionRepresentation":
        d = dict(d)
        return cls(skeleton=Skeleton.from_dict(d.pop("skeleton")), **d)


def modi_representation(skeleton: Skeleton, feet: Sequence[int] | None = None, root: str = "velocity",
                        **kwargs: Any) -> MotionRepresentation:
    """MoDi: quaternions (K=4), root velocity, contacts on ``skeleton.detect_feet()`` (one per side)."""
    feet = skeleton.detect_feet() if feet is None else list(feet)
    return MotionRepresentation(skeleton, list(feet), rotation="quat", root=root, **kwargs)


def ganimator_representation(skeleton: Skeleton, feet: Sequence[int] | None = None, root: str = "velocity",
                             **kwargs: Any) -> MotionRepresentation:
    """GANimator: 6D rotations (K=6), root velocity, contacts on ankle and toe per side
    (``detect_feet(per_side=2)``), contacts wired to the root-motion entity too."""
    feet = skeleton.detect_feet(per_side=2) if feet is None else list(feet)
    kwargs.setdefault("contacts_to_root_motion", True)
    return MotionRepresentation(skeleton, list(feet), rotation="6d", root=root, **kwargs)
