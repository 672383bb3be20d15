"""Ill-posed motion tasks solved by projecting onto MoDi's natural-motion manifold: m -> G(I(m)) (paper 001 §4.2).

Every application writes, for each input, three BVH files and one GIF with them side by side: ``input`` (what the
user gave), ``naive`` (what one gets without the generative prior) and ``encoder`` (G(I(m))):

========== ============================================ ============================================================
task       naive result                                 encoder result
========== ============================================ ============================================================
invert     optimisation into W+ (``latent.inversion``)   one forward pass of the encoder
prefix     the last visible pose held, root stopped      G(I_prefix(m with frames >= t zeroed)) (prefix-trained I)
fuse       hard cut: frames < t of A, >= t of B          G(I(cut)): smooth transition, both ends kept
denoise    Gaussian temporal smoothing of the noisy m    G(I(noisy m))
edit       a crude edit (right arm raised from frame t)  G(I(edited m)): the edit made natural
========== ============================================ ============================================================

Motions are normalised model tensors (B, K, E, T) (``latent.space.load_bvh_window`` reads BVH files).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from modi.core.kinematics import forward_kinematics
from modi.core.rotations import axis_angle_to_quat, quat_inverse, quat_mul, quat_normalize
from modi.data.representation import continuous_quats
from modi.errors import UserError
from modi.models.modi.encoder.training import EncoderBundle
from modi.models.modi.latent.editing import bone_elevation, find_right_arm, gral_score
from modi.models.modi.latent.inversion import invert
from modi.models.modi.latent.space import mean_motion, write_motions


def _write_triplet(bundle: EncoderBundle, out_dir: str | Path, stem: str, inp: Tensor, naive: Tensor, enc: Tensor,
                   labels: Sequence[str] = ("input", "naive", "encoder")) -> dict[str, Any]:
    x = torch.cat([inp.reshape(1, *inp.shape[-3:]), naive.reshape(1, *naive.shape[-3:]),
                   enc.reshape(1, *enc.shape[-3:])]).cpu()
    names = [f"{stem}_{lab}" for lab in ("input", "naive", "encoder")]
    paths = write_motions(bundle.codec, x, out_dir, names, gif=f"{stem}.gif", titles=list(labels),
                          view=f"{stem}.html")
    return {"bvh": [str(p) for p in paths], "gif": str(Path(out_dir) / f"{stem}.gif")}


def _mse(a: Tensor, b: Tensor, frames: slice | None = None) -> float:
    if frames is not None:
        a, b = a[..., frames], b[..., frames]
    return float((a.float().cpu() - b.float().cpu()).pow(2).mean())


def _check(bundle: EncoderBundle, x: Tensor) -> Tensor:
    k, e, t = bundle.g.output_shape
    if x.ndim == 3:
        x = x.unsqueeze(0)
    if x.ndim != 4 or tuple(x.shape[1:]) != (k, e, t):
        raise UserError(f"motions must be (B, {k}, {e}, {t}) model windows, got {tuple(x.shape)}")
    return x.float()


# --------------------------------------------------------------------------------------------- inversion
def invert_motions(bundle: EncoderBundle, x: Tensor, out_dir: str | Path, names: Sequence[str] | None = None,
                   optim_steps: int = 200, progress: bool = True) -> list[dict[str, Any]]:
    """Invert unseen motions: the encoder's one-pass projection beside optimisation-based inversion (``optim_steps``
    Adam steps in W+; 0 puts the mean motion there instead)."""
    x = _check(bundle, x)
    names = list(names) if names is not None else [f"motion{i:03d}" for i in range(len(x))]
    _, rec = bundle.project(x)
    if optim_steps > 0:
        naive = invert(bundle.g, bundle.codec, x, steps=optim_steps, progress=progress).motion
        label = f"optimised W+ ({optim_steps} steps)"
    else:
        naive = mean_motion(bundle.g).expand_as(x)
        label = "mean motion"
    out = []
    for i, name in enumerate(names):
        r = _write_triplet(bundle, out_dir, name, x[i], naive[i], rec[i], ("input", label, "encoder"))
        r.update(l2_naive=_mse(naive[i], x[i]), l2_encoder=_mse(rec[i], x[i]))
        out.append(r)
    return out


# --------------------------------------------------------------------------------------------- prefix
def hold_after(codec: Any, x: Tensor, t: int) -> Tensor:
    """The naive completion: frames >= t repeat frame t-1's pose, the root stops (zero horizontal velocity)."""
    raw = codec.normalizer.denormalize(x.float().cpu())
    held = raw.clone()
    held[..., t:] = raw[..., t - 1:t]
    J = codec.rep.n_joints
    if codec.rep.root == "velocity":
        held[:, 0, J, t:] = 0.0
        held[:, 2, J, t:] = 0.0
    return codec.normalizer.normalize(held)


