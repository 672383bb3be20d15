"""Semantic editing in W (paper 000 §4.4, 001 §4.1 and App. C.2): attribute scores, a linear SVM boundary, w + α·n.

Following InterFaceGAN (Shen et al.), an attribute is scored on generated motions, the top and bottom ``ratio``
of the samples become the two classes of a linear SVM in W, and the unit normal ``n`` of its hyperplane is the edit
direction: ``G(w + α n)`` should show more of the attribute as α grows, and little else should change.

Attributes (all computed from decoded motions, so any rig works):

* ``gral`` -- gradual right-arm lifting (App. C.2): the angle of the right shoulder and of the right elbow is
  averaged over windows of 8 frames with stride 4; each window scores 1 when its average exceeds the previous
  window's; the score is the mean over both joints' increments (1: the arm rises the whole time, 0: it falls).
  The paper's angle is each joint's rotation angle; how big a rotation is says little about *up* on rigs whose
  rest pose is a T- or A-pose (a hanging arm is already rotated 80 degrees), so by default the angle is the
  bone's *elevation* -- 0 hanging down, 90 horizontal, 180 straight up -- of the upper arm (shoulder) and the
  forearm (elbow). ``angle="rotation"`` uses the paper's literal joint rotation angles.
* ``gral_released`` -- gral as the authors' ``latent_space_edit.py`` (``r_hand_lift_up_score``) computes it: for
  the right upper arm (``RightArm``) and the right clavicle (``RightShoulder``), the joint's local rotation angle
  (|w| convention, 0..180) plus the rest-pose angle between the bone to its parent and the bone to its child,
  taken mod 360 and reversed (360 - angle); windows of 8 frames every 4; the count of windows whose average exceeds
  the previous one divided by the number of *windows*; the mean of the two joints. Its boundary is fitted with
  ``fit_boundary(method="released")`` (SVC with a linear kernel, as InterFaceGAN) on 10k samples in the paper.
* ``verticality`` -- (head height - lowest ankle height) / (head-to-ankle bone length): ~1 standing, 0 lying,
  -1 upside down (paper 000 §4.4's definition).
* ``speed`` -- mean horizontal root speed in body heights per second.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from modi.errors import UserError
from modi.models.modi.latent.space import pyplot, random_w, save_figure, seed_w, synthesize

UP = torch.tensor([0.0, 1.0, 0.0])


# --------------------------------------------------------------------------------------------- joints by name
def _side(name: str) -> str | None:
    """'R', 'L' or None from common naming styles: RightArm, Hand_R, r_wrist, rHand, RHand, hand.r."""
    low = name.lower()
    for side, word in (("R", "right"), ("L", "left")):
        c = side.lower()
        if word in low or re.search(rf"(^|[_.\-\s]){c}($|[_.\-\s])", low) or re.match(rf"[{c}{side}][A-Z]", name):
            return side
    return None


def find_right_arm(skeleton: Any) -> tuple[int, int, int]:
    """(shoulder, elbow, wrist) joint indices of the right arm: the right hand/wrist joint, its parent (the elbow)
    and grandparent (the shoulder ball joint), e.g. RightArm/RightForeArm/RightHand or UpperArm_R/LowerArm_R/Hand_R."""
    names = list(skeleton.names)
    hands = [j for j, n in enumerate(names) if _side(n) == "R" and re.search(r"hand|wrist", n, re.I)
             and not re.search(r"thumb|index|middle|ring|pinky|finger|end", n, re.I)]
    if not hands:
        raise UserError("no right hand/wrist joint found by name (looked for 'Right...Hand', 'Hand_R', 'r_wrist'...)")
    wrist = hands[0]
    elbow = skeleton.parents[wrist]
    shoulder = skeleton.parents[elbow] if elbow >= 0 else -1
    if elbow < 0 or shoulder < 0:
        raise UserError(f"right hand joint {names[wrist]!r} needs a parent (elbow) and grandparent (shoulder)")
    return shoulder, elbow, wrist


def find_head(skeleton: Any) -> int:
    """The head joint by name ('Head', not an end site), else the highest joint of the rest pose."""
    for j, n in enumerate(skeleton.names):
        if re.search(r"head", n, re.I) and not re.search(r"end|top|site", n, re.I):
            return j
    return int(np.argmax(skeleton.rest_positions()[:, 1]))


def _chain_length(skeleton: Any, a: int, b: int) -> float:
    """Bone length along the tree path between joints a and b."""
    lengths = np.linalg.norm(np.asarray(skeleton.offsets, dtype=np.float64), axis=1)
    anc_a = [a] + list(skeleton.ancestors(a))
    anc_b = [b] + list(skeleton.ancestors(b))
    common = next(x for x in anc_a if x in anc_b)
    total = 0.0
    for start in (a, b):
        x = start
        while x != common:
            total += lengths[x]
            x = skeleton.parents[x]
    return float(total)


# --------------------------------------------------------------------------------------------- scores
def bone_elevation(positions: Tensor, joint: int, child: int) -> Tensor:
    """Angle in degrees between the bone joint->child and straight down: 0 hanging, 90 level, 180 pointing up.
    ``positions`` (..., T, J, 3), Y up -> (..., T)."""
    d = positions[..., child, :] - positions[..., joint, :]
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(1e-9)
    cos_down = -(d * UP.to(d)).sum(-1)
    return torch.rad2deg(torch.arccos(cos_down.clamp(-1.0, 1.0)))


def rotation_angle(rotations: Tensor, joint: int) -> Tensor:
    """The rotation angle (degrees, 0..180) of one joint's local quaternion, (..., T, J, 4) -> (..., T)."""
    q = rotations[..., joint, :]
    return torch.rad2deg(2.0 * torch.atan2(torch.linalg.vector_norm(q[..., 1:], dim=-1), q[..., 0].abs()))


