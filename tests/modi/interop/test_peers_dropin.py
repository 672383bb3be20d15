"""The drop-in (benchmarks/peers/modi_dropin.py) computes what the authors' own layers compute.

Oracle: their ``ModulatedConv`` / ``EqualConv`` / ``Generator`` / ``Discriminator`` and their ``train.main``
(../shared/peers/MoDi, run on the CPU by benchmarks/peers/released_modi.py), on the same weights and inputs.
"""
from __future__ import annotations

import contextlib
import copy
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[3]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from peers_support import rel  # noqa: E402
from benchmarks.peers import released_modi as R  # noqa: E402
from benchmarks.peers.modi_dropin import MaskViolation, dropin  # noqa: E402

pytestmark = [pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning"),  # the released sources' old idioms
              pytest.mark.filterwarnings("ignore::SyntaxWarning"),
              pytest.mark.filterwarnings("ignore::RuntimeWarning"),
              pytest.mark.filterwarnings("ignore::UserWarning")]
TOL = 1e-6




@pytest.fixture(scope="module")
def peer():
    try:
        R.require_peer()
        R.require_data()
    except R.PeerUnavailable as exc:
        pytest.skip(str(exc))
    with R.peer_runtime() as ns:
        yield ns


@pytest.fixture(scope="module")
def data(peer, tmp_path_factory):
    return R.prepare_dataset(tmp_path_factory.mktemp("dropin") / "edge_rot_bandai.npy",
                             sorted(R.require_data().glob("*.bvh"))[:2])


def _models(peer, args, patched: bool):
    """(G, D) of their classes (or the drop-in's), float64; the drop-in's load their weights."""
    statics = R.motion_statics(peer, args)
    R.seed_all(0)
    g, d, _ = R.build_models(peer, args, statics)
    g, d = g.double(), d.double()
    if not patched:
        return g, d
    with dropin(peer):
        R.seed_all(1)  # other random weights: only the loaded ones can make them agree
        g2, d2, _ = R.build_models(peer, args, statics)
    g2, d2 = g2.double(), d2.double()
    g2.load_state_dict(g.state_dict())
    d2.load_state_dict(d.state_dict())
    return g2, d2


def _layers(g, d):
    """Every layer type the drop-in replaces, by name: generator (modulated) and discriminator (conv, scaler)."""
    return {"modulated in place (3 taps)": g.conv1.conv, "modulated upsampling": g.convs[0].conv,
            "modulated to-motion (1x1)": g.to_xyz1.conv, "conv 1x1 (from motion)": d.convs[0],
            "conv in place (3 taps)": d.convs[1].convs[0], "scaler: blur + 3-tap stride 2": d.convs[1].convs[-1],
            "scaler: blur + 1x1 stride 2 (skip)": d.convs[1].skip, "final conv (+ stddev channel)": d.final_conv}


def _weight_grad_dense(mod) -> torch.Tensor:
    """Their dense weight gradient, or the drop-in's compact one laid out as theirs (zeros off the mask)."""
    w = mod.weight
    if hasattr(mod, "pair_index"):
        saved = w.data
        w.data = w.grad
        try:
            return mod.dense_weight()
        finally:
            w.data = saved
    return w.grad * mod.mask


@pytest.mark.parametrize("feet", [False, True], ids=["released flags", "with --foot contacts"])
def test_every_replaced_layer_equals_theirs(peer, data, feet):
    args = R.make_args(data, feet=feet)
    theirs, ours = _layers(*_models(peer, args, False)), _layers(*_models(peer, args, True))
    torch.manual_seed(2)
    for name, a in theirs.items():
        b = ours[name]
        conv_a = a if hasattr(a, "mask") else next(m for m in a if hasattr(m, "mask"))
        conv_b = b if hasattr(b, "mask") else next(m for m in b if hasattr(m, "mask"))
        assert type(conv_b).__name__.startswith("DropIn") and not type(conv_a).__name__.startswith("DropIn"), name
        if "blur" in name:  # the scaler's anti-alias filter is the drop-in's too
            assert [type(m).__name__ for m in b][0] == "DropInBlur" and type(a[0]).__name__ == "Blur", name
            assert b[0].as_modi, name
        # the patched layer stores only the connected pairs; what it writes back is their weight x mask
        assert rel(conv_b.state_dict()["weight"], conv_a.weight * conv_a.mask) == 0.0, name
        assert conv_b.weight.numel() <= conv_a.weight.numel(), name  # equal where a level is fully connected
        n_in = conv_a.weight.shape[-4] if conv_a.weight.dim() == 6 else conv_a.weight.shape[1]
        e_in = conv_a.weight.shape[-2]
        if "upsampling" in name:
            e_in = conv_a.weight.shape[-3]  # coarse entities in
        x = torch.randn(3, n_in, e_in, 16, dtype=torch.float64)
        style = torch.randn(3, args.latent, dtype=torch.float64)
        outs, grads = [], []
        for m, conv in ((a, conv_a), (b, conv_b)):
            xi = x.clone().requires_grad_(True)
            si = style.clone().requires_grad_(True)
            y = m(xi, si) if hasattr(conv, "modulation") else m(xi)
            r = torch.sin(torch.arange(y.numel(), dtype=torch.float64)).view_as(y)
            m.zero_grad()
            (y * r).sum().backward()
            g = {"input": xi.grad, "weight": _weight_grad_dense(conv)}
            if hasattr(conv, "modulation"):
                g.update(style=si.grad, affine_w=conv.modulation.weight.grad, affine_b=conv.modulation.bias.grad)
            outs.append(y)
            grads.append(g)
        assert outs[0].shape == outs[1].shape, name
        assert rel(outs[1], outs[0]) <= TOL, name
        for k in grads[0]:
            assert rel(grads[1][k], grads[0][k]) <= TOL, f"{name}: gradient of {k}"


