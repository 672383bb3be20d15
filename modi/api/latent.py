"""MoDi's latent-space applications as files: what ``modi latent ACTION`` writes (BVH + GIF previews, plots, JSON).

Each call takes a :class:`modi.ModiGenerator` (:func:`open_generator` opens a checkpoint as the CLI does), writes into
``out`` and returns what it wrote; the in-memory forms (``list[Motion]``) are the generator's own methods
(:meth:`ModiGenerator.truncate`, :meth:`~ModiGenerator.interpolate`, :meth:`~ModiGenerator.crowd`, ...). Motions are
synthesised with the generator's fixed noise, so a latent fixes its motion.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from modi.api._util import existing_file
from modi.api.generator import LatentLike, ModiGenerator, _steps, open_generator
from modi.errors import UserError
from modi.models.modi.latent import space
from modi.models.modi.latent.clustering import ClusterResult, cluster_latent_space
from modi.models.modi.latent.crowd import SIGMA_RANGE, Crowd, simulate_crowd
from modi.models.modi.latent.editing import Boundary, EditReport, edit_latents, edit_report, plot_report
from modi.models.modi.latent.inversion import InversionResult, invert, plot_history


def _sequence(gen: ModiGenerator, seq: Tensor, out: Path, gif: str, label: str) -> list[Path]:
    c = seq.shape[0] - 1
    return space.write_motions(gen.codec, space.synthesize(gen.network, seq), out,
                               [f"step_{i:02d}" for i in range(c + 1)], gif=gif,
                               titles=[f"{label} {i}/{c}" for i in range(c + 1)])


def write_mean(gen: ModiGenerator, out: str | os.PathLike) -> dict[str, Path]:
    """``modi latent mean``: the mean motion G(w̄) as ``mean.bvh`` + ``mean.gif`` and w̄ as ``mean_w.npy``."""
    out = Path(out)
    w = gen.mean_latent()
    space.write_motions(gen.codec, space.mean_motion(gen.network, w), out, ["mean"], gif="mean.gif",
                        titles=["mean motion G(w_avg)"])
    space.save_latent(out / "mean_w.npy", w)
    return {"bvh": out / "mean.bvh", "gif": out / "mean.gif", "latent": out / "mean_w.npy"}


def write_truncation(gen: ModiGenerator, latent: LatentLike, out: str | os.PathLike, steps: int = 4) -> list[Path]:
    """``modi latent truncate``: ``steps + 1`` motions from a latent to the mean (``step_NN``, side by side in
    ``truncation.gif``); returns the motion files."""
    seq = space.truncation_sequence(gen.latent(latent), _steps(steps), gen.mean_latent())
    return _sequence(gen, seq, Path(out), "truncation.gif", "to mean")


def write_interpolation(gen: ModiGenerator, a: LatentLike, b: LatentLike, out: str | os.PathLike,
                        steps: int = 4) -> tuple[list[Path], str]:
    """``modi latent interpolate``: ``steps + 1`` motions from ``a`` to ``b`` (in W+ when either is W+), side by
    side in ``interpolation.gif``; returns the motion files and the space (``"W"`` or ``"W+"``)."""
    seq = space.interpolation_sequence(gen.latent(a), gen.latent(b), _steps(steps))
    return _sequence(gen, seq, Path(out), "interpolation.gif", ""), "W+" if seq.ndim == 3 else "W"


def write_clusters(gen: ModiGenerator, out: str | os.PathLike, *, n: int = 10_000, k: int = 8,
                   per_cluster: int = 4, pick: str = "random", tsne_max: int = 2000, seed: int = 0) -> ClusterResult:
    """``modi latent cluster``: K-means on ``n`` sampled W codes, a t-SNE map (``tsne.png``, ``tsne_max`` samples;
    0: none) and ``per_cluster`` members of each cluster (``pick``: random or nearest the centre) as BVH + one GIF
    per cluster; ``clusters.json`` has sizes and members. Cost: ``n`` mappings, K-means and t-SNE (seconds)."""
    if n < k:
        raise UserError(f"--n ({n}) must be at least --k ({k})")
    if per_cluster < 0 or tsne_max < 0:
        raise UserError("--per-cluster and --tsne-max must be >= 0")
    return cluster_latent_space(gen.network, gen.codec, out, n=n, k=k, per_cluster=per_cluster, seed=seed,
                                tsne_max=tsne_max, how=pick, render=per_cluster > 0)


def write_edit(gen: ModiGenerator, out: str | os.PathLike, *, attribute: str = "gral", svm: str = "ours",
               n: int = 2000, ratio: float = 0.2, boundary: str | os.PathLike | None = None, held_out: int = 16,
               first_seed: int = 100_000, alphas: Sequence[float] = (-3, -2, -1, 0, 1, 2, 3), render: int = 2,
               seed: int = 0) -> tuple[Boundary, EditReport]:
    """``modi latent edit``: fit an attribute's boundary in W (:meth:`ModiGenerator.fit_boundary`, written as
    ``boundary.json``) or read a saved one, score ``held_out`` seeds along ``w + α σ n`` (``report.json``,
    ``score_vs_alpha.png``) and render the first ``render`` of them (``edit_SEED.gif`` + BVH). Returns the boundary
    and the report. Cost: ``n`` syntheses and an SVM fit, then ``held_out × len(alphas)`` syntheses."""
    alphas = [float(a) for a in alphas]
    if any(b <= a for a, b in zip(alphas, alphas[1:])):
        raise UserError(f"--alphas must be increasing, got {' '.join(f'{a:g}' for a in alphas)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if held_out < 1:
        raise UserError(f"--held-out must be >= 1, got {held_out}")
    g, codec = gen.network, gen.codec
    if boundary:
        found = Boundary.load(boundary)
        if len(found.normal) != g.latent_dim:
            raise UserError(f"{boundary}: boundary has {len(found.normal)} dims, the model {g.latent_dim}")
    else:
        if n < 10:
            raise UserError(f"--n must be >= 10, got {n}")
        found = gen.fit_boundary(attribute, n=n, seed=seed, ratio=ratio, method=svm)
        found.save(out / "boundary.json")
    seeds = list(range(first_seed, first_seed + held_out))
    report = edit_report(g, codec, found, seeds, alphas, attribute=attribute)
    (out / "report.json").write_text(json.dumps(report.to_dict(), indent=1))
    plot_report(report, out / "score_vs_alpha.png")
    for s in seeds[:max(0, render)]:
        lat = edit_latents(space.seed_w(g, [s])[0], found.normal, report.alphas)
        names = [f"edit_{s}_alpha{a:+.1f}".replace(".", "p") for a in report.alphas_sigma]
        space.write_motions(codec, space.synthesize(g, lat), out / f"edit_{s}", names, gif=f"../edit_{s}.gif",
                            view=f"edit_{s}.html", titles=[f"alpha={a:+g} sd" for a in report.alphas_sigma])
    return found, report


def write_crowd(gen: ModiGenerator, latent: LatentLike, out: str | os.PathLike, *, k: int = 8, sigma: float = 0.4,
                seed: int = 0, include_source: bool = True, spacing: float | None = None) -> Crowd:
    """``modi latent crowd``: ``k`` variations ``w + σ ε`` of one motion placed on a grid ``spacing`` apart (None:
    0.9 body heights) as ``crowd_NN.bvh`` and one scene in ``crowd.gif`` (``crowd_00_source``: the motion itself,
    with ``include_source``). The paper uses σ in :data:`SIGMA_RANGE`."""
    return simulate_crowd(gen.network, gen.codec, gen.latent(latent), out, k=k, sigma=sigma, seed=seed,
                          include_source=include_source, spacing=spacing)


def write_inversion(gen: ModiGenerator, bvh: str | os.PathLike, out: str | os.PathLike, *, start: int = 0,
                    steps: int = 300, lr: float = 0.02, lambda_fk: float = 1.0, init: str = "mean") -> InversionResult:
    """``modi latent invert``: optimise a W+ latent to match a window of a BVH clip (:meth:`ModiGenerator.invert`)
    and write input and result side by side (``inversion.gif`` + BVH), the latent (``wplus.npy``), the losses
    (``history.json``) and their curve (``loss.png``). Cost: ``steps`` generator forward and backward passes."""
    out = Path(out)
    if steps < 0:
        raise UserError(f"--steps must be >= 0, got {steps}")
    if lr <= 0 or lambda_fk < 0:
        raise UserError("--lr must be positive and --lambda-fk >= 0")
    existing_file(bvh)
    target = space.load_bvh_window(gen.codec, bvh, gen.n_frames, start).unsqueeze(0)
    res = invert(gen.network, gen.codec, target, steps=steps, lr=lr, lambda_fk=lambda_fk, init=init)
    space.write_motions(gen.codec, torch.cat([target.cpu(), res.motion.cpu()]), out, ["input", "inverted"],
                        gif="inversion.gif", titles=["input", f"G(W+) after {steps} steps"])
    space.save_latent(out / "wplus.npy", res.wplus[0])
    (out / "history.json").write_text(json.dumps({"total": res.history, "rec": res.rec, "fk": res.fk}))
    plot_history(res, out / "loss.png")
    return res


__all__ = ["open_generator", "write_mean", "write_truncation", "write_interpolation", "write_clusters",
           "write_edit", "write_crowd", "write_inversion", "SIGMA_RANGE"]
