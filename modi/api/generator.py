"""A trained MoDi generator as one object: sampling, the latent-space applications and inversion, all returning
:class:`modi.Motion`.

Latents: a W vector ``(D,)``, a W+ tensor ``(L, D)``, an integer seed (the latent of motion 0 of
``modi generate --seed N``), ``"mean"`` (w̄) or a path to a ``.npy`` latent; :meth:`ModiGenerator.latent` turns any of
them into a tensor. The latent applications synthesise with the generator's fixed noise, so a latent fixes its motion
(as ``modi latent``); :meth:`ModiGenerator.sample` draws per-motion noise exactly as ``modi generate`` does, so
``modi.load(ckpt).generate(n, seed=s)`` is the ``n`` motions ``modi generate CKPT --n n --seed s`` writes.
"""
from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from modi.api._util import check_device, existing_file, set_threads
from modi.core.skeleton import Skeleton
from modi.data.motion import Motion
from modi.errors import UserError
from modi.io.formats import check_finite
from modi.models.modi.checkpoint import load_checkpoint
from modi.models.modi.latent import space
from modi.models.modi.latent.crowd import crowd_latents, grid_offsets
from modi.models.modi.latent.editing import Boundary, edit_latents, sample_boundary
from modi.models.modi.latent.inversion import invert as invert_latent
from modi.models.modi.sampling import cleanup_feet, generate_tensors, load_generator, write_outputs

LatentLike = Union[Tensor, np.ndarray, int, str, os.PathLike]


@dataclass
class Inversion:
    """What :meth:`ModiGenerator.invert` found: the W+ ``latent`` (L, D), its ``motion``, the ``target`` window it
    matched, and the loss before every step and after the last (``history``; ``rec``/``fk`` its two terms)."""

    latent: Tensor
    motion: Motion
    target: Motion
    history: list[float] = field(default_factory=list)
    rec: list[float] = field(default_factory=list)
    fk: list[float] = field(default_factory=list)

    def __repr__(self) -> str:
        loss = f"loss {self.history[0]:.4g} -> {self.history[-1]:.4g}" if self.history else "no steps"
        return f"Inversion(W+ {tuple(self.latent.shape)}, {loss})"