def test_their_skeleton_end_to_end_with_r1_and_path_length_graphs(peer, data):
    """Their Generator/Discriminator on Bandai's skeleton, every resolution, the D score, and second-order
    gradients (R1 through D, path length through G) with respect to every parameter."""
    args = R.make_args(data)
    (g, d), (g2, d2) = _models(peer, args, False), _models(peer, args, True)
    torch.manual_seed(3)
    z = [torch.randn(4, args.latent, dtype=torch.float64)]
    real = torch.randn(4, 4, g.convs[-1].conv.weight.shape[-2], 64, dtype=torch.float64)
    results = []
    for gen, disc in ((g, d), (g2, d2)):
        motions = gen(z, return_sub_motions=True)[0]
        x = real.clone().requires_grad_(True)
        score = disc(x)[0]
        (gx,) = torch.autograd.grad(score.sum(), x, create_graph=True)
        fake_score = disc(motions[-1])[0]
        wplus = gen.style(z[0]).unsqueeze(1).repeat(1, gen.n_latent, 1).detach().requires_grad_(True)
        m = gen([wplus], input_is_latent=True)[0]
        (gw,) = torch.autograd.grad((m * torch.cos(m.detach())).sum(), wplus, create_graph=True)
        gen.zero_grad()
        disc.zero_grad()
        (gx.pow(2).sum() + fake_score.sum() + gw.pow(2).sum().sqrt()).backward()
        grads = {}
        for side, net in (("g", gen), ("d", disc)):
            masked = {n for n, mod in net.named_modules() if isinstance(getattr(mod, "mask", None), torch.Tensor)}
            grads.update({f"{side}.{n}.weight": _weight_grad_dense(net.get_submodule(n)) for n in masked})
            grads.update({f"{side}.{n}": p.grad for n, p in net.named_parameters()
                          if p.grad is not None and n.rsplit(".", 1)[0] not in masked})
        results.append((motions, score, gx, grads))
    (m1, s1, gx1, gr1), (m2, s2, gx2, gr2) = results
    for level, (a, b) in enumerate(zip(m1, m2)):
        assert rel(b, a) <= TOL, f"generator output at level {level}"
    assert rel(s2, s1) <= TOL and rel(gx2, gx1) <= TOL
    assert gr1.keys() == gr2.keys() and len(gr1) > 20
    for k in gr1:
        assert rel(gr2[k], gr1[k]) <= TOL, f"gradient of {k}"


@contextlib.contextmanager
def _recorded_losses(tm):
    """Their per-iteration loss dict (what ``reduce_loss_dict`` receives), as floats."""
    seen: list[dict[str, float]] = []
    old = tm.reduce_loss_dict

    def record(d):
        seen.append({k: float(v) for k, v in d.items()})
        return old(d)

    tm.reduce_loss_dict = record
    try:
        yield seen
    finally:
        tm.reduce_loss_dict = old


@contextlib.contextmanager
def _float64_training():
    """Their train.py in float64: new tensors default to float64 and their ``real_img.float()`` keeps float64.
    (In float32 the first Adam step turns rounding-level gradient differences into ~lr-sized ones, so
    float32 losses after an update agree only to ~1e-3.)"""
    old_dtype, old_float = torch.get_default_dtype(), torch.Tensor.float
    torch.set_default_dtype(torch.float64)
    torch.Tensor.float = torch.Tensor.double  # type: ignore[method-assign]
    try:
        yield
    finally:
        torch.set_default_dtype(old_dtype)
        torch.Tensor.float = old_float  # type: ignore[method-assign]


