"""Sampling from a trained GANimator: any length, crowds, style transfer, key-frame editing, trajectory control,
streaming (the paper's Algorithm 1), BVH/GIF output, IK contact clean-up and the single-sequence metrics.

All levels live on fixed time grids (level ``l`` of an ``N``-frame output has ``ceil(N * rate_l)`` frames, and
frame ``i`` of it always sits at the same instant), so a longer output is an extension of a shorter one except
near its end. :class:`TrajectoryStream` relies on that: when new trajectory frames arrive it recomputes only a
window covering the new frames plus the receptive field at every level, and emits only frames that no future
input can change — exactly the frames a full recomputation would produce.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence as Seq

import numpy as np
import torch
from torch import Tensor

from modi.core.ik import fix_foot_contact
from modi.core.kinematics import forward_kinematics
from modi.core.rotations import quat_to_euler
from modi.errors import UserError
from modi.evaluation.single import rotation_features, single_sequence_metrics
from modi.io.bvh import Bvh
from modi.io.formats import check_finite, save_motion
from modi.models.ganimator.data import K, coarsest_needed, features_to_motion, load_sequence, resample
from modi.models.ganimator.data import Sequence as Clip
from modi.models.ganimator.editing import min_output_frames
from modi.models.ganimator.networks import GanimatorModel, make_noise, synthesize
from modi.models.ganimator.training import load_model, run_summary

# ------------------------------------------------------------------------------------------- decoding / output


def decode(model: GanimatorModel, feats: Tensor, base: int = 0, root_start: Tensor | None = None
           ) -> tuple[Tensor, Tensor, Tensor]:
    """Features ``(6, E, T)`` -> local quats ``(T, J, 4)``, root ``(T, 3)`` (starting at ``root_start``, by
    default where the training clip started), contact labels ``(T, C)`` in [0, 1]."""
    start = model.seqs[base].root_start if root_start is None else root_start
    quats, root, contacts = features_to_motion(feats.detach().cpu().to(torch.float32), model.n_joints,
                                               start.detach().cpu().to(torch.float32), sixd=model.seqs[base].sixd)
    return quats, root, contacts.clamp(0.0, 1.0)


def positions_of(seq: Clip, quats: Tensor, root: Tensor) -> Tensor:
    pos, _ = forward_kinematics(quats.to(torch.float64), torch.as_tensor(seq.skeleton.offsets), seq.skeleton.parents,
                                root.to(torch.float64))
    return pos


def fix_contacts(seq: Clip, quats: Tensor, root: Tensor, contacts: Tensor) -> tuple[Tensor, Tensor]:
    """IK clean-up: pin each foot while its predicted label is on (``modi.core.ik.fix_foot_contact``)."""
    if not seq.feet:
        return quats, root

    q, r = fix_foot_contact(quats.to(torch.float64), root.to(torch.float64), seq.skeleton, list(seq.feet),
                            contacts > 0.5, tol=1e-5 * seq.size)
    return q.to(quats.dtype), r.to(root.dtype)


def to_bvh(seq: Clip, quats: Tensor, root: Tensor, fps: float | None = None):
    """A ``modi.io.bvh.Bvh`` in the *source file's* units (root: 6 channels, other joints: 3 rotation channels)."""
    sk = seq.skeleton
    inv = 1.0 / seq.scale
    orders = list(sk.rotation_orders or ["ZYX"] * sk.n_joints)
    T, J = quats.shape[:2]
    eul = torch.empty(T, J, 3, dtype=torch.float64)
    q = quats.to(torch.float64)
    for order in set(orders):
        idx = [j for j, o in enumerate(orders) if o == order]
        eul[:, idx] = quat_to_euler(q[:, idx], order)
    channels, cols = [], []
    for j in range(J):
        rot = [f"{a}rotation" for a in orders[j]]
        if j == 0:
            channels.append(["Xposition", "Yposition", "Zposition"] + rot)
            cols.append(root.to(torch.float64) * inv)
        else:
            channels.append(rot)
        cols.append(eul[:, j])
    motion = torch.cat(cols, dim=1).numpy()
    return Bvh(names=list(sk.names), parents=list(sk.parents), offsets=sk.offsets * inv, channels=channels,
               end_sites={k: np.asarray(v) * inv for k, v in sk.end_sites.items()},
               frame_time=1.0 / float(fps or seq.fps), motion=motion)


