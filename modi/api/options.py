"""The facts the CLI's parsers need before any work: choices, defaults and help text that the domain code owns.

Read from their sources here (never restated) so that a command module imports them from ``modi.api`` and nothing
deeper; everything here is cheap to import (no model is built, no file read).
"""
from __future__ import annotations

from modi.core.body import UNITS_MM
from modi.core.contacts import PREVIEW_RULE
from modi.data.dataset import DatasetConfig
from modi.data.procedural import KINDS as PROCEDURAL_KINDS
from modi.models.ganimator.config import PRESETS as GANIMATOR_PRESETS
from modi.models.ganimator.config import preset as ganimator_preset
from modi.models.modi.config import ABLATIONS as MODI_ABLATIONS
from modi.models.modi.config import PRESETS as MODI_PRESETS
from modi.models.modi.graphs import GRAPH_MODES
from modi.models.precision import PRECISIONS

LENGTH_UNITS = tuple(UNITS_MM)  # the named length units of the mm metrics (besides "auto")
GANIMATOR_PRESET_WHAT = {"paper": "the published schedule", "fast": "a CPU schedule", "tiny": "a smoke test"}


def ganimator_preset_help() -> str:
    """The GANimator presets and their schedules, read from ``modi.models.ganimator.config``."""
    parts = []
    for name in GANIMATOR_PRESETS:
        cfg = ganimator_preset(name)
        first, rest = cfg.block_budgets(2)
        coarse = f", {first} on the coarsest" if first != rest else ""
        parts.append(f"{name}: {GANIMATOR_PRESET_WHAT.get(name, 'preset')} ({rest} iterations per block{coarse}; "
                     f"{cfg.d_steps} discriminator steps per generator step)")
    return "; ".join(parts)


__all__ = ["PREVIEW_RULE", "DatasetConfig", "PROCEDURAL_KINDS", "GANIMATOR_PRESETS", "MODI_PRESETS", "MODI_ABLATIONS",
           "LENGTH_UNITS", "PRECISIONS", "GRAPH_MODES", "ganimator_preset_help"]
