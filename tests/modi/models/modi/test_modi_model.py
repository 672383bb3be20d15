"""MoDi networks, losses and config: shapes through every level, latent handling, ablations, loss values."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from modi.models.modi.config import ABLATIONS, MoDiConfig, ModelConfig, make_config
from modi.models.modi.losses import (contact_probability, d_logistic_loss, d_r1_penalty,
                                    foot_contact_consistency_loss, foot_touch_loss, g_nonsaturating_loss,
                                    lazy_regularization_adam_params, path_length_penalty)
from modi.models.modi.fastpaths import inv_std_entities_frames, std_entities_frames, std_normalised_leaky_relu_
from modi.models.modi.levels import build_levels
from modi.models.modi.networks import Discriminator, Generator, StyledConv, minibatch_stddev
from modi_ext.fir import blur_time as fir_blur_time
from modi_ext.fir import downsample_time as fir_downsample_time
from modi_ext.fir import upsample_time as fir_upsample_time
from modi_ext.layers import fused_leaky_relu
from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import build_hierarchy

K = 4


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny(levels: int, **kw) -> ModelConfig:
    """A tiny model with one channel width per hierarchy level (so every level is used)."""
    base = dict(latent_dim=16, n_mlp=2, channels=tuple([6] * levels))
    base.update(kw)
    return ModelConfig(**base)


def humanoid() -> Skeleton:
    from modi.data.procedural import builtin_skeleton

    return builtin_skeleton()


def random_tree(n: int, seed: int) -> Skeleton:
    rng = random.Random(seed)
    parents = [-1] + [rng.randrange(j) for j in range(1, n)]
    offsets = np.random.default_rng(seed).normal(size=(n, 3))
    return Skeleton([f"j{j}" for j in range(n)], parents, offsets)


def leaves(sk: Skeleton) -> list[int]:
    return [j for j in range(1, sk.n_joints) if not sk.children(j)][:2]


SKELETONS = [
    ("humanoid", humanoid, None),
    ("chain5", lambda: Skeleton([f"c{j}" for j in range(5)], [-1, 0, 1, 2, 3], np.ones((5, 3))), [4]),
    ("star", lambda: Skeleton([f"s{j}" for j in range(7)], [-1, 0, 0, 0, 0, 0, 0], np.ones((7, 3))), [1, 2]),
    ("random9", lambda: random_tree(9, 3), "leaves"),
    ("random14", lambda: random_tree(14, 11), "leaves"),
    ("random20", lambda: random_tree(20, 5), "leaves"),
]


def hierarchy_of(make, feet):
    sk = make()
    if feet == "leaves":
        feet = leaves(sk)
    elif feet is None:
        feet = sk.detect_feet()
    return sk, build_hierarchy(sk, feet)


@pytest.mark.parametrize("name,make,feet", SKELETONS, ids=[s[0] for s in SKELETONS])
def test_shapes_through_every_level(name, make, feet):
    sk, h = hierarchy_of(make, feet)
    L = h.n_levels
    n_frames = max(16, 2 ** (L - 1))  # every level doubles time
    cfg = tiny(L)
    levels = build_levels(h, cfg, n_frames)
    assert len(levels) == L
    # coarse -> fine entity counts are the hierarchy's, reversed; frames double per level
    assert [lv.n_entities for lv in levels] == h.entity_counts[::-1]
    assert [lv.n_frames for lv in levels] == [n_frames // 2 ** (L - 1 - i) for i in range(L)]
    g, d = Generator(cfg, levels, K), Discriminator(cfg, levels, K)
    seen = []
    hooks = [m.register_forward_hook(lambda mod, inp, out: seen.append(tuple(out.shape)))
             for m in g.modules() if isinstance(m, StyledConv)]
    b = 3
    x = g(torch.randn(b, cfg.latent_dim))
    for hk in hooks:
        hk.remove()
    expect = [(b, levels[0].channels, levels[0].n_entities, levels[0].n_frames)]
    for lv in levels[1:]:
        expect += [(b, lv.channels, lv.n_entities, lv.n_frames)] * (1 + cfg.n_inplace_convs)
    assert seen == expect
    assert x.shape == (b, K, levels[-1].n_entities, n_frames) == (b, K, h.entity_counts[0], n_frames)
    d_seen = []
    hooks = [blk.register_forward_hook(lambda mod, inp, out: d_seen.append(tuple(out.shape))) for blk in d.blocks]
    out = d(x)
    for hk in hooks:
        hk.remove()
    assert out.shape == (b, 1)
    assert d_seen == [(b, lv.channels, lv.n_entities, lv.n_frames) for lv in levels[-2::-1]]
    out.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in d.parameters())


def test_more_levels_than_channels_uses_the_finest():
    sk, h = hierarchy_of(humanoid, None)
    cfg = tiny(3)
    levels = build_levels(h, cfg, 16)
    assert [lv.n_entities for lv in levels] == h.entity_counts[:3][::-1]
    assert levels[0].n_entities > 1
    g = Generator(cfg, levels, K)
    assert g(torch.randn(2, 16)).shape == (2, K, h.entity_counts[0], 16)


def test_frames_must_halve_cleanly():
    _, h = hierarchy_of(humanoid, None)
    with pytest.raises(ValueError, match="divisible"):
        build_levels(h, tiny(h.n_levels), 24)


@pytest.mark.parametrize("ablation", ["pool", "one-conv", "pseudo-image"])
def test_ablation_variants_shapes(ablation):
    _, h = hierarchy_of(humanoid, None)
    cfg = make_config("small", [ablation], **{"model.channels": (8, 8, 6, 6, 4), "model.latent_dim": 16,
                                             "model.n_mlp": 2})
    levels = build_levels(h, cfg.model, 16)
    g, d = Generator(cfg.model, levels, K), Discriminator(cfg.model, levels, K)
    x = g(torch.randn(2, 16))
    assert x.shape == (2, K, h.entity_counts[0], 16)
    assert d(x).shape == (2, 1)
    base = make_config("small", [], **{"model.channels": (8, 8, 6, 6, 4), "model.latent_dim": 16, "model.n_mlp": 2})
    g0 = Generator(base.model, build_levels(h, base.model, 16), K)
    n0 = sum(p.numel() for p in g0.parameters())
    n1 = sum(p.numel() for p in g.parameters())
    assert n1 != n0  # the switch really changes the architecture
    if ablation == "one-conv":
        assert g.n_latent == g0.n_latent - (len(levels) - 1)


def test_pseudo_image_is_not_skeleton_aware_but_skeleton_model_is():
    """The skeleton-aware generator's finest in-place conv mixes only neighbouring entities; the pseudo-image
    one mixes entity rows by index adjacency."""
    sk, h = hierarchy_of(humanoid, None)
    cfg = tiny(h.n_levels)
    levels = build_levels(h, cfg, 16)
    g = Generator(cfg, levels, K)
    conv = g.blocks[-1][1].conv  # an in-place modulated conv at the finest level
    x = torch.zeros(1, 6, levels[-1].n_entities, 16, requires_grad=True)
    w = torch.randn(1, 16)
    e = 3
    conv(x, w)[0, :, e].sum().backward()
    touched = sorted(set(torch.nonzero(x.grad[0].abs().sum((0, 2)) > 0).flatten().tolist()))
    assert touched == levels[-1].neighbors[e]


def test_wplus_equals_w_and_mixing_boundary():
    _, h = hierarchy_of(humanoid, None)
    cfg = tiny(h.n_levels)
    g = Generator(cfg, build_levels(h, cfg, 16), K).eval()
    z1, z2 = torch.randn(2, 16), torch.randn(2, 16)
    w1, w2 = g.mapping(z1), g.mapping(z2)
    a = g(z1, noise_mode="const")
    b = g(w1.unsqueeze(1).repeat(1, g.n_latent, 1), input_is_w=True, noise_mode="const")
    assert torch.allclose(a, b, atol=1e-6)
    mixed = g([z1, z2], inject_index=3, noise_mode="const", return_latents=True)[1]
    assert torch.allclose(mixed[:, :3], w1.unsqueeze(1).expand(-1, 3, -1))
    assert torch.allclose(mixed[:, 3:], w2.unsqueeze(1).expand(-1, g.n_latent - 3, -1))
    with pytest.raises(ValueError, match="W\\+"):
        g(torch.randn(2, g.n_latent + 1, 16), input_is_w=True)


def test_truncation_zero_gives_the_mean_motion():
    _, h = hierarchy_of(humanoid, None)
    cfg = tiny(h.n_levels)
    g = Generator(cfg, build_levels(h, cfg, 16), K).eval()
    g.w_avg.normal_()
    out = g(torch.randn(3, 16), truncation_psi=0.0, noise_mode="const")
    ref = g(g.w_avg.expand(1, -1), input_is_w=True, noise_mode="const")
    assert torch.allclose(out, ref.expand_as(out), atol=1e-5)


def test_noise_modes():
    _, h = hierarchy_of(humanoid, None)
    cfg = tiny(h.n_levels, noise_injection=True)
    g = Generator(cfg, build_levels(h, cfg, 16), K).eval()
    for layer in g.styled_layers():
        layer.noise.weight.data.fill_(0.5)
    z = torch.randn(2, 16)
    assert torch.equal(g(z, noise_mode="const"), g(z, noise_mode="const"))
    assert not torch.equal(g(z, noise_mode="random"), g(z, noise_mode="random"))
    assert len(g.noise_shapes()) == len(g.styled_layers())


def test_mapping_lr_multiplier_and_pixel_norm():
    g = Generator(tiny(2), build_levels(hierarchy_of(humanoid, None)[1], tiny(2), 16), K)
    lin = g.mapping.net[1]
    assert lin.weight.std().item() == pytest.approx(100.0, rel=0.2)  # N(0,1)/0.01, scaled back at run time
    z = torch.randn(4, 16)
    assert torch.allclose(g.mapping(z), g.mapping(z * 7.0), atol=1e-5)  # pixel norm: scale invariant


def test_fir_filters():
    ones = torch.ones(1, 10)
    assert torch.allclose(fir_upsample_time(ones)[..., 1:-1], torch.ones(1, 18))  # DC gain 1 inside
    ramp = torch.arange(8.0)
    up = fir_upsample_time(ramp)
    assert torch.allclose(up[2:-1], torch.arange(2, 15).float() / 2 - 0.25)  # quarter-sample linear interpolation
    down = fir_downsample_time(torch.ones(1, 16))
    assert down.shape[-1] == 8 and torch.allclose(down[..., 1:-1], torch.ones(1, 6))
    assert fir_blur_time(torch.ones(3, 9)).shape == (3, 9)


def test_fir_upsample_is_the_filtered_zero_insertion():
    """The transposed-conv form equals StyleGAN2's definition (zero-insert, pad (2, 1), [1 3 3 1] / 4 with gain 2) to
    rounding (its sums run in another order), and its gradients are that linear map's."""
    def zero_inserted(x):
        n = x.shape[-1]
        y = x.new_zeros(*x.shape[:-1], 2 * n)
        y[..., ::2] = x
        y = F.pad(y, (2, 1))
        return 0.25 * y[..., :2 * n] + 0.75 * y[..., 1:2 * n + 1] + 0.75 * y[..., 2:2 * n + 2] + 0.25 * y[..., 3:]

    g = torch.Generator().manual_seed(3)
    for shape in [(7,), (2, 3, 5, 1), (3, 4, 6, 16)]:
        x = torch.randn(shape, generator=g)
        torch.testing.assert_close(fir_upsample_time(x), zero_inserted(x), rtol=0, atol=1e-6)
    x = torch.randn(2, 3, 9, dtype=torch.float64, generator=g, requires_grad=True)
    gy = torch.randn(2, 3, 18, dtype=torch.float64, generator=g)
    torch.testing.assert_close(torch.autograd.grad(fir_upsample_time(x), x, gy)[0],
                               torch.autograd.grad(zero_inserted(x), x, gy)[0], rtol=1e-14, atol=1e-14)


