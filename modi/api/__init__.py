"""modi's public Python API: the objects and functions ``import modi`` gives (``modi.load``, ``modi.Motion``, ...).

Everything here returns :class:`modi.Motion` where it returns motion; every mistake of the caller's is a
:class:`modi.errors.UserError` whose message is the line the CLI prints for the same mistake. The CLI commands are
thin layers over these calls (``modi/cli/commands``: parse, one call here, print).
"""
from __future__ import annotations

from modi.api.encoder import Encoder
from modi.api.evaluation import evaluate, evaluate_real, evaluate_single
from modi.api.files import FileInfo, load
from modi.api.ganimator import GanimatorRun
from modi.api.generator import Boundary, Inversion, ModiGenerator
from modi.api.topology import Topology
from modi.api.training import Progress, TrainingInterrupted, train_ganimator, train_modi
from modi.api.viewing import show

__all__ = ["load", "FileInfo", "ModiGenerator", "Inversion", "Boundary", "Encoder", "GanimatorRun", "train_modi",
           "train_ganimator", "Progress", "TrainingInterrupted", "evaluate", "evaluate_real", "evaluate_single", "Topology", "show"]
