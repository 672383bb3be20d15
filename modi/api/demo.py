"""``modi demo`` from Python: the README's main job in one call -- procedural data, a few CPU minutes of MoDi
training, sampled motions."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from modi.api.generator import ModiGenerator
from modi.errors import UserError
from modi.models.modi.config import make_config
from modi.models.modi.sampling import render_gif, write_outputs
from modi.models.modi.training import Trainer, prepare_data, write_procedural_data


@dataclass
class Demo:
    """What :func:`run_demo` made: the run's ``checkpoint``, the sampled motion files, the folders, the seconds it
    took, and whether training was ``interrupted`` (then nothing was sampled)."""

    out: Path
    checkpoint: Path | None
    samples: list[Path] = field(default_factory=list)
    seconds: float = 0.0
    interrupted: bool = False

    @property
    def run_dir(self) -> Path:
        return self.out / "run"


def run_demo(out: str | os.PathLike = "demo_out", *, iters: int = 300, clips: int = 48, n: int = 8, seed: int = 0,
             threads: int = 1, progress: bool = True, log: Callable[[str], Any] | None = None) -> Demo:
    """Write ``clips`` procedural clips (``OUT/data``), train the ``small`` MoDi preset on them for ``iters``
    iterations (``OUT/run``: checkpoint, TensorBoard, log.jsonl), then sample ``n`` motions (``OUT/samples``: BVH,
    contact labels, ``samples.gif``) beside a GIF of real training windows (``OUT/training_examples.gif``).
    ``log`` gets the data line before training. Cost: about 0.65 CPU seconds an iteration (minutes in all)."""
    if iters < 0:
        raise UserError(f"--iters must be >= 0, got {iters}")
    if clips < 2:
        raise UserError(f"--clips must be >= 2, got {clips}")
    if n < 1:
        raise UserError(f"--n must be >= 1, got {n}")
    if threads < 1:
        raise UserError(f"--threads must be >= 1, got {threads}")
    torch.set_num_threads(threads)
    out = Path(out)
    run_dir = out / "run"
    if (run_dir / "checkpoint.pt").exists():
        raise UserError(f"{out} already holds a demo run; choose another --out or delete it")
    t0 = time.perf_counter()
    cfg = make_config("small", **{"train.iters": iters, "train.seed": seed, "train.sample_every": 0,
                                  "train.ckpt_every": max(50, iters // 4 or 1), "train.log_every": 10})
    data_dir = write_procedural_data(out / "data", n_clips=clips, seed=seed, fps=cfg.data.fps)
    data = prepare_data(data_dir, cfg, cache=False)
    if log is not None:
        log(f"modi demo: {clips} procedural clips -> {data.windows.shape[0]} training windows "
            f"{tuple(data.windows.shape[1:])}; hierarchy {data.hierarchy.entity_counts}; "
            f"training the small preset for {iters} iterations")
    result = Trainer(cfg, data, run_dir, progress=progress, write_samples=False).train()
    if result.interrupted:
        return Demo(out, result.checkpoint, seconds=time.perf_counter() - t0, interrupted=True)
    real = data.windows[torch.linspace(0, data.windows.shape[0] - 1, n).long()]
    dec = data.codec.decode(real)
    render_gif(data.codec, [p.numpy() for p in dec["positions"]], [(c > 0.5).numpy() for c in dec["contacts"]],
               out / "training_examples.gif", view="training_examples.html")
    gen = ModiGenerator.from_checkpoint(result.checkpoint)
    written = write_outputs(gen.codec, gen.sample_tensors(n, seed=seed), out / "samples", gif=True,
                            gif_name="samples.gif")
    return Demo(out, result.checkpoint, written, time.perf_counter() - t0)


__all__ = ["run_demo", "Demo"]