def test_minibatch_stddev_values():
    x = torch.zeros(4, 2, 3, 5)
    x[1] = 2.0  # groups of 4: {0,1,2,3}; channel std over the group of [0,2,0,0] is sqrt(0.75)
    y = minibatch_stddev(x, 4)
    assert y.shape == (4, 3, 3, 5)
    assert torch.allclose(y[:, 2], torch.full((4, 3, 5), math.sqrt(0.75 + 1e-8)))
    y2 = minibatch_stddev(torch.zeros(6, 2, 3, 5), 4)  # 6 is not divisible by 4: groups of 3
    assert torch.allclose(y2[:, 2], torch.full((6, 3, 5), 1e-4))


def test_adversarial_and_r1_values():
    zero = torch.zeros(5, 1)
    assert d_logistic_loss(zero, zero).item() == pytest.approx(2 * math.log(2))
    assert g_nonsaturating_loss(zero).item() == pytest.approx(math.log(2))
    w = torch.randn(12)
    x = torch.randn(3, 12, requires_grad=True)
    assert d_r1_penalty((x @ w).unsqueeze(1), x).item() == pytest.approx(float(w @ w), rel=1e-5)


def test_path_length_of_a_linear_map():
    torch.manual_seed(0)
    a = torch.randn(2, 3, 4)  # fake = sum_l w[:, l] . a -> dfake/dw = a for every style
    wplus = torch.randn(6, 5, 2, requires_grad=True)
    fake = torch.einsum("bld,dke->bke", wplus, a).unsqueeze(-1).expand(-1, -1, -1, 1)
    pen, mean, lengths = path_length_penalty(fake, wplus, 0.0, decay=0.01)
    assert lengths.shape == (6,)
    assert mean.item() == pytest.approx(0.01 * lengths.mean().item(), rel=1e-5)
    assert pen.item() == pytest.approx(((lengths - mean) ** 2).mean().item(), rel=1e-5)