class ModiGenerator:
    """A trained MoDi generator (the EMA weights by default) with its motion codec.

    Build it with :func:`modi.load` (a checkpoint from ``modi train``, or an imported released one) or
    :meth:`from_checkpoint`. Every method that makes motion returns ``list[Motion]`` on the training skeleton, at
    the training frame rate, with contact labels.
    """

    def __init__(self, network: torch.nn.Module, codec: Any, config: Any, *, path: str | None = None,
                 step: int | None = None) -> None:
        self.network = network.eval()
        for p in self.network.parameters():
            p.requires_grad_(False)
        self.codec = codec
        self.config = config
        self.path = path
        self.step = step

    @classmethod
    def from_checkpoint(cls, ckpt: str | os.PathLike | dict, *, device: str | torch.device = "cpu",
                        ema: bool = True) -> "ModiGenerator":
        """Read a MoDi checkpoint (as data only: a file that names code is refused unrun); ``ema=False`` takes the
        raw generator. Cost: reading the file and building the network (well under a second on a CPU).
        ``CheckpointError`` for anything else."""
        st = load_checkpoint(ckpt)
        g, codec, cfg = load_generator(st, ema=ema, device=device)
        return cls(g, codec, cfg, path=None if isinstance(ckpt, dict) else str(ckpt), step=int(st.get("step", 0)))

    # ------------------------------------------------------------------------------------------- facts
    @property
    def skeleton(self) -> Skeleton:
        """The training skeleton (what every motion is on)."""
        return self.codec.skeleton

    @property
    def fps(self) -> float:
        return float(self.codec.fps)

    @property
    def n_frames(self) -> int:
        """Frames of every generated motion."""
        return int(self.network.output_shape[2])

    @property
    def latent_dim(self) -> int:
        return int(self.network.latent_dim)

    @property
    def n_latent(self) -> int:
        """Styles in a W+ latent (one per synthesis layer)."""
        return int(self.network.n_latent)

    @property
    def feet(self) -> list[str]:
        """The joints with contact labels."""
        return [self.skeleton.names[f] for f in self.codec.feet]

    @property
    def device(self) -> torch.device:
        return next(self.network.parameters()).device

    def __repr__(self) -> str:
        where = f", {self.path}" if self.path else ""
        return (f"ModiGenerator({self.skeleton.n_joints} joints, {self.n_frames} frames at {self.fps:g} fps, "
                f"latent {self.latent_dim}, step {self.step}{where})")

    # ------------------------------------------------------------------------------------------- sampling
    def sample_tensors(self, n: int, *, seed: int = 0, psi: float = 1.0, batch: int = 256) -> Tensor:
        """``n`` normalised model tensors ``(n, K, E, T)`` (what :meth:`generate` decodes): motion ``i`` of a seed is
        the same whatever ``n`` or ``batch``."""
        if not -2.0 <= float(psi) <= 2.0:
            raise UserError(f"psi must be in [-2, 2], got {psi}")
        x, _ = generate_tensors(None, int(n), seed=int(seed), psi=float(psi), batch=int(batch),
                                model=(self.network, self.codec, self.config))
        check_finite(x)
        return x

    def generate(self, n: int = 1, *, seed: int = 0, psi: float = 1.0, ik: bool = False,
                 batch: int = 256) -> list[Motion]:
        """``n`` generated motions: the ones ``modi generate CKPT --n n --seed seed --psi psi`` writes (the same
        verb as :meth:`modi.api.ganimator.GanimatorRun.generate`).

        ``psi`` truncates toward the mean (1: none, 0: the mean motion); ``ik`` pins each foot while its contact
        label is on. Cost: one generator pass per ``batch`` motions (milliseconds each on a CPU for the small
        preset) plus decoding."""
        return self.decode(self.sample_tensors(n, seed=seed, psi=psi, batch=batch), ik=ik)

    def sample(self, n: int = 1, **kw) -> list[Motion]:
        """The old name of :meth:`generate` (kept so scripts keep working; it warns once)."""
        warnings.warn("ModiGenerator.sample is now ModiGenerator.generate", DeprecationWarning, stacklevel=2)
        return self.generate(n, **kw)

    def write_samples(self, out: str | os.PathLike, n: int = 16, *, seed: int = 0, psi: float = 1.0,
                      ik: bool = False, batch: int = 256, gif_max: int = 16) -> tuple[list[Path], float]:
        """``modi generate``: write the ``n`` motions :meth:`generate` gives as ``motion_NNNN`` files (the requested
        ``--format``s) with ``motion_NNNN_contacts.npy``, and the first ``gif_max`` in ``samples.gif`` (0: none).
        Returns the motion files and the seconds sampling took (decoding and writing go ``batch`` at a time)."""
        t0 = time.perf_counter()
        x = self.sample_tensors(n, seed=seed, psi=psi, batch=batch)
        seconds = time.perf_counter() - t0
        written: list[Path] = []
        for start in range(0, int(n), int(batch)):  # decode/write in chunks to bound memory
            written += write_outputs(self.codec, x[start:start + batch], out, ik=ik, start_index=start, gif=False)
        if gif_max:
            write_outputs(self.codec, x[:gif_max], out, bvh=False, contacts=False, gif=True, max_gif=gif_max, ik=ik)
        return written, seconds

    def decode(self, x: Tensor, *, ik: bool = False) -> list[Motion]:
        """Normalised model tensors ``(B, K, E, T)`` -> motions with contact labels (``ik``: feet pinned)."""
        x = x.detach().float().cpu()
        if x.ndim == 3:
            x = x.unsqueeze(0)
        check_finite(x, "the motions")
        codec = self.codec
        if len(x) == 0:
            return []
        motions = codec.to_motions(x)
        with torch.no_grad():
            labels = [(c > 0.5).numpy() for c in codec.decode(x)["contacts"]]
        out = []
        names = [codec.skeleton.names[f] for f in codec.feet]
        for m, c in zip(motions, labels):
            if ik:
                m = cleanup_feet(m, c, codec.feet)
            out.append(Motion(m.skeleton, m.rotations, m.root_positions, m.fps, m.unit,
                              contacts={name: c[:, k] for k, name in enumerate(names)}))
        return out

    def encode_motion(self, motion: Motion | str | os.PathLike, *, start: int = 0) -> Tensor:
        """A clip on the model's skeleton (joints matched by name, resampled to the model's rate) as one
        normalised window ``(K, E, T)`` starting at frame ``start`` (after resampling)."""
        t = self.n_frames
        if isinstance(motion, (str, os.PathLike)):
            return space.load_bvh_window(self.codec, motion, t, start)
        return space.window_from_motion(self.codec, motion, t, start)

    # ------------------------------------------------------------------------------------------- latents
    def latent(self, spec: LatentLike) -> Tensor:
        """A latent as a tensor: W ``(D,)`` or W+ ``(L, D)``, from a tensor or array, a seed, ``"mean"`` or a path
        to a ``.npy`` latent (what ``modi latent`` accepts)."""
        g = self.network
        if isinstance(spec, (Tensor, np.ndarray)):
            w = torch.as_tensor(np.asarray(spec) if isinstance(spec, np.ndarray) else spec).float().to(self.device)
            if w.ndim in (2, 3) and w.shape[0] == 1 and not (w.ndim == 2 and w.shape == (g.n_latent, g.latent_dim)):
                w = w[0]
            space.check_latent(g, w.unsqueeze(0), "latent")
        elif isinstance(spec, bool):
            raise UserError(f"not a latent: {spec!r}")
        elif isinstance(spec, int):
            if spec < 0:
                raise UserError(f"a seed must be >= 0, got {spec}")
            w = space.seed_w(g, [spec])[0]
        else:
            text = os.fspath(spec) if isinstance(spec, os.PathLike) else str(spec).strip()
            if text != "mean" and not text.startswith("seed:") and not text.lstrip("-").isdigit() \
                    and not Path(text).is_file():
                raise UserError(f"{spec}: no such latent file (give a seed, 'mean' or a .npy latent)")
            w, _ = space.parse_latent(g, text)
        if not bool(torch.isfinite(w).all()):
            raise UserError(f"the latent {spec if not isinstance(spec, (Tensor, np.ndarray)) else ''} holds NaN or "
                            "infinite values".replace("  ", " "))
        return w

    def mean_latent(self) -> Tensor:
        """w̄ ``(D,)``: the mean of W tracked during training (estimated when it was never tracked)."""
        return space.mean_w(self.network)

    def synthesize(self, latents: Tensor | Sequence[LatentLike]) -> list[Motion]:
        """Motions of latents (a batch ``(B, D)`` / ``(B, L, D)``, or a list of anything :meth:`latent` takes), with
        the generator's fixed noise (so a latent fixes its motion)."""
        if isinstance(latents, Tensor) and latents.ndim in (2, 3) and not (
                latents.ndim == 2 and latents.shape == (self.n_latent, self.latent_dim)):
            w = latents.to(self.device)
        else:
            items = [self.latent(x) for x in latents]
            if len({tuple(w.shape) for w in items}) > 1:  # mixed W and W+: lift to W+
                items = [space.as_wplus(self.network, w)[0] if w.ndim == 1 else w for w in items]
            w = torch.stack(items) if items else torch.zeros(0, self.latent_dim)
        return self.decode(space.synthesize(self.network, w))

    def mean_motion(self) -> Motion:
        """The mean motion G(w̄)."""
        return self.decode(space.mean_motion(self.network, self.mean_latent()))[0]

    def interpolate(self, a: LatentLike, b: LatentLike, steps: int = 4) -> list[Motion]:
        """``steps + 1`` motions from latent ``a`` to ``b`` (``a + i/steps (b - a)``; in W+ when either is W+), as
        ``modi latent interpolate``."""
        seq = space.interpolation_sequence(self.latent(a), self.latent(b), _steps(steps))
        return self.decode(space.synthesize(self.network, seq))

    def truncate(self, latent: LatentLike, steps: int = 4) -> list[Motion]:
        """``steps + 1`` motions from a latent to the mean (``modi latent truncate``)."""
        seq = space.truncation_sequence(self.latent(latent), _steps(steps), self.mean_latent())
        return self.decode(space.synthesize(self.network, seq))

    def crowd(self, latent: LatentLike, k: int = 8, *, sigma: float = 0.4, seed: int = 0,
              include_source: bool = True, spacing: float | None = 0.0) -> list[Motion]:
        """``k`` variations ``w + σ ε`` of one motion (``modi latent crowd``; the first is the motion itself with
        ``include_source``). ``spacing`` places them on a grid that far apart (None: 0.9 body heights; 0: each at
        its own start)."""
        w = self.latent(latent)
        lat = crowd_latents(w, int(k), float(sigma), int(seed))
        if include_source:
            lat = torch.cat([w.unsqueeze(0), lat])
        motions = self.decode(space.synthesize(self.network, lat))
        spacing = 0.9 * self.codec.height if spacing is None else float(spacing)
        if not spacing:
            return motions
        out = []
        for m, off in zip(motions, grid_offsets(len(motions), spacing)):
            out.append(Motion(m.skeleton, m.rotations, m.root_positions + torch.as_tensor(off, dtype=m.rotations.dtype),
                              m.fps, m.unit, contacts=m.contacts))
        return out

    def fit_boundary(self, attribute: str = "gral", *, n: int = 2000, seed: int = 0, ratio: float = 0.2,
                     method: str = "ours") -> Boundary:
        """An attribute's boundary in W (``modi latent edit``): score ``n`` sampled motions (``gral``,
        ``gral_released``, ``verticality``, ``speed``), fit a linear SVM between the top and bottom ``ratio``.
        Cost: ``n`` syntheses and an SVM fit (seconds for a few thousand)."""
        if n < 10:
            raise UserError(f"n must be >= 10, got {n}")
        boundary, _, scores = sample_boundary(self.network, self.codec, attribute, n=n, seed=seed, ratio=ratio,
                                              method=method)
        boundary.extra["score_mean"] = float(np.mean(scores))
        boundary.extra["score_std"] = float(np.std(scores))
        return boundary

    def edit(self, latent: LatentLike, boundary: Boundary | str | os.PathLike,
             alphas: Sequence[float] = (-3, -2, -1, 0, 1, 2, 3)) -> list[Motion]:
        """One motion edited along a boundary (a :class:`Boundary`, or a saved boundary JSON): ``w + α σ n`` for each
        α in ``alphas`` (units of the boundary's σ), as ``modi latent edit`` renders them."""
        if not isinstance(boundary, Boundary):
            boundary = Boundary.load(boundary)
        if len(boundary.normal) != self.latent_dim:
            raise UserError(f"the boundary has {len(boundary.normal)} dims, the model {self.latent_dim}")
        lat = edit_latents(self.latent(latent), boundary.normal, [float(a) * boundary.sigma for a in alphas])
        return self.decode(space.synthesize(self.network, lat))

    def invert(self, motion: Motion | str | os.PathLike, *, start: int = 0, steps: int = 300, lr: float = 0.02,
               lambda_fk: float = 1.0, init: str = "mean", progress: bool = False) -> Inversion:
        """Optimise a W+ latent so its motion matches a window of ``motion`` (a Motion or a BVH path on the model's
        skeleton, joints matched by name), as ``modi latent invert``. Cost: ``steps`` generator forward and
        backward passes."""
        if steps < 0:
            raise UserError(f"steps must be >= 0, got {steps}")
        if lr <= 0 or lambda_fk < 0:
            raise UserError("lr must be positive and lambda_fk >= 0")
        target = self.encode_motion(motion, start=start).unsqueeze(0)
        res = invert_latent(self.network, self.codec, target, steps=steps, lr=lr, lambda_fk=lambda_fk, init=init,
                            progress=progress)
        result, target_m = self.decode(torch.cat([res.motion.cpu(), target.cpu()]))
        return Inversion(res.wplus[0].detach(), result, target_m, list(res.history), list(res.rec), list(res.fk))

    @staticmethod
    def save_latent(path: str | os.PathLike, latent: Tensor) -> Path:
        """Write a latent as float32 ``.npy`` (readable by :meth:`latent` and ``modi latent``)."""
        return space.save_latent(path, latent)


def open_generator(ckpt: str | os.PathLike, *, device: str = "cpu", threads: int | None = None,
                   ema: bool = True) -> ModiGenerator:
    """A checkpoint's generator as ``modi generate`` and ``modi latent`` open it: torch's CPU ``threads`` set
    (None: torch's choice), ``device`` checked, the file checked, then read (well under a second)."""
    set_threads(threads)
    check_device(device)
    existing_file(ckpt, "MoDi checkpoint file")
    return ModiGenerator.from_checkpoint(ckpt, device=device, ema=ema)


def _steps(n: int) -> int:
    if int(n) < 1:
        raise UserError(f"--steps must be >= 1, got {n}")
    return int(n)


__all__ = ["ModiGenerator", "Inversion", "Boundary", "open_generator"]
