"""The metrics of ``modi eval`` from Python, without the glue: distribution metrics (FID, KID, precision, recall,
diversity) and plausibility of MoDi samples against real clips, and GANimator's single-sequence coverage and
diversity against the source, with SinMDM's scorecard (SIFID, inter/intra diversity, harmonic mean) beside them."""
from __future__ import annotations

import os
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Sequence, Union

import numpy as np

from modi.api._util import set_threads
from modi.api.generator import ModiGenerator
from modi.core.kinematics import bvh_positions
from modi.data.motion import Motion
from modi.errors import UserError
from modi.evaluation.distribution import distribution_metrics
from modi.evaluation import features as F
from modi.evaluation.features import FeatureExtractor, load_extractor
from modi.evaluation.plausibility import aggregate, guess_feet, planted_heights, plausibility_metrics
from modi.evaluation.report import to_markdown, write_json, write_reports
from modi.evaluation.scorecard import HM_NORMALISERS, scorecard_metrics
from modi.evaluation.single import bare_name, shared_joints, shared_pose_frames, single_sequence_metrics
from modi.faults import existing_file, unique_names
from modi.io import bvh as bvh_io

MotionSource = Union[Motion, str, os.PathLike]


def _extractor(features: FeatureExtractor | str | os.PathLike) -> FeatureExtractor:
    return features if isinstance(features, FeatureExtractor) else load_extractor(features)


def _real_clips(ext: FeatureExtractor, files: Sequence[Path]) -> list[np.ndarray]:
    out = []
    for f in files:
        b = bvh_io.load(f)
        out.append(ext.clip_positions(bvh_positions(b), list(b.names), float(b.fps)))
    return out


def _plausibility_set(clips: list[np.ndarray], ext: FeatureExtractor, ref: list[np.ndarray]) -> dict[str, Any]:
    """Mean plausibility figures of clips in the extractor's joints and fps; planted foot heights from ``ref``."""
    c = ext.config
    feet = guess_feet(c.joint_names)
    heights = planted_heights(ref, feet, c.up_axis)
    per = [plausibility_metrics(x, c.fps, feet, up_axis=c.up_axis, foot_heights=heights, body_height=c.body_height)
           for x in clips if len(x) >= 4]
    if not per:
        raise UserError("no clip has the 4 frames plausibility needs")
    out = aggregate(per)
    out["feet"] = [c.joint_names[f] for f in feet]
    out["planted_heights"] = heights
    return out


def evaluate(samples: ModiGenerator | str | os.PathLike | Sequence[Motion], *,
             features: FeatureExtractor | str | os.PathLike, data: str | os.PathLike, n: int = 2000, seed: int = 0,
             psi: float = 1.0, ik: bool = False, stride: int = 32, k: int = 3, kid_blocks: int = 10,
             diversity_pairs: int = 200) -> dict[str, Any]:
    """``modi eval gen``: FID, KID, precision, recall and diversity of generated motions against the windows of every
    BVH clip under ``data`` (in the feature extractor's space, ``modi eval train-features``), plus plausibility (foot
    skating, floating, jitter) of both sets.

    ``samples``: a generator (or its checkpoint path), from which ``n`` motions of ``seed`` are sampled (``psi``,
    ``ik`` as :meth:`ModiGenerator.sample`), or motions already made. Returns the report ``modi eval gen`` prints.
    Cost: sampling, the extractor on every window (seconds for a few thousand on a CPU) and the metrics."""
    if n < 4:
        raise UserError(f"--n must be at least 4, got {n}")
    ext = _extractor(features)
    root = Path(data)
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() == ".bvh") if root.is_dir() else []
    if not files:
        raise UserError(f"no .bvh files under {root}")
    t0 = time.perf_counter()
    real = _real_clips(ext, files)
    what: dict[str, Any] = {}
    if isinstance(samples, (str, os.PathLike)):
        what["ckpt"] = str(samples)
        samples = ModiGenerator.from_checkpoint(samples)
    if hasattr(samples, "generate"):  # a ModiGenerator (or anything that generates like one)
        what.setdefault("ckpt", getattr(samples, "path", None))
        motions = samples.generate(n, seed=seed, psi=psi, ik=ik)
    else:
        motions = list(samples)
        if not motions:
            raise UserError("no motions to evaluate")
    gen = [ext.clip_positions(m.positions(), m.skeleton.names, m.fps) for m in motions]
    f_real = ext.features(ext.windows(real, stride))
    f_gen = ext.features(ext.windows(gen, tail=False))  # a 64-frame MoDi sample is exactly one window
    dist = distribution_metrics(f_real, f_gen, k=k, kid_blocks=kid_blocks, diversity_pairs=diversity_pairs,
                                seed=seed)
    return {
        **what,
        "features": str(features) if not isinstance(features, FeatureExtractor) else "(in memory)",
        "n_generated_motions": len(motions),
        "psi": psi,
        "ik": bool(ik),
        "distribution (generated vs real)": dist,
        "plausibility (generated)": _plausibility_set(gen, ext, real),
        "plausibility (real)": _plausibility_set(real, ext, real),
        "seconds": time.perf_counter() - t0,
    }