def test_foot_losses():
    c_on = torch.ones(2, 2, 10)
    assert foot_touch_loss(c_on).item() == pytest.approx(math.log1p(math.exp(-6.0)), rel=1e-5)
    assert contact_probability(torch.tensor(0.0)).item() < 0.01
    still = torch.zeros(2, 10, 2, 3)
    assert foot_contact_consistency_loss(still, c_on, 30.0, 170.0).item() == 0.0
    moving = torch.zeros(2, 10, 2, 3)
    moving[:, :, :, 0] = torch.arange(10.0).view(1, 10, 1) * 17.0  # 17 cm/frame = 3 heights/s at 30 fps
    full = foot_contact_consistency_loss(moving, c_on, 30.0, 170.0).item()
    assert full == pytest.approx(9.0 * float(contact_probability(torch.tensor(1.0))), rel=1e-5)
    off = foot_contact_consistency_loss(moving, torch.zeros(2, 2, 10), 30.0, 170.0).item()
    assert off < 0.01 * full
    with pytest.raises(ValueError):
        foot_contact_consistency_loss(moving, torch.zeros(2, 3, 10), 30.0, 170.0)


def test_lazy_regularization_correction():
    lr, betas = lazy_regularization_adam_params(0.002, (0.0, 0.99), 16)
    assert lr == pytest.approx(0.002 * 16 / 17)
    assert betas == (0.0, pytest.approx(0.99 ** (16 / 17)))


