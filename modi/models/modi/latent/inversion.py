"""Inversion by optimisation into W+ (paper 000 §4.3, eq. 9): find latents whose motion matches a given one.

``argmin_w ||G(w) - m||² + λ_FK ||FK(G(w)) - FK(m)||²`` with Adam over one W+ tensor per motion, the generator
frozen and its noise fixed. The first term is the MSE on the normalised representation (what the generator
outputs); the second the MSE of global joint positions in tenths of the body size (``space.position_scale``),
which mainly fixes
what rotation errors do to the end effectors. W+ (a style per layer) reaches much more than W (Abdal et al.).
Starting from the mean latent rather than random noise converges faster and stays in the well-behaved region.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor
from tqdm import tqdm

from modi.models.modi.latent.space import as_wplus, mean_w, position_scale, pyplot, random_w, save_figure


@dataclass
class InversionResult:
    """``wplus`` (B, L, D) and its motions (B, K, E, T); ``history`` holds the mean total loss before every step
    and after the last one (``steps + 1`` values), ``rec``/``fk`` the two terms."""

    wplus: Tensor
    motion: Tensor
    history: list[float] = field(default_factory=list)
    rec: list[float] = field(default_factory=list)
    fk: list[float] = field(default_factory=list)


def inversion_loss(codec: Any, pred: Tensor, target: Tensor, lambda_fk: float, scale: float,
                   target_pos: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Per-motion (total, rec, fk) losses (each (B,)): representation MSE + λ · position MSE (positions × scale)."""
    rec = (pred - target).pow(2).flatten(1).mean(1)
    if lambda_fk <= 0:
        return rec, rec, torch.zeros_like(rec)
    pp = codec.decode(pred)["positions"] * scale
    tp = codec.decode(target)["positions"] * scale if target_pos is None else target_pos
    fk = (pp - tp).pow(2).flatten(1).mean(1)
    return rec + lambda_fk * fk, rec, fk


def invert(g: Any, codec: Any, target: Tensor, steps: int = 300, lr: float = 0.02, lambda_fk: float = 1.0,
           init: str = "mean", seed: int = 0, progress: bool = True,
           callback: Callable[[int, float], None] | None = None) -> InversionResult:
    """Optimise W+ latents so that G(W+) matches ``target`` (B, K, E, T), normalised like the model's data.

    ``init``: ``"mean"`` (w̄ in every layer) or ``"random"`` (a mapped random z per motion).
    """
    if target.ndim == 3:
        target = target.unsqueeze(0)
    k, e, t = g.output_shape
    if target.ndim != 4 or tuple(target.shape[1:]) != (k, e, t):
        raise ValueError(f"target must be (B, {k}, {e}, {t}) normalised motions, got {tuple(target.shape)}")
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if lr <= 0:
        raise ValueError(f"lr must be positive, got {lr}")
    dev = next(g.parameters()).device
    target = target.to(dev).float()
    b = target.shape[0]
    if init == "mean":
        w0 = mean_w(g).to(dev).unsqueeze(0).expand(b, -1)
    elif init == "random":
        w0 = random_w(g, b, seed).to(dev)
    else:
        raise ValueError(f"init must be 'mean' or 'random', not {init!r}")
    wplus = as_wplus(g, w0).clone().contiguous().requires_grad_(True)
    for p in g.parameters():
        p.requires_grad_(False)
    scale = position_scale(codec)
    with torch.no_grad():
        target_pos = codec.decode(target)["positions"] * scale if lambda_fk > 0 else None
    opt = torch.optim.Adam([wplus], lr=lr, betas=(0.9, 0.999))
    res = InversionResult(wplus=wplus, motion=target)
    bar = None
    if progress:
        bar = tqdm(total=steps, desc="invert", dynamic_ncols=True, leave=False)
    try:
        for i in range(steps + 1):
            pred = g.synthesis(wplus, noise_mode="const")
            total, rec, fk = inversion_loss(codec, pred, target, lambda_fk, scale, target_pos)
            res.history.append(float(total.detach().mean()))
            res.rec.append(float(rec.detach().mean()))
            res.fk.append(float(fk.detach().mean()))
            if callback is not None:
                callback(i, res.history[-1])
            if i == steps:
                break
            opt.zero_grad(set_to_none=True)
            total.sum().backward()  # per-motion losses are independent: the sum optimises each one
            opt.step()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{res.history[-1]:.4f}", rec=f"{res.rec[-1]:.4f}")
    finally:
        if bar is not None:
            bar.close()
    with torch.no_grad():
        res.wplus = wplus.detach()
        res.motion = g.synthesis(res.wplus, noise_mode="const")
    return res


def plot_history(res: InversionResult, path: str | os.PathLike) -> Path:
    """PNG of the inversion's loss curve (total and representation term, log scale)."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(5, 3.4), dpi=120)
    ax.semilogy(res.history, label="total")
    ax.semilogy(res.rec, label="representation MSE")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


__all__ = ["InversionResult", "inversion_loss", "invert", "plot_history"]