def write_bvh(seq: Clip, quats: Tensor, root: Tensor, path: str | Path, contacts: Tensor | None = None) -> Path:
    """Write the motion at ``path`` in the requested ``--format`` formats (``modi.io.formats``); ``contacts`` (T, F) in
    ``seq.feet`` order go into glTF extras. Returns the first format's path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = None
    if contacts is not None and seq.feet:
        c = contacts.detach().cpu().numpy()
        labels = {seq.skeleton.names[f]: c[:, k] for k, f in enumerate(seq.feet)}
    return save_motion(to_bvh(seq, quats, root), path, contacts=labels)


# ------------------------------------------------------------------------------------------- metrics


def rotation_frames(quats: Tensor) -> Tensor:
    """Per-frame pose vectors for the single-sequence metrics (6D of every local rotation, as the authors)."""
    return rotation_features(quats.to(torch.float64), representation="6d")


def metrics_against_sources(model: GanimatorModel, samples: Seq[Tensor]) -> dict:
    """Coverage (30-frame windows, threshold 2.0), global diversity (PNN, segments >= 30) and local diversity
    (15-frame windows) of decoded samples against each training clip."""
    gens = [rotation_frames(decode(model, s)[0]) for s in samples]
    out = {}
    for seq in model.seqs:
        src = rotation_frames(seq.rotations())
        r = single_sequence_metrics(gens, src)
        out[seq.name] = {k: float(r[k]) for k in ("coverage", "global_diversity", "local_diversity")}
    return out


def evaluate_run(run: str | Path, n: int = 10, n_frames: int | None = None, seed: int = 0) -> dict:
    """Sample ``n`` motions and report the metrics per training clip, plus the run's schedule and timings."""
    model = load_model(run)
    T = n_frames or model.seqs[0].n_frames
    gen = torch.Generator().manual_seed(seed)
    samples = [model.sample(T, 1, generator=gen)[0] for _ in range(n)]
    rec = [model.reconstruct(m)[0] for m in range(len(model.seqs))]
    metrics = metrics_against_sources(model, samples)
    for f in metrics.values():  # the number of samples and their length beside every figure
        f.update(samples=n, frames=T)
    figures = {"protocol": "ours", "samples": n, "frames": T, "metrics": metrics}
    figures["reconstruction_l1"] = {s.name: float((r - s.features).abs().mean()) for s, r in zip(model.seqs, rec)}
    summary = run_summary(run)
    figures["levels"] = summary["lengths"]
    figures["blocks"] = [{"levels": b, "seconds": round(s, 1)} for b, s in zip(summary["blocks"],
                                                                               summary["block_seconds"])]
    figures["preset"] = summary["config"]["preset"]
    figures["iterations_per_block"] = summary["block_iterations"]
    return figures


# ------------------------------------------------------------------------------------------- applications


def coarse_from_clip(model: GanimatorModel, clip: Clip, n_frames: int, frame_step: float = 1.0,
                     base: int = 0, level: int = 0) -> Tensor:
    """A clip as level ``level`` of an ``n_frames`` output ``(1, 6, E, L)`` (the coarsest by default).

    ``frame_step``: output frames per clip frame (1 for a content motion at the model's rate; ``n_frames / F`` for
    ``F`` key-frames spread over the output). Root displacement is rescaled to per-output-frame units.
    """
    f = clip.features.clone()
    J = model.n_joints
    f[0, J] = f[0, J] / frame_step
    f[2, J] = f[2, J] / frame_step
    L = model.level_lengths(n_frames, base)[level]
    F = f.shape[-1]
    return (resample(f, L, F / L) if L != F else f).unsqueeze(0).to(model.device)


