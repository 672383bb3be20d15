"""MoDi's latent spaces W and W+: seeds, the mean, truncation and interpolation (paper 000 §4.2, 001 App. C.1).

A *truncation* sequence walks from a latent ``w`` to the mean ``w̄`` in ``C`` steps, ``w_i = w + i/C (w̄ - w)``;
an *interpolation* sequence does the same toward another latent. Latents are W vectors ``(B, D)`` or W+ tensors
``(B, L, D)`` (one style per synthesis layer); every function here takes either.

Determinism: "seed s" is the latent of motion 0 of ``modi generate --seed s`` (same z). Latent applications
synthesise with the generator's *fixed* noise maps (``noise_mode="const"``), so a latent alone fixes its motion
and two latents differ only by what the latent space encodes -- which is what interpolation and editing study.

This module also holds the helpers every latent/encoder application shares: loading a model, reading latents
from ``.npy`` files, turning BVH clips into model windows, and writing BVH + GIF previews.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from modi.core.body import UNITS_MM
from modi.data.dataset import motion_from_bvh
from modi.data.motion import Motion
from modi.errors import UserError
from modi.faults import atomic_save_npy
from modi.io import bvh as bvh_io
from modi.io.formats import check_finite, save_motion
from modi.models.modi.sampling import latents_and_noise, load_generator, render_gif

ModelBundle = tuple  # (Generator, MotionCodec, MoDiConfig), as returned by ``load_model``


# --------------------------------------------------------------------------------------------- model
def load_model(ckpt: str | os.PathLike | dict, device: str | torch.device = "cpu", ema: bool = True) -> ModelBundle:
    """``(generator in eval mode with frozen weights, codec, config)`` from a MoDi checkpoint."""
    g, codec, cfg = load_generator(ckpt, ema=ema, device=device)
    for p in g.parameters():
        p.requires_grad_(False)
    return g, codec, cfg


def _device(g: Any) -> torch.device:
    return next(g.parameters()).device


# --------------------------------------------------------------------------------------------- latents
def seed_z(g: Any, seeds: Sequence[int]) -> Tensor:
    """z of "seed s" for each seed: the latent of motion 0 of ``modi generate --seed s``."""
    if len(seeds) == 0:
        return torch.zeros(0, g.latent_dim)
    return torch.cat([latents_and_noise(g, [0], int(s))[0] for s in seeds]).to(_device(g))


@torch.no_grad()
def map_z(g: Any, z: Tensor, batch: int = 1024) -> Tensor:
    """z (N, D) -> w (N, D) through the mapping network, in batches."""
    if z.ndim != 2 or z.shape[1] != g.latent_dim:
        raise ValueError(f"z must be (N, {g.latent_dim}), got {tuple(z.shape)}")
    z = z.to(_device(g))
    return torch.cat([g.mapping(z[i:i + batch]) for i in range(0, z.shape[0], batch)]) if len(z) else z.clone()


def seed_w(g: Any, seeds: Sequence[int]) -> Tensor:
    """W latents (N, D) of the given seeds."""
    return map_z(g, seed_z(g, seeds))


def random_w(g: Any, n: int, seed: int = 0, batch: int = 1024) -> Tensor:
    """``n`` W samples from one seeded stream (for clustering, boundaries, mean estimates)."""
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    z = torch.randn(n, g.latent_dim, generator=torch.Generator().manual_seed(int(seed)))
    return map_z(g, z, batch)


def estimate_mean_w(g: Any, n: int = 10_000, seed: int = 0) -> Tensor:
    """w̄ estimated as the mean of ``n`` mapped samples, shape (D,)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    return random_w(g, n, seed).mean(0)


def mean_w(g: Any, n: int = 10_000, seed: int = 0) -> Tensor:
    """w̄ (D,): the mean of W tracked during training (``g.w_avg``), or an estimate when it was never tracked."""
    w_avg = getattr(g, "w_avg", None)
    if w_avg is not None and bool(torch.any(w_avg != 0)):
        return w_avg.detach().clone()
    return estimate_mean_w(g, n, seed)