def test_config_presets_roundtrip_and_errors():
    paper = make_config("paper")
    assert paper.model.channels == (256, 128, 64, 64, 32)
    assert (paper.train.batch, paper.train.iters, paper.train.lr, paper.train.mixing) == (16, 80000, 0.002, 0.9)
    assert (paper.train.r1_gamma, paper.train.d_reg_every, paper.train.path_weight, paper.train.g_reg_every,
            paper.train.path_batch_shrink) == (10.0, 16, 2.0, 4, 2)
    assert (paper.train.touch_weight, paper.train.contact_weight) == (0.01, 1.0)
    assert (paper.model.latent_dim, paper.model.n_mlp, paper.model.lr_mlp) == (512, 8, 0.01)
    for name in ABLATIONS:
        cfg = make_config("small", [name])
        assert MoDiConfig.from_dict(cfg.to_dict()) == cfg
    assert make_config("small", ["pool"]).model.scaler == "pool"
    assert make_config("small", ["positions"]).data.rotation == "positions"
    with pytest.raises(ValueError, match="unknown ablation"):
        make_config("small", ["nope"])
    with pytest.raises(ValueError, match="unknown config key"):
        make_config("small", **{"model.nope": 1})
    with pytest.raises(ValueError, match="scaler"):
        make_config("small", **{"model.scaler": "avg"})
    with pytest.raises(ValueError, match="unknown"):
        MoDiConfig.from_dict({**paper.to_dict(), "model": {**paper.to_dict()["model"], "extra": 1}})


