"""Distribution metrics over feature vectors: FID, KID, precision/recall, diversity (MoDi, Appendix D.3).

All functions take ``(N, D)`` arrays of penultimate-layer features (numpy or torch) and compute in float64.
Every result is invariant to the order of the samples: the random parts (KID's standard-error blocks,
diversity's random pairs) first put the rows in a canonical (lexicographic) order, then draw with a seed.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

__all__ = [
    "frechet_distance",
    "kernel_distance",
    "precision_recall",
    "diversity",
    "distribution_metrics",
    "as_features",
]


def as_features(x: Any, name: str = "features", min_rows: int = 2) -> np.ndarray:
    """``x`` as a finite float64 ``(N, D)`` array, or a ValueError naming ``name`` and the problem."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D (N, D) array of feature vectors, got shape {tuple(a.shape)}")
    if a.shape[0] < min_rows:
        raise ValueError(f"{name}: needs at least {min_rows} samples, got {a.shape[0]}")
    if a.shape[1] < 1:
        raise ValueError(f"{name}: feature dimension is 0")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    return a


def _pair(a: Any, b: Any, min_rows: int = 2) -> tuple[np.ndarray, np.ndarray]:
    a = as_features(a, "first set", min_rows)
    b = as_features(b, "second set", min_rows)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"feature dimensions differ: {a.shape[1]} vs {b.shape[1]}")
    return a, b


def _canonical(a: np.ndarray) -> np.ndarray:
    """Rows sorted lexicographically, so seeded random draws do not depend on the input order."""
    return a[np.lexsort(a.T[::-1])]


