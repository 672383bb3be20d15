"""SinMDM's scorecard for single-motion methods: SIFID, inter- and intra-diversity, and their harmonic mean.

Raab et al., "Single Motion Diffusion" (ICLR 2024) score a model trained on one motion with metrics taken from
single-image generation (SinGAN, Shaham et al. 2019), measured in the feature space of a pretrained motion encoder
(docs/scorecard.md has the definitions, the citations and what was trained here):

* **SIFID** -- SinGAN's single-image FID on motion: the Frechet distance between Gaussians fitted to the encoder's
  *temporal* feature vectors (one per output time step, as SinGAN takes one per spatial position) of the real
  motion and of one generated motion; averaged over the generated motions. Lower is better.
* **inter-diversity** -- the mean feature distance between *different* generated motions (each pooled over time to
  one vector). Higher is better.
* **intra-diversity** -- the mean feature distance between sub-windows of *one* motion; the score is its
  difference from the real motion's own intra-diversity, ``|intra(generated) - intra(real)|``: a generator should
  vary within a motion as much as the input does, not more (noise) and not less (a frozen pose). Lower is better.
* **harmonic mean** -- of the three after normalising each to "higher is better" in [0, 1] with the authors'
  normalisers (their repository's issue #26: the 90th percentile of scores over various architectures):
  ``s = (11.889 - SIFID) / 11.889``, ``v = inter / 1.67``, ``d = (1.151 - diff) / 1.151``,
  ``HM = 3 / (1/s + 1/v + 1/d)``. A term at or past its normaliser (``s <= 0`` or ``d <= 0``) makes HM 0, the limit
  of the formula as that term goes to 0 (the plain formula would turn negative and rank such a model above others).

The normalisers are in the units of the paper's encoder (Guo et al.'s HumanML3D evaluator); another encoder has
another scale, so the harmonic mean ranks methods scored with the *same* encoder, never against the paper's table.

Every function is deterministic: all pairs and every window are used where the authors' code draws random ones.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from modi.evaluation.distribution import as_features, frechet_distance

__all__ = [
    "HM_NORMALISERS",
    "sifid",
    "mean_pairwise_distance",
    "inter_diversity",
    "intra_diversity",
    "harmonic_mean",
    "motion_features",
    "scorecard_metrics",
]

#: (SIFID, inter-diversity, intra-diversity difference): the SinMDM authors' normalisers (SinMDM issue #26).
HM_NORMALISERS: tuple[float, float, float] = (11.889, 1.67, 1.151)


def sifid(real: Any, generated: Any) -> float:
    """Frechet distance between Gaussian fits of two sets of temporal feature vectors ``(n, D)`` (rows are samples):
    one real motion's and one generated motion's. The same estimator as FID (``frechet_distance``), applied inside
    one motion as SinGAN's SIFID applies it inside one image."""
    return frechet_distance(as_features(real, "real temporal features"),
                            as_features(generated, "generated temporal features"))


def mean_pairwise_distance(x: Any, name: str = "embeddings") -> float:
    """Mean Euclidean distance over all unordered pairs of rows of ``x (n, D)``, ``n >= 2``."""
    a = as_features(x, name)
    d2 = (a * a).sum(1)[:, None] + (a * a).sum(1)[None, :] - 2.0 * a @ a.T
    iu = np.triu_indices(a.shape[0], k=1)
    return float(np.sqrt(np.clip(d2[iu], 0.0, None)).mean())


def inter_diversity(embeddings: Any) -> float:
    """Diversity *between* generated motions: mean distance over all pairs of their embeddings ``(n, D)``."""
    return mean_pairwise_distance(embeddings, "motion embeddings (one per generated motion, at least 2)")


def intra_diversity(window_embeddings: Any) -> float:
    """Diversity *within* one motion: mean distance over all pairs of its sub-windows' embeddings ``(m, D)``."""
    return mean_pairwise_distance(window_embeddings, "sub-window embeddings (at least 2 windows)")