def evaluate_real(data: str | os.PathLike, *, features: FeatureExtractor | str | os.PathLike, stride: int = 32,
                  k: int = 3, kid_blocks: int = 10, diversity_pairs: int = 200, seed: int = 0) -> dict[str, Any]:
    """``modi eval real``: the floor a generator is judged against -- the distribution metrics of the extractor's
    held-out clips against its training clips (both under ``data``), and the held-out clips' plausibility."""
    ext = _extractor(features)
    root = Path(data)
    if not root.is_dir():
        raise UserError(f"data folder not found: {root}")
    train_files = ext.info.get("train_files")
    held_files = ext.info.get("heldout_files")
    if not train_files or not held_files:
        raise UserError(f"{features} holds no train/held-out split (was it trained with held-out clips?)")
    missing = [f for f in train_files + held_files if not (root / f).is_file()]
    if missing:
        raise UserError(f"{len(missing)} clip(s) of the extractor's split are not under {root}, e.g. {missing[0]}")
    t0 = time.perf_counter()
    train = _real_clips(ext, [root / f for f in train_files])
    held = _real_clips(ext, [root / f for f in held_files])
    f_train = ext.features(ext.windows(train, stride))
    f_held = ext.features(ext.windows(held, stride))
    return {
        "data": str(root),
        "features": str(features) if not isinstance(features, FeatureExtractor) else "(in memory)",
        "settings": {"stride": stride, "k": k, "kid_blocks": kid_blocks, "diversity_pairs": diversity_pairs,
                     "seed": seed},
        "extractor_heldout_top1": ext.info.get("val_top1"),
        "distribution (held-out vs train)": distribution_metrics(f_train, f_held, k=k, kid_blocks=kid_blocks,
                                                                 diversity_pairs=diversity_pairs, seed=seed),
        "plausibility (held-out clips)": _plausibility_set(held, ext, train),
        "seconds": time.perf_counter() - t0,
    }


def _as_motion(item: MotionSource, fps: float | None = None, remedy: str = "") -> Motion:
    """A Motion, or a BVH read as one; ``fps`` replaces the header's rate, else the header must be plausible."""
    if isinstance(item, Motion):
        return item if fps is None else Motion(item.skeleton, item.rotations, item.root_positions, fps, item.unit)
    p = Path(item)
    if not p.is_file():
        raise UserError(f"{p} is a folder, not a BVH file" if p.is_dir() else f"no such BVH file: {p}")
    b = bvh_io.load(p, check_frame_time=False)  # checked here, to name the option that fixes it
    if fps is not None:
        b.frame_time = 1.0 / fps
    elif not 0 < b.frame_time < 0.5:
        raise UserError(f"{p}: implausible Frame Time {b.frame_time:g} s in the header (the rate must be above "
                        f"2 fps){remedy}")
    return Motion.from_bvh(b)


def _bvh_files(items: Sequence[MotionSource]) -> list[MotionSource]:
    """Motions and paths as given, a folder replaced by the ``.bvh`` files directly inside it (sorted by name)."""
    out: list[MotionSource] = []
    for g in items:
        if not isinstance(g, Motion) and Path(g).is_dir():
            files = sorted(p for p in Path(g).iterdir() if p.suffix.lower() == ".bvh" and p.is_file())
            if not files:
                raise UserError(f"no .bvh files in the folder {g}")
            out.extend(files)
        else:
            out.append(g)
    return out


