"""Checkpoints written before ``EqualLinear`` became one class (``modi_ext.layers``) still load, key for key, and
give the same outputs.

``data/state_dicts_before_issue50.pt`` was written by the code as it stood before the change: tiny generators and
discriminators of the default model and of the two ablations that hold an ``EqualLinear`` in another place (the
pseudo-image convs' modulation, the pooling scaler), both encoder heads, and their outputs for fixed inputs. Loading
is strict, so a renamed, added or dropped parameter fails here."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import build_hierarchy
from modi.models.modi.config import ModelConfig
from modi.models.modi.encoder.model import EncoderConfig, MotionEncoder
from modi.models.modi.levels import build_levels
from modi.models.modi.networks import Discriminator, Generator

FIXTURE = Path(__file__).parent / "data" / "state_dicts_before_issue50.pt"
VARIANTS = ("conv", "pseudo", "pool")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def before():
    return torch.load(FIXTURE, weights_only=True)


def _levels(cfg: ModelConfig):
    sk = Skeleton([f"c{j}" for j in range(5)], [-1, 0, 1, 2, 3], np.ones((5, 3)))
    return build_levels(build_hierarchy(sk, [4]), cfg, 8)


@pytest.mark.parametrize("variant", VARIANTS)
def test_generator_and_discriminator_load_and_agree(before, variant):
    rec = before[variant]
    cfg = ModelConfig(**{**rec["cfg"], "channels": tuple(rec["cfg"]["channels"])})
    levels = _levels(cfg)
    G, D = Generator(cfg, levels, 3), Discriminator(cfg, levels, 3)
    assert sorted(G.state_dict()) == sorted(rec["G"]) and sorted(D.state_dict()) == sorted(rec["D"])
    G.load_state_dict(rec["G"], strict=True)
    D.load_state_dict(rec["D"], strict=True)
    with torch.no_grad():
        motion = G(rec["z"], noise_mode="const")
        torch.testing.assert_close(motion, rec["motion"])
        torch.testing.assert_close(D(motion), rec["d"])


@pytest.mark.parametrize("head", ["released", "ours"])
def test_encoder_loads_and_agrees(before, head):
    rec = before["conv"]
    cfg = ModelConfig(**{**rec["cfg"], "channels": tuple(rec["cfg"]["channels"])})
    enc = rec[f"E_{head}"]
    E = MotionEncoder(cfg, _levels(cfg), EncoderConfig.from_dict(enc["ecfg"]))
    assert sorted(E.state_dict()) == sorted(enc["state"])
    E.load_state_dict(enc["state"], strict=True)
    with torch.no_grad():
        torch.testing.assert_close(E(rec["motion"]), enc["w"])


def test_the_equal_linear_keys_are_weight_and_bias(before):
    """The mapping network's and the discriminator head's linear layers, by name, as checkpoints hold them."""
    g, d = before["conv"]["G"], before["conv"]["D"]
    assert {"mapping.net.1.weight", "mapping.net.1.bias", "conv1.conv.affine.weight", "conv1.conv.affine.bias"} <= set(g)
    assert {"final_linear.0.weight", "final_linear.0.bias", "final_linear.1.weight", "final_linear.1.bias"} <= set(d)
    assert {"conv1.conv.modulation.weight", "conv1.conv.modulation.bias"} <= set(before["pseudo"]["G"])