def window_means(angles: Tensor, window: int = 8, stride: int = 4) -> Tensor:
    """Averages over windows of ``window`` frames every ``stride`` frames: (..., T) -> (..., n_windows)."""
    if angles.shape[-1] < window + stride:
        raise ValueError(f"need at least {window + stride} frames for two windows, got {angles.shape[-1]}")
    return angles.unfold(-1, window, stride).mean(-1)


def rising_fraction(angles: Tensor, window: int = 8, stride: int = 4) -> Tensor:
    """Per sequence, the fraction of windowed averages that exceed the previous one (App. C.2's per-joint score)."""
    avg = window_means(angles, window, stride)
    return (avg[..., 1:] > avg[..., :-1]).to(angles.dtype).mean(-1)


def gral_score(codec: Any, x: Tensor, angle: str = "elevation", window: int = 8, stride: int = 4) -> Tensor:
    """Gradual right-arm lifting score in [0, 1] per motion (see the module docstring)."""
    shoulder, elbow, wrist = find_right_arm(codec.skeleton)
    with torch.no_grad():
        dec = codec.decode(x.detach().float())
    if angle == "elevation":
        a_s = bone_elevation(dec["positions"], shoulder, elbow)
        a_e = bone_elevation(dec["positions"], elbow, wrist)
    elif angle == "rotation":
        a_s = rotation_angle(dec["rotations"], shoulder)
        a_e = rotation_angle(dec["rotations"], elbow)
    else:
        raise ValueError(f"angle must be 'elevation' or 'rotation', not {angle!r}")
    return 0.5 * (rising_fraction(a_s, window, stride) + rising_fraction(a_e, window, stride))


def released_arm_angles(codec: Any, rotations: Tensor) -> tuple[Tensor, Tensor]:
    """The released gral's two angle sequences (degrees, (..., T) each): right upper arm and right clavicle, each
    ``360 - ((rotation angle + rest-pose angle parent-bone/child-bone) mod 360)``."""
    sk = codec.skeleton
    upper, elbow, _ = find_right_arm(sk)
    clavicle = int(sk.parents[upper])
    if clavicle < 0:
        raise UserError(f"the right upper arm {sk.names[upper]!r} needs a parent (the clavicle/shoulder joint)")
    offsets = torch.as_tensor(np.asarray(sk.offsets, dtype=np.float64))
    out = []
    for center, end in ((upper, elbow), (clavicle, upper)):
        to_parent, to_child = -offsets[center], offsets[end]
        cos = (to_parent @ to_child) / ((to_parent.norm() + 1e-20) * (to_child.norm() + 1e-20))
        rest = float(torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0))))
        angle = rotation_angle(rotations.double(), center) + rest
        out.append((360.0 - torch.remainder(angle, 360.0)).to(rotations.dtype))
    return out[0], out[1]