def _extractor_clip(ext: FeatureExtractor, m: Motion, label: str, unit: str) -> np.ndarray:
    """``m``'s global joint positions in ``unit`` (the source's: a file another tool wrote in metres meets a
    centimetre source) on the extractor's joints, matched by bare name (namespace prefix ignored)."""
    by_bare = {bare_name(n): n for n in ext.config.joint_names}
    names = [by_bare.get(bare_name(n), n) for n in m.skeleton.names]
    try:
        return ext.clip_positions(m.positions(unit).detach().cpu().numpy(), names, m.fps)
    except UserError as exc:
        raise UserError(f"{label}: {exc}") from None


def evaluate_single(generated: Sequence[MotionSource], source: MotionSource, *, fps: float = 30.0,
                    gen_fps: float | None = None, joints: str = "reduced", representation: str = "6d",
                    window: int = 30, threshold: float = 2.0, min_segment: int = 30,
                    local_window: int = 15, features: FeatureExtractor | str | os.PathLike | None = None,
                    sifid_stride: int = 8, normalisers: Sequence[float] = HM_NORMALISERS) -> dict[str, Any]:
    """``modi eval single``: GANimator's coverage (``window``-frame windows within ``threshold``), global diversity
    (patched nearest neighbour, segments >= ``min_segment``) and local diversity (``local_window``-frame windows) of
    generated motions (Motions, BVH paths, or folders of BVH files) against the ``source`` clip, as the GANimator
    authors measure them: at ``fps``, on the (``joints="reduced"``) joints every file shares, matched by name.
    ``gen_fps`` is the generated files' true rate when their header is wrong.

    With ``features`` (a feature-extractor file from ``modi eval train-features`` on the source's rig, or one
    loaded) it adds SinMDM's scorecard under ``"scorecard"``: SIFID (temporal feature vectors of windows every
    ``sifid_stride`` frames), inter-diversity, intra-diversity and its difference from the source's, and the
    harmonic mean with ``normalisers`` (default: the SinMDM authors', see :mod:`modi.evaluation.scorecard`).
    Returns the means, the protocol and per-motion values."""
    if joints not in ("reduced", "all"):
        raise UserError(f"joints must be 'reduced' or 'all', got {joints!r}")
    if sifid_stride < 1:
        raise UserError(f"--sifid-stride must be at least 1 frame, got {sifid_stride}")
    if len(normalisers) != 3 or not all(np.isfinite(float(n)) and float(n) > 0 for n in normalisers):
        raise UserError(f"the harmonic mean's normalisers must be three positive numbers (SIFID, inter-diversity, "
                        f"intra-diversity difference), got {list(normalisers)}")
    ext = None if features is None else _extractor(features)
    generated = _bvh_files(generated)
    labels = [str(g) if not isinstance(g, Motion) else f"motion {i}" for i, g in enumerate(generated)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # stretchy-bone warnings do not affect rotation metrics
        src = _as_motion(source)
        gens = [_as_motion(g, gen_fps, "; give the generated files' true frame rate with --gen-fps")
                for g in generated]
    if not gens:
        raise UserError("no generated motions to score")
    src, gens = src.resample(fps), [m.resample(fps) for m in gens]
    try:
        src_frames, feats, names = shared_pose_frames(src, gens, joints == "reduced", representation, labels=labels)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    t0 = time.perf_counter()
    try:
        res = single_sequence_metrics(feats, src_frames, coverage_window=window, threshold=threshold,
                                      min_segment=min_segment, local_window=local_window)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    card = None
    if ext is not None:
        clip_src = _extractor_clip(ext, src, "source", src.unit)
        clips = [_extractor_clip(ext, m, label, src.unit) for m, label in zip(gens, labels)]
        try:
            card = scorecard_metrics(ext, clip_src, clips, sifid_stride=sifid_stride, normalisers=normalisers)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        card["features"] = str(features) if not isinstance(features, FeatureExtractor) else "(in memory)"
        for row, v in zip(res["per_sequence"], card.pop("per_sequence")):
            row.update(v)
    lengths = sorted({int(f.shape[0]) for f in feats})
    left_out = [n for n in shared_joints([src.skeleton], joints == "reduced") if n not in names]
    return {
        "coverage": res["coverage"],
        "global_diversity": res["global_diversity"],
        "local_diversity": res["local_diversity"],
        **({} if card is None else {"scorecard": card}),
        "source": str(source) if not isinstance(source, Motion) else "(motion)",
        "protocol": {
            "joints": joints,
            "n_joints": len(names),
            "joint_names": names,
            "fps": fps,
            "gen_fps": gen_fps,
            "n_samples": len(feats),
            "sample_frames": lengths[0] if len(lengths) == 1 else lengths,
            "source_frames": int(src_frames.shape[0]),
            "representation": representation,
        },
        "settings": res["settings"],
        "seconds": time.perf_counter() - t0,
        "per_file": [dict(file=label, frames=int(f.shape[0]), **v)
                     for label, f, v in zip(labels, feats, res["per_sequence"])],
        "source_joints": src.n_joints,
        "left_out": left_out,
    }


UP_AXES = {"x": 0, "y": 1, "z": 2}


def train_features(data: str | os.PathLike, out: str | os.PathLike, *, label_key: str = "content",
                   window: int = 64, fps: float = 30.0, stride: int = 4, eval_stride: int = 16,
                   holdout: float = 0.2, epochs: int = 12, batch_size: int = 64, lr: float = 2e-3,
                   max_minutes: float | None = None, up_axis: str = "y", seed: int = 0, threads: int | None = None,
                   json_path: str | os.PathLike | None = None, log: Callable[[str], Any] | None = None,
                   warn: Callable[[str], Any] | None = None) -> dict[str, Any]:
    """``modi eval train-features``: train the ST-GCN action recogniser whose penultimate features FID, KID,
    precision, recall and diversity use, on the labelled BVH clips of ``data`` (a JSON beside each; split by file,
    stratified by class), and save it to ``out`` (with the training summary to ``json_path``). ``log`` gets the
    data line before training, ``warn`` the warnings. Returns the training history (``val_top1`` etc. when clips
    were held out) with ``train_clips``/``heldout_clips``. Cost: ``epochs`` passes over the windows (minutes on a
    CPU for a few thousand)."""
    if json_path and Path(json_path).absolute() == Path(out).absolute():
        raise UserError(f"--json {json_path} is also --out, the extractor file; choose another name")
    set_threads(None if threads is None else max(1, threads))
    if window < 8:
        raise UserError(f"--window must be at least 8 frames, got {window}")
    if not 0 < holdout < 1:
        raise UserError(f"--holdout must be between 0 and 1, got {holdout}")
    if up_axis not in UP_AXES:
        raise UserError(f"--up-axis must be one of x, y, z, got {up_axis!r}")
    clips, class_names, joints, parents, height = F.load_labelled_folder(data, label_key, fps)
    train_idx, held_idx = F.split_by_file(clips, holdout, seed)
    config = F.FeatureConfig(joint_names=joints, parents=parents, class_names=class_names, window=window, fps=fps,
                             up_axis=UP_AXES[up_axis], body_height=height, pairs=F.lr_pairs(joints, parents))
    if not config.pairs and warn is not None:
        warn("modi: warning: no left/right joint pair found by name; windows keep their heading")
    wtr, ltr = F.windows_and_labels([clips[i] for i in train_idx], window, stride)
    if held_idx:
        who, lho = F.windows_and_labels([clips[i] for i in held_idx], window, eval_stride)
    else:
        who, lho = None, None
    if log is not None:
        log(f"{len(train_idx)} training clips ({len(wtr)} windows), {len(held_idx)} held-out clips "
            f"({0 if who is None else len(who)} windows), {len(class_names)} classes, {len(joints)} joints")
    extractor, hist = F.train_feature_extractor(
        wtr, ltr, config, who, lho, epochs=epochs, batch_size=batch_size, lr=lr,
        max_seconds=None if max_minutes is None else 60.0 * max_minutes, seed=seed)
    extractor.info.update({
        "data": str(Path(data).resolve()),
        "label_key": label_key,
        "train_files": [clips[i].name for i in train_idx],
        "heldout_files": [clips[i].name for i in held_idx],
        "seed": seed,
        "stride": stride,
        "eval_stride": eval_stride,
    })
    extractor.save(out)
    if json_path:
        summary = {k: v for k, v in hist.items() if k != "epochs"}
        summary["out"] = str(out)
        write_json({"summary": summary, "epochs": hist["epochs"]}, json_path)
    return {**hist, "train_clips": len(train_idx), "heldout_clips": len(held_idx)}


def _feet(path: Path, names: list[str], given: Sequence[str] | None) -> list[int]:
    """Foot joints of a clip: guessed by name, or the ``given`` names (exact, or modulo a namespace prefix)."""
    if given is None:
        try:
            return guess_feet(names)
        except ValueError:
            raise UserError(f"{path}: no foot joints found by name (foot/toe/ankle/heel); name them with "
                            f"--feet JOINT ... (joints: {', '.join(names[:12])}{', ...' if len(names) > 12 else ''})"
                            ) from None
    unique_names("--feet", given)
    # a name matches exactly, or modulo a namespace prefix (``mixamorig:LeftToeBase`` = ``LeftToeBase``)
    bare = [bare_name(n) for n in names]
    idx = []
    for n in given:
        hits = [j for j, (full, b) in enumerate(zip(names, bare)) if n in (full, b)]
        if len(hits) > 1:
            raise UserError(f"{path}: --feet: {n!r} names {len(hits)} joints; give the full names")
        idx.append(hits[0] if hits else -1)
    missing = [n for n, j in zip(given, idx) if j < 0]
    if missing:
        raise UserError(f"{path}: --feet: no joint named {', '.join(missing)}")
    if 0 in idx:
        raise UserError(f"--feet: the root joint {names[0]} cannot be a foot")
    return idx


def evaluate_plausibility(clips: Sequence[str | os.PathLike], *, up_axis: str = "y",
                          feet: Sequence[str] | None = None, ground: float = 0.0,
                          json_path: str | os.PathLike | None = None,
                          each: Callable[[dict[str, Any]], Any] | None = None) -> dict[str, Any]:
    """``modi eval plausibility``: foot skating (horizontal foot speed in contact), floating / penetration against
    the ground at ``ground`` along ``up_axis``, and jitter (mean jerk) of BVH clips, in the files' units. ``feet``:
    foot joints by name (default: joints named foot/toe/ankle/heel). ``each`` gets every clip's figures as they
    come. Returns ``{"mean": ..., "per_file": [...]}`` (also written to ``json_path``). Cost: one FK pass a clip."""
    if up_axis not in UP_AXES:
        raise UserError(f"--up-axis must be one of x, y, z, got {up_axis!r}")
    per = []
    for f in clips:
        p = existing_file(f)
        b = bvh_io.load(p)
        names = list(b.names)
        foot = _feet(p, names, feet)
        try:
            m = plausibility_metrics(bvh_positions(b), float(b.fps), foot, up_axis=UP_AXES[up_axis], ground=ground)
        except ValueError as exc:
            raise UserError(f"{p}: {exc}") from None
        row = dict(file=str(p), **m)
        per.append(row)
        if each is not None:
            each(row)
    out = {"mean": aggregate([{k: v for k, v in m.items() if k != "file"} for m in per]), "per_file": per}
    if json_path:
        write_json(out, json_path)
    return out


def write_report(results: dict[str, Any], title: str, *, json_path: str | os.PathLike | None = None,
                 md_path: str | os.PathLike | None = None) -> str:
    """Write an evaluation report as JSON and / or Markdown; returns its Markdown (what ``modi eval`` prints when
    no Markdown file is asked for)."""
    write_reports(results, json_path, md_path, title)
    return to_markdown(results, title)


__all__ = ["evaluate", "evaluate_real", "evaluate_single", "evaluate_plausibility", "train_features",
           "write_report", "UP_AXES"]