def harmonic_mean(sifid_value: float, inter: float, intra_diff: float,
                  normalisers: Sequence[float] = HM_NORMALISERS) -> float:
    """SinMDM's harmonic mean of the normalised SIFID, inter-diversity and intra-diversity difference (see the
    module docstring); 0 when a lower-is-better score reaches its normaliser or inter-diversity is 0."""
    norms = [float(n) for n in normalisers]
    if len(norms) != 3 or not all(np.isfinite(n) and n > 0 for n in norms):
        raise ValueError(f"normalisers must be three positive numbers (SIFID, inter, intra diff), got {normalisers}")
    ns, nv, nd = norms
    values = (float(sifid_value), float(inter), float(intra_diff))
    if not all(np.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"scores must be finite and non-negative, got {values}")
    terms = ((ns - values[0]) / ns, values[1] / nv, (nd - values[2]) / nd)
    if min(terms) <= 0:
        return 0.0
    return 3.0 / sum(1.0 / t for t in terms)


def motion_features(extractor: Any, clip: np.ndarray, sifid_stride: int) -> dict[str, np.ndarray]:
    """What the scorecard needs of one clip (``(T, J, 3)`` positions in the extractor's joints and fps):

    * ``temporal`` ``(n, D)``: the temporal feature vectors of windows every ``sifid_stride`` frames (plus one at
      the clip's end), every output time step of every window a sample;
    * ``windows`` ``(m, D)``: the pooled features of the clip's disjoint ``window``-frame sub-windows;
    * ``embedding`` ``(D,)``: their mean -- the encoder's temporal average pooling carried over the whole clip.
    """
    w = extractor.config.window
    if clip.shape[0] < 2 * w:
        raise ValueError(f"a clip of {clip.shape[0]} frames at {extractor.config.fps:g} fps is shorter than two "
                         f"{w}-frame windows of the feature network (intra-diversity compares sub-windows)")
    temporal = extractor.temporal_features(extractor.windows([clip], stride=sifid_stride, tail=True))
    windows = extractor.features(extractor.windows([clip], stride=w, tail=False))
    return {"temporal": temporal.reshape(-1, temporal.shape[-1]), "windows": windows,
            "embedding": windows.mean(axis=0)}


def scorecard_metrics(extractor: Any, source: np.ndarray, generated: Sequence[np.ndarray], *, sifid_stride: int = 8,
                      normalisers: Sequence[float] = HM_NORMALISERS) -> dict[str, Any]:
    """SIFID, inter-diversity, intra-diversity (and its difference from the source's) and the harmonic mean of
    ``generated`` clips against one ``source`` clip, all ``(T, J, 3)`` positions already in the extractor's joints
    and fps (``FeatureExtractor.clip_positions``). With one generated clip inter-diversity and the harmonic mean are
    None. Raises ``ValueError`` on clips shorter than two feature windows or a bad stride."""
    if not generated:
        raise ValueError("no generated clips to score")
    if sifid_stride < 1:
        raise ValueError(f"sifid_stride must be >= 1, got {sifid_stride}")
    src = motion_features(extractor, source, sifid_stride)
    gens = []
    for i, g in enumerate(generated):
        try:
            gens.append(motion_features(extractor, g, sifid_stride))
        except ValueError as exc:
            raise ValueError(f"generated[{i}]: {exc}") from None
    per_sifid = [sifid(src["temporal"], g["temporal"]) for g in gens]
    per_intra = [intra_diversity(g["windows"]) for g in gens]
    real_intra = intra_diversity(src["windows"])
    inter = inter_diversity(np.stack([g["embedding"] for g in gens])) if len(gens) > 1 else None
    diff = abs(float(np.mean(per_intra)) - real_intra)
    s = float(np.mean(per_sifid))
    return {
        "sifid": s,
        "inter_diversity": inter,
        "intra_diversity": float(np.mean(per_intra)),
        "intra_diversity_source": real_intra,
        "intra_diversity_diff": diff,
        "harmonic_mean": None if inter is None else harmonic_mean(s, inter, diff, normalisers),
        "normalisers": {"sifid": float(normalisers[0]), "inter_diversity": float(normalisers[1]),
                        "intra_diversity_diff": float(normalisers[2])},
        "settings": {"window": extractor.config.window, "fps": extractor.config.fps, "sifid_stride": sifid_stride,
                     "temporal_vectors_source": int(src["temporal"].shape[0])},
        "per_sequence": [{"sifid": a, "intra_diversity": b} for a, b in zip(per_sifid, per_intra)],
    }
