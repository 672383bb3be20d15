"""GANimator training: WGAN-GP per level, L1 reconstruction from fixed noise, contact consistency, level blocks.

One iteration of a block (two consecutive levels by default) is, for every training clip in turn:
``d_steps`` discriminator updates on fresh random samples (with a pool of past fakes), ``g_steps`` adversarial
generator updates (+ contact consistency), and one reconstruction update from the clip's fixed noise ``z*``.
Inside a block the finer level sees the coarser level's live output, but each level learns only from its own
losses (the authors' scheme; the output is detached between levels). Levels below the block are frozen.

The checkpoint is one file (written atomically) holding the config, the clips in GANimator form, the pyramid,
noise amplitudes, ``z*``, every network and optimiser, the fake pools, the RNG state and the position in the
schedule, so ``train`` on the same run directory resumes exactly where it stopped, and ``generate`` needs
nothing else. Ctrl-C and SIGTERM finish the iteration and save (``modi.faults``); the run folder is locked
meanwhile, ``log.jsonl`` gets the losses every ``LOG_EVERY`` iterations, and ``progress.json`` (rewritten
atomically at most once a second) says where the schedule stands, for front ends such as the Blender add-on.

An iteration asks nothing of the device: its losses stay device tensors, read at log iterations (every
``LOG_EVERY`` and a block's last); a NaN/inf loss skips its optimiser step on the device (fused Adam's
``found_inf``) and is reported at the next log iteration or save, which stops the run as a non-finite loss always
did (``NonFiniteLossError``, naming the first one), so no non-finite weight ever exists and none is saved.

Precision (docs/precision.md): with ``precision="bf16"`` the generators' and discriminators' forward passes run under
bf16 autocast, the WGAN-GP's included (in bf16 it keeps as many digits as the WGAN loss itself); the losses and the
contact consistency (FK) take their outputs cast to fp32, and the weights, optimiser states, fake pools and
checkpoint stay fp32. The checkpoint records the precision; a resume keeps it unless another is asked for.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor, nn
from tqdm import tqdm

from modi import faults
from modi._version import __version__ as modi_version
from modi.core.rotations import sixd_to_quat
from modi.core.skeleton import Skeleton
from modi.errors import CheckpointError, NonFiniteLossError, UserError
from modi.io.safe_load import UnreadableFileError, earlier_modi_globals, load_data
from modi.models.ganimator.config import GanimatorConfig
from modi.models.ganimator.data import K, check_compatible, real_pyramid, resample, sequence_pyramid
from modi.models.ganimator.data import Sequence as Clip
from modi.models.ganimator.networks import GanimatorModel, synthesize
from modi.models.optim import frozen_heap, fused_adam, fused_groups
from modi.models.precision import DEFAULT_PRECISION, PRECISIONS, check_precision, precision_autocast, widened
from modi_ext.layers import ForwardKinematics

FORMAT = "modi.ganimator/1"
CHECKPOINT_NAME = "ganimator.ckpt"
LOG_EVERY = 10  # iterations between lines of RUN/log.jsonl (and the iterations whose losses are read)
GUARDED = {"D": "discriminator", "G": "generator adversarial + contact", "R": "reconstruction"}  # the updates
PROGRESS_NAME = "progress.json"  # RUN/progress.json: block, iteration, totals, ETA, state (see Trainer._progress)


# ------------------------------------------------------------------------------------------- (de)serialising


def skeleton_to_dict(s: Skeleton) -> dict:
    return {"names": list(s.names), "parents": list(s.parents), "offsets": torch.as_tensor(s.offsets),
            "end_sites": {int(k): torch.as_tensor(np.asarray(v, dtype=np.float64)) for k, v in s.end_sites.items()},
            "rotation_orders": list(s.rotation_orders or [])}


def skeleton_from_dict(d: dict) -> Skeleton:
    return Skeleton(list(d["names"]), list(d["parents"]), d["offsets"].numpy(),
                    {int(k): v.numpy() for k, v in d["end_sites"].items()}, list(d["rotation_orders"]) or None)


def clip_to_dict(c: Clip) -> dict:
    return {"name": c.name, "skeleton": skeleton_to_dict(c.skeleton), "feet": list(c.feet), "features": c.features,
            "root_start": c.root_start, "fps": float(c.fps), "scale": float(c.scale),
            "contact_threshold": float(c.contact_threshold), "size": float(c.size),
            "kept_joints": list(c.kept_joints), "sixd": c.sixd}


def clip_from_dict(d: dict) -> Clip:
    return Clip(name=d["name"], skeleton=skeleton_from_dict(d["skeleton"]), feet=list(d["feet"]),
                features=d["features"], root_start=d["root_start"], fps=d["fps"], scale=d["scale"],
                contact_threshold=d["contact_threshold"], size=d["size"], kept_joints=list(d["kept_joints"]),
                sixd=d.get("sixd", "columns"))  # clips saved before the option were column 6D


def model_payload(model: GanimatorModel) -> dict:
    """What ``generate`` needs: config, clips, pyramid, amplitudes, z*, generator weights."""
    return {"config": model.cfg.to_dict(), "clips": [clip_to_dict(c) for c in model.seqs],
            "lengths": model.lengths, "amps": model.amps, "z_stars": [z.detach().cpu() for z in model.z_stars],
            "gens": [g.state_dict() for g in model.gens]}


def model_from_payload(p: dict, with_discriminators: bool = False, device: str = "cpu") -> GanimatorModel:
    cfg = GanimatorConfig.from_dict(p["config"])
    clips = [clip_from_dict(c) for c in p["clips"]]
    model = GanimatorModel(cfg, clips, p["lengths"], p["amps"], p["z_stars"], with_discriminators=with_discriminators)
    for g, sd in zip(model.gens, p["gens"]):
        g.load_state_dict(sd)
    return model.to(device)


def atomic_save(obj: dict, path: Path, previous: str | None = None) -> None:
    """Write to a temporary file in the same directory, fsync, then rename over the target (``modi.faults``: a
    full disk is one line naming ``previous``, the position of the checkpoint left intact)."""
    faults.atomic_torch_save(obj, path, previous_step=previous)


def checkpoint_path(run: str | Path) -> Path:
    run = Path(run)
    return run if run.suffix == ".ckpt" or run.is_file() else run / CHECKPOINT_NAME


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during ``Trainer.run``: the run was checkpointed at an iteration boundary and can be
    resumed; ``exit_code`` is 130 / 143."""

    def __init__(self, checkpoint: Path, signum: int | None = None) -> None:
        super().__init__(f"checkpoint saved to {checkpoint}")
        self.checkpoint = checkpoint
        self.signum = signum
        self.exit_code = faults.exit_code(signum)