def check_content_level(model: GanimatorModel, level: int) -> int:
    """The level a content clip is injected at: 0 (style transfer) up to the level below the finest."""
    top = model.n_levels - 2
    if not 0 <= int(level) <= top:
        raise UserError(f"--content-level {level}: this run has {model.n_levels} levels; inject at 0 (style "
                        f"transfer) to {top} (harmonisation keeps more of the content the finer the level)")
    return int(level)


def style_transfer(model: GanimatorModel, content: str | Path, seed: int = 0, level: int = 0) -> Tensor:
    """The content motion at pyramid level ``level`` with the trained clip's finer detail: ``(1, 6, E, T)``.

    Level 0 is style transfer: only the content's coarse motion survives. A finer level is harmonisation (as
    SinGAN's): a clip pasted together by hand keeps its poses and timing, and the levels above ``level``
    regenerate the detail in the run's style, which smooths the seams."""
    level = check_content_level(model, level)
    clip = load_sequence(content, model.cfg, like=model.seqs[0])
    coarse = coarse_from_clip(model, clip, clip.n_frames, level=level)
    return model.sample(clip.n_frames, 1, replace={level: coarse}, generator=torch.Generator().manual_seed(seed))


def keyframe_edit(model: GanimatorModel, keyframes: str | Path, n_frames: int | None = None, seed: int = 0) -> Tensor:
    """Edited coarse-level poses (a BVH with one frame per coarse frame) -> full-rate motion through them."""
    clip = load_sequence(keyframes, model.cfg, like=model.seqs[0])
    T = n_frames or model.seqs[0].n_frames
    coarse = coarse_from_clip(model, clip, T, frame_step=T / clip.n_frames)
    return model.sample(T, 1, replace={0: coarse}, generator=torch.Generator().manual_seed(seed))


def trajectory_conditions(model: GanimatorModel, traj: Tensor, n_frames: int) -> list[Tensor]:
    """Full-rate constraint ``(1, 6, 2, T)`` -> one per level on the fixed grids."""
    rates = model.rates[0]
    lengths = model.level_lengths(n_frames)
    return [resample(traj, L, 1.0 / r) if L != n_frames else traj for L, r in zip(lengths, rates)]


def load_trajectory(model: GanimatorModel, path: str | Path) -> tuple[Tensor, Tensor]:
    """Root trajectory (root motion + root rotation entities) of a BVH ``(1, 6, 2, T)`` and its start position."""
    clip = load_sequence(path, model.cfg, like=model.seqs[0])
    return clip.features[:, model.cond_entities].unsqueeze(0).to(model.device), clip.root_start


def sample_trajectory(model: GanimatorModel, n_frames: int, seed: int = 0) -> Tensor:
    """A random trajectory from the unconditional run a conditional model was trained against."""
    src = getattr(model, "cond_source", None)
    if src is None:
        raise UserError("this conditional run carries no trajectory source; pass --trajectory BVH")
    full = src.sample(n_frames, 1, fine_noise=True, generator=torch.Generator().manual_seed(seed))
    return full[:, :, model.cond_entities]