def complete_prefix(bundle: EncoderBundle, x: Tensor, out_dir: str | Path, names: Sequence[str] | None = None
                    ) -> list[dict[str, Any]]:
    """Predict the rest of each motion from its first ``t`` frames with the prefix-trained encoder."""
    t = bundle.prefix_frames
    if t is None:
        raise UserError("this encoder was trained on whole motions; prediction from a prefix needs an encoder "
                        "trained with 'modi encoder train ... --prefix T'")
    x = _check(bundle, x)
    names = list(names) if names is not None else [f"motion{i:03d}" for i in range(len(x))]
    _, rec = bundle.project(x, prefix_frames=t)
    naive = hold_after(bundle.codec, x, t)
    out = []
    for i, name in enumerate(names):
        r = _write_triplet(bundle, out_dir, name, x[i], naive[i], rec[i],
                           (f"input (first {t} frames seen)", "hold last pose", "encoder completion"))
        r.update(prefix_frames=t, l2_prefix_encoder=_mse(rec[i], x[i], slice(0, t)),
                 l2_suffix_encoder=_mse(rec[i], x[i], slice(t, None)),
                 l2_suffix_naive=_mse(naive[i], x[i], slice(t, None)))
        out.append(r)
    return out


# --------------------------------------------------------------------------------------------- fusion
def concatenate(a: Tensor, b: Tensor, t: int) -> Tensor:
    """Frames [0, t) of ``a`` then [t, T) of ``b``. With root velocities the trajectory continues from A's."""
    if a.shape != b.shape:
        raise UserError(f"the two motions differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    T = a.shape[-1]
    if not 0 < t < T:
        raise UserError(f"fusion frame must be in 1..{T - 1}, got {t}")
    return torch.cat([a[..., :t], b[..., t:]], -1)


def fusion_errors(result: Tensor, a: Tensor, b: Tensor, t: int, margin: int = 4) -> dict[str, float]:
    """MSE of the result's prefix (frames < t - margin) against A and B, and of its suffix (>= t + margin)."""
    pre, suf = slice(0, max(1, t - margin)), slice(min(result.shape[-1] - 1, t + margin), None)
    return {"prefix_vs_a": _mse(result, a, pre), "prefix_vs_b": _mse(result, b, pre),
            "suffix_vs_b": _mse(result, b, suf), "suffix_vs_a": _mse(result, a, suf)}


def fuse(bundle: EncoderBundle, a: Tensor, b: Tensor, t: int) -> tuple[Tensor, Tensor]:
    """(naive cut, G(I(cut))) for pairs of motions (B, K, E, T)."""
    a, b = _check(bundle, a), _check(bundle, b)
    naive = concatenate(a, b, t)
    return naive, bundle.project(naive)[1].cpu()


def fuse_motions(bundle: EncoderBundle, a: Tensor, b: Tensor, t: int, out_dir: str | Path, name: str = "fusion",
                 margin: int = 4) -> dict[str, Any]:
    naive, rec = fuse(bundle, a, b, t)
    r = _write_triplet(bundle, out_dir, name, a[0] if a.ndim == 4 else a, naive[0], rec[0],
                       ("A (prefix source)", f"cut at frame {t}", "encoder fusion"))
    b_paths = write_motions(bundle.codec, (b if b.ndim == 4 else b.unsqueeze(0))[:1].cpu(), out_dir,
                            [f"{name}_B"], gif=None)
    r["bvh"].append(str(b_paths[0]))
    r.update(t=t, **fusion_errors(rec[0], a.reshape(rec[0].shape), b.reshape(rec[0].shape), t, margin))
    return r


# --------------------------------------------------------------------------------------------- denoising
def add_noise(codec: Any, x: Tensor, sigma: float, seed: int = 0) -> Tensor:
    """Gaussian noise of std ``sigma`` (normalised units) on every joint-rotation channel; root and contacts kept."""
    if sigma < 0:
        raise UserError(f"noise sigma must be >= 0, got {sigma}")
    g = torch.Generator().manual_seed(int(seed))
    noisy = x.float().cpu().clone()
    J = codec.rep.n_joints
    noisy[:, :, :J] += sigma * torch.randn(noisy[:, :, :J].shape, generator=g)
    return noisy


def smooth_time(x: Tensor, sigma_frames: float) -> Tensor:
    """Gaussian smoothing along time (edge-replicated), the classical denoiser."""
    if sigma_frames <= 0:
        return x.clone()
    r = max(1, int(math.ceil(3 * sigma_frames)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype) / sigma_frames) ** 2)
    k = k / k.sum()
    flat = x.reshape(-1, 1, x.shape[-1])
    padded = torch.nn.functional.pad(flat, (r, r), mode="replicate")
    return torch.nn.functional.conv1d(padded, k.view(1, 1, -1)).reshape(x.shape)