# what to do with a checkpoint modi cannot read as data (the authors' runs convert through 'modi import')
_INSTEAD = ("re-train it with 'modi ganimator train', or convert a run of the authors' released code with "
            "'modi import ganimator-released'")


def read_checkpoint(run: str | Path) -> dict:
    """The checkpoint of a run folder (or ``.ckpt`` file), read as data only (``modi.io.safe_load``): every
    ``modi.ganimator/1`` file modi has written holds plain containers and tensors; one that names any other code is
    refused, unrun, with one line."""
    path = checkpoint_path(run)
    if not path.is_file():
        if path.parent.is_dir() and (path.parent / "gen000.pt").is_file():
            raise CheckpointError(f"no GANimator checkpoint at {path}: {path.parent} looks like a run of the authors' "
                                  "released code; convert it with 'modi import ganimator-released'")
        raise CheckpointError(f"no GANimator checkpoint at {path}")
    try:
        ck = load_data(path, "GANimator checkpoint", allowed=earlier_modi_globals(), hint=f"; {_INSTEAD}")
    except UnreadableFileError as exc:  # a truncated or foreign file
        raise CheckpointError(f"cannot read checkpoint {path}: not a checkpoint, or a truncated/damaged one "
                              f"({exc.reason})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        found = ck.get("format") if isinstance(ck, dict) else None
        what = "a MoDi checkpoint: sample it with 'modi generate'" if found == "modi-checkpoint" else _INSTEAD
        raise CheckpointError(f"{path} is not a GANimator checkpoint (format {found or '?'}, expected {FORMAT}); "
                              f"{what}")
    return ck


def load_model(run: str | Path, device: str = "cpu") -> GanimatorModel:
    """The trained generator of a run directory (or ``.ckpt`` file), ready to sample."""
    ck = read_checkpoint(run)
    model = model_from_payload(ck["model"], device=device)
    model.trained_levels = ck["state"]["levels_done"]
    if ck.get("cond_source") is not None:
        model.cond_source = model_from_payload(ck["cond_source"], device=device)
    else:
        model.cond_source = None
    model.eval()
    return model


# ------------------------------------------------------------------------------------------- losses


class FakePool:
    """History of generated samples (pix2pix's image pool): half the time D sees an older fake."""

    def __init__(self, size: int) -> None:
        self.size = int(size)
        self.items: list[Tensor] = []

    def query(self, fake: Tensor) -> Tensor:
        if self.size <= 0:
            return fake
        fake = fake.detach()
        if len(self.items) < self.size:
            self.items.append(fake.clone())
            return fake
        if float(torch.rand(())) > 0.5:
            i = int(torch.randint(self.size, ()))
            old = self.items[i]
            self.items[i] = fake.clone()
            return old
        return fake


def gradient_penalty(disc: nn.Module, real: Tensor, fake: Tensor) -> Tensor:
    """WGAN-GP: (||grad D(interp)|| - 1)^2, the norm taken over all channels of each frame."""
    alpha = torch.rand((1,), device=real.device)
    interp = (alpha * real + (1 - alpha) * fake.detach()).requires_grad_(True)
    score = disc(interp)
    (grad,) = torch.autograd.grad(score.sum(), interp, create_graph=True)
    # the norm over channels and entities of each frame, as a sum of squares: torch's norm over those strided axes
    # took ~2x as long with its backward (clamped so that a zero gradient has a zero gradient, as norm's has)
    norm = grad.square().sum((1, 2)).clamp_min(1e-30).sqrt()
    return ((norm - 1.0) ** 2).mean()


class ContactConsistency(nn.Module):
    """Either the foot is still or its contact label is off: mean(|foot velocity| * sigmoid(12 (c - 0.5))).

    ``rate`` (a level's length / the source's) converts the level's per-source-frame root displacement and its foot
    displacement per level frame to per-source-frame units; ``rate=1`` measures everything per level frame, as the
    released code does (``contact_rescale=False``), which makes the loss ~1/rate stronger at coarse levels.
    """

    def __init__(self, skeleton: Skeleton, feet: Sequence[int], sixd: str = "rows") -> None:
        super().__init__()

        self.fk = ForwardKinematics(skeleton.parents, torch.as_tensor(skeleton.offsets, dtype=torch.float32))
        self.feet = list(feet)
        # the feet as a device index (a Python list would upload one every call)
        self.register_buffer("feet_index", torch.tensor(self.feet, dtype=torch.long), persistent=False)
        self.J = skeleton.n_joints
        self.sixd = sixd

    def forward(self, x: Tensor, rate: float = 1.0) -> Tensor:
        if not self.feet:
            return x.new_zeros(())

        J = self.J
        # (B, T, J, 6), contiguous: the Gram-Schmidt norms over a strided last axis ran ~10x slower than this copy
        rot6 = x[:, :, :J].permute(0, 3, 2, 1).contiguous()
        quats = sixd_to_quat(rot6, layout=self.sixd)
        rm = x[:, :, J]  # (B, 6, T): per-fine-frame displacement, so scale to this level's frame step
        dx, y, dz = rm[:, 0] / rate, rm[:, 1], rm[:, 2] / rate
        root = torch.stack([torch.cumsum(dx, -1), y, torch.cumsum(dz, -1)], dim=-1)  # (B, T, 3)
        pos = self.fk(quats, root).index_select(2, self.feet_index)  # (B, T, C, 3)
        vel = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1) * rate
        vel = torch.cat([torch.zeros_like(vel[:, :1]), vel], dim=1)  # (B, T, C)
        label = x[:, 0, J + 1:].transpose(1, 2)  # (B, T, C)
        return (vel * torch.sigmoid((label - 0.5) * 12.0)).mean()


