"""Training MoDi: data preparation and the StyleGAN2-style ``Trainer`` (the codec is ``modi.models.modi.codec``).

One iteration (after rosinality/stylegan2-pytorch and the MoDi authors' ``train.py``): a discriminator step on
the non-saturating loss, lazy R1 every ``d_reg_every`` steps, a generator step on the non-saturating loss plus
MoDi's foot-touch and contact-consistency terms (through the FK op), lazy path-length regularisation every
``g_reg_every`` steps, then the EMA generator and the tracked mean of W are updated.

Exact resume: every source of randomness is a torch RNG whose state goes into the checkpoint (the global CPU/CUDA
generators for latents and noise), the real windows of a step follow from the step alone (one permutation per
epoch, cut into the ranks' shards: ``distributed.shard_indices``), the optimisers' states are saved, and the loop
only stops at iteration boundaries -- so ``k`` steps, save, load, ``n - k`` steps equals ``n`` steps.

A step asks nothing of the host, so a GPU never waits on Python and a CUDA graph can replay it: its random choices (style mixing, the inject index) are drawn on the
device and applied as masks, so every step of a kind (plain, path length, R1, both) runs the same ops at the same
shapes; the real windows' indices reach the device once per epoch; the losses stay on the device and are read at
``log_every`` steps (and at saves). A step with a NaN/inf loss is skipped on the device (fused Adam's ``found_inf``),
reported at the next log step, and ``NONFINITE_STEPS`` such steps in a row stop the run as a non-finite loss always
did: ``NonFiniteLossError``, no checkpoint written.

CUDA graphs (``cuda_graphs``; ``modi.models.modi.graphs``): a step is ``_prepare_step`` (what it takes from the host,
written into device buffers: the EMA weight and, under graphs, the windows' indices) then ``_step_body`` (device work
only), which one graph per kind captures after a warm-up and replays.

Precision (docs/precision.md): with ``precision="bf16"`` the networks' forward passes run under bf16 autocast, R1's
included; the losses and the foot terms (FK) take the networks' outputs cast to fp32; the path-length regulariser runs
wholly in fp32 (its penalty, a small spread of large lengths, came out up to a fifth off float64's in bf16, where R1
stays as close as the adversarial losses: measured in docs/precision.md). Weights, gradients, optimiser states and
checkpoints stay fp32, and bf16 has fp32's exponent range, so no loss is scaled.

Ctrl-C and SIGTERM (``modi.faults.stop_on_signals``) stop at the next boundary on every rank and save; the run
folder is locked while ``train`` runs (``modi.faults.hold_run_folder``).
"""
from __future__ import annotations

import inspect
import json
import os
import shutil
import tempfile
import time
import warnings
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel as DDP
from tqdm import tqdm

from modi import faults
from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import build_hierarchy
from modi.data.dataset import DatasetConfig, build_dataset
from modi.data.normalization import Normalizer
from modi.data.procedural import write_dataset
from modi.errors import CheckpointError, NonFiniteLossError, UserError
from modi.models.modi.checkpoint import atomic_torch_save, checkpoint_dict, load_checkpoint
from modi.models.modi.codec import MotionCodec
from modi.models.modi.config import MoDiConfig
from modi.models.modi.distributed import epoch_order as _epoch_order
from modi.models.modi.distributed import init_distributed_from_env, shard_indices, under_torchrun
from modi.models.modi.graphs import (CaptureBackend, CudaGraphBackend, GraphFallbackWarning, StepGraphs,
                                     auto_enables_graphs, check_graph_mode)
from modi.models.modi.levels import LevelSpec, build_levels
from modi.models.modi.losses import (
    d_logistic_loss,
    d_r1_penalty,
    foot_contact_consistency_loss,
    foot_contact_speed_loss,
    foot_touch_loss,
    g_nonsaturating_loss,
    lazy_regularization_adam_params,
    path_length_penalty,
)
from modi.models.modi.networks import Discriminator, Generator
from modi.models.modi.sampling import write_outputs
from modi.models.optim import frozen_heap, fused_adam, fused_groups, set_capturable
from modi.models.precision import DEFAULT_PRECISION, PRECISIONS, check_precision, precision_autocast, widened

NONFINITE_STEPS = 8  # steps in a row skipped for a NaN/inf loss that stop the run (read at log steps and saves)
GUARDED = ("d", "r1", "g", "touch", "contact", "path")  # the losses the non-finite guard watches, in its order


# =============================================================================================== data
@dataclass
class TrainingData:
    """Normalised training windows plus everything the model and checkpoint need about them."""

    codec: MotionCodec
    windows: Tensor  # (N, K, E, T) normalised, float32
    hierarchy: Any  # modi.core.skeleton_graph.PoolingHierarchy
    source: str
    summary: dict[str, Any] = field(default_factory=dict)

    @property
    def skeleton(self) -> Any:
        return self.codec.skeleton


def _dataset_config(cfg: MoDiConfig) -> Any:
    return DatasetConfig(fps=cfg.data.fps, window=cfg.data.n_frames, stride=cfg.data.stride, root=cfg.data.root,
                         rotation="quat", feet=cfg.data.feet, drop_patterns=cfg.data.drop_patterns,
                         keep_joints=cfg.data.keep_joints, drop_root_anchor=cfg.data.drop_root_anchor,
                         leaf_rotations=cfg.data.leaf_rotations)


def write_procedural_data(out_dir: str | os.PathLike, n_clips: int = 48, frames: int = 160, seed: int = 0,
                          fps: float = 30.0) -> Path:
    """Write the built-in procedural clips (walk/run/jump/wave/squat/idle) as BVH files; returns the folder."""
    out = Path(out_dir)
    write_dataset(out, n_clips=n_clips, frames=frames, seed=seed, fps=fps)
    return out


def data_root(source: str | os.PathLike, fps: float, work_dir: str | os.PathLike | None = None,
              what: str = "training data") -> Path:
    """The BVH folder ``source`` names: itself, or for the word ``procedural`` the built-in clips written (once) to
    ``work_dir/procedural_data`` (a temp dir when ``work_dir`` is None)."""
    if str(source) == "procedural":
        base = Path(work_dir) if work_dir is not None else Path(tempfile.mkdtemp(prefix="modi_proc_"))
        folder = base / "procedural_data"
        if not any(folder.glob("*.bvh")):
            # written beside, then renamed into place: the ranks of a run share the folder and write it at the
            # same time; none may read a half-written set (the first rename wins, the others' copies are dropped)
            base.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=".procedural_data.", dir=base))
            try:
                write_procedural_data(tmp, fps=fps)
                try:
                    os.rename(tmp, folder)
                except OSError:
                    if not any(folder.glob("*.bvh")):
                        raise
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        return folder
    root = Path(source)
    if not root.exists():
        raise UserError(f"{what} not found: {root} (give a BVH folder or the word 'procedural')")
    return root


