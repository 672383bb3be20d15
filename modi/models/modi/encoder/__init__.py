"""The MoDi encoder into W+ (paper 001 §3.4, §4.2) and the ill-posed tasks it solves.

* ``model``        -- the reverse-hierarchy encoder predicting W+ (offset from the mean latent)
* ``training``     -- losses (rec, contact BCE, root, FK positions), data split, trainer, checkpoints
* ``metrics``      -- the paper's Table 5 errors and trivial baselines
* ``applications`` -- inversion, prefix completion, fusion, denoising, spatial editing (BVH + GIF side by side)
"""
from __future__ import annotations

import importlib
from typing import Any

_SUBMODULES = ("model", "training", "metrics", "applications")


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f"modi.models.modi.encoder.{name}")
    for sub in _SUBMODULES:
        mod = importlib.import_module(f"modi.models.modi.encoder.{sub}")
        if name in getattr(mod, "__all__", ()):
            return getattr(mod, name)
    raise AttributeError(f"module 'modi.models.modi.encoder' has no attribute {name!r}")
