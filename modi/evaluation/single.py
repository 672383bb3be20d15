"""Single-sequence metrics of GANimator (§4.3, Appendix B): coverage, global (PNN) and local diversity.

Every metric compares per-frame pose vectors built from the *local* joint rotation matrices (root
orientation included, root translation excluded). The distance of two frames is the Frobenius norm of
the difference of their stacked rotation matrices, ``c(x, y) = sqrt(sum_j |R_j(x) - R_j(y)|_F^2)``
(the L2 norm over all joints -- *not* a per-joint mean); the distance of two aligned windows of ``T``
frames is the per-frame mean ``(1/T) sum_t c(x_t, y_t)``, and the threshold applies to that mean.
This is the authors' released definition (ganimator ``evaluations/``), which stacks the first two
*rows* of each matrix (a 6-D rotation): ``representation="6d"``, the default, because coverage's
threshold 2.0 and the published tables were computed that way. ``"matrix"`` uses all nine entries, as
the paper's wording reads; it puts the same poses about 1.26x further apart (measured on Joe's salsa),
so its coverage at 2.0 is lower. Windows: every window of the sequence (the paper); the released code
skips the last one.

Files from other tools (GenMM, the authors' code, our own ``modi ganimator generate``) name the same rig with or
without a namespace prefix and list siblings in any order: :func:`shared_pose_frames` matches joints by bare name
and builds both sides' pose vectors on the joints they share, after GANimator's joint reduction by default (the
authors score a Mixamo character on its 24 reduced joints; fingers and head-top move the figures a lot).

Speed: the frame-distance table ``C (L x N)`` is one batched GEMM; prefix sums along its diagonals (a
fixed source-minus-generated offset) give every window sum in O(1). The PNN dynamic program then keeps, per diagonal, the running minimum of
``G[l] - S_d[l]`` over admissible segment starts, so each step is a vector op over diagonals and the
whole DP is O(L * (L + N)) per sequence instead of the O(L^2 N) triple loop, batched over sequences.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from modi.core.joint_reduction import reduce_joints
from modi.core.rotations import quat_to_matrix
from modi.core.skeleton import strip_namespace

__all__ = [
    "rotation_features",
    "frame_distances",
    "window_distances",
    "coverage",
    "local_diversity",
    "patched_nearest_neighbour",
    "single_sequence_metrics",
    "bare_name",
    "shared_joints",
    "shared_pose_frames",
]


def rotation_features(rotations: Any, representation: str = "6d") -> torch.Tensor:
    """Per-frame pose vectors ``(T, F)`` from local rotations.

    ``rotations`` is ``(T, J, 4)`` unit quaternions (w, x, y, z) or ``(T, J, 3, 3)`` matrices.
    ``representation``: ``"6d"`` (first two rows, F = 6J, as in the GANimator authors' evaluation code) or
    ``"matrix"`` (all 9 entries, F = 9J).
    """
    r = torch.as_tensor(rotations)
    if not r.is_floating_point():
        r = r.double()
    if r.ndim == 3 and r.shape[-1] == 4:
        m = quat_to_matrix(r.double())
    elif r.ndim == 4 and r.shape[-2:] == (3, 3):
        m = r.double()
    else:
        raise ValueError(f"rotations: expected (T, J, 4) quaternions or (T, J, 3, 3) matrices, got {tuple(r.shape)}")
    if representation == "matrix":
        return m.reshape(m.shape[0], -1)
    if representation == "6d":
        return m[..., :2, :].reshape(m.shape[0], -1)
    raise ValueError(f"representation must be 'matrix' or '6d', got {representation!r}")


def _as_frames(x: Any, name: str) -> torch.Tensor:
    t = torch.as_tensor(x)
    if t.ndim != 2:
        raise ValueError(f"{name}: expected (frames, features), got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    return t.double()


def frame_distances(gen: torch.Tensor, src: torch.Tensor) -> torch.Tensor:
    """``C[..., i, k] = |gen_i - src_k|``: a GEMM-based distance table, batched over leading dims of ``gen``."""
    gen = gen.double()
    src = src.double()
    d2 = (gen * gen).sum(-1, keepdim=True) + (src * src).sum(-1) - 2.0 * torch.matmul(gen, src.T)
    return d2.clamp_min_(0.0).sqrt_()


def _diagonal_prefix(cost: torch.Tensor) -> torch.Tensor:
    """Exclusive prefix sums along the diagonals of ``cost (B, L, N)``.

    Returns ``E (B, L + 1, N + 1)`` with ``E[b, u, k] = sum_{t = 1}^{min(u, k)} C[b, u - t, k - t]``, so the cost of
    aligning generated frames ``[l, i)`` with source frames ``[l + d, i + d)`` is ``E[i, i + d] - E[l, l + d]``.
    Built row by row (one vector add per generated frame): no skewed copy, no gather.
    """
    b, L, N = cost.shape
    out = torch.zeros(b, L + 1, N + 1, dtype=cost.dtype)
    for u in range(L):
        torch.add(cost[:, u, :], out[:, u, :N], out=out[:, u + 1, 1:])
    return out


def _window_table(E: torch.Tensor, L: int, N: int, T: int) -> torch.Tensor:
    """Mean per-frame cost of every aligned window pair: ``W[b, i, k]`` for gen window i, source window k."""
    return (E[:, T : L + 1, T : N + 1] - E[:, : L - T + 1, : N - T + 1]) / T


def window_distances(gen: Any, src: Any, window: int) -> torch.Tensor:
    """``W[i, k]``: mean frame distance between generated window ``i`` and source window ``k`` (both length ``window``)."""
    g, s = _as_frames(gen, "generated"), _as_frames(src, "source")
    _check(g, s, window)
    E = _diagonal_prefix(frame_distances(g[None], s))
    return _window_table(E, g.shape[0], s.shape[0], window)[0]


def _pnn_dp(E: torch.Tensor, L: int, N: int, tmin: int) -> torch.Tensor:
    """Minimal total cost of covering frames ``[0, L)`` with segments of >= ``tmin`` frames, each copied from a
    contiguous stretch of the source: ``G[i] = min_{l <= i - tmin, d} G[l] + E[i, i + d] - E[l, l + d]``.

    ``run[d + L - 1]`` holds ``min_l G[l] - E[l, l + d]`` over the starts admitted so far (l <= i - tmin and
    source frame l + d inside the source), so each step costs O(N) per sequence.
    """
    B = E.shape[0]
    G = torch.full((B, L + 1), float("inf"), dtype=E.dtype)
    G[:, 0] = 0.0
    run = torch.full((B, L + N - 1), float("inf"), dtype=E.dtype)
    for i in range(tmin, L + 1):
        l = i - tmin
        # a segment starting at generated frame l may start at source frames 0..N-1 (diagonals d = -l..N-1-l)
        a = L - 1 - l
        torch.minimum(run[:, a : a + N], G[:, l : l + 1] - E[:, l, :N], out=run[:, a : a + N])
        # a segment ending (exclusive) at i ends at source frames 1..N (diagonals d = 1-i..N-i)
        a = L - i
        G[:, i] = (run[:, a : a + N] + E[:, i, 1:]).amin(dim=1)
    return G[:, L]


def _check(g: torch.Tensor, s: torch.Tensor, window: int) -> None:
    if g.shape[1] != s.shape[1]:
        raise ValueError(f"generated and source pose vectors differ in size ({g.shape[1]} vs {s.shape[1]}): "
                         "different skeletons or representations")
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    if g.shape[0] < window:
        raise ValueError(f"generated sequence has {g.shape[0]} frames, fewer than the {window}-frame window")
    if s.shape[0] < window:
        raise ValueError(f"source sequence has {s.shape[0]} frames, fewer than the {window}-frame window")


def coverage(gen: Any, src: Any, window: int = 30, threshold: float = 2.0) -> float:
    """Fraction of source windows whose nearest generated window is closer than ``threshold``."""
    w = window_distances(gen, src, window)
    return float((w.amin(dim=0) < threshold).double().mean())


def local_diversity(gen: Any, src: Any, window: int = 15) -> float:
    """Mean over generated windows of the distance to their nearest source window."""
    return float(window_distances(gen, src, window).amin(dim=1).mean())


def patched_nearest_neighbour(gen: Any, src: Any, min_segment: int = 30) -> float:
    """Global diversity: per-frame cost of the best patched nearest neighbour (segments >= ``min_segment``)."""
    g, s = _as_frames(gen, "generated"), _as_frames(src, "source")
    _check(g, s, min_segment)
    E = _diagonal_prefix(frame_distances(g[None], s))
    return float(_pnn_dp(E, g.shape[0], s.shape[0], min_segment)[0] / g.shape[0])


def single_sequence_metrics(
    generated: Sequence[Any],
    source: Any,
    coverage_window: int = 30,
    threshold: float = 2.0,
    min_segment: int = 30,
    local_window: int = 15,
    batch_elements: int = 20_000_000,
) -> dict[str, Any]:
    """Coverage, global diversity (PNN) and local diversity of each generated sequence against one source.

    ``generated``: sequence of ``(L_i, F)`` pose vectors; ``source``: ``(N, F)``. Sequences of equal length
    are processed together in batches of about ``batch_elements`` table entries. Returns the means under
    ``"coverage"``, ``"global_diversity"``, ``"local_diversity"`` and the per-sequence values under ``"per_sequence"``.
    """
    if len(generated) == 0:
        raise ValueError("no generated sequences given")
    s = _as_frames(source, "source")
    gens = [_as_frames(g, f"generated[{i}]") for i, g in enumerate(generated)]
    longest = max(coverage_window, min_segment, local_window)
    for i, g in enumerate(gens):
        try:
            _check(g, s, longest)
        except ValueError as exc:
            raise ValueError(f"generated[{i}]: {exc}") from None
    N = s.shape[0]
    cov = np.zeros(len(gens))
    glob = np.zeros(len(gens))
    loc = np.zeros(len(gens))
    by_len: dict[int, list[int]] = {}
    for i, g in enumerate(gens):
        by_len.setdefault(g.shape[0], []).append(i)
    for L, members in by_len.items():
        per = max(1, batch_elements // (L * N))
        for c in range(0, len(members), per):
            ids = members[c : c + per]
            E = _diagonal_prefix(frame_distances(torch.stack([gens[i] for i in ids]), s))
            # min over generated windows for coverage, over source windows for local diversity
            T = coverage_window
            near = (E[:, T:, T:] - E[:, : L - T + 1, : N - T + 1]).amin(dim=1) / T
            cov[ids] = (near < threshold).double().mean(dim=1).numpy()
            T = local_window
            near = (E[:, T:, T:] - E[:, : L - T + 1, : N - T + 1]).amin(dim=2) / T
            loc[ids] = near.mean(dim=1).numpy()
            del near
            glob[ids] = (_pnn_dp(E, L, N, min_segment) / L).numpy()
    return {
        "coverage": float(cov.mean()),
        "global_diversity": float(glob.mean()),
        "local_diversity": float(loc.mean()),
        "n_sequences": len(gens),
        "settings": {
            "coverage_window": coverage_window,
            "threshold": threshold,
            "min_segment": min_segment,
            "local_window": local_window,
        },
        "per_sequence": [
            {"coverage": float(a), "global_diversity": float(b), "local_diversity": float(c)}
            for a, b, c in zip(cov, glob, loc)
        ],
    }


# ---------------------------------------------------------------------------------------- matching skeletons


bare_name = strip_namespace  # one definition, in modi.core.skeleton


def _bare_names(skeleton: Any, label: str) -> list[str]:
    names = [bare_name(n) for n in skeleton.names]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"{label}: two joints are named {dup!r} once the namespace prefix is dropped")
    return names


def shared_joints(skeletons: Sequence[Any], reduce: bool = True, labels: Sequence[str] | None = None) -> list[str]:
    """Bare names of the joints that every skeleton has, in the first skeleton's order.

    ``reduce``: each skeleton first gets GANimator's joint reduction (:func:`modi.core.joint_reduction.reduce_joints`:
    fingers and head-top dropped), so a full Mixamo source and a 24-joint output meet on the published joint set.
    """
    labels = list(labels) if labels is not None else [f"skeleton {i}" for i in range(len(skeletons))]
    common: list[str] | None = None
    for sk, label in zip(skeletons, labels):
        names = _bare_names(sk, label)
        kept = [names[j] for j in (reduce_joints(sk) if reduce else range(len(names)))]
        common = kept if common is None else [n for n in common if n in kept]
    return common or []


def shared_pose_frames(
    source: Any,
    generated: Sequence[Any],
    reduce: bool = True,
    representation: str = "6d",
    labels: Sequence[str] | None = None,
) -> tuple[torch.Tensor, list[torch.Tensor], list[str]]:
    """Pose vectors of the source and of each generated :class:`modi.data.motion.Motion` on their shared joints.

    Returns ``(source (N, F), [generated (L_i, F)], joint names)``; the joints are :func:`shared_joints` of all
    skeletons, in the source's order, so neither the namespace prefix nor sibling order matters. Joints outside
    that set are removed with :meth:`Motion.subset`, which composes a removed inner joint's rotation into its kept
    children, so a local rotation means the same thing on both sides. Raises ``ValueError`` when the source's root
    is not shared or a shared joint hangs from a different parent (not the same rig).
    """
    labels = list(labels) if labels is not None else [f"generated[{i}]" for i in range(len(generated))]
    motions = [source, *generated]
    joints = shared_joints([m.skeleton for m in motions], reduce, ["source", *labels])
    root = bare_name(source.skeleton.names[0])
    if root not in joints:
        raise ValueError(f"the generated files do not share the source's root joint {root!r}")
    frames, src_parents = [], None
    for m, label in zip(motions, ["source", *labels]):
        names = _bare_names(m.skeleton, label)
        keep = [names.index(n) for n in joints]
        if sorted(keep) != list(range(len(names))):
            m = m.subset(keep)
            names = [bare_name(n) for n in m.skeleton.names]
        order = [names.index(n) for n in joints]
        parents = [None if m.skeleton.parents[j] < 0 else names[m.skeleton.parents[j]] for j in order]
        if src_parents is None:
            src_parents = parents
        else:
            for n, p, q in zip(joints, parents, src_parents):
                if p != q:
                    raise ValueError(f"{label}: joint {n!r} hangs from {p!r}, in the source from {q!r} "
                                     "(not the same rig)")
        frames.append(rotation_features(m.rotations[:, order], representation))
    return frames[0], frames[1:], joints