def prepare_data(source: str | os.PathLike, cfg: MoDiConfig, *, work_dir: str | os.PathLike | None = None,
                 cache: bool = True, progress: bool = False, normalizer: Any = None) -> TrainingData:
    """Load a BVH folder (or the word ``procedural``) into normalised training windows for ``cfg``.

    ``procedural`` writes the built-in clips under ``work_dir/procedural_data`` first (or a temp dir).
    ``normalizer`` (e.g. a resumed checkpoint's) replaces the statistics fitted on the data.
    """
    cfg.validate()
    src = str(source)
    root = data_root(source, cfg.data.fps, work_dir)
    ds = build_dataset(root, _dataset_config(cfg), cache=cache, progress=progress)
    windows = ds.train
    codec = MotionCodec(ds.representation, ds.normalizer, cfg.data.fps, positions=False)
    if cfg.data.rotation == "positions":
        codec = MotionCodec(ds.representation, ds.normalizer, cfg.data.fps, positions=True)
        windows = codec.positions_from_raw_quat(ds.train.to(torch.float64), ds.representation).to(ds.train.dtype)
        codec.normalizer = Normalizer.fit(windows, skip_entities=ds.representation.contacts)
    if normalizer is not None:
        if tuple(normalizer.mean.shape) != tuple(windows.shape[1:3]):
            raise UserError(f"checkpoint normalisation is for (K, E) = {tuple(normalizer.mean.shape)}, "
                            f"this data has {tuple(windows.shape[1:3])}")
        codec.normalizer = normalizer
    hierarchy = build_hierarchy_for(codec, cfg)
    norm = codec.normalizer.normalize(windows).float().contiguous()
    summary = {k: v for k, v in ds.summary().items() if isinstance(v, (int, float, str, list, bool))}
    return TrainingData(codec=codec, windows=norm, hierarchy=hierarchy, source=src, summary=summary)


def build_hierarchy_for(codec: MotionCodec, cfg: MoDiConfig) -> Any:
    return build_hierarchy(codec.skeleton, codec.feet, neighbor_distance=cfg.model.neighbor_distance,
                           siblings=cfg.model.neighbors == "siblings", pooling=cfg.model.pooling)


def build_models(cfg: MoDiConfig, levels: list[LevelSpec], n_channels: int) -> tuple[Generator, Discriminator]:
    return Generator(cfg.model, levels, n_channels), Discriminator(cfg.model, levels, n_channels)


# =============================================================================================== helpers
def _requires_grad(model: nn.Module, flag: bool) -> None:
    for p in model.parameters():
        p.requires_grad_(flag)


@torch.no_grad()
def _accumulate(ema: nn.Module, model: nn.Module, decay: float | None = None, *, weight: Tensor | None = None
                ) -> None:
    """EMA of the parameters, ``ema += (1 - decay) * (model - ema)``, or with ``weight`` (``1 - decay`` as a 0-d
    tensor on their device: the trainer's, filled each step) instead of ``decay``; and the tracked mean of W copied.
    The other buffers (constant noise, the layers' index maps) never change in training: they are left alone (a
    copy would bump their versions)."""
    mine, theirs = list(ema.parameters()), [p.detach() for p in model.parameters()]
    if weight is None:
        torch._foreach_lerp_(mine, theirs, 1.0 - float(decay))
    elif weight.device.type == "cpu":  # lerp per tensor with the 0-d weight: bit-equal to the float form
        torch._foreach_lerp_(mine, theirs, [weight] * len(mine))
    else:  # three multi-tensor launches (a per-tensor weight list would take the per-tensor path)
        diff = torch._foreach_sub(theirs, mine)
        torch._foreach_mul_(diff, weight)
        torch._foreach_add_(mine, diff)
    if isinstance(getattr(model, "w_avg", None), Tensor):
        ema.w_avg.copy_(model.w_avg)




def _dist() -> tuple[bool, int, int]:
    if dist.is_available() and dist.is_initialized():
        return True, dist.get_rank(), dist.get_world_size()
    return False, 0, 1


# =============================================================================================== trainer
@dataclass
class TrainResult:
    step: int
    interrupted: bool
    checkpoint: Path | None
    seconds: float
    last_losses: dict[str, float]
    signum: int | None = None  # the signal that stopped the run (SIGINT / SIGTERM)

    @property
    def exit_code(self) -> int:
        """0, or 130 / 143 for a run stopped by Ctrl-C / SIGTERM."""
        return faults.exit_code(self.signum) if self.interrupted else 0