def _psd_sqrt(s: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(s)
    return (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T


def frechet_distance(a: Any, b: Any) -> float:
    """FID: ``|mu_a - mu_b|^2 + Tr(S_a + S_b - 2 (S_a S_b)^(1/2))`` between Gaussian fits of two feature sets.

    The trace of the matrix square root is taken from the eigenvalues of the symmetric PSD matrix
    ``S_a^(1/2) S_b S_a^(1/2)``, which is stable where ``scipy.linalg.sqrtm`` of the non-symmetric product
    can return complex noise, and is 0 for a set against itself up to rounding.
    """
    a, b = _pair(a, b)
    mu = a.mean(0) - b.mean(0)
    sa = np.atleast_2d(np.cov(a, rowvar=False))
    sb = np.atleast_2d(np.cov(b, rowvar=False))
    ra = _psd_sqrt(sa)
    m = ra @ sb @ ra
    eig = np.linalg.eigvalsh((m + m.T) / 2)
    tr_covmean = float(np.sqrt(np.clip(eig, 0.0, None)).sum())
    value = float(mu @ mu + np.trace(sa) + np.trace(sb) - 2.0 * tr_covmean)
    return max(value, 0.0)


def _mmd2_unbiased(a: np.ndarray, b: np.ndarray, degree: int, gamma: float, coef0: float) -> float:
    m, n = a.shape[0], b.shape[0]
    kaa = (a @ a.T * gamma + coef0) ** degree
    kbb = (b @ b.T * gamma + coef0) ** degree
    kab = (a @ b.T * gamma + coef0) ** degree
    saa = (kaa.sum() - np.trace(kaa)) / (m * (m - 1))
    sbb = (kbb.sum() - np.trace(kbb)) / (n * (n - 1))
    return float(saa + sbb - 2.0 * kab.mean())


def kernel_distance(
    a: Any,
    b: Any,
    n_blocks: int = 10,
    degree: int = 3,
    gamma: float | None = None,
    coef0: float = 1.0,
    seed: int = 0,
) -> tuple[float, float]:
    """KID (Binkowski et al. 2018): unbiased MMD^2 with the kernel ``(gamma x.y + coef0)^degree``.

    Returns ``(kid, std_err)``. ``kid`` is the unbiased estimate on the two full sets (deterministic).
    ``std_err`` comes from ``n_blocks`` disjoint random blocks of each set: the spread of the per-block
    estimates divided by ``sqrt(n_blocks)``. Because the estimator's variance scales as 1/n, this matches
    the standard error of the full-set estimate (NaN when fewer than two blocks of two samples fit).
    ``gamma`` defaults to ``1 / D``. KID can be slightly negative when the sets match: that is unbiasedness.
    """
    a, b = _pair(a, b)
    if degree < 1:
        raise ValueError(f"degree must be >= 1, got {degree}")
    gamma = 1.0 / a.shape[1] if gamma is None else float(gamma)
    kid = _mmd2_unbiased(a, b, degree, gamma, coef0)
    blocks = min(int(n_blocks), a.shape[0] // 2, b.shape[0] // 2)
    if blocks < 2:
        return kid, float("nan")
    rng = np.random.default_rng(seed)
    ia = np.array_split(rng.permutation(a.shape[0]), blocks)
    ib = np.array_split(rng.permutation(b.shape[0]), blocks)
    ca, cb = _canonical(a), _canonical(b)
    vals = np.array([_mmd2_unbiased(ca[x], cb[y], degree, gamma, coef0) for x, y in zip(ia, ib)])
    return kid, float(vals.std(ddof=1) / math.sqrt(blocks))


def _pairwise(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distances in float64, exact for identical rows (no |a|^2+|b|^2-2ab cancellation)."""
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")


def _kth_neighbour_radius(x: torch.Tensor, k: int, chunk: int) -> torch.Tensor:
    radii = []
    for s in range(0, x.shape[0], chunk):
        d = _pairwise(x[s : s + chunk], x)
        idx = torch.arange(s, min(s + chunk, x.shape[0]))
        d[idx - s, idx] = float("inf")  # a sample is not its own neighbour
        radii.append(d.kthvalue(k, dim=1).values)
    return torch.cat(radii)


def _inside_manifold(query: torch.Tensor, support: torch.Tensor, radii: torch.Tensor, chunk: int) -> torch.Tensor:
    inside = []
    for s in range(0, query.shape[0], chunk):
        d = _pairwise(query[s : s + chunk], support)
        inside.append((d <= radii[None, :]).any(dim=1))
    return torch.cat(inside)


def precision_recall(real: Any, fake: Any, k: int = 3, chunk: int = 1024) -> tuple[float, float]:
    """Improved precision and recall (Kynkäänniemi et al. 2019) by k-NN manifold estimates.

    Each set's manifold is the union of balls around its samples with radius = distance to the k-th
    nearest other sample of the same set. Precision = fraction of ``fake`` inside the real manifold
    (fidelity); recall = fraction of ``real`` inside the fake manifold (coverage of the real data).
    """
    r, f = _pair(real, fake, min_rows=k + 1)
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    rt, ft = torch.from_numpy(r), torch.from_numpy(f)
    r_radii = _kth_neighbour_radius(rt, k, chunk)
    f_radii = _kth_neighbour_radius(ft, k, chunk)
    precision = _inside_manifold(ft, rt, r_radii, chunk).double().mean().item()
    recall = _inside_manifold(rt, ft, f_radii, chunk).double().mean().item()
    return float(precision), float(recall)


def diversity(features: Any, n_pairs: int = 200, seed: int = 0) -> float:
    """Diversity as in Action2Motion / ACTOR: mean Euclidean distance over ``n_pairs`` random pairs.

    Pairs are drawn with replacement between distinct samples after putting the rows in canonical order,
    so the value depends on the set and the seed, not on the sample order.
    """
    x = _canonical(as_features(features, "features"))
    if n_pairs < 1:
        raise ValueError(f"n_pairs must be >= 1, got {n_pairs}")
    n = x.shape[0]
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, size=n_pairs)
    j = (i + rng.integers(1, n, size=n_pairs)) % n  # j != i
    return float(np.linalg.norm(x[i] - x[j], axis=1).mean())


def distribution_metrics(
    real: Any,
    fake: Any,
    k: int = 3,
    kid_blocks: int = 10,
    diversity_pairs: int = 200,
    seed: int = 0,
) -> dict[str, float]:
    """All of MoDi's table columns for one (real, fake) pair of feature sets, as a flat dict."""
    r, f = _pair(real, fake, min_rows=max(2, k + 1))
    kid, kid_se = kernel_distance(r, f, n_blocks=kid_blocks, seed=seed)
    precision, recall = precision_recall(r, f, k=k)
    return {
        "fid": frechet_distance(r, f),
        "kid": kid,
        "kid_std_err": kid_se,
        "precision": precision,
        "recall": recall,
        "diversity": diversity(f, n_pairs=diversity_pairs, seed=seed),
        "diversity_real": diversity(r, n_pairs=diversity_pairs, seed=seed),
        "n_real": int(r.shape[0]),
        "n_fake": int(f.shape[0]),
        "feature_dim": int(r.shape[1]),
    }
