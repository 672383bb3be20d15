"""GANimator's single-sequence metrics under the authors' released evaluation protocol (``evaluate.py``).

``modi ganimator eval RUN --protocol paper``. What the released script does, and this module reproduces:

* **Samples**: 200 random motions of ``2 x`` the *total* length of the training clips (all of them when mixing).
  The level pyramid is rebuilt for that length with the training rule (coarsest ``int(N * coarse_ratio)``, then
  ``x scale_factor`` up to ``N``), dropping its coarsest levels while it has more than the model; upsampling is
  linear interpolation to each level's size. Only level 0 gets noise: one channel of ``N(0, 1)`` shared by every
  channel and entity, scaled by the first clip's level-0 amplitude.
* **Features**: the generator's *raw* output, not decoded to rotations: each frame is the 6D of every (reduced)
  joint followed by the 6 channels of every contact entity (label and five free channels), the root-motion entity
  dropped (the released ``[..., :-6]``). The source side is the training clip's tensor (6D of its rotations, 0/1
  contact labels and zeros). The 6D layout is the model's (``sixd``: rows, as the authors, for new runs; columns
  for runs trained before the option, whose figures are then not the released features).
* **Metrics**: coverage (30-frame windows, threshold 2.0), global diversity (patched nearest neighbour, segments
  >= 30) and local diversity (15-frame windows) of each sample against each training clip, computed by
  :func:`modi.evaluation.single.single_sequence_metrics` (every window; the released code skips the last one).
* **Several clips**: the released loop appends every (sample, clip) score to the same three lists and prints their
  means after each clip, never resetting them, so its second figure averages both clips. Both are reported: the
  per-clip figures (``per_sequence``) and the released script's running averages (``released_running``).

The default protocol (``ours``, :func:`modi.models.ganimator.generate.evaluate_run`) decodes samples to rotations as any
BVH output would be scored; this one is for comparing with the paper's tables.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor

from modi.errors import UserError
from modi.evaluation.single import single_sequence_metrics
from modi.models.ganimator.data import pyramid_lengths
from modi.models.ganimator.networks import GanimatorModel, make_noise, synthesize
from modi.models.ganimator.training import load_model

METRICS = ("coverage", "global_diversity", "local_diversity")
N_SAMPLES = 200


def paper_pyramid(model: GanimatorModel, n_frames: int) -> list[int]:
    """Level lengths of an ``n_frames`` sample as the released ``evaluate.py`` builds them: the training rule applied
    to ``n_frames``, its coarsest levels dropped while it has more levels than the model."""
    cfg = model.cfg
    lengths = pyramid_lengths(int(n_frames), cfg.coarse_ratio, cfg.scale_factor)
    while len(lengths) > model.n_levels:
        lengths = lengths[1:]
    if len(lengths) < model.n_levels:
        raise UserError(f"a {n_frames}-frame sample has only {len(lengths)} pyramid levels; the model has "
                        f"{model.n_levels} (use more frames)")
    return lengths


def paper_features(x: Tensor, n_joints: int) -> Tensor:
    """``(B, 6, E, T)`` generator output (or ``(6, E, T)`` clip features) -> per-frame vectors ``(B, T, 6 (E - 1))``:
    every joint's 6D then every contact entity's 6 channels, raw; the root-motion entity (``n_joints``) dropped."""
    if x.ndim == 3:
        x = x.unsqueeze(0)
    B, K, E, T = x.shape
    keep = [e for e in range(E) if e != n_joints]
    return x[:, :, keep].permute(0, 3, 2, 1).reshape(B, T, K * len(keep)).to(torch.float64)


@torch.no_grad()
def sample_paper(model: GanimatorModel, n: int, n_frames: int, seed: int = 0, batch: int = 8) -> Iterator[Tensor]:
    """``n`` random samples ``(b, 6, E, n_frames)``, yielded in batches of ``batch``; noise at level 0 only, drawn
    one sample at a time from ``seed`` (so the samples do not depend on ``batch``)."""
    lengths = paper_pyramid(model, n_frames)
    rates = [L / lengths[-1] for L in lengths]  # consecutive ratios L_{l-1} / L_l: interpolation to each size
    gen = torch.Generator().manual_seed(int(seed))
    amp = model.amps[0][0]
    for start in range(0, n, batch):
        b = min(batch, n - start)
        z = torch.cat([make_noise(1, lengths[0], amp, gen, model.device) for _ in range(b)])
        noises: list[Tensor | None] = [z] + [None] * (model.n_levels - 1)
        yield synthesize(model.gens, rates, lengths, noises, model.n_entities, batch=b)[-1]


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def score_samples(features: Sequence[Tensor], sources: Sequence[Tensor], names: Sequence[str]) -> dict[str, Any]:
    """Per-sample scores of ``features`` (each ``(T, F)``) against every source ``(N, F)``:
    ``{name: {"coverage": [...], "global_diversity": [...], "local_diversity": [...]}}``."""
    out: dict[str, Any] = {}
    for name, src in zip(names, sources):
        try:
            r = single_sequence_metrics(list(features), src)
        except ValueError as exc:
            raise UserError(f"{name}: {exc}") from None
        out[name] = {k: [p[k] for p in r["per_sequence"]] for k in METRICS}
    return out


def summarise(scores: dict[str, dict[str, list[float]]], n_samples: int, n_frames: int,
              source_frames: dict[str, int]) -> tuple[dict, list[dict]]:
    """Per-sequence means, and the released script's running means (lists never reset across sequences); every
    figure carries the number of samples and their length."""
    per_sequence: dict[str, dict] = {}
    running: list[dict] = []
    pooled: dict[str, list[float]] = {k: [] for k in METRICS}
    seen: list[str] = []
    for name, s in scores.items():
        per_sequence[name] = {**{k: _mean(s[k]) for k in METRICS}, "samples": n_samples, "frames": n_frames,
                              "source_frames": source_frames[name]}
        for k in METRICS:
            pooled[k].extend(s[k])
        seen.append(name)
        running.append({"after": name, "sequences": list(seen), **{k: _mean(pooled[k]) for k in METRICS},
                        "samples": n_samples, "frames": n_frames, "pairs": len(pooled["coverage"])})
    return per_sequence, running


def evaluate_paper(run: str | Path | GanimatorModel, n: int = N_SAMPLES, n_frames: int | None = None,
                   seed: int = 0, batch: int = 8, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The released protocol on a run directory (or a loaded model); see the module docstring."""
    if n < 1:
        raise UserError("--n must be at least 1")
    model = run if isinstance(run, GanimatorModel) else load_model(run)
    model.eval()
    J = model.n_joints
    total = sum(s.n_frames for s in model.seqs)
    T = int(n_frames) if n_frames else 2 * total
    lengths = paper_pyramid(model, T)
    names = [s.name for s in model.seqs]
    if len(set(names)) != len(names):
        names = [f"{i}:{s}" for i, s in enumerate(names)]
    sources = [paper_features(s.features.to(torch.float32), J)[0] for s in model.seqs]
    scores: dict[str, dict[str, list[float]]] = {name: {k: [] for k in METRICS} for name in names}
    done = 0
    for out in sample_paper(model, n, T, seed=seed, batch=batch):
        feats = paper_features(out.detach().cpu(), J)
        for name, s in score_samples(list(feats), sources, names).items():
            for k in METRICS:
                scores[name][k].extend(s[k])
        done += out.shape[0]
        if log:
            log(f"scored {done}/{n} samples")
    per_sequence, running = summarise(scores, n, T, {nm: s.n_frames for nm, s in zip(names, model.seqs)})
    rec = {}
    for m, (name, s) in enumerate(zip(names, model.seqs)):
        with torch.no_grad():
            r = model.reconstruct(m)[0].detach().cpu()
        rec[name] = {"l1": float((r - s.features).abs().mean()), "mse": float(((r - s.features) ** 2).mean())}
    return {
        "protocol": "paper",
        "samples": n,
        "frames": T,
        "source_frames": {nm: s.n_frames for nm, s in zip(names, model.seqs)},
        "levels": lengths,
        "seed": seed,
        "sixd": model.seqs[0].sixd,
        "features": f"raw generator output: 6D of {J} joints + 6 channels of {len(model.feet)} contacts "
                    f"({6 * (model.n_entities - 1)} per frame), root motion dropped",
        "per_sequence": per_sequence,
        "released_running": running,
        "reconstruction": rec,
    }