def test_no_noise_injection_by_default_as_released():
    """Released MoDi (models/gan.py StyledConv): modulated conv + bias + leaky ReLU, no noise."""
    assert ModelConfig().noise_injection is False
    _, h = hierarchy_of(humanoid, None)
    cfg = tiny(h.n_levels)
    g = Generator(cfg, build_levels(h, cfg, 16), K).eval()
    assert all(layer.noise is None for layer in g.styled_layers())
    assert g.noise_shapes() == [] and not any("noise" in k for k in g.state_dict())
    z = torch.randn(2, 16)
    out = g(z)  # every noise mode gives the same motion: nothing random besides the latent
    for mode in ("random", "const", "none"):
        assert torch.equal(g(z, noise_mode=mode), out)
    assert torch.equal(g(z, noise=[]), out)
    with pytest.raises(ValueError, match="noise_mode"):
        g(z, noise_mode="bogus")


def test_sampling_draws_no_noise_when_off():
    from modi.models.modi.sampling import latents_and_noise

    _, h = hierarchy_of(humanoid, None)
    on, off = tiny(h.n_levels, noise_injection=True), tiny(h.n_levels)
    g_on = Generator(on, build_levels(h, on, 16), K).eval()
    g_off = Generator(off, build_levels(h, off, 16), K).eval()
    z_on, n_on = latents_and_noise(g_on, [0, 5], 3)
    z_off, n_off = latents_and_noise(g_off, [0, 5], 3)
    assert n_off == [] and len(n_on) == len(g_on.styled_layers())
    assert torch.equal(z_on, z_off)  # the latent of a seed does not depend on the noise option


def test_legacy_config_without_new_fields_keeps_old_behaviour():
    d = make_config("small").to_dict()
    del d["model"]["noise_injection"]
    del d["train"]["contact_loss"]
    old = MoDiConfig.from_dict(d)
    assert old.model.noise_injection is True and old.train.contact_loss == "squared"
    new = make_config("small")
    assert new.model.noise_injection is False and new.train.contact_loss == "released"
    pre = make_config("small", ["pre-release"])
    assert pre.model.noise_injection is True and pre.train.contact_loss == "squared"
    with pytest.raises(ValueError, match="contact_loss"):
        make_config("small", **{"train.contact_loss": "cubed"})


