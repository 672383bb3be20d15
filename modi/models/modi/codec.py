"""The normalised-tensor <-> motion codec of a MoDi model (shared by training, sampling, the encoder and latent tools).

Kept apart from ``training`` and ``sampling`` so neither has to import the other for it.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from modi.core.kinematics import forward_kinematics
from modi.core.skeleton import _TOE
from modi.data.motion import Motion
from modi.data.normalization import Normalizer
from modi.data.representation import MotionRepresentation
from modi.errors import UserError
from modi_ext.layers import ForwardKinematics


class MotionCodec:
    """Normalised model tensors ``(B, K, E, T)`` <-> motion quantities (rotations, root, contacts, positions).

    Wraps the dataset's :class:`~modi.data.representation.MotionRepresentation` and normaliser. With
    ``positions=True`` (the "joint positions instead of rotations" ablation) the edge entities hold each joint's
    global position relative to the root's ground point (x, z) and its absolute height, zero-padded to K.
    """

    def __init__(self, representation: Any, normalizer: Any, fps: float, positions: bool = False):
        self.rep = representation
        self.normalizer = normalizer
        self.fps = float(fps)
        self.positions_mode = bool(positions)
        sk = representation.skeleton
        self.skeleton = sk
        self.feet = list(representation.feet)
        self.height = float(sk.height())
        self._fk = None
        self._joint_index: dict = {}  # (device, joints) -> index tensor made once (a list index is a host tensor)

    # -- shape facts
    @property
    def n_channels(self) -> int:
        return int(self.rep.K)

    @property
    def n_entities(self) -> int:
        return int(self.rep.n_entities)

    def _fk_module(self, device: torch.device) -> nn.Module:
        if self._fk is None:
            self._fk = ForwardKinematics(list(self.skeleton.parents),
                                         torch.as_tensor(self.skeleton.offsets, dtype=torch.float32))
        return self._fk.to(device)

    # -- decoding (differentiable)
    def decode(self, x: Tensor) -> dict[str, Tensor]:
        """Denormalise and decode: ``positions (B,T,J,3)``, ``root (B,T,3)``, ``contacts (B,T,F)`` (raw label
        scale) and, for rotation models, ``rotations (B,T,J,4)``."""
        raw = self.normalizer.denormalize(x)
        quats, root, contacts = self.rep.decode_parts(raw)
        if self.positions_mode:
            J = self.skeleton.n_joints
            rel = raw[..., :3, :J, :].permute(*range(raw.ndim - 3), -1, -2, -3)  # (..., T, J, 3)
            ground = torch.stack([root[..., 0], torch.zeros_like(root[..., 1]), root[..., 2]], -1)
            positions = rel + ground.unsqueeze(-2)
            return {"positions": positions, "root": root, "contacts": contacts}
        positions = self._fk_module(x.device)(quats.contiguous(), root.contiguous())
        return {"rotations": quats, "positions": positions, "root": root, "contacts": contacts}

    @property
    def ankles(self) -> list[int]:
        """Per contact label, the ankle joint the released MoDi's contact loss measures: the parent of a toe/ball
        label joint (Bandai ``Toes_L`` -> ``Foot_L``), the label joint itself otherwise (already an ankle, or a
        non-biped leg tip)."""
        sk = self.skeleton
        out = []
        for f in self.feet:
            parent = int(sk.parents[f])
            out.append(parent if _TOE.search(sk.names[f]) and parent > 0 else f)
        return out

    def foot_terms(self, x: Tensor, joints: list[int] | None = None) -> tuple[Tensor, Tensor]:
        """(positions (B, T, F, 3) of ``joints`` (default: the contact-label joints), contact channel (B, F, T))
        for the foot-contact losses; ``joints`` has one joint per contact label."""
        d = self.decode(x)
        joints = self.feet if joints is None else list(joints)
        if len(joints) != len(self.feet):
            raise ValueError(f"need one joint per contact label ({len(self.feet)}), got {len(joints)}")
        pos = d["positions"]
        key = (pos.device, tuple(joints))
        if key not in self._joint_index:
            self._joint_index[key] = torch.as_tensor(joints, dtype=torch.long, device=pos.device)
        return pos[..., self._joint_index[key], :], d["contacts"].transpose(-1, -2)

    def to_motions(self, x: Tensor) -> list[Any]:
        """Normalised ``(B, K, E, T)`` -> list of :class:`modi.data.motion.Motion` (rotation models only)."""
        if self.positions_mode:
            raise UserError("this model generates joint positions (the 'positions' ablation), not rotations; "
                            "use sample_positions() instead of BVH output")

        d = self.decode(x.detach().float())
        return [Motion(self.skeleton, d["rotations"][i].cpu(), d["root"][i].cpu(), self.fps)
                for i in range(x.shape[0])]

    # -- encoding the positions ablation's data
    def positions_from_raw_quat(self, raw: Tensor, quat_rep: Any) -> Tensor:
        """Raw quaternion tensors (N, K, E, T) of ``quat_rep`` -> raw positions-representation tensors."""
        quats, root, _ = quat_rep.decode_parts(raw)

        offsets = torch.as_tensor(self.skeleton.offsets, dtype=raw.dtype)
        pos = forward_kinematics(quats, offsets, list(self.skeleton.parents), root)[0]  # (N, T, J, 3)
        ground = torch.stack([root[..., 0], torch.zeros_like(root[..., 1]), root[..., 2]], -1)
        rel = (pos - ground.unsqueeze(-2)).permute(0, 3, 2, 1)  # (N, 3, J, T)
        out = raw.clone()
        J = self.skeleton.n_joints
        out[:, :, :J, :] = 0
        out[:, :3, :J, :] = rel
        return out

    # -- persistence
    def state_dict(self) -> dict[str, Any]:
        return {"representation": self.rep.to_dict(), "normalizer": self.normalizer.state_dict(),
                "fps": self.fps, "positions": self.positions_mode}

    @classmethod
    def from_state_dict(cls, d: dict[str, Any]) -> "MotionCodec":
        return cls(MotionRepresentation.from_dict(d["representation"]), Normalizer.from_state_dict(d["normalizer"]),
                   float(d["fps"]), bool(d.get("positions", False)))


__all__ = ["MotionCodec"]