def as_wplus(g: Any, w: Tensor) -> Tensor:
    """W (B, D) or W+ (B, L, D) -> W+ (B, L, D)."""
    if w.ndim == 1:
        w = w.unsqueeze(0)
    return g.make_wplus(w)


def check_latent(g: Any, w: Tensor, what: str = "latent") -> Tensor:
    """Validate a latent batch: (B, D) or (B, L, D) with the generator's sizes."""
    if w.ndim == 2 and w.shape[1] == g.latent_dim:
        return w
    if w.ndim == 3 and w.shape[1] == g.n_latent and w.shape[2] == g.latent_dim:
        return w
    raise ValueError(f"{what} must be W (B, {g.latent_dim}) or W+ (B, {g.n_latent}, {g.latent_dim}), "
                     f"got {tuple(w.shape)}")


def synthesize(g: Any, w: Tensor, noise_mode: str = "const", batch: int = 256, grad: bool = False) -> Tensor:
    """Latents (B, D) or (B, L, D) -> normalised motions (B, K, E, T), with the generator's fixed noise."""
    w = check_latent(g, w.to(_device(g)))
    with torch.set_grad_enabled(grad):
        outs = [g.synthesis(as_wplus(g, w[i:i + batch]), noise_mode=noise_mode) for i in range(0, len(w), batch)]
    if not outs:
        k, e, t = g.output_shape
        return torch.zeros(0, k, e, t)
    return torch.cat(outs)


def mean_motion(g: Any, w_mean: Tensor | None = None) -> Tensor:
    """The mean motion G(w̄), shape (1, K, E, T)."""
    w_mean = mean_w(g) if w_mean is None else w_mean
    return synthesize(g, w_mean.reshape(1, -1))


def truncate(w: Tensor, psi: float, w_mean: Tensor) -> Tensor:
    """``w̄ + psi (w - w̄)``: psi = 1 keeps w, psi = 0 gives the mean (works for W and W+)."""
    return w_mean.to(w) + float(psi) * (w - w_mean.to(w))


