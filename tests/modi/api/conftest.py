"""Tiny models for the public-API tests: a MoDi run trained for 2 steps on procedural clips (through
``modi.train_modi``) and a GANimator run of 2 levels trained for a few iterations on one short procedural clip
(through ``modi.train_ganimator``)."""
from __future__ import annotations

from pathlib import Path

import pytest

TINY_MODI = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
             "data.stride": 8, "train.batch": 2, "train.sample_every": 0, "train.ckpt_every": 0,
             "train.log_every": 1, "train.d_reg_every": 2, "train.g_reg_every": 2, "train.snapshot_every": 0}
TINY_GANIMATOR = dict(iterations=2, d_steps=1, base_channels=16, max_levels=2, coarse_ratio=0.5, seed=0,
                      checkpoint_every=1e9)


@pytest.fixture(scope="session")
def tiny_modi() -> dict:
    """The tiny MoDi config, for tests that train one more run (a fixture: two conftest modules cannot both be
    imported by the name ``conftest``)."""
    return dict(TINY_MODI)


@pytest.fixture(scope="session")
def tiny_ganimator() -> dict:
    return dict(TINY_GANIMATOR)


@pytest.fixture(scope="session")
def proc_dir(tmp_path_factory) -> Path:
    from modi.models.modi.training import write_procedural_data

    return write_procedural_data(tmp_path_factory.mktemp("proc") / "data", n_clips=6, frames=40, seed=1)


@pytest.fixture(scope="session")
def modi_run(proc_dir, tmp_path_factory) -> Path:
    import modi

    run = tmp_path_factory.mktemp("modi") / "run"
    modi.train_modi(proc_dir, run, config=TINY_MODI, iters=2, cache=False)
    return run


@pytest.fixture(scope="session")
def clip(proc_dir) -> Path:
    return sorted(proc_dir.glob("*.bvh"))[0]


@pytest.fixture(scope="session")
def gan_run(clip, tmp_path_factory) -> Path:
    import modi

    run = tmp_path_factory.mktemp("gan") / "run"
    modi.train_ganimator(clip, run, preset="tiny", **TINY_GANIMATOR)
    return run
