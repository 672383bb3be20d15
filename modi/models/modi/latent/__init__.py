"""MoDi's latent space applications (papers 000 §4 and 001 §4.1) on a trained generator.

* ``space``      -- seeds, the mean latent, truncation and interpolation in W and W+, shared I/O helpers
* ``clustering`` -- K-means on W, t-SNE map, cluster members side by side
* ``editing``    -- attribute scores (gral, verticality, speed), SVM boundaries, ``w + α n`` edits and reports
* ``crowd``      -- variations around one latent, rendered as one scene
* ``inversion``  -- optimisation into W+ (representation + FK-position loss)

Submodules import lazily so ``import modi.models.modi.latent`` stays cheap.
"""
from __future__ import annotations

import importlib
from typing import Any

_SUBMODULES = ("space", "clustering", "editing", "crowd", "inversion")


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f"modi.models.modi.latent.{name}")
    for sub in _SUBMODULES:
        mod = importlib.import_module(f"modi.models.modi.latent.{sub}")
        if name in getattr(mod, "__all__", ()):
            return getattr(mod, name)
    raise AttributeError(f"module 'modi.models.modi.latent' has no attribute {name!r}")
