"""Clustering W (paper 001 §4.1, Fig. 6): K-means on the W codes of many sampled motions, a t-SNE map coloured
by cluster, and sampled members of every cluster rendered side by side.

A semantically organised W shows up as clusters whose members move alike. K-means runs on every sample; t-SNE
(quadratic-ish in the number of points) on a random subset, which is plenty for a picture.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from modi.errors import UserError
from modi.models.modi.latent.space import decode_positions, pyplot, random_w, save_figure, synthesize, write_motions
from modi.models.modi.sampling import render_gif


@dataclass
class ClusterResult:
    """``labels`` (N,) and ``centers`` (k, D) of K-means on ``w`` (N, D); ``members[c]`` the rendered sample
    indices of cluster c; ``tsne`` (M, 2) the embedding of the samples ``tsne_index``; ``files`` what was written."""

    w: np.ndarray
    labels: np.ndarray
    centers: np.ndarray
    members: list[list[int]]
    tsne: np.ndarray | None = None
    tsne_index: np.ndarray | None = None
    files: dict[str, Any] = field(default_factory=dict)

    @property
    def sizes(self) -> list[int]:
        return np.bincount(self.labels, minlength=len(self.centers)).tolist()


def kmeans(w: np.ndarray, k: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,), centers (k, D)) of K-means with k-means++ init and 4 restarts."""
    from sklearn.cluster import KMeans  # lazy: scikit-learn costs ~1 s to import; only clustering needs it

    w = np.asarray(w, dtype=np.float64)
    if k < 1:
        raise UserError(f"k must be >= 1, got {k}")
    if len(w) < k:
        raise UserError(f"need at least k={k} samples to cluster, got {len(w)}")
    km = KMeans(n_clusters=k, n_init=4, random_state=seed).fit(w)
    return km.labels_.astype(np.int64), km.cluster_centers_


def tsne_embed(w: np.ndarray, n_max: int = 2000, seed: int = 0,
               perplexity: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """2-D t-SNE of at most ``n_max`` random rows of ``w``: (embedding (M, 2), row indices (M,))."""
    from sklearn.manifold import TSNE  # lazy: as KMeans above

    w = np.asarray(w, dtype=np.float64)
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.permutation(len(w))[:min(n_max, len(w))])
    if len(idx) < 5:
        raise UserError(f"t-SNE needs at least 5 samples, got {len(idx)}")
    perp = min(perplexity, max(2.0, (len(idx) - 1) / 3.0))
    emb = TSNE(n_components=2, perplexity=perp, init="pca", random_state=seed).fit_transform(w[idx])
    return emb, idx


def plot_clusters(emb: np.ndarray, labels: np.ndarray, path: str | Path, title: str = "") -> Path:
    """Scatter of a 2-D embedding coloured by cluster label, with each cluster's number at its median."""
    plt = pyplot()

    k = int(labels.max()) + 1 if len(labels) else 0
    cmap = plt.get_cmap("tab10" if k <= 10 else "tab20")
    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    for c in range(k):
        sel = labels == c
        if not sel.any():
            continue
        ax.scatter(emb[sel, 0], emb[sel, 1], s=4, color=cmap(c % cmap.N), alpha=0.7, label=f"cluster {c}")
        mx, my = np.median(emb[sel], axis=0)
        ax.text(mx, my, str(c), fontsize=12, weight="bold", ha="center", va="center",
                bbox=dict(boxstyle="round,pad=0.2", fc="white", alpha=0.7, lw=0))
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title or f"t-SNE of W, {k} K-means clusters", fontsize=10)
    ax.legend(markerscale=3, fontsize=7, loc="best", frameon=False)
    return save_figure(fig, path)


def pick_members(labels: np.ndarray, per_cluster: int, seed: int = 0, w: np.ndarray | None = None,
                 centers: np.ndarray | None = None, how: str = "random") -> list[list[int]]:
    """Sample indices per cluster: ``random`` members (the paper's choice) or the ``nearest`` to the centre."""
    rng = np.random.default_rng(seed)
    out = []
    for c in range(int(labels.max()) + 1 if len(labels) else 0):
        idx = np.nonzero(labels == c)[0]
        if how == "random":
            pick = rng.permutation(idx)[:per_cluster]
        elif how == "nearest":
            if w is None or centers is None:
                raise ValueError("how='nearest' needs w and centers")
            d = np.linalg.norm(w[idx] - centers[c], axis=1)
            pick = idx[np.argsort(d)[:per_cluster]]
        else:
            raise ValueError(f"how must be 'random' or 'nearest', not {how!r}")
        out.append([int(i) for i in pick])
    return out


def cluster_latent_space(g: Any, codec: Any, out_dir: str | Path, n: int = 10_000, k: int = 8,
                         per_cluster: int = 4, seed: int = 0, tsne_max: int = 2000, how: str = "random",
                         render: bool = True) -> ClusterResult:
    """Sample ``n`` W codes, K-means them, draw the t-SNE map (``tsne.png``) and write ``per_cluster`` members of
    each cluster as BVH plus one GIF per cluster (``cluster_C.gif``, members side by side); ``clusters.json``
    records sizes and member indices (sample i is row i of the seeded stream ``random_w(g, n, seed)``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    w_t = random_w(g, n, seed)
    w = w_t.cpu().numpy()
    labels, centers = kmeans(w, k, seed)
    res = ClusterResult(w=w, labels=labels, centers=centers, members=pick_members(labels, per_cluster, seed, w,
                                                                                    centers, how))
    if tsne_max > 0:
        res.tsne, res.tsne_index = tsne_embed(w, tsne_max, seed)
        res.files["tsne"] = str(plot_clusters(res.tsne, labels[res.tsne_index], out / "tsne.png",
                                              f"t-SNE of W ({len(res.tsne_index)} of {n} samples), "
                                              f"K-means k={k}"))
    if render:
        gifs = []
        for c, members in enumerate(res.members):
            if not members:
                continue
            x = synthesize(g, w_t[torch.as_tensor(members)])
            names = [f"cluster{c}_sample{i:05d}" for i in members]
            write_motions(codec, x, out / f"cluster_{c}", names, gif=None)
            pos, con = decode_positions(codec, x)
            gif = render_gif(codec, pos, con, out / f"cluster_{c}.gif",
                             titles=[f"cluster {c}: #{i}" for i in members], size=(200, 200),
                             view=f"cluster_{c}.html")
            gifs.append(str(gif))
        res.files["gifs"] = gifs
    summary = {"n": n, "k": k, "seed": seed, "sizes": res.sizes, "members": res.members,
               "inertia_per_sample": float(((w - centers[labels]) ** 2).sum(1).mean())}
    (out / "clusters.json").write_text(json.dumps(summary, indent=1))
    res.files["summary"] = str(out / "clusters.json")
    return res


__all__ = ["ClusterResult", "kmeans", "tsne_embed", "plot_clusters", "pick_members", "cluster_latent_space"]
