"""Run the authors' released GANimator (``../shared/peers/ganimator``, BSD-style) on the CPU, from here.

Nothing in the peer folder is modified or copied. While their code runs (:func:`peer_runtime`):

* the peer folder is first on ``sys.path``; their top-level modules (``models``, ``dataset``, ``bvh``, ``option``,
  ``utils``, ...) live in ``sys.modules`` only inside the block, so MoDi's harness (same package names) can run in
  the same process;
* ``--device`` is forced to ``cpu`` and ``Tensor.cuda()`` is an identity;
* numpy aliases removed in numpy >= 1.24 (``np.int`` ...) are restored.

:func:`train_released` runs their own ``train.py`` ``main()`` (their data loading, pyramid, models, training loop
and file writing) on a BVH, with ``--num_iters`` iterations per level block: 0 gives a random-initialisation
checkpoint, a few give one where no weight is at its initial value. Their ``create_model`` is wrapped to keep the
discriminators in memory (their ``train.py`` saves only generators). :class:`ReleasedRun` then produces their
outputs from the run folder, loaded with their own ``demo.load_all_from_path``: each level's output for given
noise, the reconstruction, the demo's random sample, the WGAN-GP and other loss terms of one step, and their BVH.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import random
import sys
import types
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch

from benchmarks.peers import unavailable_reason

REPO = Path(__file__).resolve().parents[2]
PEER = REPO.parent / "shared" / "peers" / "ganimator"
DATA = REPO.parent / "shared" / "data" / "bvh" / "ganimator"
# the Mixamo walk: a namespaced rig whose released joint order (legs first) differs from the file's (spine first)
WALK = DATA / "Joe" / "Walk-In-Circle.bvh"
BANDAI = REPO.parent / "shared" / "data" / "bvh" / "bandai-namco-1" / "data"


@dataclasses.dataclass(frozen=True)
class SkeletonTable:
    """One entry of their ``bvh/skeleton_database.py``: what their README asks a user to add for a BVH of their
    own ("specify the joint names that should be involved during the generation and the contact name")."""

    name: str
    corps: tuple[str, ...]      # the joints kept, in the order their loader lists them (its first is the root)
    contacts: tuple[str, ...]   # the joints with contact labels
    threshold: float = 0.018    # their per-frame foot displacement threshold


# Bandai-Namco's 22-joint rig as a user of theirs would enter it: every joint in the file's order, from the static
# floor root joint_Root down, and the toes as contacts (the Mixamo entry's threshold)
BANDAI_TABLE = SkeletonTable(
    "Bandai", ("joint_Root", "Hips", "Spine", "Chest", "Neck", "Head", "Shoulder_L", "UpperArm_L", "LowerArm_L",
               "Hand_L", "Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R", "UpperLeg_L", "LowerLeg_L", "Foot_L",
               "Toes_L", "UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R"), ("Toes_L", "Toes_R"))

PEER_MODULES = ("option", "models", "dataset", "bvh", "utils", "loss_recorder", "demo", "train", "fix_contact",
                "interactive_utils", "evaluate")
_NUMPY_ALIASES = {"int": int, "float": float, "bool": bool, "object": object, "complex": complex, "str": str}
_KEPT: dict[str, types.ModuleType] = {}


class PeerUnavailable(RuntimeError):
    """The released sources or the BVH data are not beside the repository."""


# what their train.py / models import (import name -> pip name; setup.py's 'peers' extra)
THIRD_PARTY = {"tqdm": "tqdm", "matplotlib": "matplotlib", "torch.utils.tensorboard": "tensorboard"}


def require_peer() -> Path:
    if not (PEER / "models" / "gan1d.py").is_file():
        raise PeerUnavailable(f"the authors' GANimator sources are not at {PEER} (../shared/peers/ganimator)")
    why = unavailable_reason("GANimator", THIRD_PARTY)
    if why is not None:
        raise PeerUnavailable(why)
    return PEER


def require_data(path: Path = WALK) -> Path:
    if not path.is_file():
        raise PeerUnavailable(f"GANimator BVH data not found at {path} (../shared/data)")
    return path


def _is_peer(name: str) -> bool:
    return name.split(".")[0] in PEER_MODULES


@contextlib.contextmanager
def _table(table: SkeletonTable | None) -> Iterator[None]:
    """``table`` appended to their ``SkeletonDatabase`` for the block (their README's step for a custom BVH; the
    peer folder's file is not edited)."""
    if table is None:
        yield
        return
    from bvh.skeleton_database import SkeletonDatabase as db

    saved = {k: getattr(db, k) for k in ("names", "corps_names", "contact_names", "contact_thresholds")}
    db.names = saved["names"] + [table.name]
    db.corps_names = saved["corps_names"] + [list(table.corps)]
    db.contact_names = saved["contact_names"] + [list(table.contacts)]
    db.contact_thresholds = saved["contact_thresholds"] + [table.threshold]
    try:
        yield
    finally:
        for k, v in saved.items():
            setattr(db, k, v)


@contextlib.contextmanager
def peer_runtime(table: SkeletonTable | None = None) -> Iterator[types.SimpleNamespace]:
    """Their modules importable and CPU-only for the duration of the block (``table``: a custom skeleton-table
    entry, as their README asks for a BVH of one's own); yields them."""
    root = require_peer()
    saved = {n: sys.modules.pop(n) for n in [n for n in sys.modules if _is_peer(n)]}
    sys.modules.update(_KEPT)
    added = [k for k in _NUMPY_ALIASES if k not in np.__dict__]
    for k in added:
        setattr(np, k, _NUMPY_ALIASES[k])
    sys.path.insert(0, str(root))
    old_cuda = torch.Tensor.cuda
    torch.Tensor.cuda = lambda self, *a, **k: self  # type: ignore[method-assign]
    try:
        import demo
        import models
        import models.architecture as architecture
        import models.utils as mutils
        import option
        import train
        from dataset import motion

        with _table(table):
            yield types.SimpleNamespace(demo=demo, models=models, architecture=architecture, utils=mutils,
                                        option=option, train=train, motion=motion, root=root)
    finally:
        torch.Tensor.cuda = old_cuda  # type: ignore[method-assign]
        with contextlib.suppress(ValueError):
            sys.path.remove(str(root))
        for k in added:
            delattr(np, k)
        for n in [n for n in sys.modules if _is_peer(n)]:
            _KEPT[n] = sys.modules.pop(n)
        sys.modules.update(saved)


def trim_bvh(src: Path, dst: Path, n_frames: int) -> Path:
    """The first ``n_frames`` frames of a BVH (a short clip keeps the released pyramid small and fast)."""
    lines = Path(src).read_text().splitlines()
    m = next(i for i, l in enumerate(lines) if l.strip().upper().startswith("MOTION"))
    head = lines[:m + 1]
    rest = lines[m + 1:]
    ft = next(l for l in rest if l.strip().lower().startswith("frame time"))
    frames = [l for l in rest if l.strip() and not l.strip().lower().startswith(("frames", "frame time"))]
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text("\n".join(head + [f"Frames: {min(n_frames, len(frames))}", ft] + frames[:n_frames]) + "\n")
    return dst


def _seed(seed: int) -> None:
    torch.manual_seed(seed)
    random.seed(seed)
    np.random.seed(seed)


def train_released(bvh: Path, save_path: Path, iters: int, seed: int = 0, extra: Sequence[str] = (),
                   table: SkeletonTable | None = None) -> "ReleasedRun":
    """Their ``train.py`` on ``bvh`` for ``iters`` iterations per block; the run folder is ``save_path``
    (``table``: the skeleton-table entry of a custom BVH, present while it trains and when the run is loaded)."""
    bvh = Path(bvh).resolve()
    save_path = Path(save_path).resolve()
    argv = ["train.py", f"--bvh_prefix={bvh.parent}", f"--bvh_name={bvh.stem}", f"--save_path={save_path}",
            f"--num_iters={iters}", "--silent=1", "--device=cpu", *extra]
    made: list[tuple[Any, Any, Any]] = []
    with peer_runtime(table) as peer:
        real_create = peer.train.create_model

        def create_model(*a: Any, **k: Any) -> Any:
            res = real_create(*a, **k)
            if isinstance(res, tuple):
                made.append(res)
            return res

        old_argv, cwd = sys.argv, os.getcwd()
        sys.argv = argv
        peer.train.create_model = create_model
        _seed(seed)
        try:
            with contextlib.redirect_stdout(open(os.devnull, "w")):
                peer.train.main()
        finally:
            peer.train.create_model = real_create
            sys.argv = old_argv
            os.chdir(cwd)
    return ReleasedRun(save_path, discs=[m[1] for m in made], table=table)


class ReleasedRun:
    """A released run folder loaded with their ``demo.load_all_from_path``; their outputs on demand.

    ``dtype``: everything (networks, data, z*, amplitudes) in this precision; float64 for equality tests.
    ``table``: the skeleton-table entry the run was trained with (a custom BVH), for their loader.
    """

    def __init__(self, path: Path, discs: Sequence[Any] = (), dtype: torch.dtype = torch.float32,
                 table: SkeletonTable | None = None) -> None:
        self.path = Path(path)
        self.dtype = dtype
        self.table = table
        self.trained_discs = list(discs)
        with peer_runtime(table) as peer:
            with contextlib.redirect_stdout(open(os.devnull, "w")):
                args, datas, gens, z_stars, amps, lengths = peer.demo.load_all_from_path(str(self.path), "cpu")
        self.args, self.motion_data, self.gens = args, datas[0], [g.to(dtype) for g in gens]
        self.z_star = z_stars[0].to(dtype)
        self.amps = amps[0].to(dtype)
        self.lengths = list(lengths[0])
        md = self.motion_data
        md.raw_motion = md.raw_motion.to(dtype)
        if getattr(md, "begin_pos", None) is not None:
            md.begin_pos = md.begin_pos.to(dtype)

    # ---------------------------------------------------------------------------------------- generation
    def draw(self, mode: str, lengths: Sequence[int], amps: Any, given_noise: Sequence[Any] | None = None
             ) -> list[torch.Tensor]:
        """Their ``draw_example`` (mode ``random`` / ``rec``) on the loaded generators: each level's output."""
        with peer_runtime(self.table) as peer, torch.no_grad():
            return peer.architecture.draw_example(self.gens, mode, self.z_star, list(lengths), amps, 1, self.args,
                                                  all_img=True, conds=None, full_noise=self.args.full_noise,
                                                  given_noise=given_noise)

    def level_outputs(self, noises: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """Each level's output ``(1, E*6, L)`` for the given per-level noise ``(1, 1, L)`` (already scaled)."""
        return self.draw("random", self.lengths, self.amps, [n.to(self.dtype) for n in noises])

    def reconstruction(self) -> list[torch.Tensor]:
        """Each level's output from their fixed noise z* (their ``rec`` mode)."""
        return self.draw("rec", self.lengths + [1], self.amps)

    def demo_sample(self, target_len: int, seed: int = 0) -> tuple[list[torch.Tensor], torch.Tensor]:
        """Their ``demo.py`` random sample of ``target_len`` frames: noise at the coarsest level only.
        Returns each level's output and the coarsest noise used ``(1, 1, L0)``."""
        with peer_runtime(self.table) as peer:
            lengths = peer.architecture.get_pyramid_lengths(self.args, target_len)
            while len(lengths) > len(self.gens):
                lengths = lengths[1:]
            _seed(seed)
            z = peer.demo.gen_noise(1, lengths[0], self.args.full_noise, "cpu").to(self.dtype)[:, :1]
        z = z * self.amps[0]
        amps2 = self.amps.clone()
        amps2[1:] = 0
        return self.draw("random", lengths, amps2, [z]), z

    def write_bvh(self, path: Path, motion: torch.Tensor) -> Path:
        """Their BVH writer (``MotionData.write``; also writes ``path.contact.npy``)."""
        with peer_runtime(self.table):
            self.motion_data.write(str(path), motion.detach().to(self.dtype))
        return Path(path)

    def reals(self) -> list[torch.Tensor]:
        """The training clip at every level, as their ``train.py`` builds it."""
        return [self.motion_data.sample(size=L) for L in self.lengths]

    # ---------------------------------------------------------------------------------------- one step
    def gan_model(self, level: int, disc_state: dict | None = None, seed: int = 0) -> Any:
        """Their ``GAN_model`` of ``level`` (their ``create_model``) with the loaded generator; the
        discriminator is freshly initialised from ``seed`` unless ``disc_state`` is given."""
        with peer_runtime(self.table) as peer:
            _seed(seed)
            with contextlib.redirect_stdout(open(os.devnull, "w")):
                gen, disc, gm = peer.models.create_model(self.args, self.motion_data)
        gen.load_state_dict(self.gens[level].state_dict())
        if disc_state is not None:
            disc.load_state_dict(disc_state)
        gm.gen, gm.disc = gen.to(self.dtype), disc.to(self.dtype)
        gm.criterion_consistency.to(self.dtype)
        return gm

    def losses(self, gm: Any, real: torch.Tensor, base: torch.Tensor, fake_delta: torch.Tensor, seed: int = 0
               ) -> dict[str, Any]:
        """Their loss terms of one D step and one G step and the reconstruction term, for the level output
        ``base + fake_delta`` (``fake_delta``: the generator's residual, with its graph): ``loss_D``, ``loss_gp``
        (with the WGAN-GP's alpha drawn after ``torch.manual_seed(seed)``), ``loss_G``, ``loss_consistency``,
        ``loss_rec`` and the gradients they leave on the discriminator (D step) and the generator (G step)."""
        with peer_runtime(self.table):
            gm.gen.output = fake_delta
            gm.forward_proxy(real, base)
            gm.disc_requires_grad_(True)
            for p in gm.disc.parameters():
                p.grad = None
            torch.manual_seed(seed)
            gm.backward_D()
            d_grads = {k: p.grad.detach().clone() for k, p in gm.disc.named_parameters() if p.grad is not None}
            gm.disc_requires_grad_(False)
            for p in gm.gen.parameters():
                p.grad = None
            gm.backward_G()
            g_grads = {k: p.grad.detach().clone() for k, p in gm.gen.named_parameters() if p.grad is not None}
            loss_rec = gm.criterion_rec(gm.fake_res, gm.real_res)
        return {"loss_D": gm.loss_D.detach(), "loss_gp": gm.loss_gp.detach(), "loss_G": gm.loss_G.detach(),
                "loss_consistency": gm.loss_consistency.detach(), "loss_rec": loss_rec.detach(),
                "d_grads": d_grads, "g_grads": g_grads}


    def train_iteration(self, levels: Sequence[int], seed: int = 0, disc_seed: int = 0,
                        masks_trainable: bool = True) -> list[Any]:
        """One iteration of their ``joint_train`` on the block ``levels`` (which must end at the finest level)
        from the loaded generators and fresh discriminators (``disc_seed``), after ``torch.manual_seed(seed)``;
        returns the block's ``GAN_model`` objects after their Adam steps (the loaded generators are not touched).

        ``masks_trainable=False`` keeps their discriminators' 0/1 masks out of training: as released, their
        ``disc_requires_grad_(True)`` re-enables the masks' gradients too, and their Adam then moves the masks."""
        import copy

        gens = copy.deepcopy(self.gens)
        if list(levels)[-1] != len(gens) - 1:
            raise ValueError("the block must end at the finest level (their noise draws cover the block's levels)")
        gms = []
        for level in levels:
            gm = self.gan_model(level, seed=disc_seed + level)
            gm.gen = gens[level]
            gm.optimizerG = torch.optim.Adam(gm.gen.parameters(), lr=self.args.lr_g)
            gm.optimizerD = torch.optim.Adam(gm.disc.parameters(), lr=self.args.lr_d)
            if not masks_trainable:
                def requires(flag: bool, disc: Any = gm.disc) -> None:
                    for name, p in disc.named_parameters():
                        if not name.endswith("mask"):
                            p.requires_grad = flag
                gm.disc_requires_grad_ = requires
            gms.append(gm)
        args = copy.copy(self.args)
        args.num_iters, args.silent = 1, 1
        recorder = types.SimpleNamespace(add_scalar=lambda *a, **k: None)
        default = torch.get_default_dtype()
        with peer_runtime(self.table) as peer:
            torch.set_default_dtype(self.dtype)  # their zeros and noise draws, in the run's precision
            _seed(seed)
            try:
                peer.architecture.joint_train([self.reals()], gens, gms, [self.lengths], [self.z_star], [self.amps],
                                              args, recorder, None)
            finally:
                torch.set_default_dtype(default)
        return gms


__all__ = ["PEER", "DATA", "WALK", "BANDAI", "SkeletonTable", "BANDAI_TABLE", "PeerUnavailable", "require_peer", "require_data", "peer_runtime", "trim_bvh",
           "train_released", "ReleasedRun"]
