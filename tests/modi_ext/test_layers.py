"""modi_ext.layers: shapes, equalised-lr scaling, dense view, ref/ext agreement, torch.compile, bad arguments."""
from __future__ import annotations

import math

import pytest
import torch

from modi_ext import HAS_EXT
from modi_ext.layers import (EqualLinear, ModulatedSkeletalConv, SkeletalConv, SkeletalDownsample,
                             SkeletalUpsample)

NEIGHBORS = [[0, 1, 2], [0, 1], [0, 2, 3], [2, 3, 4], [3, 4]]  # a 5-entity chain with a branch at 0
POOLING = [[0], [1, 2], [3, 4]]
needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")


def _modules():
    torch.manual_seed(0)
    return [
        ("conv", SkeletalConv(4, 6, NEIGHBORS, 3), (torch.randn(3, 4, 5, 8),)),
        ("conv_reflect_k5", SkeletalConv(4, 6, NEIGHBORS, 5, padding_mode="reflect"), (torch.randn(3, 4, 5, 8),)),
        ("down", SkeletalDownsample(4, 6, POOLING, 3), (torch.randn(3, 4, 5, 8),)),
        ("up", SkeletalUpsample(4, 6, POOLING, 3), (torch.randn(3, 4, 3, 8),)),
        ("mod_same", ModulatedSkeletalConv(4, 6, 7, NEIGHBORS), (torch.randn(3, 4, 5, 8), torch.randn(3, 7))),
        ("mod_down", ModulatedSkeletalConv(4, 6, 7, POOLING, mode="down"),
         (torch.randn(3, 4, 5, 8), torch.randn(3, 7))),
        ("mod_up", ModulatedSkeletalConv(4, 6, 7, POOLING, mode="up"), (torch.randn(3, 4, 3, 8), torch.randn(3, 7))),
        ("mod_same_nodemod", ModulatedSkeletalConv(4, 6, 7, NEIGHBORS, kernel_size=1, demodulate=False),
         (torch.randn(3, 4, 5, 8), torch.randn(3, 7))),
    ]


EXPECTED_SHAPES = {"conv": (3, 6, 5, 8), "conv_reflect_k5": (3, 6, 5, 8), "down": (3, 6, 3, 4), "up": (3, 6, 5, 16),
                   "mod_same": (3, 6, 5, 8), "mod_down": (3, 6, 3, 4), "mod_up": (3, 6, 5, 16),
                   "mod_same_nodemod": (3, 6, 5, 8)}