def denoise_motions(bundle: EncoderBundle, x: Tensor, out_dir: str | Path, names: Sequence[str] | None = None,
                    sigma: float = 0.5, smooth: float = 2.0, seed: int = 0, noisy: Tensor | None = None
                    ) -> list[dict[str, Any]]:
    """Add noise to clean motions (or take ``noisy`` ones as given) and clean them up: smoothing vs G(I(noisy))."""
    x = _check(bundle, x)
    names = list(names) if names is not None else [f"motion{i:03d}" for i in range(len(x))]
    noisy = add_noise(bundle.codec, x, sigma, seed) if noisy is None else _check(bundle, noisy).cpu()
    naive = smooth_time(noisy, smooth)
    _, rec = bundle.project(noisy)
    out = []
    for i, name in enumerate(names):
        r = _write_triplet(bundle, out_dir, name, noisy[i], naive[i], rec[i],
                           (f"noisy input (sd {sigma:g})", f"smoothed (sd {smooth:g} frames)", "encoder"))
        write_motions(bundle.codec, x[i:i + 1].cpu(), out_dir, [f"{name}_clean"], gif=None)
        r.update(l2_noisy=_mse(noisy[i], x[i]), l2_naive=_mse(naive[i], x[i]), l2_encoder=_mse(rec[i], x[i]))
        out.append(r)
    return out


# --------------------------------------------------------------------------------------------- spatial editing
def raise_arm(codec: Any, x: Tensor, angle: float = 90.0, start: int | None = None, joint: int | None = None
              ) -> Tensor:
    """A crude spatial edit: from frame ``start`` on, turn the right upper arm (``joint``: default the right
    shoulder found by name) by ``angle`` degrees *toward the sky* (about the world axis perpendicular to the bone
    and the vertical) -- abruptly, the way a quick keyframe edit would."""
    x = x.float().cpu()
    T = x.shape[-1]
    start = T // 2 if start is None else int(start)
    if not 0 <= start < T:
        raise UserError(f"edit start frame must be in 0..{T - 1}, got {start}")
    sk = codec.skeleton
    if joint is None:
        joint, elbow, _ = find_right_arm(sk)
    else:
        kids = sk.children(joint)
        if not kids:
            raise UserError(f"joint {sk.names[joint]!r} has no child bone to raise")
        elbow = kids[0]
    parent = sk.parents[joint]

    dec = codec.decode(x)
    rot = dec["rotations"]  # (B, T, J, 4)
    pos, grot = forward_kinematics(rot, torch.as_tensor(sk.offsets, dtype=rot.dtype), list(sk.parents), dec["root"])
    bone = pos[..., elbow, :] - pos[..., joint, :]
    axis = torch.cross(bone, torch.tensor([0.0, 1.0, 0.0]).expand_as(bone), dim=-1)
    n = torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    axis = torch.where(n > 1e-6, axis / n.clamp_min(1e-9), torch.zeros_like(axis))
    delta = axis_angle_to_quat(axis * math.radians(angle))  # world-frame turn toward +Y
    g_parent = grot[..., parent, :] if parent >= 0 else torch.tensor([1.0, 0.0, 0.0, 0.0]).expand_as(delta)
    new_local = quat_mul(quat_inverse(g_parent), quat_mul(delta, quat_mul(g_parent, rot[..., joint, :])))
    q = rot[..., joint, :].clone()
    q[:, start:] = quat_normalize(new_local[:, start:])
    q = continuous_quats(q, dim=-2)  # (B, T, 4): sign-continuous in time, like the training data
    raw = codec.normalizer.denormalize(x)
    raw[:, :4, joint, :] = q.transpose(-1, -2)
    return codec.normalizer.normalize(raw)


def edit_motions(bundle: EncoderBundle, x: Tensor, out_dir: str | Path, names: Sequence[str] | None = None,
                 angle: float = 90.0, start: int | None = None, joint: int | None = None) -> list[dict[str, Any]]:
    """Raise the right arm crudely from frame ``start`` and let G∘I turn the edit into a natural motion; reports
    the arm's mean elevation (degrees) over the edited frames and the gral score for all three."""
    x = _check(bundle, x)
    names = list(names) if names is not None else [f"motion{i:03d}" for i in range(len(x))]
    T = x.shape[-1]
    start = T // 2 if start is None else int(start)
    edited = raise_arm(bundle.codec, x, angle, start, joint)
    _, rec = bundle.project(edited)
    sk = bundle.codec.skeleton
    sh, el = find_right_arm(sk)[:2] if joint is None else (joint, sk.children(joint)[0])

    def elevation(m: Tensor) -> float:
        p = bundle.codec.decode(m.float().cpu().unsqueeze(0))["positions"][0]
        return float(bone_elevation(p, sh, el)[start:].mean())

    out = []
    for i, name in enumerate(names):
        r = _write_triplet(bundle, out_dir, name, x[i], edited[i], rec[i],
                           ("input", f"crude edit (+{angle:g} deg from frame {start})", "encoder"))
        r.update(start=start, angle=angle,
                 arm_elevation={"input": elevation(x[i]), "naive": elevation(edited[i]), "encoder": elevation(rec[i])},
                 l2_unedited_frames_encoder=_mse(rec[i], x[i], slice(0, start)))
        try:
            r["gral"] = {k: float(gral_score(bundle.codec, v[i:i + 1].cpu())[0])
                         for k, v in (("input", x), ("naive", edited), ("encoder", rec))}
        except (UserError, ValueError):
            pass
        out.append(r)
    return out


__all__ = ["invert_motions", "hold_after", "complete_prefix", "concatenate", "fusion_errors", "fuse",
           "fuse_motions", "add_noise", "smooth_time", "denoise_motions", "raise_arm", "edit_motions"]