def released_rising_score(angles: Tensor, window: int = 8, stride: int = 4) -> Tensor:
    """The released ``get_monotonous_up_score``: rises between consecutive window averages / number of windows."""
    avg = window_means(angles, window, stride)
    return (avg[..., 1:] > avg[..., :-1]).to(angles.dtype).sum(-1) / avg.shape[-1]


def gral_released_score(codec: Any, x: Tensor, window: int = 8, stride: int = 4) -> Tensor:
    """Gradual right-arm lifting as the authors' released code scores it (see the module docstring)."""
    with torch.no_grad():
        rot = codec.decode(x.detach().float())["rotations"]
    arm, clavicle = released_arm_angles(codec, rot)
    return 0.5 * (released_rising_score(arm, window, stride) + released_rising_score(clavicle, window, stride))


def verticality_score(codec: Any, x: Tensor) -> Tensor:
    """(head height - lowest ankle height) / head-to-ankle bone length, mean over frames: ~1 upright, -1 inverted."""
    sk = codec.skeleton
    head = find_head(sk)
    feet = list(codec.feet)
    if not feet:
        raise UserError("verticality needs foot joints; this model has no contact joints")
    with torch.no_grad():
        pos = codec.decode(x.detach().float())["positions"]
    length = max(_chain_length(sk, head, f) for f in feet)
    low = pos[..., feet, 1].min(-1).values
    return ((pos[..., head, 1] - low) / max(length, 1e-9)).mean(-1)


def speed_score(codec: Any, x: Tensor) -> Tensor:
    """Mean horizontal root speed, in body heights per second."""
    with torch.no_grad():
        root = codec.decode(x.detach().float())["root"]
    v = (root[..., 1:, :] - root[..., :-1, :])[..., [0, 2]]
    return torch.linalg.vector_norm(v, dim=-1).mean(-1) * codec.fps / codec.height


ATTRIBUTES: dict[str, Callable[[Any, Tensor], Tensor]] = {
    "gral": gral_score,
    "gral_released": gral_released_score,
    "verticality": verticality_score,
    "speed": speed_score,
}

ScoreFn = Callable[[Any, Tensor], Tensor]


def score_function(attribute: str | ScoreFn) -> ScoreFn:
    if callable(attribute):
        return attribute
    if attribute not in ATTRIBUTES:
        raise UserError(f"unknown attribute {attribute!r}; choose from {', '.join(ATTRIBUTES)}")
    return ATTRIBUTES[attribute]


def score_latents(g: Any, codec: Any, w: Tensor, attribute: str | ScoreFn, batch: int = 256) -> Tensor:
    """Attribute scores (N,) of the motions of latents w (N, D) or (N, L, D)."""
    fn = score_function(attribute)
    out = [fn(codec, synthesize(g, w[i:i + batch])).float().cpu() for i in range(0, len(w), batch)]
    return torch.cat(out) if out else torch.zeros(0)


# --------------------------------------------------------------------------------------------- boundary
@dataclass
class Boundary:
    """Hyperplane ``w·n + offset = 0`` in W; ``sigma`` is the std of ``w·n`` over the fitted samples (the natural
    unit for α); ``accuracy`` is the SVM's accuracy on a held-out 30% of the two extreme classes."""

    attribute: str
    normal: np.ndarray
    offset: float
    sigma: float
    accuracy: float
    n_samples: int
    ratio: float
    score_low: float
    score_high: float
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["normal"] = self.normal.astype(np.float32).tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Boundary":
        d = dict(d)
        d["normal"] = np.asarray(d["normal"], dtype=np.float64)
        return cls(**d)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict()))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Boundary":
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (OSError, ValueError, TypeError, KeyError) as exc:
            raise UserError(f"{path}: not a boundary file ({exc})") from None


SVM_METHODS = ("ours", "released")


