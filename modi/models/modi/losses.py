"""MoDi's losses: StyleGAN2's adversarial/R1/path-length terms and the foot-contact terms (paper eqs. 2-3, 11-14;
the contact consistency in both the released code's form and the paper's squared form).

The foot terms take *decoded* quantities (foot joint positions from the FK layer and the raw contact channel), so
they stay independent of how the representation is normalised; ``training.py`` does the decoding.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import autograd

CONTACT_SHARPNESS = 12.0  # s(c) = sigmoid(12 (c - 1/2)): labels 0/1 map to ~0/~1 (the authors' code does the same)


def d_logistic_loss(real_pred: torch.Tensor, fake_pred: torch.Tensor) -> torch.Tensor:
    """Non-saturating discriminator loss: softplus(-D(real)) + softplus(D(fake))."""
    return F.softplus(-real_pred).mean() + F.softplus(fake_pred).mean()


def g_nonsaturating_loss(fake_pred: torch.Tensor) -> torch.Tensor:
    """Non-saturating generator loss: -log sigmoid(D(G(z))) = softplus(-D(G(z)))."""
    return F.softplus(-fake_pred).mean()


def d_r1_penalty(real_pred: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """R1: E ||grad_x D(x)||^2 on real data (``real`` must require grad and have produced ``real_pred``)."""
    (grad,) = autograd.grad(outputs=real_pred.sum(), inputs=real, create_graph=True)
    return grad.pow(2).reshape(grad.shape[0], -1).sum(1).mean()


def path_length_penalty(fake: torch.Tensor, wplus: torch.Tensor, mean_path_length: torch.Tensor | float,
                        decay: float = 0.01) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """StyleGAN2 path-length regulariser: (|J_w^T y| - a)^2 with y ~ N(0, I) / sqrt(entities * frames).

    Returns ``(penalty, new running mean a, per-sample path lengths)``.
    """
    noise = torch.randn_like(fake) / math.sqrt(fake.shape[2] * fake.shape[3])
    (grad,) = autograd.grad(outputs=(fake * noise).sum(), inputs=wplus, create_graph=True)
    path_lengths = torch.sqrt(grad.pow(2).sum(2).mean(1))
    mean = torch.as_tensor(mean_path_length, dtype=path_lengths.dtype, device=path_lengths.device)
    path_mean = mean + decay * (path_lengths.mean().detach() - mean)
    penalty = (path_lengths - path_mean).pow(2).mean()
    return penalty, path_mean.detach(), path_lengths.detach()


def contact_probability(contact: torch.Tensor) -> torch.Tensor:
    """s(c): the generator's raw contact channel (label scale, 0 = air, 1 = ground) as a probability."""
    return torch.sigmoid(CONTACT_SHARPNESS * (contact - 0.5))


def foot_touch_loss(contact: torch.Tensor) -> torch.Tensor:
    """L_tch = E[-log s(c)] (paper eq. 2): a weak push toward feet on the ground, against floating."""
    return F.softplus(-CONTACT_SHARPNESS * (contact - 0.5)).mean()


def foot_contact_consistency_loss(foot_positions: torch.Tensor, contact: torch.Tensor, fps: float,
                                  height: float) -> torch.Tensor:
    """L_fcon = E[ ||foot velocity||^2 * s(c) ] (paper eq. 3): no sliding while a foot is labelled in contact.

    ``foot_positions``: (B, T, F, 3) global positions from FK; ``contact``: (B, F, T) raw contact channel.
    Velocity is measured in skeleton heights per second, so the weight (1 in the paper) means the same thing for
    any rig, unit and frame rate.
    """
    if foot_positions.ndim != 4 or foot_positions.shape[-1] != 3:
        raise ValueError(f"foot_positions must be (B, T, F, 3), got {tuple(foot_positions.shape)}")
    b, t, f, _ = foot_positions.shape
    if tuple(contact.shape) != (b, f, t):
        raise ValueError(f"contact must be (B, F, T) = {(b, f, t)}, got {tuple(contact.shape)}")
    if height <= 0:
        raise ValueError(f"height must be positive, got {height}")
    vel = (foot_positions[:, 1:] - foot_positions[:, :-1]) * (fps / height)  # (B, T-1, F, 3)
    speed2 = vel.pow(2).sum(-1).transpose(1, 2)  # (B, F, T-1)
    return (speed2 * contact_probability(contact[..., 1:])).mean()


def foot_contact_speed_loss(foot_positions: torch.Tensor, contact: torch.Tensor) -> torch.Tensor:
    """The released MoDi's contact consistency: E[ s(c_t) * ||p_t - p_{t-1}|| ] over batch, feet and frames.

    The foot *speed* (not squared) per frame, in the data's own units -- the authors' ``g_foot_contact_loss_v2``
    (``train.py``) on the velocity of ``utils/foot.get_foot_velo``, whose joints are the ankles (Mixamo's
    ``LeftFoot``/``RightFoot``). Unlike the squared form its gradient does not vanish for slow slides.
    ``foot_positions``: (B, T, F, 3) global positions; ``contact``: (B, F, T) raw contact channel.
    """
    if foot_positions.ndim != 4 or foot_positions.shape[-1] != 3:
        raise ValueError(f"foot_positions must be (B, T, F, 3), got {tuple(foot_positions.shape)}")
    b, t, f, _ = foot_positions.shape
    if tuple(contact.shape) != (b, f, t):
        raise ValueError(f"contact must be (B, F, T) = {(b, f, t)}, got {tuple(contact.shape)}")
    # vector_norm's backward is 0 (not NaN) where a foot does not move at all
    speed = torch.linalg.vector_norm(foot_positions[:, 1:] - foot_positions[:, :-1], dim=-1).transpose(1, 2)
    return (speed * contact_probability(contact[..., 1:])).mean()


def lazy_regularization_adam_params(lr: float, betas: tuple[float, float], reg_every: int) -> tuple[float, tuple]:
    """StyleGAN2's correction when a regulariser runs every k steps: lr * c and betas ** c with c = k / (k + 1)."""
    c = reg_every / (reg_every + 1)
    return lr * c, (betas[0] ** c, betas[1] ** c)