def test_their_train_main_gives_the_same_losses_with_the_patch(peer, data, tmp_path):
    """Their own ``train.main`` (iteration 0 with R1 and path length, then a plain one), with and without the
    drop-in: the same loss terms, and the same G, D and EMA weights in the checkpoints they write -- so their
    optimiser, EMA and checkpoint code run unchanged on the compact weights. The patched run's checkpoint is
    one of theirs: it loads into their unpatched classes."""
    args = R.make_args(data, feet=True)
    tm = R.train_module(peer)
    runs = {}
    for patched in (False, True):
        with _recorded_losses(tm) as seen, _float64_training(), \
                (dropin(peer) if patched else contextlib.nullcontext()):
            ckpt = R.trained_checkpoint(args, tmp_path / f"p{int(patched)}", iters=2)
        runs[patched] = (seen, R.load_released(ckpt))
    (l0, ck0), (l1, ck1) = runs[False], runs[True]
    assert len(l0) == len(l1) == 2
    assert {"d", "r1", "g", "path", "path_length", "foot_contact"} <= set(l0[0])
    for i in (0, 1):
        for k, v in l0[i].items():
            assert abs(l1[i][k] - v) <= TOL * max(1e-3, abs(v)), f"iteration {i} {k}: {l1[i][k]} vs theirs {v}"
    for part in ("g", "d", "g_ema"):
        a, b = ck0[part], ck1[part]
        assert a.keys() == b.keys(), part
        for k, theirs in a.items():
            if k.endswith(".weight") and k[:-6] + "mask" in a:
                theirs = theirs * a[k[:-6] + "mask"]  # their entries off the mask are dead (never read)
            assert rel(b[k], theirs) <= TOL, f"{part}.{k} after two iterations"
    g, _, _, _ = R.models_from_checkpoint(peer, ck1)  # their unpatched classes read the patched run's file
    assert type(g.conv1.conv).__name__ == "ModulatedConv"


def test_weight_outside_the_mask_is_refused_naming_the_entries(peer, data):
    args = R.make_args(data)
    g, _ = _models(peer, args, False)
    with dropin(peer):
        g2, _, _ = R.build_models(peer, args, R.motion_statics(peer, args))
    sd = copy.deepcopy(g.float().state_dict())
    key = f"convs.{len(g.convs) - 1}.conv"  # the finest in-place conv: most entity pairs unconnected
    mask = sd[f"{key}.mask"]
    off = torch.nonzero(mask[0, 0, 0] == 0)[0]  # an entity pair it does not connect (first channel pair)
    idx = (0, 0, 0, int(off[0]), int(off[1]), int(off[2]))
    sd[f"{key}.mask"][idx] = 1.0
    sd[f"{key}.weight"][idx] = 0.5
    with pytest.raises(MaskViolation, match=rf"{key}\.weight: 1 non-zero outside its skeletal mask "
                                            rf"\(first at \(0, 0, {idx[3]}, {idx[4]}, {idx[5]}\)"):
        g2.load_state_dict(sd)
    sd2 = copy.deepcopy(g.state_dict())
    sd2["convs.0.conv.mask"] = torch.ones_like(sd2["convs.0.conv.mask"])  # another pooling
    with pytest.raises(MaskViolation, match=r"convs\.0\.conv\.weight: its mask connects other entity pairs"):
        g2.load_state_dict(sd2)
    # their dead entries (random values where the mask is 0, as every checkpoint of theirs has) are fine
    g2.load_state_dict(g.state_dict())


def test_speed_harness_cycles_follow_their_lazy_intervals_and_modis(peer, data):
    """speed_released times whole cycles and files iterations by kind: both must follow their train.py's
    defaults (R1 when i % d_reg_every == 0, path length when i % g_reg_every == 0) and modi's TrainConfig."""
    import math

    from benchmarks.peers import speed_released as S
    from modi.models.modi.config import TrainConfig

    args = R.make_args(data)
    assert S.CYCLE == math.lcm(args.d_reg_every, args.g_reg_every)
    assert (TrainConfig().d_reg_every, TrainConfig().g_reg_every) == (args.d_reg_every, args.g_reg_every)
    for i in range(2 * S.CYCLE):
        r1, path = i % args.d_reg_every == 0, i % args.g_reg_every == 0
        assert S.kind(i) == ("r1+path" if r1 and path else "path" if path else "r1" if r1 else "plain")