def lerp_sequence(a: Tensor, b: Tensor, steps: int) -> Tensor:
    """``a + i/C (b - a)`` for i = 0..C (C = ``steps``): a tensor with a new leading axis of C + 1 entries.

    ``a`` and ``b`` are single latents of the same shape ((D,) or (L, D)); endpoints are returned exactly.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if a.shape != b.shape:
        raise ValueError(f"endpoints differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}; "
                         "use W+ for both (as_wplus) to mix W and W+")
    t = torch.arange(steps + 1, dtype=a.dtype, device=a.device) / steps
    seq = a.unsqueeze(0) + t.view(-1, *([1] * a.ndim)) * (b - a).unsqueeze(0)
    seq[0], seq[-1] = a, b  # exact endpoints, whatever the rounding of t * (b - a)
    return seq


def truncation_sequence(w: Tensor, steps: int, w_mean: Tensor) -> Tensor:
    """C + 1 latents from ``w`` to the mean (paper: w_i = ŵ + i/C (w̄ - ŵ)); W+ latents use w̄ in every layer."""
    target = w_mean.to(w).expand_as(w) if w.ndim == 2 else w_mean.to(w)
    return lerp_sequence(w, target.clone(), steps)


def interpolation_sequence(w_a: Tensor, w_b: Tensor, steps: int) -> Tensor:
    """C + 1 latents from ``w_a`` to ``w_b``; a W and a W+ endpoint are both lifted to W+ first."""
    if w_a.ndim != w_b.ndim:
        L = w_a.shape[0] if w_a.ndim == 2 else w_b.shape[0]
        w_a = w_a.unsqueeze(0).expand(L, -1) if w_a.ndim == 1 else w_a
        w_b = w_b.unsqueeze(0).expand(L, -1) if w_b.ndim == 1 else w_b
    return lerp_sequence(w_a, w_b.clone(), steps)


# --------------------------------------------------------------------------------------------- units
_UNITS_MM = UNITS_MM  # the mm metrics' named units (modi.core.body)


def mm_per_unit(height: float, units: str = "auto") -> float:
    """Millimetres per skeleton unit. ``auto`` guesses from the body size (``Skeleton.height()``, a human's
    foot-to-head bone chain): 0.3-5 -> metres, 30-500 -> centimetres, 500-5000 -> millimetres."""
    if units != "auto":
        if units not in _UNITS_MM:
            raise UserError(f"unknown units {units!r}; choose from auto, {', '.join(_UNITS_MM)}")
        return _UNITS_MM[units]
    h = float(height)
    if 0.3 <= h <= 5.0:
        return 1000.0
    if 30.0 <= h <= 500.0:
        return 10.0
    if 500.0 < h <= 5000.0:
        return 1.0
    raise UserError(f"cannot guess the data's length unit from a body size of {h:g} skeleton units; "
                    "pass --units (mm, cm, m, in)")


def position_scale(codec: Any) -> float:
    """Factor turning skeleton units into *tenths of the body size* (``Skeleton.height()``; about decimetres
    on a human), the unit of every position loss here (inversion, encoder). The papers do not state theirs; in
    this unit a typical reconstruction's position MSE is comparable to the representation MSE, so λ_pos = 0.1
    helps positions without drowning the rotations (Table 5's ablation shows that balance), on any rig."""
    return 10.0 / float(codec.height)


# --------------------------------------------------------------------------------------------- latent files
def save_latent(path: str | os.PathLike, w: Tensor) -> Path:
    """Write one latent ((D,) W or (L, D) W+) or a batch as float32 ``.npy``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    atomic_save_npy(path, w.detach().cpu().float().numpy())
    return path


def load_latent(g: Any, path: str | os.PathLike) -> Tensor:
    """A single latent from ``.npy``: (D,) -> W, (L, D) -> W+ (a leading batch axis of 1 is dropped)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such latent file")
    try:
        arr = np.load(path, allow_pickle=False)  # numbers only: a pickled object array could run code
    except Exception as exc:  # noqa: BLE001 - any unreadable file
        if "allow_pickle" in str(exc):
            raise UserError(f"{path}: not a .npy latent: it holds objects other than data (pickled Python "
                            "objects, not numbers); refused without running anything") from None
        raise UserError(f"{path}: not a .npy latent ({exc})") from None
    w = torch.as_tensor(np.asarray(arr, dtype=np.float32))
    if w.ndim in (2, 3) and w.shape[0] == 1:  # a batch of one: (1, D) or (1, L, D)
        w = w[0]
    if w.ndim == 1 and w.shape[0] == g.latent_dim:
        return w.to(_device(g))
    if w.ndim == 2 and w.shape == (g.n_latent, g.latent_dim):
        return w.to(_device(g))
    raise UserError(f"{path}: latent of shape {tuple(arr.shape)} does not fit this model "
                    f"(W: ({g.latent_dim},), W+: ({g.n_latent}, {g.latent_dim}))")


def parse_latent(g: Any, spec: str | int) -> tuple[Tensor, str]:
    """A latent from a CLI word: an integer seed, ``seed:N``, ``mean``, or a ``.npy`` file. Returns (w, label)."""
    s = str(spec).strip()
    if s == "mean":
        return mean_w(g), "mean"
    if s.startswith("seed:"):
        s = s[5:]
    try:
        seed = int(s)
    except ValueError:
        return load_latent(g, s), Path(s).stem
    return seed_w(g, [seed])[0], f"seed {seed}"


# --------------------------------------------------------------------------------------------- BVH -> windows
def model_window_from_motion(codec: Any, motion: Any, n_frames: int, start: int = 0) -> Tensor:
    """A Motion on the model's skeleton -> one normalised window (K, E, T) at frames ``[start, start + T)``.

    Contact labels come from the whole clip (foot speed and height, as in the dataset); the window is
    re-centred so its first frame stands at x = z = 0, as the training windows are.
    """
    rep = codec.rep
    if motion.n_frames < start + n_frames:
        raise UserError(f"clip has {motion.n_frames} frames at {codec.fps:g} fps; need {start + n_frames} "
                        f"(start {start} + window {n_frames})")
    contacts = rep.contacts_of(motion).to(torch.float64)
    rot = motion.rotations.to(torch.float64)
    root = motion.root_positions.to(torch.float64)
    x = rep.encode_parts(rot, root, contacts)[..., start:start + n_frames].clone()
    J = rep.n_joints
    if rep.root == "velocity":
        x[0, J, 0] = 0.0
        x[2, J, 0] = 0.0
    else:
        x[0, J, :] -= root[start, 0]
        x[2, J, :] -= root[start, 2]
    return codec.normalizer.normalize(x.float())


def window_from_motion(codec: Any, motion: Any, n_frames: int, start: int = 0, where: str = "motion") -> Tensor:
    """A Motion (any joint order or superset of the model's joints, matched by name; any rate) onto the model's
    skeleton and rate, cut to one normalised window (K, E, T) at ``[start, start + n_frames)``."""
    sk = codec.skeleton
    names = list(motion.skeleton.names)
    missing = [n for n in sk.names if n not in names]
    if missing:
        raise UserError(f"{where}: skeleton lacks the model's joints {missing[:5]}{'...' if len(missing) > 5 else ''}")
    keep = [names.index(n) for n in sk.names]
    if keep != list(range(len(names))):
        motion = motion.subset(keep)
    if list(motion.skeleton.parents) != list(sk.parents):
        raise UserError(f"{where}: joint hierarchy differs from the model's skeleton")

    motion = Motion(sk, motion.rotations, motion.root_positions, motion.fps)  # the model's bone lengths
    if abs(motion.fps - codec.fps) > 1e-3 * codec.fps:
        motion = motion.resample(codec.fps)
    return model_window_from_motion(codec, motion, n_frames, start)


def load_bvh_window(codec: Any, path: str | os.PathLike, n_frames: int, start: int = 0) -> Tensor:
    """Read a BVH clip onto the model's skeleton (joints matched by name), resample, cut one window (K, E, T)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such BVH file")
    return window_from_motion(codec, motion_from_bvh(bvh_io.load(path), str(path)), n_frames, start, str(path))


# --------------------------------------------------------------------------------------------- output
def decode_positions(codec: Any, x: Tensor) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Normalised tensors -> (global positions (T, J, 3), contact booleans (T, F)) per motion."""
    with torch.no_grad():
        dec = codec.decode(x.detach().float().cpu())
    return [p.numpy() for p in dec["positions"]], [(c > 0.5).numpy() for c in dec["contacts"]]


def write_motions(codec: Any, x: Tensor, out_dir: str | os.PathLike, names: Sequence[str],
                  gif: str | None = "preview.gif", titles: Sequence[str] | None = None,
                  size: tuple[int, int] = (220, 220), view: str | None = "view.html") -> list[Path]:
    """Write each motion as ``{name}.bvh`` (and/or the other ``--format`` formats) and all of them side by side in one
    GIF; returns the motion paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    x = x.detach().float().cpu()
    if len(names) != x.shape[0]:
        raise ValueError(f"{len(names)} names for {x.shape[0]} motions")
    check_finite(x, "the synthesised motions")
    paths = []
    for m, name in zip(codec.to_motions(x), names):
        paths.append(save_motion(m.to_bvh(), out / f"{name}.bvh"))
    if gif:
        pos, con = decode_positions(codec, x)
        try:
            render_gif(codec, pos, con, out / gif, titles=list(titles) if titles is not None else list(names),
                       size=size, view=view)
        except Exception as exc:  # noqa: BLE001 - a preview must not lose the BVH results
            warnings.warn(f"could not render {out / gif}: {exc}", stacklevel=2)
    return paths


__all__ = ["load_model", "seed_z", "map_z", "seed_w", "random_w", "estimate_mean_w", "mean_w", "as_wplus",
           "check_latent", "mm_per_unit", "position_scale", "synthesize", "mean_motion", "truncate",
           "lerp_sequence", "truncation_sequence",
           "interpolation_sequence", "save_latent", "load_latent", "parse_latent", "model_window_from_motion",
           "load_bvh_window", "window_from_motion", "decode_positions", "write_motions"]


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only), for the plots of the latent applications."""
    import matplotlib  # lazy: the Agg backend must be chosen before pyplot is first imported; plots are rare

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after use("Agg")

    return plt


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Lay out, write (making the folder) and close a matplotlib figure; returns the path."""
    plt = pyplot()
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