# ------------------------------------------------------------------------------------------- trainer


def read_losses(losses: dict[str, Tensor]) -> dict[str, float]:
    """The losses of an iteration as floats, in one host read."""
    if not losses:
        return {}
    return dict(zip(losses, torch.stack([v.float().reshape(()) for v in losses.values()]).tolist()))


def blocks_of(n_levels: int, group: int) -> list[list[int]]:
    return [list(range(i, min(i + group, n_levels))) for i in range(0, n_levels, group)]


class Trainer:
    """Holds the model, data pyramids, optimisers and schedule position; ``run()`` trains to the end."""

    def __init__(self, clips: Sequence[Clip], cfg: GanimatorConfig, run_dir: str | Path,
                 cond_source: GanimatorModel | None = None, precision: str | None = None) -> None:
        check_compatible(clips)
        # None: a new run's default, or a resumed run's checkpoint's; given: this precision (a resume switches)
        self._precision_asked = check_precision(precision) if precision is not None else None
        self.precision = self._precision_asked or DEFAULT_PRECISION
        self._precision_before: str | None = None  # a resumed checkpoint's, when this run switched from it
        if cfg.conditional and cond_source is None:
            raise UserError("a conditional (trajectory) model needs a trained unconditional run to sample "
                            "trajectories from (--conditional-from RUN)")
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.ckpt = checkpoint_path(self.run_dir)
        self.device = torch.device(cfg.device)
        torch.manual_seed(cfg.seed)
        self.clips = list(clips)
        lengths, _ = sequence_pyramid(self.clips, cfg)
        self.reals = [[r.unsqueeze(0).to(self.device) for r in real_pyramid(c, l)] for c, l in zip(self.clips, lengths)]
        amps = []
        for m, (c, l) in enumerate(zip(self.clips, lengths)):
            row = []
            for i in range(len(l)):
                prev = torch.zeros_like(self.reals[m][0]) if i == 0 else resample(self.reals[m][i - 1], l[i],
                                                                                    l[i - 1] / l[i])
                row.append(float(((self.reals[m][i] - prev) ** 2).mean().sqrt()))
            amps.append(row)
        E = self.clips[0].n_entities
        z_stars = [torch.randn(1, K, E, l[0]) for l in lengths]
        self.model = GanimatorModel(cfg, self.clips, lengths, amps, z_stars).to(self.device)
        self.cond_source = cond_source.to(self.device) if cond_source is not None else None
        self.consistency = ContactConsistency(self.clips[0].skeleton, self.clips[0].feet, cfg.sixd).to(self.device)
        self.blocks = blocks_of(self.model.n_levels, cfg.group_size)
        self.state = {"block": 0, "iteration": 0, "levels_done": 0, "block_seconds": [0.0] * len(self.blocks),
                      "history": []}
        self.pools = [FakePool(cfg.fake_pool) for _ in range(self.model.n_levels)]
        self.opt_g: dict[int, torch.optim.Optimizer] = {}
        self.opt_d: dict[int, torch.optim.Optimizer] = {}
        self.writer = None
        self._saved: str | None = None  # schedule position of the checkpoint on disk (for a disk-full message)
        # The non-finite guard, on the device (see _guarded_step): whether a loss was NaN/inf since the run started,
        # the first such iteration (1-based, of the block) and which update it was; read at log iterations, saves
        # and the block's end. ``losses_read``: the last iteration's losses where it was read (else empty).
        self._bad_seen = torch.zeros((), device=self.device)
        self._bad_iteration = torch.zeros((), device=self.device)
        self._bad_what = torch.zeros((), dtype=torch.long, device=self.device)
        self._iteration_dev = torch.zeros((), device=self.device)
        self._what_codes = torch.arange(len(GUARDED), device=self.device)
        self.losses_read: dict[str, float] = {}

    # --------------------------------------------------------------------------------- persistence

    def _payload(self) -> dict:
        m = self.model
        return {
            "format": FORMAT,
            "model": model_payload(m),
            "discs": [d.state_dict() for d in m.discs],
            "opt_g": {l: o.state_dict() for l, o in self.opt_g.items()},
            "opt_d": {l: o.state_dict() for l, o in self.opt_d.items()},
            "pools": [p.items for p in self.pools],
            "state": dict(self.state),
            "rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            "cond_source": model_payload(self.cond_source) if self.cond_source is not None else None,
            "modi_version": modi_version,
            "precision": self.precision,
        }

    def save(self) -> None:
        self.check_guard()
        m = self.model
        bad = [f"{kind} {l}" for kind, nets in (("generator", m.gens), ("discriminator", m.discs))
               for l, net in enumerate(nets) if not all(bool(torch.isfinite(t).all()) for t in net.parameters())]
        if bad:  # a finite loss can still step to inf weights: never write them over the last good checkpoint
            self._diverged(f"non-finite weights ({', '.join(bad)}) at the save of {self._position()}")
        atomic_save(self._payload(), self.ckpt, previous=self._saved)
        self._saved = self._position()

    def _diverged(self, what: str) -> None:
        kept = (f"the last good checkpoint, {self.ckpt} ({self._saved}), is kept" if self._saved is not None
                else "nothing was saved")
        raise NonFiniteLossError(f"{what}: GANimator training stopped; {kept}. Try another --seed, or check the "
                                 "BVH for NaN or huge values")

    def _guarded_step(self, opts: Sequence[torch.optim.Optimizer], loss: Tensor, what: str,
                      levels: Sequence[int]) -> None:
        """``loss.backward()`` and a step of ``opts``, skipped on the device when the loss is NaN/inf (fused Adam's
        ``found_inf``), the first such update recorded for ``check_guard`` to report: no host read, and no
        non-finite weight ever exists. An optimiser off the fused kernel (a checkpoint saved without it) checks on
        the host and stops at once, as every step did before."""
        bad = torch.isfinite(loss.detach()).logical_not().float().reshape(())
        if not all(fused_groups(o) for o in opts):
            if bool(bad):
                self._diverged(f"non-finite loss ({GUARDED[what]}, levels {levels[0]}-{levels[-1]}) in block "
                               f"{self.state['block'] + 1}/{len(self.blocks)}, iteration {self.state['iteration'] + 1}")
            loss.backward()
            for o in opts:
                o.step()
            return
        first = (self._bad_seen == 0) & (bad > 0)
        self._bad_iteration.copy_(torch.where(first, self._iteration_dev, self._bad_iteration))
        self._bad_what.copy_(torch.where(first, self._what_codes[list(GUARDED).index(what)], self._bad_what))
        self._bad_seen.copy_(torch.maximum(self._bad_seen, bad))
        loss.backward()
        for o in opts:
            o.found_inf = bad
            try:
                o.step()
            finally:
                del o.found_inf

    def check_guard(self) -> None:
        """Read the non-finite guard (one host read): a NaN/inf loss since the run started stops it, with the
        first one named (see ``NonFiniteLossError``)."""
        seen, iteration, what = torch.stack([self._bad_seen, self._bad_iteration,
                                             self._bad_what.to(self._bad_seen.dtype)]).tolist()
        if seen:
            levels = self.blocks[min(self.state["block"], len(self.blocks) - 1)]
            self._diverged(f"non-finite loss ({list(GUARDED.values())[int(what)]}, levels {levels[0]}-{levels[-1]}) "
                           f"in block {self.state['block'] + 1}/{len(self.blocks)}, iteration {int(iteration)}")

    def _position(self) -> str:
        b, n = self.state["block"], len(self.blocks)
        return "fully trained" if b >= n else f"block {b + 1}/{n}, iteration {self.state['iteration']}"

    def restore(self, ck: dict) -> None:
        p = ck["model"]
        names = [c["name"] for c in p["clips"]]
        if names != [c.name for c in self.clips] or p["lengths"] != self.model.lengths:
            raise CheckpointError(f"{self.ckpt} holds a run on {', '.join(names)}; use another --out to start anew")
        saved_cfg = GanimatorConfig.from_dict(p["config"])
        # the schedule length (and where to run / how often to save) may change on resume; the model may not
        free = {"iterations", "block_iterations", "coarse_multiplier", "checkpoint_every", "device"}
        diff = [k for k, v in saved_cfg.to_dict().items() if k not in free and self.cfg.to_dict().get(k) != v]
        if diff:
            saved, now = saved_cfg.to_dict(), self.cfg.to_dict()
            detail = ", ".join(f"{k}: {saved[k]!r} there, {now.get(k)!r} now" for k in diff)
            raise CheckpointError(f"{self.ckpt} was trained with other settings ({detail}); "
                                  "pass the same settings to resume it, or use another --out to start anew")
        m = self.model
        for z, zs in zip(m.z_stars, p["z_stars"]):
            z.data.copy_(zs)
        m.amps = p["amps"]
        for g, sd in zip(m.gens, p["gens"]):
            g.load_state_dict(sd)
        for d, sd in zip(m.discs, ck["discs"]):
            d.load_state_dict(sd)
        self.state = dict(ck["state"])
        for l, sd in ck["opt_g"].items():
            self._make_opts(int(l))
            self.opt_g[int(l)].load_state_dict(sd)
        for l, sd in ck["opt_d"].items():
            self._make_opts(int(l))
            self.opt_d[int(l)].load_state_dict(sd)
        for pool, items in zip(self.pools, ck["pools"]):
            pool.items = [t.to(self.device) for t in items]
        torch.set_rng_state(ck["rng"])
        if ck.get("cuda_rng") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(ck["cuda_rng"])
        saved = ck.get("precision", DEFAULT_PRECISION)
        if saved not in PRECISIONS:
            raise CheckpointError(f"{self.ckpt} was trained in precision {saved!r}, which this modi does not know "
                                  f"({', '.join(PRECISIONS)}); upgrade modi")
        if self._precision_asked is None:
            self.precision = saved
        elif self._precision_asked != saved:
            self._precision_before = saved
        self._saved = self._position()

    def _autocast(self):
        """The context of the forward passes (see the module docstring: bf16 autocast, or nothing for fp32)."""
        return precision_autocast(self.precision, self.device)

    def _make_opts(self, l: int) -> None:
        if l not in self.opt_g:
            m = self.model
            self.opt_g[l] = fused_adam(m.gens[l].parameters(), self.cfg.lr, self.cfg.betas)
            self.opt_d[l] = fused_adam(m.discs[l].parameters(), self.cfg.lr, self.cfg.betas)

    # --------------------------------------------------------------------------------- sampling helpers

    def _conds(self, m: int, lengths: Sequence[int], mode: str) -> list[Tensor] | None:
        if not self.model.cond_entities:
            return None
        ce = self.model.cond_entities
        if mode == "rec" or self.cond_source is None:
            return [r[:, :, ce] for r in self.reals[m]]
        src = self.cond_source
        T = lengths[-1]
        with torch.no_grad():
            full = src.sample(T, 1, fine_noise=True)
        return [resample(full[:, :, ce], L, T / L) if L != T else full[:, :, ce] for L in lengths]

    def _forward(self, m: int, levels: list[int], mode: str, grad: bool, cached_prev: dict) -> list[Tensor]:
        """Outputs of the block's levels for clip ``m``; levels below run frozen (cached for reconstruction)."""
        model = self.model
        lengths, rates = model.lengths[m], model.rates[m]
        lo, hi = levels[0], levels[-1] + 1
        with self._autocast():
            outs = self._synthesize(m, lo, hi, lengths, rates, mode, grad, cached_prev)
        return [widened(o) for o in outs]  # the losses, the contact terms and the fake pools in fp32 (or float64)

    def _synthesize(self, m: int, lo: int, hi: int, lengths: Sequence[int], rates: Sequence[float], mode: str,
                    grad: bool, cached_prev: dict) -> list[Tensor]:
        """``_forward``'s outputs in the precision the caller set (bf16 under bf16 autocast)."""
        model = self.model
        conds = self._conds(m, lengths, mode)
        if mode == "rec":
            noises = model.rec_noises(m)
            prev = cached_prev.get(m)
            if prev is None and lo > 0:
                with torch.no_grad():
                    prev = synthesize(model.gens, rates, lengths, noises, model.n_entities, 0, lo, conds=conds)[-1]
                cached_prev[m] = prev
        else:
            noises = [torch.randn(1, 1, 1, L, device=self.device) * a for L, a in zip(lengths, model.amps[m])]
            prev = None
            if lo > 0:
                with torch.no_grad():
                    prev = synthesize(model.gens, rates, lengths, noises, model.n_entities, 0, lo, conds=conds)[-1]
        with torch.set_grad_enabled(grad):
            return synthesize(model.gens, rates, lengths, noises, model.n_entities, lo, hi, prev=prev, conds=conds,
                              detach_between=True)

    # --------------------------------------------------------------------------------- the loop

    def run(self, progress: bool = True, log: Callable[[str], None] | None = print,
            max_seconds: float | None = None) -> GanimatorModel:
        """Train (or resume) to the end of the schedule; returns the model. ``max_seconds`` stops early
        (checkpointed) — a budgeted run that a later call continues. Ctrl-C or SIGTERM finishes the iteration,
        saves and raises ``TrainingInterrupted``; running again resumes. The run folder is locked meanwhile."""
        with faults.hold_run_folder(self.ckpt.parent):
            faults.remove_stale_temps(self.ckpt)
            return self._run_locked(progress, log, max_seconds)

    def _run_locked(self, progress: bool, log: Callable[[str], None] | None,
                    max_seconds: float | None) -> GanimatorModel:
        if self.ckpt.is_file():
            self.restore(read_checkpoint(self.ckpt))
            if log and self.state["block"] >= len(self.blocks):
                log(f"{self.ckpt} is already fully trained ({len(self.blocks)} blocks of levels); nothing to do "
                    "(choose another --out to train anew)")
            elif log:
                log(f"resuming {self.ckpt}: block {self.state['block'] + 1}/{len(self.blocks)}, "
                    f"iteration {self.state['iteration']}, in {self.precision}")
            if log and self._precision_before is not None:
                log(f"{self.ckpt} was trained in {self._precision_before}; continuing in {self.precision} as asked "
                    "(weights and optimiser states carry over unchanged)")
        # Ctrl-C / SIGTERM: finish the iteration, save, raise TrainingInterrupted (a second Ctrl-C aborts)
        with faults.stop_on_signals("iteration") as stop, frozen_heap():
            return self._run_blocks(progress, log, max_seconds, stop)

    def _run_blocks(self, progress: bool, log: Callable[[str], None] | None, max_seconds: float | None,
                    stop: Any) -> GanimatorModel:
        cfg, model = self.cfg, self.model
        try:
            from torch.utils.tensorboard import SummaryWriter  # lazy: tensorboard costs ~1 s to import, only here

            with faults.output_errors(self.run_dir / "tb"):
                self.writer = SummaryWriter(str(self.run_dir / "tb"))
        except faults.OutputError:
            raise
        except Exception:  # tensorboard missing: training works without logs
            self.writer = None
        started = time.time()
        M = len(self.clips)
        n_sub = cfg.d_steps + cfg.g_steps + 1
        while self.state["block"] < len(self.blocks):
            b = self.state["block"]
            levels = self.blocks[b]
            for l in levels:
                self._make_opts(l)
            for l in range(model.n_levels):
                req = l in levels
                for p in model.gens[l].parameters():
                    p.requires_grad_(req)
            cached_prev: dict = {}
            budget = cfg.block_budget(b)
            bar = tqdm(total=budget, initial=self.state["iteration"], disable=not progress,
                       desc=f"levels {levels[0]}-{levels[-1]} / {model.n_levels}", leave=True, mininterval=2.0)
            t_block = time.time()
            t_save = time.time()
            first_it = self.state["iteration"]
            self._iteration_dev.fill_(first_it)
            self._progress("training", force=True)
            while self.state["iteration"] < budget:
                it = self.state["iteration"] + 1
                logged = it % LOG_EVERY == 0 or it == budget  # the iterations whose losses are read
                try:
                    losses = self._iteration(levels, M, n_sub, cached_prev)
                    if logged:
                        self.check_guard()
                except NonFiniteLossError:
                    bar.close()
                    if self.writer is not None:
                        self.writer.close()
                    raise
                self.losses_read = read_losses(losses) if logged else {}
                self.state["iteration"] = it
                bar.update(1)
                self._progress("training", block_rate=(time.time() - t_block) / max(1, it - first_it))
                if logged:
                    faults.append_line(self.run_dir / "log.jsonl", json.dumps(
                        {"block": b, "iteration": it, **{k: round(v, 6) for k, v in self.losses_read.items()}}))
                if it % 50 == 0 or it == budget:  # a log iteration too (LOG_EVERY divides 50)
                    bar.set_postfix({k: f"{v:.3g}" for k, v in self.losses_read.items()
                                     if k in ("D", "G", "rec", "con")})
                    if self.writer is not None:
                        step = sum(cfg.block_budgets(b)) + it
                        with faults.output_errors(self.run_dir / "tb"):  # event files appended by the library
                            for k, v in self.losses_read.items():
                                self.writer.add_scalar(f"block{b}/{k}", v, step)
                now = time.time()
                if now - t_save > cfg.checkpoint_every:
                    self.state["block_seconds"][b] += now - t_block
                    t_block = now
                    self.save()
                    t_save = time.time()
                if it == budget:  # the block's last iteration: close the block first (its history, its save)
                    break
                if max_seconds is not None and now - started > max_seconds:
                    self.state["block_seconds"][b] += now - t_block
                    bar.close()
                    self.save()
                    self._progress("paused", force=True)
                    return model
                if stop:
                    self.state["block_seconds"][b] += now - t_block
                    bar.close()
                    self._stop(stop)
            bar.close()
            self.state["block_seconds"][b] += time.time() - t_block
            self.state["history"].append({"block": b, "levels": levels, "iterations": self.state["iteration"],
                                          **self.losses_read})
            self.state["block"] += 1
            self.state["iteration"] = 0
            self.state["levels_done"] = levels[-1] + 1
            self.save()
            if log:
                log(f"levels {levels[0]}-{levels[-1]} done in {self.state['block_seconds'][b]:.1f} s")
            if self.state["block"] < len(self.blocks):
                if max_seconds is not None and time.time() - started > max_seconds:
                    self._progress("paused", force=True)
                    return model
                if stop:
                    self._stop(stop, save=False)  # just saved
        if self.writer is not None:
            with faults.output_errors(self.run_dir / "tb"):
                self.writer.close()
        model.trained_levels = model.n_levels
        self._progress("done", force=True)
        return model

    def _progress(self, state: str, block_rate: float | None = None, force: bool = False) -> None:
        """Rewrite ``RUN/progress.json`` (atomically, at most once a second unless ``force``): the block and
        iteration, the totals, and an ETA: the current block's seconds per iteration, scaled for each block left
        by the frames of the levels it trains (an estimate). A failed write is not worth stopping a run for:
        progress is advisory."""
        now = time.time()
        if block_rate is not None:
            self._block_rate = block_rate
        if not force and now - getattr(self, "_progress_at", 0.0) < 1.0:
            return
        self._progress_at = now
        budgets = self.cfg.block_budgets(len(self.blocks))
        b = min(self.state["block"], len(self.blocks) - 1)
        done_iters = sum(budgets[:self.state["block"]]) + (self.state["iteration"] if state != "done" else 0)
        # an iteration costs about the frames of the levels it trains: weigh the blocks left by that
        frames = self.model.lengths[0]
        weight = [sum(frames[lv] for lv in levels) for levels in self.blocks]
        left = (budgets[b] - self.state["iteration"]) * weight[b] + sum(n * w for n, w in
                                                                         zip(budgets[b + 1:], weight[b + 1:]))
        rate = getattr(self, "_block_rate", None)
        levels = self.blocks[b]
        info = {"state": state, "block": b + 1, "blocks": len(self.blocks), "levels": [levels[0], levels[-1]],
                "n_levels": self.model.n_levels, "iteration": self.state["iteration"] if state != "done" else
                budgets[b], "iterations": budgets[b], "done_iterations": done_iters,
                "total_iterations": sum(budgets),
                "eta_s": None if rate is None or state == "done" else round(rate / weight[b] * left, 1),
                "time": round(now, 3)}
        try:
            faults.atomic_write(self.run_dir / PROGRESS_NAME, json.dumps(info) + "\n")
        except (OSError, faults.OutputError):
            pass

    def _stop(self, stop: Any, save: bool = True) -> None:
        """Save (the state is at an iteration boundary), close the event file and raise ``TrainingInterrupted``."""
        if save:
            self.save()
        self._progress("stopped", force=True)
        if self.writer is not None:
            with faults.output_errors(self.run_dir / "tb"):
                self.writer.close()
        raise TrainingInterrupted(self.ckpt, stop.signum)

    def _iteration(self, levels: list[int], M: int, n_sub: int, cached_prev: dict) -> dict[str, Tensor]:
        """One iteration; its losses as 0-d device tensors, not read (reading them waits for the device: the loop
        reads them at log iterations)."""
        cfg, model = self.cfg, self.model
        out: dict[str, Tensor] = {}
        self._iteration_dev.add_(1)
        for sub in range(n_sub):
            kind = "D" if sub < cfg.d_steps else ("G" if sub < cfg.d_steps + cfg.g_steps else "R")
            for m in range(M):
                reals = self.reals[m]
                if kind == "D":
                    fakes = self._forward(m, levels, "random", False, cached_prev)
                    for l in levels:
                        self.opt_d[l].zero_grad(set_to_none=True)
                    loss = total = 0.0
                    for l, fake in zip(levels, fakes):
                        d = model.discs[l]
                        pooled = self.pools[l].query(fake)
                        with self._autocast():
                            # fake and real through D as one batch (D couples no samples): half the calls
                            scores = widened(d(torch.cat([pooled, reals[l]])))
                            gp = gradient_penalty(d, reals[l], fake)
                        n_fake = pooled.shape[0]
                        loss_d = 0.5 * (scores[:n_fake].mean() - scores[n_fake:].mean())
                        loss = loss + loss_d + cfg.lambda_gp * gp
                        total = total + loss_d.detach()
                        out["gp"] = gp.detach()
                    self._guarded_step([self.opt_d[l] for l in levels], loss, "D", levels)
                    out["D"] = total / len(levels)
                elif kind == "G":
                    fakes = self._forward(m, levels, "random", True, cached_prev)
                    loss = g_adv = con = 0.0
                    for l, fake in zip(levels, fakes):
                        d = model.discs[l]
                        for p in d.parameters():
                            p.requires_grad_(False)
                        with self._autocast():
                            score = d(fake)
                        adv = -widened(score).mean()
                        for p in d.parameters():
                            p.requires_grad_(True)
                        rate = model.rates[m][l] if cfg.contact_rescale else 1.0
                        c = self.consistency(fake, rate) if cfg.lambda_contact > 0 else fake.new_zeros(())
                        loss = loss + adv + cfg.lambda_contact * c
                        g_adv = g_adv + adv.detach()
                        con = con + c.detach()
                    self._generator_step(loss, levels, "G")
                    out["G"], out["con"] = g_adv / len(levels), con / len(levels)
                else:
                    recs = self._forward(m, levels, "rec", True, cached_prev)
                    loss = rec_total = 0.0
                    for l, rec in zip(levels, recs):
                        r = (rec - reals[l]).abs().mean()
                        loss = loss + cfg.lambda_rec * r
                        rec_total = rec_total + r.detach()
                        out[f"rec{l}"] = r.detach()
                    self._generator_step(loss, levels, "R")
                    out["rec"] = rec_total / len(levels)
        return out

    def _generator_step(self, loss: Tensor, levels: Sequence[int], what: str) -> None:
        """One guarded step of the generators of ``levels`` on ``loss``."""
        for l in levels:
            self.opt_g[l].zero_grad(set_to_none=True)
        self._guarded_step([self.opt_g[l] for l in levels], loss, what, levels)