def test_output_shapes(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ref")
    for name, module, inputs in _modules():
        assert tuple(module(*inputs).shape) == EXPECTED_SHAPES[name], name


@needs_ext
def test_same_output_and_grads_on_both_paths(monkeypatch):
    for name, module, inputs in _modules():
        outs = {}
        for impl in ("ref", "ext"):
            monkeypatch.setenv("MODI_EXT_IMPL", impl)
            module.zero_grad()
            y = module(*inputs)
            y.pow(2).sum().backward()
            outs[impl] = (y.detach(), [p.grad.clone() for p in module.parameters()])
        torch.testing.assert_close(outs["ext"][0], outs["ref"][0], rtol=1e-5, atol=1e-5, msg=name)
        for ge, gr in zip(outs["ext"][1], outs["ref"][1]):
            torch.testing.assert_close(ge, gr, rtol=1e-4, atol=1e-4, msg=name)


def test_equalised_lr_uses_real_fan_in():
    conv = SkeletalConv(4, 6, NEIGHBORS, 3)
    dense = conv.dense_weight()  # (Cout, Cin, E, E, U)
    assert dense.shape == (6, 4, 5, 5, 3)
    # entity 1 has 2 neighbors -> fan-in 2*4*3; entity 2 has 3 -> 3*4*3.  Pair (1, 0) is pair index 3.
    torch.testing.assert_close(dense[:, :, 1, 0], conv.weight[:, 3].detach() / math.sqrt(2 * 4 * 3))
    torch.testing.assert_close(dense[:, :, 2, 3], conv.weight[:, 7].detach() / math.sqrt(3 * 4 * 3))
    assert dense[:, :, 1, 2].abs().max() == 0  # not a neighbor: masked
    up = SkeletalUpsample(4, 6, POOLING, 3)
    d_up = up.dense_weight()  # (Cout, Cin, E_fine, E_coarse, U)
    assert d_up.shape == (6, 4, 5, 3, 3)
    assert d_up[:, :, 0, 1].abs().max() == 0
    # every fine entity sits in exactly one coarse group -> fan-in Cin * U
    torch.testing.assert_close(d_up[:, :, 2, 1], up.weight[:, 2].detach().permute(1, 0, 2) / math.sqrt(4 * 3))


def test_unit_variance_at_init(monkeypatch):
    """Equalised lr: a unit-variance input gives roughly unit-variance output, whatever the entity's degree."""
    monkeypatch.setenv("MODI_EXT_IMPL", "ref")
    torch.manual_seed(1)
    conv = SkeletalConv(64, 64, NEIGHBORS, 3, bias=False)
    y = conv(torch.randn(8, 64, 5, 32))
    per_entity = y[..., 2:-2].std(dim=(0, 1, 3))
    assert torch.all((per_entity > 0.8) & (per_entity < 1.2)), per_entity


def test_state_dict_holds_only_parameters():
    m = ModulatedSkeletalConv(4, 6, 7, NEIGHBORS)
    assert set(m.state_dict()) == {"conv.weight", "affine.weight", "affine.bias"}
    torch.testing.assert_close(m.affine(torch.zeros(2, 7)), torch.ones(2, 4))  # bias initialised to 1
    m2 = ModulatedSkeletalConv(4, 6, 7, NEIGHBORS)
    m2.load_state_dict(m.state_dict())
    x, w = torch.randn(2, 4, 5, 6), torch.randn(2, 7)
    torch.testing.assert_close(m2(x, w), m(x, w))


def test_equal_linear_lr_mul():
    lin = EqualLinear(8, 3, bias_init=0.5, lr_mul=0.01)
    x = torch.randn(4, 8)
    want = x @ (lin.weight * 0.01 / math.sqrt(8)).t() + lin.bias * 0.01
    torch.testing.assert_close(lin(x), want)
    torch.testing.assert_close(lin.bias * 0.01, torch.full((3,), 0.5))


@pytest.mark.parametrize("impl", ["ext", "ref"])
def test_torch_compile_fullgraph_modulated_layer(monkeypatch, impl):
    if impl == "ext" and not HAS_EXT:
        pytest.skip("extension not built")
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    torch.manual_seed(2)
    torch._dynamo.reset()
    m = ModulatedSkeletalConv(4, 6, 7, NEIGHBORS, mode="same", demodulate=True)
    x, w = torch.randn(2, 4, 5, 8, requires_grad=True), torch.randn(2, 7)
    compiled = torch.compile(m, fullgraph=True, backend="aot_eager" if impl == "ref" else "inductor")
    y_c = compiled(x, w)
    y_e = m(x, w)
    torch.testing.assert_close(y_c, y_e, rtol=1e-5, atol=1e-5)
    (gc,) = torch.autograd.grad(y_c.square().sum(), x)
    (ge,) = torch.autograd.grad(y_e.square().sum(), x)
    torch.testing.assert_close(gc, ge, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("build,match", [
    (lambda: SkeletalConv(0, 4, NEIGHBORS), "in_ch"),
    (lambda: SkeletalConv(4, 4, NEIGHBORS, kernel_size=2), "kernel_size"),
    (lambda: SkeletalConv(4, 4, NEIGHBORS, padding_mode="circular"), "padding_mode"),
    (lambda: SkeletalConv(4, 4, [[0, 1], []]), r"neighbors\[1\] is empty"),
    (lambda: SkeletalConv(4, 4, [[0, 5], [1]]), "out of range"),
    (lambda: SkeletalDownsample(4, 4, [[0], [2]]), "does not cover"),
    (lambda: SkeletalUpsample(4, 4, "abc"), "pooling must be a list"),
    (lambda: ModulatedSkeletalConv(4, 4, 8, NEIGHBORS, mode="sideways"), "mode"),
])
def test_bad_constructor_arguments(build, match):
    with pytest.raises((ValueError, TypeError), match=match):
        build()


def test_bad_forward_arguments():
    m = ModulatedSkeletalConv(4, 6, 7, NEIGHBORS)
    with pytest.raises(ValueError, match="w must be"):
        m(torch.randn(2, 4, 5, 8), torch.randn(2, 6))
    with pytest.raises(ValueError, match="batch"):
        m(torch.randn(2, 4, 5, 8), torch.randn(3, 7))
    with pytest.raises(ValueError, match="entities"):
        SkeletalConv(4, 6, NEIGHBORS)(torch.randn(2, 4, 4, 8))


def test_real_hierarchy_generator_stack(shared_data, monkeypatch):
    """A MoDi-like coarse-to-fine stack on the real skeleton's hierarchy runs and gives finite gradients."""
    topology = pytest.importorskip("modi.core.skeleton_graph")
    bvh = pytest.importorskip("modi.io.bvh")
    files = sorted((shared_data / "bvh").rglob("*.bvh"))
    if not files:
        pytest.skip("no BVH files under shared data")
    h = topology.build_hierarchy(bvh.load(files[0]).skeleton())
    levels = h.levels[::-1]  # coarsest first
    pools = h.pooling[::-1]
    torch.manual_seed(3)
    x = torch.randn(2, 8, levels[0].n_entities, 4)
    w = torch.randn(2, 16)
    for i in range(1, len(levels)):
        x = ModulatedSkeletalConv(8, 8, 16, pools[i - 1], mode="up")(x, w)
        x = ModulatedSkeletalConv(8, 8, 16, levels[i].neighbors)(x, w)
    assert x.shape == (2, 8, levels[-1].n_entities, 4 * 2 ** (len(levels) - 1))
    x.square().mean().backward()
    assert torch.isfinite(x).all()