def fit_boundary(w: np.ndarray | Tensor, scores: np.ndarray | Tensor, ratio: float = 0.2, C: float = 1.0,
                 seed: int = 0, attribute: str = "custom", method: str = "ours") -> Boundary:
    """Linear SVM between the top and bottom ``ratio`` of samples by score (InterFaceGAN); unit normal toward high.

    ``method="ours"``: liblinear ``LinearSVC``, accuracy on a held-out 30% of the extremes, then refitted on all of
    them. ``method="released"`` (the authors' ``train_boundary``, from InterFaceGAN): ``SVC(kernel="linear")``
    trained on 70% of each class, accuracy on the other 30%, no refit.
    Raises ``UserError`` when the scores do not separate (all equal)."""
    from sklearn.svm import SVC, LinearSVC  # lazy: scikit-learn costs ~1 s to import; only boundaries need it

    if method not in SVM_METHODS:
        raise ValueError(f"method must be one of {', '.join(SVM_METHODS)}, not {method!r}")

    w = np.asarray(w.detach().cpu() if isinstance(w, Tensor) else w, dtype=np.float64)
    s = np.asarray(scores.detach().cpu() if isinstance(scores, Tensor) else scores, dtype=np.float64).reshape(-1)
    if w.ndim != 2 or w.shape[0] != s.shape[0]:
        raise ValueError(f"w must be (N, D) with one score per row; got {w.shape} and {s.shape}")
    if not 0 < ratio <= 0.5:
        raise ValueError(f"ratio must be in (0, 0.5], got {ratio}")
    n = len(s)
    k = max(2, int(round(n * ratio)))
    order = np.argsort(s, kind="stable")
    low, high = order[:k], order[-k:]
    if s[high].min() <= s[low].max():
        # ties across the cut: split at the median instead, strictly
        med = np.median(s)
        low, high = np.nonzero(s < med)[0], np.nonzero(s > med)[0]
        if len(low) < 2 or len(high) < 2:
            raise UserError(f"attribute {attribute!r} barely varies over {n} samples (all near {med:.3g}); "
                            "no boundary to fit -- sample more motions or pick another attribute")
    x = np.concatenate([w[low], w[high]])
    y = np.concatenate([np.zeros(len(low)), np.ones(len(high))])
    rng = np.random.default_rng(seed)
    if method == "released":  # per class: 70% train, 30% validation; the boundary is the training fit
        trn_parts, val_parts, start = [], [], 0
        for size in (len(low), len(high)):
            idx = start + rng.permutation(size)
            n_trn = max(1, int(size * 0.7))
            trn_parts.append(idx[:n_trn])
            val_parts.append(idx[n_trn:])
            start += size
        trn, val = np.concatenate(trn_parts), np.concatenate(val_parts)
        svm = SVC(kernel="linear", C=C)
        svm.fit(x[trn], y[trn])
        acc = float((svm.predict(x[val]) == y[val]).mean()) if len(val) else float("nan")
    else:
        perm = rng.permutation(len(y))
        n_val = max(1, int(0.3 * len(y)))
        val, trn = perm[:n_val], perm[n_val:]
        svm = LinearSVC(C=C, max_iter=20_000, dual="auto")
        svm.fit(x[trn], y[trn])
        acc = float((svm.predict(x[val]) == y[val]).mean())
        svm.fit(x, y)  # the final boundary uses every extreme sample
    coef = svm.coef_.reshape(-1)
    norm = float(np.linalg.norm(coef))
    if norm == 0:
        raise UserError(f"SVM for {attribute!r} found no direction")
    normal = coef / norm
    proj = w @ normal
    return Boundary(attribute=attribute, normal=normal, offset=float(svm.intercept_[0]) / norm,
                    sigma=float(proj.std()), accuracy=acc, n_samples=n, ratio=ratio,
                    score_low=float(s[low].mean()), score_high=float(s[high].mean()), extra={"svm": method})


def sample_boundary(g: Any, codec: Any, attribute: str | ScoreFn, n: int = 2000, seed: int = 0, ratio: float = 0.2,
                    name: str | None = None, method: str = "ours") -> tuple[Boundary, np.ndarray, np.ndarray]:
    """Sample ``n`` latents (one seeded stream, disjoint from the per-seed latents), score and fit a boundary
    (``method``: see ``fit_boundary``)."""
    w = random_w(g, n, seed)
    s = score_latents(g, codec, w, attribute)
    label = name or (attribute if isinstance(attribute, str) else getattr(attribute, "__name__", "custom"))
    b = fit_boundary(w, s, ratio=ratio, seed=seed, attribute=label, method=method)
    return b, w.cpu().numpy(), s.numpy()


def edit_latents(w: Tensor, normal: np.ndarray | Tensor, alphas: Sequence[float]) -> Tensor:
    """``w + α n`` for each α: (A, *w.shape). W+ latents move every layer by the same step."""
    n = torch.as_tensor(np.asarray(normal), dtype=w.dtype, device=w.device)
    if n.shape[-1] != w.shape[-1]:
        raise ValueError(f"normal has {n.shape[-1]} dims, latent {w.shape[-1]}")
    a = torch.as_tensor(list(alphas), dtype=w.dtype, device=w.device)
    return w.unsqueeze(0) + a.view(-1, *([1] * w.ndim)) * n


