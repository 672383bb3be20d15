"""modi: MoDi and GANimator motion synthesis on skeleton-aware operators (see README and docs/api.md).

The public Python API::

    import modi

    clip = modi.load("walk.bvh")                     # a modi.Motion (fps and length unit known)
    clip.positions(unit="m")                         # (T, J, 3) in metres
    gen = modi.load("runs/modi/checkpoint.pt")       # a ModiGenerator
    motions = gen.generate(8, seed=0)                  # list[modi.Motion], as `modi generate --n 8 --seed 0`
    run = modi.train_ganimator("walk.bvh", "runs/g", preset="tiny")
    run.generate(2, frames=120, seed=1)[0].to_gltf("walk.glb")
    modi.show(motions, out="view.html")

Importing ``modi`` is cheap (no torch): the names below are resolved on first use. Stable names are those in
``__all__``; everything else (``modi.models``, ``modi.core``, ...) is internal and may change.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from modi._lazy import lazy_exports
from modi._version import __version__

# public name -> the module that defines it (imported on first use: `import modi` must not import torch, so that
# the CLI can take Ctrl-C at start-up and `modi --help` stays fast)
_PUBLIC = {
    "Motion": "modi.data.motion",
    "Skeleton": "modi.core.skeleton",
    "load": "modi.api.files",
    "FileInfo": "modi.api.info",
    "inspect": "modi.api.info",
    "ModiGenerator": "modi.api.generator",
    "Inversion": "modi.api.generator",
    "Boundary": "modi.api.generator",
    "Encoder": "modi.api.encoder",
    "GanimatorRun": "modi.api.ganimator",
    "train_modi": "modi.api.training",
    "train_ganimator": "modi.api.training",
    "Progress": "modi.api.training",
    "TrainingInterrupted": "modi.api.training",
    "evaluate": "modi.api.evaluation",
    "evaluate_real": "modi.api.evaluation",
    "evaluate_single": "modi.api.evaluation",
    "Topology": "modi.api.layer_topology",
    "show": "modi.api.viewing",
    "UserError": "modi.errors",
    "BvhError": "modi.errors",
    "CheckpointError": "modi.errors",
}

__all__ = ["__version__", *_PUBLIC]

if TYPE_CHECKING:  # for type checkers and IDEs; at run time __getattr__ resolves these
    from modi.api.encoder import Encoder
    from modi.api.evaluation import evaluate, evaluate_real, evaluate_single
    from modi.api.files import load
    from modi.api.info import FileInfo, inspect
    from modi.api.ganimator import GanimatorRun
    from modi.api.generator import Boundary, Inversion, ModiGenerator
    from modi.api.layer_topology import Topology
    from modi.api.training import Progress, TrainingInterrupted, train_ganimator, train_modi
    from modi.api.viewing import show
    from modi.core.skeleton import Skeleton
    from modi.data.motion import Motion
    from modi.errors import BvhError, CheckpointError, UserError

__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
