"""modi's public Python API: the objects and functions ``import modi`` gives (``modi.load``, ``modi.Motion``, ...).

Everything here returns :class:`modi.Motion` where it returns motion; every mistake of the caller's is a
:class:`modi.errors.UserError` whose message is the line the CLI prints for the same mistake. The CLI commands are
thin layers over these calls (``modi/cli/commands``: parse, one call here, print; ``tests/modi/cli/test_thin.py``
holds them to it).

The names below are resolved on first use, so that importing one light submodule (``modi.api.options``, which the
CLI's parsers read) does not import every model.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from modi._lazy import lazy_exports

# public name -> the submodule that defines it
_PUBLIC = {
    "Encoder": ".encoder", "evaluate": ".evaluation", "evaluate_real": ".evaluation",
    "evaluate_single": ".evaluation", "load": ".files", "GanimatorRun": ".ganimator", "Boundary": ".generator",
    "Inversion": ".generator", "ModiGenerator": ".generator", "FileInfo": ".info", "inspect": ".info",
    "Topology": ".layer_topology", "Progress": ".training", "TrainingInterrupted": ".training",
    "train_ganimator": ".training", "train_modi": ".training", "show": ".viewing",
}

__all__ = ["load", "inspect", "FileInfo", "ModiGenerator", "Inversion", "Boundary", "Encoder", "GanimatorRun",
           "train_modi", "train_ganimator", "Progress", "TrainingInterrupted", "evaluate", "evaluate_real",
           "evaluate_single", "Topology", "show"]

if TYPE_CHECKING:  # for type checkers and IDEs; at run time __getattr__ resolves these
    from modi.api.encoder import Encoder
    from modi.api.evaluation import evaluate, evaluate_real, evaluate_single
    from modi.api.files import load
    from modi.api.ganimator import GanimatorRun
    from modi.api.generator import Boundary, Inversion, ModiGenerator
    from modi.api.info import FileInfo, inspect
    from modi.api.layer_topology import Topology
    from modi.api.training import Progress, TrainingInterrupted, train_ganimator, train_modi
    from modi.api.viewing import show

__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
