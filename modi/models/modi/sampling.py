"""Generating motions from a MoDi checkpoint: seeds -> latents -> motions, BVH/contacts/GIF output.

Determinism: motion ``i`` of ``seed`` draws its latent and all its noise maps from its own generator, seeded from
``(seed, i)``; the same seed therefore gives the same motions whatever the batch size or ``n``.
Truncation moves w toward the mean of W tracked during training: ``w_avg + psi (w - w_avg)``.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from modi.core.ik import fix_foot_contact
from modi.data.motion import Motion
from modi.errors import CheckpointError, UserError
from modi.faults import atomic_save_npy
from modi.io.formats import save_motion
from modi.models.modi.checkpoint import REQUIRED_KEYS, load_checkpoint  # noqa: F401 - re-exported
from modi.models.modi.codec import MotionCodec
from modi.models.modi.config import MoDiConfig
from modi.models.modi.levels import LevelSpec
from modi.models.modi.networks import Generator
from modi.viz.render import render_positions


def load_generator(ckpt: str | os.PathLike | dict, *, ema: bool = True, device: str | torch.device = "cpu"):
    """``(Generator in eval mode, MotionCodec, MoDiConfig)`` from a checkpoint (the EMA weights by default)."""
    st = load_checkpoint(ckpt)
    try:
        cfg = MoDiConfig.from_dict(st["config"])
        levels = [LevelSpec.from_dict(d) for d in st["levels"]]
        codec = MotionCodec.from_state_dict(st["codec"])
        g = Generator(cfg.model, levels, codec.n_channels)
        g.load_state_dict(st["G_ema" if ema else "G"])
    except CheckpointError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged or mismatched state
        raise CheckpointError(f"checkpoint contents do not build a generator: {exc}") from None
    return g.to(device).eval(), codec, cfg


def _sample_seed(seed: int, i: int) -> int:
    h = hashlib.blake2b(f"modi:{int(seed)}:{int(i)}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "little") & ((1 << 63) - 1)


def latents_and_noise(g: Any, indices: Sequence[int], seed: int) -> tuple[Tensor, list[Tensor]]:
    """Per-motion latents (B, D) and noise maps [(B, 1, E, T) per styled layer] for motions ``indices`` of ``seed``."""
    shapes = g.noise_shapes()
    sizes = [e * t for e, t in shapes]
    total = g.latent_dim + sum(sizes)
    flat = torch.stack([torch.randn(total, generator=torch.Generator().manual_seed(_sample_seed(seed, i)))
                        for i in indices])
    z = flat[:, :g.latent_dim]
    noise, pos = [], g.latent_dim
    for (e, t), n in zip(shapes, sizes):
        noise.append(flat[:, pos:pos + n].reshape(-1, 1, e, t))
        pos += n
    return z, noise


@torch.no_grad()
def generate_tensors(ckpt: str | os.PathLike | dict, n: int, seed: int = 0, psi: float = 1.0, batch: int = 256,
                     device: str | torch.device = "cpu", model: tuple | None = None) -> tuple[Tensor, Any]:
    """``n`` normalised motion tensors ``(n, K, E, T)`` and the codec that decodes them."""
    if n < 0:
        raise UserError(f"n must be >= 0, got {n}")
    if batch < 1:
        raise UserError(f"batch must be >= 1, got {batch}")
    g, codec, _ = model if model is not None else load_generator(ckpt, device=device)
    dev = next(g.parameters()).device
    out = []
    for start in range(0, n, batch):
        idx = list(range(start, min(n, start + batch)))
        z, noise = latents_and_noise(g, idx, seed)
        out.append(g(z.to(dev), truncation_psi=psi, noise=[x.to(dev) for x in noise]).cpu())
    if not out:
        k, e, t = g.output_shape
        return torch.zeros(0, k, e, t), codec
    return torch.cat(out), codec


def _contacts_bool(decoded_contacts: Tensor) -> Tensor:
    """Generated contact channel (label scale) -> on/off: on when s(c) > 1/2, i.e. c > 1/2."""
    return decoded_contacts > 0.5


def sample_motions(ckpt: str | os.PathLike | dict, n: int, seed: int = 0, psi: float = 1.0, batch: int = 256, *,
                   ik: bool = False, device: str | torch.device = "cpu", return_contacts: bool = False):
    """``n`` generated :class:`modi.data.motion.Motion` s (deterministic per seed); optional IK foot cleanup.

    With ``return_contacts`` returns ``(motions, contacts)`` with contacts a list of (T, F) bool arrays.
    """
    model = load_generator(ckpt, device=device)
    x, codec = generate_tensors(ckpt, n, seed, psi, batch, device, model=model)
    motions = codec.to_motions(x) if n else []
    contacts = [_contacts_bool(c).numpy() for c in codec.decode(x)["contacts"]] if n else []
    if ik:
        motions = [cleanup_feet(m, c, codec.feet) for m, c in zip(motions, contacts)]
    return (motions, contacts) if return_contacts else motions


def sample_positions(ckpt: str | os.PathLike | dict, n: int, seed: int = 0, psi: float = 1.0,
                     batch: int = 256) -> list[np.ndarray]:
    """Global joint positions ``(T, J, 3)`` of ``n`` generated motions (works for the positions ablation too)."""
    x, codec = generate_tensors(ckpt, n, seed, psi, batch)
    return [p.numpy() for p in codec.decode(x)["positions"]] if n else []


def cleanup_feet(motion: Any, contacts: np.ndarray, feet: Sequence[int]) -> Any:
    """Pin each foot while its label is on (``modi.core.ik.fix_foot_contact``); returns a new Motion."""
    rot, root = fix_foot_contact(motion.rotations, motion.root_positions, motion.skeleton, list(feet),
                                 np.asarray(contacts, dtype=bool))
    return Motion(motion.skeleton, rot, root, motion.fps)


def write_outputs(codec: Any, x: Tensor, out_dir: str | os.PathLike, *, bvh: bool = True, gif: bool = True,
                  contacts: bool = True, ik: bool = False, gif_name: str = "samples.gif", max_gif: int = 16,
                  prefix: str = "motion", start_index: int = 0) -> list[Path]:
    """Write generated tensors: ``{prefix}_NNNN.bvh`` (+ ``_contacts.npy``, (T, F) uint8 in ``codec.feet``
    order) per motion and one GIF grid of the first ``max_gif``; returns the BVH paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    x = x.detach().float().cpu()
    dec = codec.decode(x)
    con = [_contacts_bool(c).numpy() for c in dec["contacts"]]
    written: list[Path] = []
    positions = [p.numpy() for p in dec["positions"]]
    if not codec.positions_mode and (bvh or ik):
        motions = codec.to_motions(x)
        if ik:
            motions = [cleanup_feet(m, c, codec.feet) for m, c in zip(motions, con)]
            positions = [m.positions().detach().cpu().numpy() for m in motions]
        for i, m in enumerate(motions if bvh else []):
            labels = {codec.skeleton.names[f]: con[i][:, k] for k, f in enumerate(codec.feet)}
            written.append(save_motion(m.to_bvh(), out / f"{prefix}_{start_index + i:04d}.bvh", contacts=labels))
    elif codec.positions_mode:
        for i, p in enumerate(positions):
            atomic_save_npy(out / f"{prefix}_{start_index + i:04d}_positions.npy", p.astype(np.float32))
    if contacts:
        for i, c in enumerate(con):
            atomic_save_npy(out / f"{prefix}_{start_index + i:04d}_contacts.npy", c.astype(np.uint8))
    if gif and positions:
        render_gif(codec, positions[:max_gif], con[:max_gif], out / gif_name,
                   titles=[f"{start_index + i}" for i in range(min(len(positions), max_gif))])
    return written


def render_gif(codec: Any, positions: Sequence[np.ndarray], contacts: Sequence[np.ndarray] | None,
               path: str | os.PathLike, titles: Sequence[str] | None = None,
               size: tuple[int, int] = (200, 200), view: str | None = "view.html") -> Path:
    """Stick-figure GIF grid of global positions with the feet drawn red while labelled in contact, and the 3D
    viewer page ``view`` beside it (see ``modi.viz``; None: no page)."""
    sk = codec.skeleton
    per_joint = None
    if contacts is not None:
        per_joint = []
        for p, c in zip(positions, contacts):
            m = np.zeros(p.shape[:2], dtype=bool)
            m[:, codec.feet] = c
            per_joint.append(m)
    return render_positions(list(positions), list(sk.parents), path, fps=codec.fps, size=size, titles=titles,
                            contacts=per_joint, names=list(sk.names), view=view)


__all__ = ["load_checkpoint", "load_generator", "generate_tensors", "sample_motions", "sample_positions",
           "cleanup_feet", "write_outputs", "render_gif", "latents_and_noise"]
