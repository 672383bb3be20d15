"""What animators do with one clip, on a trained GANimator run: a loop, an in-between, an expansion, body-part edits
and a harmonised paste, each written as BVH, measured, and drawn (the pictures and figures of docs/single_clip.md).

    python examples/single_clip.py RUN SOURCE.bvh --out OUT [--figures docs/img]

RUN is a trained run (``modi ganimator train SOURCE.bvh --out RUN --preset fast``). OUT receives one BVH per
application and ``figures.json``: each promise measured (exact frames and joints, the loop's seam against the
source's own frame-to-frame steps) and foot skating / jitter of every output beside the source's and the run's
random motions.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image, ImageDraw  # noqa: E402

from modi.api.ganimator import GanimatorRun  # noqa: E402
from modi.core.skeleton import strip_namespace  # noqa: E402
from modi.data.motion import Motion  # noqa: E402
from modi.evaluation.plausibility import plausibility_metrics  # noqa: E402
from modi.io.formats import save_motion  # noqa: E402
from modi.models.ganimator.editing import kept_joints  # noqa: E402
from modi.viz.render import render_frames  # noqa: E402


def on_rig(run: GanimatorRun, path) -> Motion:
    """The source as modi reads it, on the run's (reduced) rig, at the run's frame rate."""
    m = Motion.from_bvh(path)
    bare = [strip_namespace(n) for n in m.skeleton.names]
    m = m.subset(sorted(bare.index(n) for n in run.skeleton.names))
    stride = max(1, round(m.fps / run.fps))
    return Motion(m.skeleton, m.rotations[::stride], m.root_positions[::stride], m.fps / stride, m.unit)


def rel(m: Motion) -> np.ndarray:
    p = m.positions().numpy()
    return p - p[:, :1]


def steps(m: Motion, loop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Mean joint displacement (root-relative) from frame t to t+1, and the change of that velocity; for a loop the
    last entries run across the seam."""
    r = rel(m)
    if loop:
        v = np.roll(r, -1, axis=0) - r
        a = np.roll(v, -1, axis=0) - v
    else:
        v = r[1:] - r[:-1]
        a = v[1:] - v[:-1]
    return np.linalg.norm(v, axis=-1).mean(-1), np.linalg.norm(a, axis=-1).mean(-1)


