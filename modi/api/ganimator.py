"""A trained GANimator run as one object: random motions of any length, key-frame editing, trajectory control and
style transfer, all returned as :class:`modi.Motion` in the training file's units (GANimator's working units, x0.1
or x0.01 of a centimetre or inch rig, stay inside).

``GanimatorRun.generate(n, frames=, seed=)`` gives the motions ``modi ganimator generate RUN --n n --frames F
--seed s`` writes (the CLI also places several motions on a crowd grid: ``spacing``)."""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from modi.core.skeleton import Skeleton
from modi.data.motion import Motion
from modi.errors import UserError
from modi.faults import atomic_write, refuse_overwrite
from modi.io.formats import save_motion
from modi.models.ganimator.evaluate_paper import N_SAMPLES, evaluate_paper, format_figures
from modi.models.ganimator.editing import edit_features, paste
from modi.models.ganimator.generate import (check_generation_inputs, decode, evaluate_run, fix_contacts,
                                            rotation_frames, sample_features)
from modi.models.ganimator.networks import GanimatorModel
from modi.models.ganimator.training import checkpoint_path, load_model
from modi.evaluation.single import single_sequence_metrics
from modi.viz.render import render_positions


class GanimatorRun:
    """The generator of a GANimator run (``modi ganimator train``, or an imported run of the authors' code).

    Build it with :func:`modi.load` (the run folder or its ``ganimator.ckpt``) or :meth:`from_checkpoint`."""

    def __init__(self, model: GanimatorModel, *, path: str | None = None) -> None:
        self.model = model.eval()
        self.path = path
        seq = model.seqs[0]
        inv = 1.0 / seq.scale
        sk = seq.skeleton
        self._skeleton = Skeleton(list(sk.names), list(sk.parents), sk.offsets * inv,
                                  {k: np.asarray(v) * inv for k, v in sk.end_sites.items()},
                                  list(sk.rotation_orders or ["ZYX"] * sk.n_joints))
        self._unit = Motion(self._skeleton, torch.zeros(1, sk.n_joints, 4), torch.zeros(1, 3), seq.fps).unit

    @classmethod
    def from_checkpoint(cls, run: str | os.PathLike, *, device: str | torch.device = "cpu") -> "GanimatorRun":
        """Read a run folder or its checkpoint file (as data only); ``CheckpointError`` for anything else."""
        if not Path(run).exists():
            raise UserError(f"{run}: no such GANimator run folder or checkpoint file")
        return cls(load_model(run, device=str(device)), path=str(run))

    # ------------------------------------------------------------------------------------------- facts
    @property
    def skeleton(self) -> Skeleton:
        """The (reduced) training skeleton in the file's units: what every motion is on."""
        return self._skeleton

    @property
    def unit(self) -> str:
        """The length unit of the training file (and of every motion)."""
        return self._unit

    @property
    def fps(self) -> float:
        return float(self.model.seqs[0].fps)

    @property
    def n_frames(self) -> int:
        """Frames of the (first) training clip: the default length of a motion."""
        return int(self.model.seqs[0].n_frames)

    @property
    def clips(self) -> list[str]:
        """Names of the training clips."""
        return [s.name for s in self.model.seqs]

    @property
    def feet(self) -> list[str]:
        return [self._skeleton.names[f] for f in self.model.seqs[0].feet]

    @property
    def body_size(self) -> float:
        """A size of the body in the file's units (the crowd spacing's scale)."""
        seq = self.model.seqs[0]
        return float(seq.size / seq.scale)

    @property
    def scale(self) -> float:
        """GANimator's working units per file unit (a power of ten)."""
        return float(self.model.seqs[0].scale)

    @property
    def conditional(self) -> bool:
        """Whether the run is trajectory-conditioned."""
        return bool(self.model.cond_entities)

    def __repr__(self) -> str:
        where = f", {self.path}" if self.path else ""
        return (f"GanimatorRun({self._skeleton.n_joints} joints, {len(self.clips)} clip(s) of {self.n_frames} frames "
                f"at {self.fps:g} fps, {self.model.n_levels} levels{', conditional' if self.conditional else ''}"
                f"{where})")

    # ------------------------------------------------------------------------------------------- generation
    def generate(self, n: int = 1, *, frames: int | None = None, seed: int = 0,
                 keyframes: str | os.PathLike | None = None, trajectory: str | os.PathLike | None = None,
                 style: str | os.PathLike | None = None, style_level: int = 0, loop: bool = False,
                 loop_root: str = "travel", inbetween: tuple[str | os.PathLike, str | os.PathLike] | None = None,
                 expand: str | os.PathLike | None = None, at: int | None = None,
                 edit: str | os.PathLike | None = None, keep: str | Sequence[str] | None = None, stream: int = 0,
                 fine_noise: bool = False, ik: bool = False, spacing: float | None = 0.0) -> list[Motion]:
        """``n`` motions with contact labels, in the training file's units.

        * random (default): ``frames`` frames each (default: the training clip's);
        * ``keyframes``: a BVH of coarse-level poses on the run's rig (key-frame editing);
        * ``trajectory``: a root-trajectory BVH for a trajectory-conditioned run (which samples one when not
          given); ``stream`` feeds it in segments of that many frames (same result);
        * ``style``: a content BVH whose coarse motion gets the training clip's detail (style transfer); with
          ``style_level`` > 0 the content enters at that finer level and keeps its poses: harmonisation of a clip
          pasted together by hand;
        * ``loop``: ``frames`` frames whose last frame flows into the first; ``loop_root="return"`` brings the root
          back to its start, ``"travel"`` lets it move on;
        * ``inbetween=(START, END)``: START, then ``frames`` generated frames, then END (clips, or ``PATH@F`` for
          frame F as a pose), both kept exactly and where they are in the scene;
        * ``expand``: a clip inside a ``frames``-frame motion, unchanged from frame ``at`` (default: centred);
        * ``edit`` with ``keep``: the clip's kept joints (names, or ``"upper"`` / ``"lower"``) unchanged bit for
          bit, the rest generated to go with them.

        A given span or joint is exact on the returned motion before ``ik``. ``seed`` fixes the result (as
        ``modi ganimator generate --seed``); ``fine_noise`` adds noise at every level; ``ik`` pins each foot while
        its contact label is on; ``spacing`` places several motions on a grid that far apart (None: 1.5 body sizes,
        as the CLI's crowd; 0: each at its own start). Cost: one pass through the level generators per motion
        (milliseconds for a small run on a CPU)."""
        m = self.model
        edits = {"--loop": loop, "--inbetween": inbetween, "--expand": expand, "--edit": edit}
        chosen = [k for k, v in {**edits, "--content": style, "--keyframes": keyframes,
                                 "--trajectory": trajectory}.items() if v]
        if len(chosen) > 1:
            raise UserError(f"use only one of {', '.join(chosen)}")
        if any(edits.values()):
            samples, constraints, start, _ = edit_features(
                m, int(n), frames, int(seed), loop=loop, loop_root=loop_root, inbetween=inbetween, expand=expand,
                at=at, edit=edit, keep=keep, fine_noise=fine_noise)
            return self.decode(samples, start=start, ik=ik, spacing=spacing, constraints=constraints)
        if keep is not None or at is not None:
            raise UserError("--keep goes with --edit CLIP" if keep is not None else "--at goes with --expand CLIP")
        check_generation_inputs(m, frames, content=style, keyframes=keyframes, trajectory=trajectory,
                                content_level=style_level)
        samples, start, _ = sample_features(m, int(n), frames, int(seed), content=style, keyframes=keyframes,
                                            trajectory=trajectory, stream=int(stream), fine_noise=fine_noise,
                                            content_level=int(style_level))
        return self.decode(samples, start=start, ik=ik, spacing=spacing)

    def decode(self, samples: Sequence[Tensor], *, start: Tensor | None = None, ik: bool = False,
               spacing: float | None = 0.0, constraints: Sequence | None = None) -> list[Motion]:
        """Generator outputs ``(6, E, T)`` -> motions (see :meth:`generate` for ``ik`` and ``spacing``);
        ``constraints`` (from :func:`modi.models.ganimator.editing.edit_features`) paste the given rotations and
        root track back exactly, before ``ik``."""
        seq = self.model.seqs[0]
        inv = 1.0 / seq.scale
        step = 1.5 * seq.size if spacing is None else float(spacing) * seq.scale  # working units
        cols = max(1, math.ceil(math.sqrt(len(samples))))
        names = self._skeleton.names
        out = []
        for i, s in enumerate(samples):
            quats, root, contacts = decode(self.model, s, root_start=start)
            c = constraints[i] if constraints is not None else None
            if c is not None:
                quats, root = paste(c, quats.to(torch.float64), root)
            if ik:
                quats, root = fix_contacts(seq, quats, root, contacts)
            if len(samples) > 1 and step:  # a crowd: on a grid
                root = root.clone()
                root[:, 0] += (i % cols) * step
                root[:, 2] += (i // cols) * step
            labels = {names[f]: (contacts[:, k] > 0.5) for k, f in enumerate(seq.feet)}
            out.append(Motion(self._skeleton, quats.to(torch.float64), root.to(torch.float64) * inv, seq.fps,
                              self._unit, contacts=labels))
        return out

    def write(self, motions: Sequence[Motion], out: str | os.PathLike, *,
              gif: bool = True) -> tuple[list[Path], Path | None]:
        """Write motions as ``modi ganimator generate`` does: ``sample.bvh`` (several: ``sample_NNN.bvh``, the
        requested ``--format``s, with contact labels) and, with ``gif``, ``sample.gif`` (several: ``crowd.gif``,
        one scene) with the viewer page ``view.html``. Returns the motion files and the GIF (None without)."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        crowd = len(motions) > 1
        written = [save_motion(m.to_bvh(), out / (f"sample_{i:03d}.bvh" if crowd else "sample.bvh"),
                               contacts=m.contact_arrays())
                   for i, m in enumerate(motions)]
        if not gif:
            return written, None
        sk = self._skeleton
        masks = []
        for m in motions:
            mask = np.zeros((m.n_frames, sk.n_joints), dtype=bool)
            for name, c in (m.contacts or {}).items():
                mask[:, sk.names.index(name)] = c.numpy()
            masks.append(mask)
        path = out / ("crowd.gif" if crowd else "sample.gif")
        render_positions([(m.positions() * self.scale).numpy() for m in motions], list(sk.parents), path,
                         fps=self.fps, names=list(sk.names), contacts=masks, layout="scene" if crowd else "grid",
                         view="view.html")
        return written, path

    # ------------------------------------------------------------------------------------------- metrics
    def metrics(self, motions: Sequence[Motion]) -> dict[str, dict[str, Any]]:
        """Coverage (30-frame windows, threshold 2.0), global and local diversity of motions on the run's skeleton
        against each training clip (what ``modi ganimator generate --eval`` prints)."""
        gens = [rotation_frames(m.rotations) for m in motions]
        out: dict[str, dict[str, Any]] = {}
        lengths = sorted({m.n_frames for m in motions})
        for seq in self.model.seqs:
            r = single_sequence_metrics(gens, rotation_frames(seq.rotations()))
            out[seq.name] = {k: float(r[k]) for k in ("coverage", "global_diversity", "local_diversity")}
            out[seq.name].update(samples=len(motions), frames=lengths[0] if len(lengths) == 1 else lengths)
        return out

    def evaluate(self, *, n: int | None = None, frames: int | None = None, seed: int = 0,
                 protocol: str = "ours") -> dict[str, Any]:
        """``modi ganimator eval``: sample and score against every training clip. ``protocol="ours"`` (10
        samples of the clip's length by default, rotations decoded as any BVH output) or ``"paper"`` (the authors'
        released evaluate.py: 200 samples of 2x the total source length, raw generator channels)."""
        if self.path is None:
            raise UserError("evaluate needs a run on disk (load it with modi.load(RUN))")
        if n is not None and n < 1:
            raise UserError("--n must be at least 1")
        if frames is not None and frames < 30:
            raise UserError("--frames must be at least 30 (the coverage window)")
        if protocol == "paper":
            return evaluate_paper(self.path, n=n or N_SAMPLES, n_frames=frames, seed=seed)
        if protocol != "ours":
            raise UserError(f"protocol must be 'ours' or 'paper', got {protocol!r}")
        return evaluate_run(self.path, n=n or 10, n_frames=frames, seed=seed)

    @property
    def checkpoint(self) -> Path | None:
        """The checkpoint file of the run (None for a run built in memory)."""
        return None if self.path is None else checkpoint_path(self.path)


def evaluate_ganimator(run: str | os.PathLike, *, n: int | None = None, frames: int | None = None, seed: int = 0,
                       protocol: str = "ours", json_path: str | os.PathLike | None = None) -> dict[str, Any]:
    """``modi ganimator eval``: :meth:`GanimatorRun.evaluate` of the run at ``run``, the figures also written
    as JSON to ``json_path`` (never over the run's checkpoint). :func:`format_figures` makes the table the CLI
    prints. Cost: sampling and scoring ``n`` motions (seconds for ours, minutes for the paper's protocol)."""
    if json_path:
        refuse_overwrite(json_path, [checkpoint_path(run)], "--json")
    figures = GanimatorRun.from_checkpoint(run).evaluate(n=n, frames=frames, seed=seed, protocol=protocol)
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(json_path, json.dumps(figures, indent=2) + "\n")
    return figures


__all__ = ["GanimatorRun", "evaluate_ganimator", "format_figures"]