def conditional_generate(model: GanimatorModel, traj: Tensor, seed: int = 0) -> Tensor:
    if not model.cond_entities:
        raise UserError("this run is not trajectory-conditioned (train it with --conditional-from RUN)")
    T = traj.shape[-1]
    conds = trajectory_conditions(model, traj, T)
    return model.sample(T, 1, conds=conds, generator=torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------------------- streaming


def _window_resample(x: Tensor, x_start: int, L_in: int, out_start: int, out_stop: int, ratio: float) -> Tensor:
    """:func:`resample` evaluated only for output frames ``[out_start, out_stop)`` from a window of the input that
    begins at frame ``x_start`` of an ``L_in``-frame signal."""
    i = torch.arange(out_start, out_stop, dtype=torch.float64)
    pos = ((i + 0.5) * ratio - 0.5).clamp(0.0, L_in - 1)
    lo = pos.floor().long()
    hi = (lo + 1).clamp(max=L_in - 1)
    w = (pos - lo.to(torch.float64)).to(x.dtype).to(x.device)
    lo_w, hi_w = (lo - x_start).to(x.device), (hi - x_start).to(x.device)
    if int(lo_w.min()) < 0 or int(hi_w.max()) >= x.shape[-1]:
        raise RuntimeError("streaming window does not cover the resampling support (internal error)")
    return x.index_select(-1, lo_w) * (1 - w) + x.index_select(-1, hi_w) * w


class TrajectoryStream:
    """Interactive trajectory-conditioned generation (Algorithm 1 of the paper), exact by construction.

    ``extend(segment)`` appends root-trajectory frames ``(1, 6, 2, n)`` and returns the newly *final* output
    frames ``(1, 6, E, k)``: those whose receptive field, through every level, no longer reaches the end of the
    input. Only a window of each level (the new frames plus the receptive field) is recomputed. ``finish()``
    emits the remaining tail. Noise is drawn per fixed block of frames from ``seed``, so the result does not
    depend on how the trajectory was cut into segments and equals :meth:`offline` on the whole trajectory.
    """

    NOISE_BLOCK = 64

    def __init__(self, model: GanimatorModel, seed: int = 0, fine_noise: bool = False) -> None:
        if not model.cond_entities:
            raise UserError("streaming needs a trajectory-conditioned run (train with --conditional-from RUN)")
        self.model = model
        self.seed = int(seed)
        self.fine_noise = fine_noise
        self.rates = list(model.rates[0])
        self.R = model.gens[0].receptive_radius
        self.traj: Tensor | None = None
        self.emitted = 0
        self.windows: list[int] = []  # frames recomputed per level on the last call (for inspection)

    # noise: block b of level l comes from its own generator, so any prefix is reproducible
    def _noise(self, level: int, start: int, stop: int) -> Tensor | None:
        if level > 0 and not self.fine_noise:
            return None
        amp = self.model.amps[0][level]
        B = self.NOISE_BLOCK
        chunks = []
        for b in range(start // B, (max(stop, start + 1) - 1) // B + 1):
            g = torch.Generator().manual_seed(self.seed * 1000003 + level * 7919 + b)
            chunks.append(torch.randn(B, generator=g))
        z = torch.cat(chunks)[start - (start // B) * B: stop - (start // B) * B]
        return (z * amp).view(1, 1, 1, -1).to(self.model.device)

    def noises(self, lengths: Seq[int]) -> list[Tensor | None]:
        return [self._noise(l, 0, L) for l, L in enumerate(lengths)]

    def _lengths(self, N: int) -> list[int]:
        return [max(1, math.ceil(N * r - 1e-6)) for r in self.rates]

    def stable_frames(self, N: int) -> int:
        """How many final frames of an ``N``-frame input can no longer change when more input arrives."""
        lengths = self._lengths(N)
        U_prev = None
        U = 0
        for l, (L, r) in enumerate(zip(lengths, self.rates)):
            # condition at this level: frame j reads fine frames floor(src)+{0,1}; final once both exist
            j = np.arange(L)
            src = np.clip((j + 0.5) / r - 0.5, 0, None)
            ok = np.floor(src) + 1 <= N - 1 if r < 1 else j < N
            S = int(np.argmin(ok)) if not ok.all() else L
            if l > 0:
                rho = self.rates[l - 1] / r
                src_up = np.clip((j + 0.5) * rho - 0.5, 0, None)
                ok_up = np.floor(src_up) + 1 < U_prev
                S = min(S, int(np.argmin(ok_up)) if not ok_up.all() else L)
            U = max(0, min(S, L) - self.R)
            U_prev = U
        return U

    def _run(self, N: int, e0: int) -> Tensor:
        """Final-level frames ``[e0, N)`` of the ``N``-frame input, computing only the needed windows."""
        m = self.model
        lengths = self._lengths(N)
        n = len(lengths)
        need = [0] * n
        win = [0] * n
        need[-1] = e0
        for l in range(n - 1, -1, -1):
            win[l] = max(0, need[l] - self.R)
            if l > 0:
                rho = self.rates[l - 1] / self.rates[l]
                pos = max(0.0, (win[l] + 0.5) * rho - 0.5)
                need[l - 1] = min(int(math.floor(pos)), lengths[l - 1] - 1)
        self.windows = [L - w for L, w in zip(lengths, win)]
        prev = None
        E = m.n_entities
        for l in range(n):
            L, w = lengths[l], win[l]
            if l == 0:
                base = torch.zeros(1, K, E, L - w, device=m.device)
            else:
                base = _window_resample(prev, win[l - 1], lengths[l - 1], w, L, self.rates[l - 1] / self.rates[l])
            cond = _window_resample(self.traj, 0, N, w, L, 1.0 / self.rates[l])
            z = self._noise(l, w, L)
            x = base if z is None else base + z
            with torch.no_grad():
                prev = m.gens[l](x, base, cond) + base
        return prev[..., e0 - win[-1]:]

    def extend(self, segment: Tensor) -> Tensor:
        seg = segment.to(self.model.device, torch.float32)
        if seg.ndim != 4 or seg.shape[:3] != (1, K, len(self.model.cond_entities)):
            raise ValueError(f"segment must be (1, {K}, {len(self.model.cond_entities)}, n), got {tuple(seg.shape)}")
        self.traj = seg if self.traj is None else torch.cat([self.traj, seg], dim=-1)
        N = self.traj.shape[-1]
        stop = self.stable_frames(N)
        if stop <= self.emitted or N <= self.R:
            return torch.zeros(1, K, self.model.n_entities, 0, device=self.model.device)
        out = self._run(N, self.emitted)[..., : stop - self.emitted]
        self.emitted = stop
        return out

    def finish(self) -> Tensor:
        """Emit everything not yet emitted (the end of the input is now known to be the end)."""
        if self.traj is None:
            raise ValueError("nothing streamed yet")
        N = self.traj.shape[-1]
        out = self._run(N, self.emitted)
        self.emitted = N
        return out

    def offline(self, traj: Tensor) -> Tensor:
        """The same generator run on the whole trajectory at once (what streaming must reproduce)."""
        m = self.model
        N = traj.shape[-1]
        lengths = self._lengths(N)
        conds = [resample(traj.to(m.device, torch.float32), L, 1.0 / r) for L, r in zip(lengths, self.rates)]
        with torch.no_grad():
            return synthesize(m.gens, self.rates, lengths, self.noises(lengths), m.n_entities, conds=conds)[-1]


# ------------------------------------------------------------------------------------------- the command


def check_generation_inputs(model: GanimatorModel, frames: int | None = None, content: str | Path | None = None,
                            keyframes: str | Path | None = None, trajectory: str | Path | None = None,
                            content_level: int = 0) -> None:
    """Refuse an output length or an input clip too short for the run's pyramid (``UserError`` naming the option),
    before anything is generated or written."""
    need, n_min = coarsest_needed(model.cfg), min_output_frames(model)
    why = (f"the coarsest pyramid level ({model.rates[0][0]:.3g} of the length) must have {need} frames or more for "
           f"the convolutions' reflect padding of {need - 1} frames")
    if frames is not None and frames < n_min:
        raise UserError(f"--frames {frames} is too short for this run: at least {n_min} frames, because {why}")
    if sum(x is not None for x in (content, keyframes, trajectory)) > 1:
        raise UserError("use only one of --content, --keyframes, --trajectory")
    if content_level:
        if content is None:
            raise UserError("--content-level goes with --content CLIP")
        check_content_level(model, content_level)
    for opt, path in (("--content", content), ("--keyframes", keyframes), ("--trajectory", trajectory)):
        if path is None:
            continue
        if not Path(path).is_file():
            raise UserError(f"{opt} {path}: no such BVH file")
        clip = load_sequence(path, model.cfg, like=model.seqs[0])
        if opt == "--keyframes":
            if clip.n_frames < 2:
                raise UserError(f"--keyframes {path}: {clip.n_frames} frame at {clip.fps:g} fps (after resampling); "
                                "key-frame editing needs at least 2 key-frames (the root motion is their difference)")
        elif clip.n_frames < n_min:
            raise UserError(f"{opt} {path}: {clip.n_frames} frames at {clip.fps:g} fps (after resampling) is too short "
                            f"for this run: at least {n_min} frames, because {why}")


def sample_features(model: GanimatorModel, n: int = 1, frames: int | None = None, seed: int = 0, *,
                    content: str | Path | None = None, keyframes: str | Path | None = None,
                    trajectory: str | Path | None = None, stream: int = 0, fine_noise: bool = False,
                    content_level: int = 0) -> tuple[list[Tensor], Tensor | None, str]:
    """What ``modi ganimator generate`` samples: ``(features (6, E, T) per motion, root start or None, mode)``.

    Random motions draw from one generator seeded with ``seed``; style transfer (``content``; ``content_level`` >
    0: harmonisation), key-frame editing (``keyframes``) and trajectory control (``trajectory``, or a trajectory
    sampled from the run's source for a
    conditional run) use ``seed + i`` for motion ``i``. ``stream`` feeds a trajectory in segments of that many
    frames (:class:`TrajectoryStream`, equal to the offline result)."""
    seq = model.seqs[0]
    if n < 1:
        raise UserError("--n must be at least 1")
    if frames is not None and frames < 2:
        raise UserError("--frames must be at least 2")
    if sum(x is not None for x in (content, keyframes, trajectory)) > 1:
        raise UserError("use only one of --content, --keyframes, --trajectory")
    samples: list[Tensor] = []
    start = None  # root position of frame 0: the input's for content / key-frames / trajectories
    if content:
        start = load_sequence(content, model.cfg, like=seq).root_start
        for i in range(n):
            samples.append(style_transfer(model, content, seed=seed + i, level=content_level)[0])
        mode = "style transfer" if content_level == 0 else f"harmonisation (level {content_level})"
    elif keyframes:
        start = load_sequence(keyframes, model.cfg, like=seq).root_start
        for i in range(n):
            samples.append(keyframe_edit(model, keyframes, frames, seed=seed + i)[0])
        mode = "key-frame editing"
    elif trajectory or model.cond_entities:
        if not model.cond_entities:
            raise UserError("--trajectory needs a trajectory-conditioned run (train with --conditional-from RUN)")
        for i in range(n):
            if trajectory:
                traj, start = load_trajectory(model, trajectory)
            else:
                traj = sample_trajectory(model, frames or seq.n_frames, seed=seed + i)
            if stream:
                st = TrajectoryStream(model, seed=seed + i, fine_noise=fine_noise)
                parts = [st.extend(traj[..., s:s + stream]) for s in range(0, traj.shape[-1], stream)]
                parts.append(st.finish())
                samples.append(torch.cat(parts, dim=-1)[0])
            else:
                samples.append(conditional_generate(model, traj, seed=seed + i)[0])
        mode = "trajectory" + (" (streamed)" if stream else "")
    else:
        gen = torch.Generator().manual_seed(seed)
        T = frames or seq.n_frames
        for _ in range(n):
            samples.append(model.sample(T, 1, fine_noise=fine_noise, generator=gen)[0])
        mode = "random"
    check_finite(samples)
    return samples, start, mode


__all__ = ["decode", "positions_of", "fix_contacts", "to_bvh", "write_bvh", "metrics_against_sources",
           "evaluate_run", "coarse_from_clip", "style_transfer", "keyframe_edit", "trajectory_conditions",
           "load_trajectory", "sample_trajectory", "conditional_generate", "TrajectoryStream", "sample_features",
           "check_generation_inputs", "min_output_frames", "rotation_frames", "make_noise"]