def test_released_contact_loss_is_speed_not_squared():
    from modi.models.modi.losses import CONTACT_SHARPNESS, foot_contact_speed_loss

    pos = torch.zeros(2, 5, 2, 3)
    pos[:, :, 0, 0] = torch.arange(5.0) * 3.0  # foot 0 slides 3 units per frame along x; foot 1 still
    pos[:, :, 1, 2] = torch.tensor([0.0, 0.0, 4.0, 4.0, 4.0])  # foot 1 jumps 4 units once
    contact = torch.ones(2, 2, 5)  # label scale: on
    s = torch.sigmoid(torch.tensor(CONTACT_SHARPNESS * 0.5))
    expected = s * (4 * 3.0 + 4.0) / 8  # mean over feet x (T-1) frames of s(c) * per-frame speed
    assert foot_contact_speed_loss(pos, contact).item() == pytest.approx(expected.item(), rel=1e-6)
    contact[:, 0, 1:] = 0.0  # labelled in the air: the slide of foot 0 costs (almost) nothing
    assert foot_contact_speed_loss(pos, contact).item() < 0.51 * expected.item()
    # finite gradient where a foot does not move at all (speed 0), nonzero where it slides slowly
    p = torch.zeros(1, 4, 1, 3, requires_grad=True)
    with torch.no_grad():
        p[0, 2:, 0, 0] = 1e-4
    foot_contact_speed_loss(p, torch.ones(1, 1, 4)).backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().max() > 0.1
    with pytest.raises(ValueError):
        foot_contact_speed_loss(pos, contact[:, :1])


def test_codec_ankles_are_the_toe_parents():
    from modi.models.modi.codec import MotionCodec
    from modi.data.normalization import Normalizer
    from modi.data.representation import modi_representation

    sk = humanoid()
    rep = modi_representation(sk)
    codec = MotionCodec(rep, Normalizer(torch.zeros(rep.K, rep.n_entities), torch.ones(rep.K, rep.n_entities)), 30.0)
    assert [sk.names[j] for j in codec.feet] == ["LeftToe", "RightToe"]
    assert [sk.names[j] for j in codec.ankles] == ["LeftFoot", "RightFoot"]