def train(clips: Sequence[Clip], cfg: GanimatorConfig, run_dir: str | Path, progress: bool = True,
          cond_source: GanimatorModel | None = None, log: Callable[[str], None] | None = print,
          max_seconds: float | None = None, precision: str | None = None) -> GanimatorModel:
    """Train (or resume) a GANimator run in ``run_dir``; returns the model (generators in eval mode). ``precision``:
    ``fp32`` or ``bf16`` (None: a resumed checkpoint's, else fp32)."""
    trainer = Trainer(clips, cfg, run_dir, cond_source=cond_source, precision=precision)
    model = trainer.run(progress=progress, log=log, max_seconds=max_seconds)
    model.eval()
    return model


def run_summary(run: str | Path) -> dict:
    """Schedule position and wall time per block of a run (for reports)."""
    ck = read_checkpoint(run)
    st = ck["state"]
    cfg = GanimatorConfig.from_dict(ck["model"]["config"])
    blocks = blocks_of(len(ck["model"]["lengths"][0]), cfg.group_size)
    return {"lengths": ck["model"]["lengths"], "blocks": blocks, "block_seconds": st["block_seconds"],
            "levels_done": st["levels_done"], "block": st["block"], "iteration": st["iteration"],
            "history": st["history"], "block_iterations": cfg.block_budgets(len(blocks)), "config": cfg.to_dict()}


__all__ = ["Trainer", "TrainingInterrupted", "NonFiniteLossError", "train", "load_model", "read_checkpoint", "checkpoint_path", "run_summary", "FakePool",
           "gradient_penalty", "ContactConsistency", "model_payload", "model_from_payload", "atomic_save",
           "blocks_of"]
