"""The README's picture: MoDi samples beside a GANimator variation and its source, as one small GIF.

    python examples/readme_gif.py MODI_CHECKPOINT GANIMATOR_RUN SOURCE.bvh --out docs/img/modi.gif

MODI_CHECKPOINT is any MoDi checkpoint; GANIMATOR_RUN a trained run on SOURCE.bvh. The README's GIF (0.59 MB) came
from these, each on one core of a 2-core machine:

    modi demo --out demo_out --iters 1500                     # procedural data, 20 minutes
    modi ganimator train Joe/Salsa-Dancing-6.bvh --out runs/salsa --preset fast --threads 1
    python examples/readme_gif.py demo_out/run/checkpoint.pt runs/salsa Joe/Salsa-Dancing-6.bvh --out docs/img/modi.gif

The GIF plays ``--seconds`` at 15 fps in 200-pixel panels, which keeps it under 1 MB.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

import modi
from modi.core.skeleton import strip_namespace
from modi.data.motion import Motion
from modi.viz.render import render_positions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("modi_checkpoint")
    ap.add_argument("ganimator_run")
    ap.add_argument("source")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    fps = 15.0
    gen = modi.load(a.modi_checkpoint)
    run = modi.load(a.ganimator_run)
    n = int(a.seconds * fps)
    mo = gen.generate(2, seed=a.seed)
    var = run.generate(1, frames=int(a.seconds * run.fps), seed=a.seed)[0]
    src = Motion.from_bvh(a.source)
    bare = [strip_namespace(x) for x in src.skeleton.names]
    src = src.subset(sorted(bare.index(x) for x in run.skeleton.names))

    def at_fps(m: Motion) -> np.ndarray:
        """``n`` frames of the motion's positions at 15 fps (a short clip repeats)."""
        p = m.positions().numpy()
        idx = np.round(np.arange(n) * m.fps / fps).astype(int) % len(p)
        return p[idx]

    motions = [mo[0], mo[1], src, var]
    parents = [list(m.skeleton.parents) for m in motions]
    names = [list(m.skeleton.names) for m in motions]
    titles = ["MoDi sample (make demo)", "MoDi sample (make demo)", "GANimator: the one source clip",
              "GANimator: a new variation"]
    out = render_positions([at_fps(m) for m in motions], parents, a.out, fps=fps, size=(200, 200), titles=titles,
                           names=names)
    print(f"{out}: {Path(out).stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