def format_figures(figures: dict[str, Any]) -> str:
    """Readable lines for either protocol, the number of samples and their length beside every figure."""
    def row(label: str, f: dict, extra: str = "") -> str:
        return (f"{label:<28s} coverage {f['coverage']:.3f}  global div {f['global_diversity']:.3f}  "
                f"local div {f['local_diversity']:.3f}  ({f['samples']} samples x {f['frames']} frames{extra})")

    lines = []
    if figures.get("protocol") == "paper":
        total = sum(figures["source_frames"].values())
        how = f"2 x {total} source frames" if figures["frames"] == 2 * total else f"{total} source frames"
        lines.append(f"protocol paper (released evaluate.py): {figures['samples']} samples x {figures['frames']} "
                     f"frames ({how}), levels {figures['levels']}, {figures['sixd']} 6D; {figures['features']}")
        for name, f in figures["per_sequence"].items():
            lines.append(row(name, f, f", source {f['source_frames']} frames"))
        if len(figures["released_running"]) > 1:
            for f in figures["released_running"]:
                lines.append(row(f"released running avg to {f['after']}", f, f"; {f['pairs']} sample-clip pairs"))
        for name, r in figures["reconstruction"].items():
            lines.append(f"{name:<28s} reconstruction L1 {r['l1']:.4f}  MSE x 1e5 {r['mse'] * 1e5:.2f}")
    else:
        lines.append(f"protocol ours (rotations decoded from the samples, as from BVH): {figures['samples']} samples "
                     f"x {figures['frames']} frames")
        for name, f in figures["metrics"].items():
            lines.append(row(name, f))
        for name, l1 in figures.get("reconstruction_l1", {}).items():
            lines.append(f"{name:<28s} reconstruction L1 {l1:.4f}")
    return "\n".join(lines)


__all__ = ["evaluate_paper", "paper_pyramid", "paper_features", "sample_paper", "score_samples", "summarise",
           "format_figures", "N_SAMPLES"]
