"""Evaluation: the metrics MoDi and GANimator report, and the feature extractor they need.

* ``distribution`` -- FID, KID (+ standard error), precision/recall, diversity over feature vectors (MoDi).
* ``features`` -- the ST-GCN action recogniser whose penultimate features those metrics use.
* ``single`` -- coverage, patched-nearest-neighbour global diversity, local diversity (GANimator).
* ``scorecard`` -- SIFID, inter- and intra-diversity and their harmonic mean over a feature network (SinMDM).
* ``plausibility`` -- foot skating, floating/penetration, jitter in the skeleton's units.
* ``report`` -- JSON and Markdown reports.

The array-level metrics are re-exported here; ``features`` (the network) is imported on demand.
"""
from __future__ import annotations

from modi.evaluation.distribution import (
    diversity,
    distribution_metrics,
    frechet_distance,
    kernel_distance,
    precision_recall,
)
from modi.evaluation.single import (
    coverage,
    local_diversity,
    patched_nearest_neighbour,
    rotation_features,
    single_sequence_metrics,
)

__all__ = [
    "diversity",
    "distribution_metrics",
    "frechet_distance",
    "kernel_distance",
    "precision_recall",
    "coverage",
    "local_diversity",
    "patched_nearest_neighbour",
    "rotation_features",
    "single_sequence_metrics",
]