def strip(run: GanimatorRun, m: Motion, frames: list[int], labels: list[str], path: Path) -> None:
    """A film strip of ``frames`` of ``m``, each captioned."""
    p = m.positions().numpy()
    fixed = [np.repeat(p[f][None], 2, axis=0) for f in frames]
    imgs = [render_frames([x], list(run.skeleton.parents), size=(200, 220))[0].convert("RGB") for x in fixed]
    out = Image.new("RGB", (200 * len(imgs), 240), "white")
    for i, (im, lab) in enumerate(zip(imgs, labels)):
        out.paste(im, (200 * i, 20))
        ImageDraw.Draw(out).text((200 * i + 8, 4), lab, fill=(0, 0, 0))
    out.save(path, optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("source")
    ap.add_argument("--out", required=True)
    ap.add_argument("--figures", default=None, help="also draw the pictures into this folder")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    run = GanimatorRun.from_checkpoint(a.run)
    src = on_rig(run, a.source)
    name = Path(a.source).stem
    T = src.n_frames
    names = run.skeleton.names
    feet = [names.index(f) for f in run.feet]
    res: dict = {"run": str(a.run), "source": str(a.source), "frames": T, "fps": run.fps}

    def plaus(m: Motion) -> dict:
        f = plausibility_metrics(m.positions().numpy(), m.fps, feet)
        return {k: round(float(f[k]), 3) for k in ("foot_skating", "jitter")}

    def save(m: Motion, stem: str) -> None:
        save_motion(m.to_bvh(), out / f"{stem}.bvh", contacts=m.contact_arrays())

    res["plausibility"] = {"source": plaus(src)}
    rnd = run.generate(3, frames=2 * T, seed=a.seed + 100)
    res["plausibility"]["random (3 of 2x the source)"] = [plaus(m) for m in rnd]

    # loop: twice the source's length, the root back at its start
    loop = run.generate(1, frames=T, loop=True, loop_root="return", seed=a.seed)[0]
    save(loop, "loop")
    s_step, s_acc = steps(src)
    l_step, l_acc = steps(loop, loop=True)
    res["loop"] = {"frames": T, "seam_step": float(l_step[-1]),
                   "source_step_percentile_of_seam": float((s_step < l_step[-1]).mean() * 100),
                   "seam_velocity_change": float(l_acc[-2:].max()),
                   "source_velocity_change_percentile_of_seam": float((s_acc < l_acc[-2:].max()).mean() * 100),
                   "source_step_max": float(s_step.max()), "source_velocity_change_max": float(s_acc.max()),
                   "plausibility": plaus(loop)}

    # in-between: from the source's frame 0 pose to its frame T // 2 pose in 60 frames
    mid = T // 2
    ib = run.generate(1, frames=60, inbetween=(f"{a.source}@0", f"{a.source}@{mid}"), seed=a.seed)[0]
    save(ib, "inbetween")
    res["inbetween"] = {"frames": ib.n_frames, "start_exact": bool(torch.equal(ib.rotations[0], src.rotations[0])),
                        "end_exact": bool(torch.equal(ib.rotations[-1], src.rotations[mid])),
                        "end_root_error": float((ib.root_positions[-1] - src.root_positions[mid]).norm()),
                        "plausibility": plaus(ib)}

    # expansion: the source inside a motion 2x its length, from frame T // 2
    ex = run.generate(1, frames=2 * T, expand=a.source, at=T // 2, seed=a.seed)[0]
    save(ex, "expand")
    res["expand"] = {"frames": ex.n_frames, "at": T // 2,
                     "clip_exact": bool(torch.equal(ex.rotations[T // 2:T // 2 + T], src.rotations)),
                     "plausibility": plaus(ex)}

    # body parts: keep the lower body, then the upper
    edits = {}
    for keep in ("lower", "upper"):
        e = run.generate(1, edit=a.source, keep=keep, seed=a.seed)[0]
        save(e, f"edit_{keep}")
        k = kept_joints(run.model, keep)
        edits[keep] = e
        res[f"edit_{keep}"] = {"kept": [names[j] for j in k],
                               "kept_exact": bool(torch.equal(e.rotations[:, k], src.rotations[:, k])),
                               "plausibility": plaus(e)}

    # harmonisation: two pieces of the source pasted by hand, then injected at each level
    cut = T // 3
    pasted = Motion(src.skeleton, torch.cat([src.rotations[:cut], src.rotations[2 * cut:]]),
                    torch.cat([src.root_positions[:cut], src.root_positions[2 * cut:] - src.root_positions[2 * cut]
                               + src.root_positions[cut - 1]]), src.fps, src.unit)
    save_motion(pasted.to_bvh(), out / "pasted.bvh")
    res["harmonise"] = {"cut_frame": cut, "levels": {}}
    harm = {}
    for level in range(run.model.n_levels - 1):
        h = run.generate(1, style=out / "pasted.bvh", style_level=level, seed=a.seed)[0]
        harm[level] = h
        st, ac = steps(h)
        res["harmonise"]["levels"][level] = {
            "step_at_cut": float(st[cut - 1]), "velocity_change_at_cut": float(ac[cut - 2:cut].max()),
            "content_error": float(np.linalg.norm(rel(h) - rel(pasted), axis=-1).mean()), "plausibility": plaus(h)}
    pst, pac = steps(pasted)
    res["harmonise"]["pasted"] = {"step_at_cut": float(pst[cut - 1]), "velocity_change_at_cut": float(pac[cut - 2:cut].max()),
                                  "plausibility": plaus(pasted)}
    (out / "figures.json").write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))
    if not a.figures:
        return

    fig_dir = Path(a.figures)
    fig_dir.mkdir(parents=True, exist_ok=True)
    hand = next((names.index(n) for n in names if "hand" in n.lower()), len(names) - 1)
    # loop: two repetitions of a hand's height, the seam marked; the seam's step among the source's steps
    fig, ax = plt.subplots(1, 2, figsize=(9, 2.6))
    h2 = np.concatenate([rel(loop)[:, hand, 1]] * 2)
    ax[0].plot(h2, lw=1)
    ax[0].axvline(T - 0.5, color="r", ls="--", lw=1, label="seam")
    ax[0].set(title=f"loop x2: {names[hand]} height", xlabel="frame")
    ax[0].legend(loc="upper right", fontsize=7)
    ax[1].hist(s_step, bins=40, color="0.7", label="source steps")
    ax[1].axvline(l_step[-1], color="r", lw=1.5, label="seam step")
    ax[1].set(title="pose step per frame", xlabel="mean joint displacement")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(fig_dir / f"single_clip_loop_{name}.png", dpi=80)
    plt.close(fig)
    # in-between: a film strip
    n = ib.n_frames
    picks = [0, n // 5, 2 * n // 5, 3 * n // 5, 4 * n // 5, n - 1]
    strip(run, ib, picks, ["start (given)"] + [f"frame {f}" for f in picks[1:-1]] + ["end (given)"],
          fig_dir / f"single_clip_inbetween_{name}.png")
    # body parts and expansion: curves of a kept and a regenerated joint against the source
    fig, ax = plt.subplots(1, 3, figsize=(12, 2.6))
    e = edits["lower"]
    kept = kept_joints(run.model, "lower")
    knee = next((j for j in kept if "leg" in names[j].lower() and j != 0), kept[-1])
    other = next(j for j in range(len(names)) if j not in kept and "arm" in names[j].lower()) \
        if any("arm" in names[j].lower() and j not in kept for j in range(len(names))) else \
        next(j for j in range(len(names)) if j not in kept)
    for axis, j, title in ((ax[0], knee, "kept"), (ax[1], other, "generated")):
        axis.plot(src.rotations[:, j, 0].numpy(), lw=2.5, color="0.75", label="source")
        axis.plot(e.rotations[:, j, 0].numpy(), lw=1, color="C0", label="edit (keep lower)")
        axis.set(title=f"{title}: {names[j]} (quaternion w)", xlabel="frame")
        axis.legend(fontsize=7)
    ax[2].plot(rel(ex)[:, hand, 1], lw=1, label="expanded")
    ax[2].plot(np.arange(T // 2, T // 2 + T), rel(src)[:, hand, 1], lw=2.5, color="0.75", alpha=0.8, label="source")
    ax[2].axvspan(T // 2, T // 2 + T - 1, color="C2", alpha=0.1)
    ax[2].set(title=f"expansion: {names[hand]} height", xlabel="frame")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(fig_dir / f"single_clip_parts_expand_{name}.png", dpi=80)
    plt.close(fig)
    # harmonisation: the pasted cut, and the outputs injected at three levels
    fig, ax = plt.subplots(figsize=(6, 2.6))
    w = slice(max(0, cut - 40), cut + 40)
    x = np.arange(T)[w]
    ax.plot(x, rel(pasted)[w, hand, 1], lw=2.5, color="0.75", label="pasted by hand")
    for level in (0, run.model.n_levels // 2, run.model.n_levels - 2):
        ax.plot(x, rel(harm[level])[w, hand, 1], lw=1, label=f"--content-level {level}")
    ax.axvline(cut - 0.5, color="r", ls="--", lw=1)
    ax.set(title=f"harmonisation: {names[hand]} height at the cut", xlabel="frame")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(fig_dir / f"single_clip_harmonise_{name}.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    main()