@pytest.mark.parametrize("crop", [0, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_std_normalised_leaky_relu_is_the_autograd_form(dtype, crop):
    """Sampling's in-place form of the released generator's activation demodulation + bias + leaky ReLU: the
    values of the autograd form, on a contiguous tensor and on the cropped view the StyleGAN2-padded upsampler
    leaves (which it must copy, not write through)."""
    g = torch.Generator().manual_seed(crop)
    full = torch.randn(4, 6, 5, 11 + crop, generator=g, dtype=dtype) * 3 + 1
    x = full[..., crop:]
    bias = torch.randn(6, generator=g, dtype=dtype)
    want = fused_leaky_relu(x / std_entities_frames(x), bias)
    kept = full.clone()
    got = std_normalised_leaky_relu_(x if crop else x.clone(), bias)
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(got, want, rtol=tol, atol=tol)
    if crop:
        assert torch.equal(full, kept)  # the view was copied, its base left as it was


def test_styled_conv_samples_as_it_trains(monkeypatch):
    """The released StyledConv (activation demodulation) takes the in-place path under no_grad, with the output of
    the autograd path it takes when training."""
    import modi.models.modi.networks as networks

    class StyleScale(torch.nn.Module):  # a stand-in conv: what matters here is what follows it
        def forward(self, x, w):
            return x * w.mean(1).view(-1, 1, 1, 1)

    torch.manual_seed(0)
    layer = StyledConv(StyleScale(), 6, 5, 16, use_noise=False, demodulate_activations=True)
    with torch.no_grad():
        layer.act.bias.normal_()
    calls = []
    real = networks.std_normalised_leaky_relu_
    monkeypatch.setattr(networks, "std_normalised_leaky_relu_", lambda *a: calls.append(1) or real(*a))
    x, w = torch.randn(3, 6, 5, 16), torch.randn(3, 8)
    want = layer(x, w)
    assert want.grad_fn is not None and not calls
    with torch.no_grad():
        got = layer(x, w)
    assert calls == [1]
    torch.testing.assert_close(got, want.detach(), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("shape", [(3, 4, 5, 7), (2, 1, 1, 9), (1, 3, 24, 64)])
def test_std_entities_frames_is_torch_std_with_its_gradients(shape):
    """The released generator's activation demodulation divides by this: it must equal torch's unbiased std over
    (entities, frames), with first and second derivatives (path length and R1 differentiate through it)."""
    g = torch.Generator().manual_seed(sum(shape))
    x = (torch.randn(shape, generator=g, dtype=torch.float64) * 3 + 1).requires_grad_(True)
    torch.testing.assert_close(std_entities_frames(x), x.std((2, 3), keepdim=True), rtol=1e-12, atol=0)
    assert torch.autograd.gradcheck(std_entities_frames, (x,))
    assert torch.autograd.gradgradcheck(std_entities_frames, (x,))


@pytest.mark.filterwarnings(r"ignore:std\(\)..degrees of freedom:UserWarning")  # the reference at n = 1
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(3, 4, 5, 7), (2, 1, 1, 9), (2, 3, 24, 64), (1, 2, 1, 1)])
def test_inv_std_entities_frames_is_one_over_torch_std(shape, dtype):
    """Sampling's 1 / std from layer-norm moments: torch's unbiased std over (entities, frames), inverted, also where
    the mean is a hundred times the spread (a one-pass sum of squares would lose digits there) and, for a single
    value, nan as torch.std gives it."""
    g = torch.Generator().manual_seed(sum(shape))
    x = torch.randn(shape, generator=g, dtype=dtype) + 100.0 * torch.randn(shape[:2] + (1, 1), generator=g,
                                                                           dtype=dtype)
    want = x.double().std((2, 3), keepdim=True).reciprocal()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(inv_std_entities_frames(x).double(), want, rtol=tol, atol=0, equal_nan=True)


@pytest.mark.parametrize("variant", ["default", "stylegan2-padding", "pool", "noise"])
def test_fused_activation_equals_the_unfused_layers(variant):
    """Where the bias + leaky ReLU runs in the skeletal op's epilogue (StyledConv.fuse_act, ConvAct.slot), the
    generator and discriminator give what the separate activation modules give, values and every gradient
    (float64); where something sits between conv and activation (pooling, noise), nothing is fused."""
    from modi.models.modi.networks import ConvAct

    _, h = hierarchy_of(humanoid, None)
    kw = {"stylegan2-padding": dict(time_padding="stylegan2"), "pool": dict(scaler="pool"),
          "noise": dict(noise_injection=True)}.get(variant, {})
    cfg = tiny(h.n_levels, **kw)
    levels = build_levels(h, cfg, 16)
    torch.manual_seed(0)
    g, d = Generator(cfg, levels, K).double(), Discriminator(cfg, levels, K).double()
    with torch.no_grad():
        for m in list(g.modules()) + list(d.modules()):
            if isinstance(m, (StyledConv, ConvAct)):
                m.act.bias.normal_()  # zero-initialised: make the bias matter
    styled = [m for m in g.modules() if isinstance(m, StyledConv)]
    convacts = [m for m in d.modules() if isinstance(m, ConvAct)]
    fused = sum(m.fuse_act for m in styled) + sum(m.slot is not None for m in convacts)
    if variant == "noise":
        assert not any(m.fuse_act for m in styled)
    elif variant == "pool":  # the unpooling up-convs and the pooling down-convs are not fused, the rest are
        assert not all(m.fuse_act for m in styled) and any(m.fuse_act for m in styled)
        assert any(m.slot is None for m in convacts)
    else:
        assert all(m.fuse_act for m in styled) and all(m.slot is not None for m in convacts)
    assert fused > 0

    def run():
        torch.manual_seed(1)
        z = torch.randn(2, cfg.latent_dim, dtype=torch.float64)
        x = g(z, noise_mode="const")
        out = d(x)
        params = list(g.parameters()) + list(d.parameters())
        grads = torch.autograd.grad(out.square().sum(), params, allow_unused=True)
        return [x, out] + [gr for gr in grads if gr is not None]

    got = run()
    for m in styled:
        m.fuse_act = False
    for m in convacts:
        m.slot = None
    want = run()
    assert len(got) == len(want)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
