"""Crowd simulation (paper 000 §4.5, 001 §4.1): variations of one motion sampled around its latent.

Each variation is ``G(w + σ ε)`` with ``ε ~ N(0, I)`` in W (the paper samples N(w, σ²) with σ between 0.1 and
0.8: small σ gives the same action performed slightly differently, large σ drifts toward other actions). A W+
latent (e.g. an inverted clip) moves every layer by the same ε, so the variation stays a W-style change.
Characters are spread on a grid on the ground so they do not stand inside each other; the BVH files carry that
placement, so importing them together in Blender reproduces the scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from modi.data.motion import Motion
from modi.errors import UserError
from modi.io.formats import check_finite, save_motion
from modi.models.modi.latent.space import check_latent, synthesize
from modi.viz.render import render_positions

SIGMA_RANGE = (0.1, 0.8)


def crowd_latents(w: Tensor, k: int, sigma: float, seed: int = 0) -> Tensor:
    """``k`` latents ``w + σ ε`` around one latent ``w`` ((D,) or (L, D)); ε shared across W+ layers."""
    if k < 1:
        raise UserError(f"the crowd needs at least one variation, got k={k}")
    if not sigma > 0 or not math.isfinite(sigma):
        raise UserError(f"sigma must be positive, got {sigma}")
    gen = torch.Generator().manual_seed(int(seed))
    eps = torch.randn(k, w.shape[-1], generator=gen).to(w)
    if w.ndim == 2:
        eps = eps.unsqueeze(1)
    return w.unsqueeze(0) + float(sigma) * eps


def grid_offsets(n: int, spacing: float) -> np.ndarray:
    """(n, 3) ground offsets (x, 0, z) on a centred, roughly square grid with ``spacing`` between neighbours."""
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    out = np.zeros((n, 3))
    for i in range(n):
        r, c = divmod(i, cols)
        out[i, 0] = (c - (cols - 1) / 2) * spacing
        out[i, 2] = (r - (rows - 1) / 2) * spacing
    return out


@dataclass
class Crowd:
    latents: Tensor
    motions: Tensor
    offsets: np.ndarray
    files: dict[str, Any] = field(default_factory=dict)


def simulate_crowd(g: Any, codec: Any, w: Tensor, out_dir: str | Path, k: int = 8, sigma: float = 0.4,
                   seed: int = 0, include_source: bool = True, spacing: float | None = None,
                   gif: bool = True, size: tuple[int, int] = (520, 400)) -> Crowd:
    """Sample ``k`` variations of the motion of ``w`` and write ``crowd_NN.bvh`` (placed on a grid) plus
    ``crowd.gif`` with every character in one scene. ``include_source`` adds the original motion as ``crowd_00``."""
    w = check_latent(g, w.unsqueeze(0), "w")[0]
    lat = crowd_latents(w, k, sigma, seed)
    if include_source:
        lat = torch.cat([w.unsqueeze(0), lat])
    x = synthesize(g, lat)
    check_finite(x, "the crowd's motions")
    n = x.shape[0]
    spacing = float(spacing) if spacing is not None else 0.9 * codec.height
    offsets = grid_offsets(n, spacing)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res = Crowd(latents=lat, motions=x, offsets=offsets)
    positions, paths = [], []
    for i, m in enumerate(codec.to_motions(x)):
        off = torch.as_tensor(offsets[i], dtype=m.root_positions.dtype)
        placed = Motion(m.skeleton, m.rotations, m.root_positions + off, m.fps)
        name = f"crowd_{i:02d}" + ("_source" if include_source and i == 0 else "")
        paths.append(str(save_motion(placed.to_bvh(), out / f"{name}.bvh")))
        positions.append(placed.positions().detach().cpu().numpy())
    res.files["bvh"] = paths
    if gif:
        sk = codec.skeleton
        res.files["gif"] = str(render_positions(positions, list(sk.parents), out / "crowd.gif", fps=codec.fps,
                                                size=size, layout="scene", names=list(sk.names),
                                                view="view.html"))
    return res


__all__ = ["SIGMA_RANGE", "crowd_latents", "grid_offsets", "Crowd", "simulate_crowd"]