# --------------------------------------------------------------------------------------------- report
@dataclass
class EditReport:
    """Scores of held-out seeds edited along a boundary: ``scores[i, j]`` for seed i at ``alphas[j]`` (α in W
    units; ``alphas_sigma`` the same in units of the boundary's sigma)."""

    attribute: str
    seeds: list[int]
    alphas: list[float]
    alphas_sigma: list[float]
    scores: np.ndarray
    mean: list[float]
    monotonic: bool
    seeds_monotonic: float
    spearman: float

    def to_dict(self) -> dict:
        d = asdict(self)
        d["scores"] = self.scores.tolist()
        return d

    def summary(self) -> str:
        pts = ", ".join(f"{a:+.2g}σ: {m:.3f}" for a, m in zip(self.alphas_sigma, self.mean))
        return (f"{self.attribute}: mean score vs α [{pts}]; mean rises monotonically: "
                f"{'yes' if self.monotonic else 'NO'}; per-seed monotone: {self.seeds_monotonic:.0%}; "
                f"Spearman(α, score) = {self.spearman:.2f} over {len(self.seeds)} held-out seeds")


def _is_monotone(v: np.ndarray, tol: float = 1e-9) -> bool:
    return bool(np.all(np.diff(v) >= -tol))


def edit_report(g: Any, codec: Any, boundary: Boundary, seeds: Sequence[int], alphas_sigma: Sequence[float],
                attribute: str | ScoreFn | None = None) -> EditReport:
    """Edit held-out seeds by ``α = a · sigma`` for each ``a`` in ``alphas_sigma`` and score them."""
    from scipy.stats import spearmanr  # lazy: scipy.stats costs ~0.5 s to import

    attribute = boundary.attribute if attribute is None else attribute
    alphas_sigma = [float(a) for a in alphas_sigma]
    if sorted(alphas_sigma) != alphas_sigma or len(set(alphas_sigma)) < 2:
        raise UserError("alphas must be at least two increasing values")
    alphas = [a * boundary.sigma for a in alphas_sigma]
    w = seed_w(g, list(seeds))
    edited = edit_latents(w, boundary.normal, alphas)  # (A, S, D)
    a_n, s_n = edited.shape[:2]
    sc = score_latents(g, codec, edited.reshape(a_n * s_n, -1), attribute).reshape(a_n, s_n).T.numpy()
    mean = sc.mean(0)
    rho = spearmanr(np.repeat([alphas], s_n, 0).reshape(-1), sc.reshape(-1)).statistic
    name = attribute if isinstance(attribute, str) else boundary.attribute
    return EditReport(attribute=name, seeds=[int(s) for s in seeds], alphas=alphas, alphas_sigma=alphas_sigma,
                      scores=sc, mean=[float(m) for m in mean], monotonic=_is_monotone(mean),
                      seeds_monotonic=float(np.mean([_is_monotone(r) for r in sc])),
                      spearman=float(rho) if math.isfinite(float(rho)) else 0.0)


def plot_report(report: EditReport, path: str | Path) -> Path:
    """PNG of score vs α: each held-out seed thin, the mean thick."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(5, 3.6), dpi=120)
    for row in report.scores:
        ax.plot(report.alphas_sigma, row, color="0.75", lw=0.8)
    ax.plot(report.alphas_sigma, report.mean, color="C0", lw=2.5, marker="o", label="mean over seeds")
    ax.set_xlabel("α (units of σ of w·n)")
    ax.set_ylabel(f"{report.attribute} score")
    ax.set_title(f"{report.attribute}: Spearman {report.spearman:.2f}, monotone mean: "
                 f"{'yes' if report.monotonic else 'no'}", fontsize=9)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


__all__ = ["find_right_arm", "find_head", "bone_elevation", "rotation_angle", "window_means", "rising_fraction",
           "gral_score", "gral_released_score", "released_arm_angles", "released_rising_score", "SVM_METHODS",
           "verticality_score", "speed_score", "ATTRIBUTES", "score_function", "score_latents",
           "Boundary", "fit_boundary", "sample_boundary", "edit_latents", "EditReport", "edit_report",
           "plot_report"]