class Trainer:
    """Trains G/D on ``data`` into ``run_dir`` (checkpoints, TensorBoard scalars, ``log.jsonl``, sample previews).

    In a ``torch.distributed`` process group the models are wrapped in DDP (gradients averaged), each rank draws
    its own latents and noise and trains on its own shard of each batch, and rank 0 writes every file.
    """

    def __init__(self, cfg: MoDiConfig, data: TrainingData, run_dir: str | os.PathLike, *,
                 device: str | torch.device | None = None, resume: str | os.PathLike | dict | None = None,
                 progress: bool = True, tensorboard: bool = True, write_samples: bool = True,
                 log: Callable[[str], None] | None = None, precision: str | None = None,
                 cuda_graphs: str = "auto", graph_backend: CaptureBackend | None = None):
        self.cfg = cfg.validate()
        self.cuda_graphs = check_graph_mode(cuda_graphs)  # asked; ``graphs`` / ``graphs_record()``: what runs
        self.graphs: StepGraphs | None = None
        # None: a new run's default, or a resumed run's checkpoint's; given: this precision (a resume switches)
        self._precision_asked = check_precision(precision) if precision is not None else None
        self.precision = self._precision_asked or DEFAULT_PRECISION
        self.data = data
        self.codec = data.codec
        self.run_dir = Path(run_dir)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.distributed, self.rank, self.world = _dist()
        tc = cfg.train
        if tc.batch % self.world != 0:
            raise UserError(f"batch {tc.batch} is not divisible by the {self.world} processes")
        self.local_batch = tc.batch // self.world
        self.progress = progress and self.rank == 0
        self.write_samples = write_samples
        self.log = log or (lambda msg: print(msg, flush=True))

        if data.windows.ndim != 4 or data.windows.shape[1] != self.codec.n_channels:
            raise ValueError(f"training windows must be (N, {self.codec.n_channels}, E, T), got "
                             f"{tuple(data.windows.shape)}")
        if data.windows.shape[-1] != cfg.data.n_frames:
            raise ValueError(f"training windows have {data.windows.shape[-1]} frames, config says {cfg.data.n_frames}")
        self.windows = data.windows.to(self.device)
        self.levels = build_levels(data.hierarchy, cfg.model, cfg.data.n_frames)
        if self.levels[-1].n_entities != self.codec.n_entities:
            raise ValueError(f"hierarchy's finest level has {self.levels[-1].n_entities} entities, the representation "
                             f"{self.codec.n_entities}")

        torch.manual_seed(tc.seed)  # identical initial weights on every rank
        self.G, self.D = build_models(cfg, self.levels, self.codec.n_channels)
        self.G.to(self.device)
        self.D.to(self.device)
        self.G_ema = Generator(cfg.model, self.levels, self.codec.n_channels).to(self.device).eval()
        self.G_ema.load_state_dict(self.G.state_dict())
        _requires_grad(self.G_ema, False)

        g_lr, g_betas = lazy_regularization_adam_params(tc.lr, (tc.beta1, tc.beta2), tc.g_reg_every)
        d_lr, d_betas = lazy_regularization_adam_params(tc.lr, (tc.beta1, tc.beta2), tc.d_reg_every)
        self._capturable = self.device.type == "cuda"  # a CUDA graph may hold the optimiser steps
        self.g_optim = fused_adam(self.G.parameters(), g_lr, g_betas, capturable=self._capturable)
        self.d_optim = fused_adam(self.D.parameters(), d_lr, d_betas, capturable=self._capturable)

        self.step = 0
        self.mean_path_length = torch.zeros((), device=self.device)  # updated in place
        self._orders: dict[int, Tensor] = {}  # the newest epochs' window orders (see _batch_indices)
        self._stream: tuple[int, Tensor] | None = None  # (first epoch, its order ++ the next ones') on the device
        dev = self.device
        self._ema_weight = torch.zeros((), device=dev)  # 1 - the EMA decay of this step (filled, not rebound)
        self._skip_run = torch.zeros((), device=dev)  # steps in a row skipped for a non-finite loss
        self._skip_count = torch.zeros((), device=dev)  # steps skipped since the last report
        self._skip_first = torch.zeros(len(GUARDED), device=dev)  # which losses were non-finite when the run began
        self._no_flag = torch.zeros(1, device=dev)
        self._flags: dict[str, Tensor] = {}  # this step's non-finite flags (1-element float tensors)
        self._pending: dict[str, Tensor] | None = None  # the losses of the last step, unread (device tensors)
        if self.distributed:
            self._check_same_data()
        self.sample_z = torch.randn(tc.n_samples, cfg.model.latent_dim,
                                    generator=torch.Generator().manual_seed(tc.seed + 12345))
        self.last_losses = {}
        self._latest_reg: dict[str, Tensor | float] = {}
        self.stop = faults.StopRequest()
        self._saved_step: int | None = None  # step of the checkpoint on disk (named by a disk-full error)
        torch.manual_seed(tc.seed * 1000 + 1 + self.rank)  # per-rank latents and noise
        if resume is not None:
            self.load_state(resume)

        self.graphs, self._graphs_why = self._make_graphs(graph_backend)
        self.g_train: nn.Module = self.G
        self.d_train: nn.Module = self.D
        if self.distributed:

            ids = [self.device.index] if self.device.type == "cuda" else None
            # Buffers (w_avg, constant noise) are identical on every rank by construction and updated with
            # all-reduced values, so DDP need not re-broadcast them each forward.
            no_sync = ({"forward_sync_buffers": False} if "forward_sync_buffers" in
                       inspect.signature(DDP.__init__).parameters else {"broadcast_buffers": False})
            warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
            self.g_train = DDP(self.G, device_ids=ids, **no_sync)
            self.d_train = DDP(_PairD(self.D), device_ids=ids, **no_sync)
        else:
            self.d_train = _PairD(self.D)
        self.writer = None
        if tensorboard and self.rank == 0:
            try:
                from torch.utils.tensorboard import SummaryWriter  # lazy: tensorboard costs ~1 s to import, only here

                with faults.output_errors(self.run_dir / "tb"):  # a resume drops the events past its step
                    self.writer = SummaryWriter(str(self.run_dir / "tb"), purge_step=self.step or None)
            except faults.OutputError:
                raise
            except Exception as exc:  # noqa: BLE001 - tensorboard is optional at run time
                warnings.warn(f"TensorBoard logging disabled: {exc}", stacklevel=2)

    # ------------------------------------------------------------------------------------------- CUDA graphs
    def _make_graphs(self, backend: CaptureBackend | None) -> tuple[StepGraphs | None, str]:
        """The step's graphs (``modi.models.modi.graphs``) for ``cuda_graphs``, or None and why this run is eager.
        ``backend`` replaces the CUDA one (tests run the step through ``graphs.OpTape`` on the CPU)."""
        mode = self.cuda_graphs
        if mode == "off":
            return None, "off"
        if self.distributed:  # DDP's bucketed all-reduces are not captured here
            if mode == "on" and self.rank == 0:
                warnings.warn(f"modi train: CUDA graphs run in one process only; this run has {self.world} (DDP) "
                              f"and trains eagerly", GraphFallbackWarning, stacklevel=3)
            return None, f"one process only; this run has {self.world}"
        if backend is None:
            if self.device.type != "cuda":
                if mode == "on":
                    warnings.warn(f"modi train: CUDA graphs need a CUDA device; this run is on {self.device} and "
                                  f"trains eagerly", GraphFallbackWarning, stacklevel=3)
                return None, f"needs a CUDA device; this run is on {self.device}"
            if mode == "auto" and not auto_enables_graphs(self.device):
                return None, "auto: off until a GPU run has shown a graphed cycle equal to an eager one"
            backend = CudaGraphBackend(self.device)
        # the step's window indices, filled before each step (a graph reads this buffer, not a slice of the order)
        self._index_buffer = torch.zeros(self.local_batch, dtype=torch.long, device=self.device)
        return StepGraphs(backend, on_fail=self._after_failed_capture), "on"

    def _after_failed_capture(self) -> None:
        self._flags = {}  # a half-run body's non-finite flags; the eager retry makes its own
        for opt in (self.g_optim, self.d_optim):
            opt.__dict__.pop("found_inf", None)

    def graphs_record(self) -> dict[str, Any]:
        """What ``cuda_graphs`` asked and what ran (``ran``: on, off, or fell back: eager after a failed capture),
        as the run's summary line and checkpoint record it."""
        rec: dict[str, Any] = {"asked": self.cuda_graphs, "ran": "off", "reason": self._graphs_why}
        if self.graphs is not None:
            rec.update(self.graphs.report())
            rec["ran"] = "on" if self.graphs.active else "fell back"
            rec["reason"] = self.graphs.fallback or ""
        return rec

    def graphs_summary(self) -> str:
        """One phrase for the run's summary line: ``CUDA graphs on`` or ``CUDA graphs off (why)``."""
        rec = self.graphs_record()
        return f"CUDA graphs {rec['ran']}" + (f" ({rec['reason']})" if rec["reason"] else "")

    def _step_kind(self) -> str:
        """plain, path, r1 or r1+path: the lazy regularisers this step runs (one graph each)."""
        tc = self.cfg.train
        r1 = tc.r1_gamma > 0 and self.step % tc.d_reg_every == 0
        path = tc.path_weight > 0 and self.step % tc.g_reg_every == 0
        return "r1+path" if r1 and path else "r1" if r1 else "path" if path else "plain"

    # ------------------------------------------------------------------------------------------- randomness
    def _z(self, n: int) -> tuple[list[Tensor], Tensor | None]:
        """The latents of ``n`` motions and where they mix, drawn on the device from the global torch RNG.

        With ``mixing > 0`` every call draws a uniform (mix with probability ``mixing``), two latents and an inject
        index in ``[1, n_latent)``, in that order, whether it mixes or not, and returns the index as a 0-d tensor
        (``n_latent`` when it does not mix: every style from the first latent) for ``Generator.make_wplus``: the
        same ops every step. (Runs of modi 0.1 drew one latent and no index when not mixing; their checkpoints
        resume on this stream, whose draws differ from the first non-mixing step on.) With ``mixing == 0``: one
        latent, no index."""
        dim = self.cfg.model.latent_dim
        if self.cfg.train.mixing <= 0:
            return [torch.randn(n, dim, device=self.device)], None
        n_latent = self.G.n_latent
        u = torch.rand((), device=self.device)
        zs = list(torch.randn(2, n, dim, device=self.device).unbind(0))
        index = torch.randint(1, n_latent, (), device=self.device)
        return zs, torch.where(u < self.cfg.train.mixing, index, n_latent)

    def _batch_indices(self, step: int | None = None) -> Tensor:
        """This rank's windows at ``step`` (default the current one): its shard of the step's global batch, from a
        permutation of all windows per epoch (``distributed.shard_indices``): each window once per epoch across the
        ranks, and a function of the step alone, so a resume continues the same stream."""
        return shard_indices(self.windows.shape[0], self.cfg.train.batch, self.world, self.rank,
                             self.cfg.train.seed, self.step if step is None else step, self._orders)

    def _device_indices(self, step: int | None = None) -> Tensor:
        """``_batch_indices(step)`` as a slice of the epochs' orders held on the device: they are sent there once
        per epoch (when the step's first window opens a new one), not once per step."""
        step = self.step if step is None else step
        n, local = self.windows.shape[0], self.local_batch
        pos = step * self.cfg.train.batch + self.rank * local
        epoch, within = divmod(pos, n)
        if self._stream is None or self._stream[0] != epoch:
            span = (local - 1) // n + 1  # the epochs after this one that a shard starting in it may reach
            for e in range(epoch, epoch + span + 1):
                if e not in self._orders:
                    self._orders[e] = _epoch_order(n, self.cfg.train.seed, e)
            stream = torch.cat([self._orders[e] for e in range(epoch, epoch + span + 1)])
            for old in [e for e in self._orders if e < epoch]:
                del self._orders[old]
            self._stream = (epoch, stream.to(self.windows.device))
        return self._stream[1][within:within + local]

    def _real_batch(self) -> Tensor:
        return self.windows[self._index_buffer if self.graphs is not None else self._device_indices()]

    def _check_same_data(self) -> None:
        """Every rank must hold the same windows in the same order (the shards are cut from one permutation):
        compare their number and a checksum across the ranks."""
        w = self.windows.detach().double()
        mine = torch.tensor([float(w.shape[0]), float(w.sum()),
                             float((w.flatten(1).sum(1) * torch.arange(1, w.shape[0] + 1, dtype=w.dtype,
                                                                       device=w.device)).sum())],
                            dtype=torch.float64, device=self.device)
        every = [torch.zeros_like(mine) for _ in range(self.world)]
        dist.all_gather(every, mine)
        for r, theirs in enumerate(every):
            if not torch.allclose(theirs, every[0], rtol=1e-9, atol=1e-6):
                raise UserError(f"rank {r} has {int(theirs[0])} training windows and rank 0 {int(every[0][0])}, or "
                                f"other ones: every process must read the same data (the same DATA_DIR and options "
                                f"on every machine)")

    # ------------------------------------------------------------------------------------------- checks
    def _nonfinite(self, losses: dict[str, Tensor]) -> Tensor:
        """1.0 where a loss is NaN/inf, else 0.0 (float, one per loss, the maximum over the ranks), recorded as
        this step's flags for the guard; no host read."""
        vals = torch.stack([v.detach().float().reshape(()) for v in losses.values()])
        bad = torch.isfinite(vals).logical_not_().float()
        if self.distributed:
            dist.all_reduce(bad, op=dist.ReduceOp.MAX)
        for i, k in enumerate(losses):
            self._flags[k] = bad[i:i + 1]
        return bad

    def _guarded_step(self, opt: torch.optim.Optimizer, losses: dict[str, Tensor]) -> Tensor:
        """The optimiser step, skipped on the device when a loss is non-finite (fused Adam's ``found_inf``).
        An optimiser off the fused kernel (a checkpoint saved without it) has no ``found_inf``: it checks on the host
        and stops at once. Returns the flags (see ``_nonfinite``)."""
        bad = self._nonfinite(losses)
        if not fused_groups(opt):
            if bool(bad.any()):
                raise self._nonfinite_error([k for k, b in zip(losses, bad.tolist()) if b > 0], self.step)
            opt.step()
            return bad
        opt.found_inf = bad.amax()
        try:
            opt.step()
        finally:
            del opt.found_inf
        return bad

    def _count_skips(self) -> None:
        """After a step: count it as skipped when a loss was non-finite (in a row, and since the last report)."""
        flags = torch.cat([self._flags.get(k, self._no_flag) for k in GUARDED])
        self._flags = {}
        bad = flags.amax()
        self._skip_run.mul_(bad).add_(bad)
        self._skip_count.add_(bad)
        self._skip_first.copy_(torch.where(self._skip_run == 1, flags, self._skip_first))

    def _nonfinite_error(self, names: list[str], step: int) -> NonFiniteLossError:
        last = self.run_dir / "checkpoint.pt"
        where = f"; the last good checkpoint is {last}" if last.is_file() else ""
        return NonFiniteLossError(
            f"non-finite loss ({', '.join(names)}) at step {step}: training stopped without writing a "
            f"checkpoint{where}. Try a lower learning rate or check the data for NaN/huge values.")

    def _check_skips(self, saving: bool = False) -> int:
        """Read the guard (a host read: at log steps and saves). Raises ``NonFiniteLossError`` after
        ``NONFINITE_STEPS`` skipped steps in a row, or before a save while steps are being skipped and a weight is
        not finite (no checkpoint from non-finite weights). Returns the steps skipped since the last report (and,
        but for a save, resets that count: the next log step reports them)."""
        run, count, *first = torch.cat([self._skip_run.reshape(1), self._skip_count.reshape(1),
                                        self._skip_first]).tolist()
        run, count = int(run), int(count)
        if run and (run >= NONFINITE_STEPS or (saving and not self._weights_finite())):
            names = [k for k, b in zip(GUARDED, first) if b > 0]
            raise self._nonfinite_error(names, self.step - run)
        if count and not saving:
            self._skip_count.zero_()
        return count

    def _weights_finite(self) -> bool:
        tensors = [t for m in (self.G, self.D, self.G_ema) for t in (*m.parameters(), *m.buffers())
                   if t.is_floating_point()]
        return bool(torch.stack([torch.isfinite(t).all() for t in tensors]).all())

    def _all_mean(self, t: Tensor) -> Tensor:
        if self.distributed:
            t = t.clone()
            dist.all_reduce(t)
            t /= self.world
        return t

    # ------------------------------------------------------------------------------------------- one iteration
    def run_step(self) -> dict[str, Tensor]:
        """One D step (+ lazy R1), one G step (+ lazy path length), EMA and mean-W updates; the losses as 0-d
        device tensors, not read (no host sync: read them with ``read_losses``, or use ``train_step``). Under CUDA
        graphs the step's kind is replayed (after its warm-up and capture: ``graphs.StepGraphs``)."""
        self._prepare_step()
        if self.graphs is None:
            out = self._step_body()
        else:
            out = self.graphs.run(self._step_kind(), self._step_body)
        self.step += 1
        # lazy regularisers run on other steps than the logged ones: their latest values are reported with each
        self._latest_reg.update({k: v for k, v in out.items() if k in ("r1", "path", "path_length")})
        self._pending = out
        return out

    def _prepare_step(self) -> None:
        """What a step takes from the host, written into device buffers before it runs (a graph holds the
        buffers, not the values): this step's EMA weight, and under graphs its windows' indices."""
        self._ema_weight.fill_(1.0 - self._ema_decay())
        if self.graphs is not None:
            self._index_buffer.copy_(self._device_indices())

    def _step_body(self) -> dict[str, Tensor]:
        """The device work of one step, all of it (what a graph of the step's kind holds)."""
        out = self._d_step()
        out.update(self._g_step())
        self._count_skips()
        return out

    def train_step(self) -> dict[str, float]:
        """``run_step`` with its losses read (one host read)."""
        return read_losses(self.run_step())

    def d_step(self) -> dict[str, float]:
        """Discriminator update on the non-saturating loss, plus lazy R1 every ``d_reg_every`` steps."""
        self._prepare_step()
        return read_losses(self._d_step())

    def g_step(self) -> dict[str, float]:
        """Generator update (adversarial + foot terms), lazy path length, mean-W tracking and the EMA copy."""
        self._prepare_step()
        return read_losses(self._g_step())

    def _d_step(self) -> dict[str, Tensor]:
        tc = self.cfg.train
        _requires_grad(self.G, False)
        _requires_grad(self.D, True)
        real = self._real_batch()
        zs, inject = self._z(self.local_batch)
        with self._autocast():
            with torch.no_grad():
                fake = self.G(zs, inject_index=inject)
            fake_pred, real_pred = self.d_train(fake, real)
        fake_pred, real_pred = widened(fake_pred), widened(real_pred)  # the losses in fp32 (or float64)
        d_loss = d_logistic_loss(real_pred, fake_pred)
        self.d_optim.zero_grad(set_to_none=True)
        d_loss.backward()
        self._guarded_step(self.d_optim, {"d": d_loss})
        out = {"d": d_loss.detach(), "real_score": real_pred.detach().mean(), "fake_score": fake_pred.detach().mean()}
        if self.step % tc.d_reg_every == 0 and tc.r1_gamma > 0:
            real_r = real.detach().requires_grad_(True)
            with self._autocast():
                pred = self.d_train(real_r)
            r1 = d_r1_penalty(widened(pred), real_r)
            self.d_optim.zero_grad(set_to_none=True)
            (tc.r1_gamma / 2 * r1 * tc.d_reg_every + 0 * pred[0, 0]).backward()
            self._guarded_step(self.d_optim, {"r1": r1})
            out["r1"] = r1.detach()
        return out

    def _g_step(self) -> dict[str, Tensor]:
        tc = self.cfg.train
        _requires_grad(self.G, True)
        _requires_grad(self.D, False)
        zs, inject = self._z(self.local_batch)
        with self._autocast():
            fake = self.g_train(zs, inject_index=inject)
            fake_pred = self.D(fake)
        fake = widened(fake)  # the foot terms (FK) and the losses in fp32 (or float64)
        g_loss = g_nonsaturating_loss(widened(fake_pred))
        total = g_loss
        losses = {"g": g_loss}
        if tc.touch_weight > 0 or tc.contact_weight > 0:
            if tc.contact_loss == "released":  # speed of the ankles, data units
                foot_pos, contact = self.codec.foot_terms(fake, self.codec.ankles)
                fcon = foot_contact_speed_loss(foot_pos, contact)
            else:  # "squared": speed^2 of the contact joints in body heights per second
                foot_pos, contact = self.codec.foot_terms(fake)
                fcon = foot_contact_consistency_loss(foot_pos, contact, self.codec.fps, self.codec.height)
            touch = foot_touch_loss(contact)
            total = total + tc.touch_weight * touch + tc.contact_weight * fcon
            losses.update(touch=touch, contact=fcon)
        self.g_optim.zero_grad(set_to_none=True)
        total.backward()
        self._guarded_step(self.g_optim, losses)
        out = {k: v.detach() for k, v in losses.items()}

        if self.step % tc.g_reg_every == 0 and tc.path_weight > 0:  # fp32 in every precision (module docstring)
            n = max(1, self.local_batch // tc.path_batch_shrink)
            zp, inject_p = self._z(n)
            fake_p, wplus = self.g_train(zp, inject_index=inject_p, return_latents=True)
            path, mean_path, lengths = path_length_penalty(fake_p, wplus, self.mean_path_length, tc.path_decay)
            self.g_optim.zero_grad(set_to_none=True)
            (tc.path_weight * tc.g_reg_every * path + 0 * fake_p[0, 0, 0, 0]).backward()
            bad = self._guarded_step(self.g_optim, {"path": path})
            # in place (a graph holds the tensor); a skipped step keeps the running mean
            self.mean_path_length.copy_(torch.where(bad[0] > 0, self.mean_path_length,
                                                    self._all_mean(mean_path.detach())))
            out.update(path=path.detach(), path_length=lengths.mean())

        with torch.no_grad():  # mean of W (truncation target), averaged over processes so replicas agree
            w_mean = self._all_mean(self.G.mapping(zs[0]).mean(0))
            self.G.w_avg.lerp_(w_mean, 1.0 - tc.w_avg_beta)
        _accumulate(self.G_ema, self.G, weight=self._ema_weight)
        return out

    def _autocast(self):
        """The context of the forward passes (see the module docstring: bf16 autocast, or nothing for fp32). Under
        graphs, autocast keeps no cache of cast weights (as torch advises: a replay must redo each cast, never read
        one cached outside it); the casts are the same, so are the results."""
        ctx = precision_autocast(self.precision, self.device)
        if self.graphs is not None and isinstance(ctx, torch.autocast):
            return torch.autocast(self.device.type, dtype=ctx.fast_dtype, cache_enabled=False)
        return ctx

    def _ema_decay(self) -> float:
        """EMA with a half-life of ``ema_kimg`` thousand samples, ramped up to 5% of the samples seen (StyleGAN2-ADA)
        so short runs are not dominated by the random initialisation."""
        tc = self.cfg.train
        seen = (self.step + 1) * tc.batch
        half_life = min(tc.ema_kimg * 1000.0, 0.05 * seen)
        return 0.5 ** (tc.batch / max(half_life, 1e-8))

    @property
    def last_losses(self) -> dict[str, float]:
        """The losses of the last step (and the latest lazy regularisers'), read from the device when asked."""
        if self._pending is not None:
            pending, self._pending = self._pending, None
            self._last_losses = read_losses({**self._latest_reg, **pending})
        return self._last_losses

    @last_losses.setter
    def last_losses(self, value: dict[str, float]) -> None:
        self._pending = None
        self._last_losses = dict(value)

    # ------------------------------------------------------------------------------------------- loop
    def train(self, iters: int | None = None) -> TrainResult:
        """Run until ``iters`` total steps (default ``cfg.train.iters``). Ctrl-C or SIGTERM (on any rank) finishes
        the step, saves a checkpoint and returns (``interrupted``; ``exit_code`` 130 / 143). Rank 0 holds the run
        folder's lock meanwhile."""
        tc = self.cfg.train
        target = tc.iters if iters is None else int(iters)
        self.stop = faults.StopRequest()
        lock = faults.hold_run_folder(self.run_dir) if self.rank == 0 else nullcontext()
        with lock, faults.stop_on_signals("iteration", self.stop, notice=self.rank == 0,
                                          insist=not under_torchrun()), frozen_heap():
            if self.rank == 0:
                faults.remove_stale_temps(self.run_dir / "checkpoint.pt")
                _cut_log(self.run_dir / "log.jsonl", self.step)
            return self._train_to(target)

    def _train_to(self, target: int) -> TrainResult:
        tc = self.cfg.train
        t0 = time.time()
        bar = None
        if self.progress:
            bar = tqdm(total=target, initial=min(self.step, target), dynamic_ncols=True, smoothing=0.05,
                       desc="modi train")
        interrupted = False
        ckpt: Path | None = None
        last_t, last_step = time.time(), self.step  # mean time per step since the last logged step
        try:
            while self.step < target:
                if self.stop.agreed(self.device):
                    interrupted = True
                    break
                self.run_step()  # no host read: the losses are read at log steps (and by a save)
                log_step = self.step % tc.log_every == 0 or self.step == target
                losses = None
                if log_step:
                    skipped = self._check_skips()
                    losses = dict(self.last_losses)
                    if skipped:
                        losses["skipped"] = float(skipped)
                        if self.rank == 0:
                            self.log(f"step {self.step}: skipped {skipped} step(s) with a non-finite loss since the "
                                     f"last log (no update was applied)")
                self._after_step(losses)
                if bar is not None:
                    bar.update(1)
                    if losses is not None:
                        bar.set_postfix({k: f"{losses[k]:.3f}" for k in ("d", "g", "contact") if k in losses})
                if self.rank == 0 and log_step:
                    now = time.time()
                    losses["sec_per_iter"] = (now - last_t) / max(1, self.step - last_step)
                    last_t, last_step = now, self.step
                    try:
                        self._log_scalars(losses)
                    except faults.OutputError as exc:  # DDP: the other ranks stop with it at the next step
                        if not self.distributed:
                            raise
                        self.stop.fail(exc)
                if tc.sample_every and self.step % tc.sample_every == 0 and self.write_samples:
                    self.write_sample_grid()
                if tc.ckpt_every and self.step % tc.ckpt_every == 0:
                    ckpt = self.save_checkpoint()
                if tc.snapshot_every and self.step % tc.snapshot_every == 0:
                    self.save_checkpoint(self.run_dir / "checkpoints" / f"step_{self.step:07d}.pt")
            if self.distributed:
                self.stop.agreed(self.device)  # a log error of the last step is raised on every rank
            # stopped right after a periodic save (a signal during the save): that checkpoint is this step's
            ckpt = self.save_checkpoint() if self._saved_step != self.step or ckpt is None else ckpt
            # a stopped run saves and leaves at once (a scheduler's grace period is short): no extra preview
            if not interrupted and self.write_samples and (not tc.sample_every or self.step % tc.sample_every != 0):
                self.write_sample_grid()
        finally:
            if bar is not None:
                bar.close()
            if self.writer is not None:
                with faults.output_errors(self.run_dir / "tb"):
                    self.writer.flush()
        if interrupted and self.rank == 0:
            self.log(f"interrupted at step {self.step}: checkpoint saved to {ckpt}")
        return TrainResult(self.step, interrupted, ckpt, time.time() - t0, dict(self.last_losses),
                           self.stop.signum if interrupted else None)

    def _after_step(self, losses: dict[str, float] | None) -> None:
        """Called after every step of ``train``: ``losses`` at log steps (already read), None otherwise."""

    def request_stop(self) -> None:
        """Ask the loop to save and return at the next iteration boundary (what Ctrl-C does)."""
        self.stop.set()

    def _log_scalars(self, losses: dict[str, float]) -> None:
        rec = {"step": self.step, **{k: round(v, 6) for k, v in losses.items()}}
        self.run_dir.mkdir(parents=True, exist_ok=True)
        faults.append_line(self.run_dir / "log.jsonl", json.dumps(rec))
        if self.writer is not None:
            groups = {"d": "loss/d", "g": "loss/g", "r1": "loss/r1", "path": "loss/path", "touch": "loss/touch",
                      "contact": "loss/contact", "real_score": "score/real", "fake_score": "score/fake",
                      "path_length": "reg/path_length", "sec_per_iter": "time/sec_per_iter"}
            with faults.output_errors(self.run_dir / "tb"):  # event files are appended by the library
                for k, v in losses.items():
                    self.writer.add_scalar(groups.get(k, k), v, self.step)

    # ------------------------------------------------------------------------------------------- samples
    def write_sample_grid(self) -> Path | None:
        """Fixed latents through G_ema -> ``samples/step_XXXXXXX/`` (BVH per motion + one GIF grid). Rank 0 only."""
        if self.rank != 0:
            return None

        out = self.run_dir / "samples" / f"step_{self.step:07d}"
        with torch.no_grad():
            x = self.G_ema(self.sample_z.to(self.device), noise_mode="const")
        try:
            write_outputs(self.codec, x, out, gif=True, bvh=not self.codec.positions_mode, gif_name="grid.gif")
        except Exception as exc:  # noqa: BLE001 - a preview must never kill a long run
            warnings.warn(f"could not write samples at step {self.step}: {exc}", stacklevel=2)
            return None
        return out

    # ------------------------------------------------------------------------------------------- checkpoints
    @property
    def saved_step(self) -> int | None:
        """The step of ``RUN/checkpoint.pt`` as this run wrote or loaded it (None before the first save)."""
        return self._saved_step

    def _rng_state(self) -> dict[str, Any]:
        st = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            st["cuda"] = torch.cuda.get_rng_state_all()
        return st

    def state_dict(self) -> dict[str, Any]:
        """Everything to generate, and to resume exactly (plain containers + tensors: loads with weights_only)."""
        rng = self._rng_state()
        rngs = [rng]
        if self.distributed:  # the ranks' random states; and their steps, which must agree before a save
            every: list[Any] = [None] * self.world
            dist.all_gather_object(every, (self.step, rng))
            steps = [s for s, _ in every]
            if len(set(steps)) != 1:
                raise RuntimeError(f"the ranks are at different steps {steps}: not saving a checkpoint")
            rngs = [r for _, r in every]
        return checkpoint_dict(
            config=self.cfg, codec=self.codec, levels=self.levels, G=self.G, G_ema=self.G_ema, D=self.D,
            step=self.step,
            hierarchy=self.data.hierarchy.to_dict(),
            g_optim=self.g_optim.state_dict(),
            d_optim=self.d_optim.state_dict(),
            mean_path_length=float(self.mean_path_length),
            rng=rngs,
            world_size=self.world,
            data_source=self.data.source,
            data_summary=_plain(self.data.summary),
            last_losses=dict(self.last_losses),
            precision=self.precision,
            cuda_graphs=_plain(self.graphs_record()),
        )

    def save_checkpoint(self, path: str | os.PathLike | None = None) -> Path:
        """Write the checkpoint atomically (rank 0; other ranks take part in gathering RNG states). Refused
        (``NonFiniteLossError``) while steps are being skipped for non-finite losses and a weight is not finite."""
        self._check_skips(saving=True)
        state = self.state_dict()
        path = Path(path) if path is not None else self.run_dir / "checkpoint.pt"
        main = path == self.run_dir / "checkpoint.pt"
        error = None
        if self.rank == 0:
            try:
                atomic_torch_save(state, path, previous_step=self._saved_step if main else None)
            except faults.OutputError as exc:
                error = exc
        if self.distributed:  # doubles as the barrier: every rank learns whether rank 0's write failed

            failed = torch.tensor([int(error is not None)], device=self.device)
            dist.all_reduce(failed)
            if error is None and int(failed.item()):
                raise UserError(f"rank 0 could not write {path} (see its message)")
        if error is not None:
            raise error
        if main:
            self._saved_step = self.step
        return path

    def load_state(self, ckpt: str | os.PathLike | dict) -> None:
        """Restore models, optimisers, step and RNG states from a checkpoint of the same model and skeleton."""
        st = load_checkpoint(ckpt) if not isinstance(ckpt, dict) else ckpt
        if MoDiConfig.from_dict(st["config"]).to_dict()["model"] != self.cfg.to_dict()["model"]:
            raise CheckpointError("checkpoint was trained with a different model config; "
                                  "resume with the same preset and model options")
        if not self.codec.skeleton.same_as(_skeleton_from(st)):
            raise CheckpointError("checkpoint was trained on a different skeleton than this data")
        try:
            self.G.load_state_dict(st["G"])
            self.G_ema.load_state_dict(st["G_ema"])
            self.D.load_state_dict(st["D"])
            self.g_optim.load_state_dict(st["g_optim"])
            self.d_optim.load_state_dict(st["d_optim"])
        except (RuntimeError, KeyError, ValueError) as exc:
            raise CheckpointError(f"checkpoint does not match this model: {exc}") from None
        for opt in (self.g_optim, self.d_optim):  # this run's device decides, not the saved flag
            set_capturable(opt, self._capturable)
        saved = st.get("precision", DEFAULT_PRECISION)
        if saved not in PRECISIONS:
            raise CheckpointError(f"checkpoint was trained in precision {saved!r}, which this modi does not know "
                                  f"({', '.join(PRECISIONS)}); upgrade modi")
        if self._precision_asked is None:
            self.precision = saved
        elif self._precision_asked != saved and self.rank == 0:
            self.log(f"modi train: the checkpoint was trained in {saved}; continuing in {self.precision} as asked "
                     f"(weights and optimiser states carry over unchanged)")
        self.step = int(st["step"])
        self._saved_step = self.step
        self.mean_path_length.fill_(float(st.get("mean_path_length", 0.0)))
        self.last_losses = dict(st.get("last_losses", {}))
        self._latest_reg = {k: v for k, v in self.last_losses.items() if k in ("r1", "path", "path_length")}
        rngs = st.get("rng") or []
        if len(rngs) == self.world:
            rng = rngs[self.rank]
            torch.set_rng_state(rng["torch"])  # (older checkpoints also hold a "data" generator: unused)
            if "cuda" in rng and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(rng["cuda"])
        else:
            warnings.warn(f"checkpoint was written by {len(rngs)} process(es), this run has {self.world}: "
                          "random streams restart (training continues, but not bit-for-bit)", stacklevel=2)
            torch.manual_seed(self.cfg.train.seed * 1000 + self.rank + 7 * self.step)
        if self.graphs is not None:  # the optimisers' state tensors are new: every kind is captured again
            self.graphs.reset()


def read_losses(losses: dict[str, Tensor | float]) -> dict[str, float]:
    """Losses as floats: the tensors read in one host read (the values ``float(t)`` gives)."""
    keys = [k for k, v in losses.items() if isinstance(v, Tensor)]
    vals = torch.stack([losses[k].detach().double().reshape(()) for k in keys]).tolist() if keys else []
    got = dict(zip(keys, vals))
    return {k: got[k] if k in got else float(v) for k, v in losses.items()}


class _PairD(nn.Module):
    """Runs D on fake and real in ONE forward (so DDP sees one forward per backward), with separate
    minibatch-stddev groups for each."""

    def __init__(self, d: Discriminator):
        super().__init__()
        self.d = d

    def forward(self, x: Tensor, y: Tensor | None = None):
        if y is None:
            return self.d(x)
        return self.d(x), self.d(y)


def _plain(obj: Any) -> Any:
    """Plain Python containers/scalars only (numpy scalars -> Python), so checkpoints load with weights_only."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (str, int, float, bool)) or obj is None or isinstance(obj, Tensor):
        return obj
    if hasattr(obj, "item"):
        return obj.item()
    return str(obj)


def _cut_log(path: Path, step: int) -> None:
    """Drop the records of ``log.jsonl`` past ``step``: a run killed after its last checkpoint logged steps that
    its resume trains again, and the log must read as one run (steps increasing)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    except (FileNotFoundError, UnicodeDecodeError):
        return
    keep = []
    for line in lines:
        try:
            rec_step = int(json.loads(line).get("step", 0))
        except (ValueError, AttributeError, TypeError):
            continue  # a half-written last line of a killed run
        if rec_step <= step:
            keep.append(line if line.endswith("\n") else line + "\n")
    if len(keep) != len(lines):
        faults.atomic_write(path, "".join(keep))


def newest_checkpoint(run_dir: str | os.PathLike, warn: Callable[[str], None] | None = None
                      ) -> tuple[Path, dict[str, Any]] | None:
    """``(path, state)`` of the newest checkpoint of the run in ``run_dir`` that loads: ``checkpoint.pt``, or a
    newer snapshot (``checkpoints/step_*.pt``), or when ``checkpoint.pt`` cannot be read the newest snapshot that
    can (``warn`` is told why); None when there is none."""
    run_dir = Path(run_dir)
    warn = warn or (lambda msg: warnings.warn(msg, stacklevel=3))
    main_path, main_state = run_dir / "checkpoint.pt", None
    if main_path.is_file():
        try:
            main_state = load_checkpoint(main_path)
        except CheckpointError as exc:
            warn(f"{main_path} cannot be read ({exc}): looking for a snapshot")

    def snap_step(p: Path) -> int:
        try:
            return int(p.stem.split("_", 1)[1])
        except (IndexError, ValueError):
            return -1

    snaps = sorted((p for p in (run_dir / "checkpoints").glob("step_*.pt") if snap_step(p) >= 0),
                   key=snap_step, reverse=True)
    for snap in snaps:
        if main_state is not None and snap_step(snap) <= int(main_state["step"]):
            break
        try:
            return snap, load_checkpoint(snap)
        except CheckpointError as exc:
            warn(f"{snap} cannot be read ({exc}): trying an older one")
    return (main_path, main_state) if main_state is not None else None


def _skeleton_from(st: dict[str, Any]) -> Any:
    return Skeleton.from_dict(st["skeleton"])


def seconds_per_iteration(trainer: Trainer, n: int = 5, warmup: int = 1) -> float:
    """Mean wall time of ``n`` full training iterations (after ``warmup``), lazy regularisers included in
    proportion (steps 0, 16, ... run R1; 0, 4, ... path length) -- a benchmark helper, not used by training."""
    losses: dict[str, Tensor] = {}
    for _ in range(warmup):
        losses = trainer.run_step()
    read_losses(losses)  # a read waits for the device
    t = time.perf_counter()
    for _ in range(n):
        losses = trainer.run_step()
    read_losses(losses)
    return (time.perf_counter() - t) / n


__all__ = ["MotionCodec", "TrainingData", "prepare_data", "write_procedural_data", "Trainer", "TrainResult",
           "NonFiniteLossError", "atomic_torch_save", "init_distributed_from_env", "build_models",
           "seconds_per_iteration", "newest_checkpoint", "read_losses", "NONFINITE_STEPS"]
