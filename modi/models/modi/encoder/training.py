"""Training the encoder (paper 001 §3.4, eqs. 4-8) with the generator frozen.

``L = λ_rec L_rec + λ_fcon L_fcon + λ_root L_root + λ_pos L_pos``. Two forms (``EncoderTrainConfig.losses``):

* ``released`` (default; the authors' ``train_encoder.py`` defaults and ``models/encoder_mask.py``), weights
  10 / 1000 / 20 / 1: ``L_root`` on the root-motion entity and the *real* root rotation (the first joint below
  constant placeholder roots such as Bandai's ``joint_Root``, see ``root_rotation_entity``); ``L_pos`` the MSE of
  FK positions with the root translation zeroed (local), in the data's units. Adam lr 0.002·16/17, betas
  (0, 0.99^(16/17)) (``optimizer="released"``).
* ``ours`` (this package's earlier form), weights 1 / 100 / 2 / 0.1: ``L_root`` on entity 0, ``L_pos`` on global
  positions in tenths of the body size (``latent.space.position_scale``); Adam lr 0.002, betas (0.9, 0.99).

In both: ``L_rec`` -- MSE between m and G(I(m)) on the normalised representation; ``L_fcon`` -- BCE between the
data's contact labels and s(contact channel of G(I(m))), s = the generator's own contact sigmoid
(``modi_model.losses.contact_probability``).

Data: the windows of the generator's own dataset configuration, split 80/20 *by file* exactly as the generator's
training split (``modi.data.dataset``), so the test split is unseen by the generator and the encoder alike. The
prefix variant (§4.2) zeroes every frame from ``prefix_frames`` on (plus a visibility channel) and is still
supervised by the whole motion.

The checkpoint is one file written atomically; it embeds the generator it was trained against (config, codec,
levels, EMA weights), so applications need nothing else, and resuming continues the same run exactly. Ctrl-C and
SIGTERM finish the step and save (``modi.faults``); the checkpoint's name is locked while training runs.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from modi import faults
from modi._version import __version__ as modi_version
from modi.data.dataset import build_dataset
from modi.errors import CheckpointError, UserError
from modi.io.safe_load import load_data
from modi.models.modi.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, read_tagged
from modi.models.modi.config import DataConfig, MoDiConfig
from modi.models.modi.encoder.metrics import evaluate_encoder
from modi.models.modi.encoder.model import ENCODER_HEADS, EncoderConfig, MotionEncoder, build_encoder, encode
from modi.models.modi.latent.space import load_model, position_scale, random_w, synthesize
from modi.models.modi.losses import contact_probability
from modi.models.modi.training import _dataset_config, data_root

ENCODER_FORMAT = "modi-encoder"
ENCODER_VERSION = 1


# loss weights (rec, contact, root, pos) of the two loss forms; see the module docstring
LOSS_WEIGHTS = {
    "released": {"lambda_rec": 10.0, "lambda_contact": 1000.0, "lambda_root": 20.0, "lambda_pos": 1.0},
    "ours": {"lambda_rec": 1.0, "lambda_contact": 100.0, "lambda_root": 2.0, "lambda_pos": 0.1},
}
# Adam (lr, beta1, beta2): the released train_encoder.py uses the discriminator's lazy-R1-corrected settings
_C = 16 / 17
OPTIMIZERS = {"released": (0.002 * _C, 0.0, 0.99 ** _C), "ours": (0.002, 0.9, 0.99)}
# training options a resumed run keeps from its checkpoint: the loss form and weights, the optimizer, the head
# (the encoder's architecture as a whole is compared through its saved EncoderConfig)
RESUMED_OPTIONS = ("losses", "optimizer", "head", "lr", "beta1", "beta2", "lambda_rec", "lambda_contact",
                   "lambda_root", "lambda_pos", "generated", "lambda_latent")
# what checkpoints written before an option existed were trained with (before 'losses'/'optimizer'/'head' were
# saved, the only form was this package's: "ours" losses and optimizer, bottleneck head)
_OLD_TRAIN_OPTIONS = {"losses": "ours", "optimizer": "ours", "head": "bottleneck", "generated": 0.0,
                      "lambda_latent": 0.0}


@dataclass
class EncoderTrainConfig:
    """Encoder training options. ``None`` weights and Adam settings take the values of ``losses`` and
    ``optimizer`` (``LOSS_WEIGHTS``, ``OPTIMIZERS``) on construction; explicit values override them."""

    iters: int = 5000
    batch: int = 16
    lr: float | None = None
    beta1: float | None = None
    beta2: float | None = None
    lambda_rec: float | None = None
    lambda_contact: float | None = None
    lambda_root: float | None = None
    lambda_pos: float | None = None
    losses: str = "released"  # "released" | "ours" (root entity, position term and default weights)
    optimizer: str = "released"  # "released" | "ours" (default lr and betas)
    head: str = "released"  # encoder head: "released" | "bottleneck" (see modi.models.modi.encoder.model)
    prefix_frames: int | None = None
    channel_multiplier: float = 1.0
    hidden: int | None = None  # bottleneck-head width (None: the encoder's default)
    generated: float = 0.0  # fraction of every batch replaced by generator samples (the authors' code's option)
    lambda_latent: float = 0.0  # on those samples: MSE between I(G(w+)) and w+, in units of W's spread
    units: str = "auto"  # only for the mm metrics
    seed: int = 0
    log_every: int = 20
    ckpt_every: int = 250
    eval_every: int = 500

    def __post_init__(self) -> None:
        for name, value in LOSS_WEIGHTS.get(self.losses, {}).items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        for name, value in zip(("lr", "beta1", "beta2"), OPTIMIZERS.get(self.optimizer, ())):
            if getattr(self, name) is None:
                setattr(self, name, value)

    def validate(self) -> "EncoderTrainConfig":
        if self.losses not in LOSS_WEIGHTS:
            raise UserError(f"losses must be one of {', '.join(LOSS_WEIGHTS)}, not {self.losses!r}")
        if self.optimizer not in OPTIMIZERS:
            raise UserError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, not {self.optimizer!r}")
        if self.head not in ENCODER_HEADS:
            raise UserError(f"head must be one of {', '.join(ENCODER_HEADS)}, not {self.head!r}")
        if self.iters < 0 or self.batch < 1:
            raise UserError(f"iters must be >= 0 and batch >= 1 (got {self.iters}, {self.batch})")
        if self.lr <= 0 or not (0.0 <= self.beta1 < 1.0 and 0.0 <= self.beta2 < 1.0):
            raise UserError(f"lr must be positive and betas in [0, 1), got {self.lr}, ({self.beta1}, {self.beta2})")
        for name in ("lambda_rec", "lambda_contact", "lambda_root", "lambda_pos"):
            if getattr(self, name) < 0:
                raise UserError(f"{name} must be >= 0")
        if self.channel_multiplier <= 0:
            raise UserError("channel_multiplier must be positive")
        if self.hidden is not None and self.hidden < 1:
            raise UserError(f"hidden must be a positive width, got {self.hidden}")
        if not 0.0 <= self.generated <= 1.0 or self.lambda_latent < 0:
            raise UserError("generated must be in [0, 1] and lambda_latent >= 0")
        if self.lambda_latent > 0 and self.generated == 0:
            raise UserError("lambda_latent needs generated samples (generated > 0)")
        return self


# =============================================================================================== data
@dataclass
class EncoderData:
    """Normalised windows of the train and test splits (by file) and where they came from."""

    train: Tensor
    test: Tensor
    source: str
    info: dict[str, Any] = field(default_factory=dict)


def load_encoder_data(codec: Any, gcfg: Any, source: str | os.PathLike, *, cache: bool = True,
                      progress: bool = False, work_dir: str | os.PathLike | None = None) -> EncoderData:
    """Windows of ``source`` (BVH folder or 'procedural') cut and split like the generator's training data,
    normalised with the generator's statistics."""
    if getattr(codec, "positions_mode", False):
        raise UserError("the encoder needs a rotation model; this checkpoint is the 'positions' ablation")
    src = str(source)
    root = data_root(source, gcfg.data.fps, work_dir, what="data")
    dcfg = _dataset_config(gcfg)  # the generator's own mapping from its config to the dataset: same windows, split
    ds = build_dataset(root, dcfg, cache=cache, progress=progress)
    if not ds.skeleton.same_as(codec.skeleton):
        a, b = ds.skeleton, codec.skeleton
        if a.names != b.names or a.parents != b.parents:
            why = f"{a.n_joints} vs {b.n_joints} joints, or other names or hierarchy"
        else:
            j = int(np.abs(a.offsets - b.offsets).max(axis=1).argmax())
            why = (f"same joints, but bone offsets differ, most at {a.names[j]}: {np.round(a.offsets[j], 3).tolist()} "
                   f"vs {np.round(b.offsets[j], 3).tolist()}")
        raise UserError(f"{src}: its skeleton differs from the generator's ({why})")
    if ds.test.shape[0] == 0:
        raise UserError(f"{src}: the 20% test split has no windows (too few or too short clips)")
    norm = codec.normalizer
    info = {k: v for k, v in ds.summary().items() if isinstance(v, (int, float, str, bool, list))}
    return EncoderData(norm.normalize(ds.train).float().contiguous(), norm.normalize(ds.test).float().contiguous(),
                       src, info)


def split_windows(x: Tensor, test_fraction: float = 0.2, seed: int = 0) -> EncoderData:
    """A seeded 80/20 split of in-memory windows (for data that has no files, e.g. generated motions)."""
    n = x.shape[0]
    n_test = max(1, int(round(n * test_fraction)))
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    return EncoderData(x[perm[n_test:]].contiguous(), x[perm[:n_test]].contiguous(), "tensor",
                       {"train_windows": n - n_test, "test_windows": n_test})


# =============================================================================================== losses
def root_rotation_entity(codec: Any) -> int:
    """The entity of the motion's real root rotation: the root joint, unless it is a placeholder -- a joint with one
    child whose rotation never changes in the data (Bandai's ``joint_Root`` above ``Hips``) -- in which case its
    child, and so on. Constancy is read from the normaliser (a std at its floor on every channel)."""
    sk, std = codec.skeleton, codec.normalizer.std
    j = 0
    while len(sk.children(j)) == 1 and float(std[:, j].max()) <= _CONSTANT_STD:
        j = int(sk.children(j)[0])
    return j


_CONSTANT_STD = 1e-3 * (1 + 1e-4)  # Normalizer.fit's floor (min_std 1e-3): a channel that never changes


def encoder_losses(codec: Any, pred: Tensor, target: Tensor, cfg: EncoderTrainConfig, scale: float,
                   target_decoded: dict[str, Tensor] | None = None, root_entity: int = 0) -> dict[str, Tensor]:
    """The four terms and their weighted total (eq. 8).

    ``cfg.losses == "released"`` (the authors' train_encoder.py / models/encoder_mask.py): the root term is the MSE
    on the root-motion entity plus the real root rotation ``root_entity`` (``root_rotation_entity``), the position
    term the MSE of FK positions with the root translation zeroed, in the data's units. ``"ours"``: root term on
    entity 0, position term on global positions times ``scale`` (tenths of the body size)."""
    J = codec.rep.n_joints
    rec = F.mse_loss(pred, target)
    r = root_entity if cfg.losses == "released" else 0
    root = F.mse_loss(pred[:, :, J], target[:, :, J]) + F.mse_loss(pred[:, :, r], target[:, :, r])
    out = {"rec": rec, "root": root}
    need_decode = cfg.lambda_pos > 0 or cfg.lambda_contact > 0
    zero = pred.new_zeros(())
    if need_decode:
        dp = codec.decode(pred)
        dt = target_decoded if target_decoded is not None else {k: v.detach() for k, v in codec.decode(target).items()}
        if cfg.lambda_contact > 0 and dp["contacts"].shape[-1] > 0:
            labels = (dt["contacts"] > 0.5).to(pred.dtype)
            prob = contact_probability(dp["contacts"]).clamp(1e-6, 1 - 1e-6)
            out["contact"] = F.binary_cross_entropy(prob, labels)
        else:
            out["contact"] = zero
        if cfg.lambda_pos <= 0:
            out["pos"] = zero
        elif cfg.losses == "released":  # local positions (root translation zeroed), data units
            out["pos"] = F.mse_loss(dp["positions"] - dp["root"].unsqueeze(-2),
                                    dt["positions"] - dt["root"].unsqueeze(-2))
        else:
            out["pos"] = F.mse_loss(dp["positions"] * scale, dt["positions"] * scale)
    else:
        out["contact"] = out["pos"] = zero
    out["total"] = (cfg.lambda_rec * rec + cfg.lambda_contact * out["contact"] + cfg.lambda_root * root
                    + cfg.lambda_pos * out["pos"])
    return out


# =============================================================================================== checkpoints
def encoder_checkpoint_dict(*, encoder: Any, generator: dict[str, Any], step: int, **extra: Any) -> dict[str, Any]:
    """The one writer of the encoder format: the encoder, the generator bundle it inverts, the step, the versions
    that wrote it, plus ``extra`` keys (the trainer's optimiser and RNG states, an import's provenance)."""
    return {
        "format": ENCODER_FORMAT, "version": ENCODER_VERSION,
        "encoder_config": encoder.cfg.to_dict(),
        "encoder": {k: v.detach().cpu() for k, v in encoder.state_dict().items()},
        "step": int(step), "generator": generator,
        "torch_version": str(torch.__version__), "modi_version": modi_version,
        **extra,
    }


def generator_bundle(g: Any, codec: Any, gcfg: Any = None, step: int = 0) -> dict[str, Any]:
    """A MoDi-checkpoint-shaped dict holding just what generation needs (loadable by ``load_generator``)."""
    if gcfg is None:
        _, _, t = g.output_shape
        gcfg = MoDiConfig(model=g.cfg, data=DataConfig(n_frames=t, fps=codec.fps), preset="custom")
    return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "config": gcfg.to_dict(),
            "codec": codec.state_dict(), "skeleton": codec.skeleton.to_dict(),
            "levels": [lv.to_dict() for lv in g.levels], "G_ema": {k: v.detach().cpu() for k, v in
                                                                   g.state_dict().items()}, "step": int(step)}


@dataclass
class EncoderBundle:
    """A trained encoder with the generator it inverts into."""

    encoder: MotionEncoder
    g: Any
    codec: Any
    gcfg: Any
    cfg: EncoderConfig
    train_cfg: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def prefix_frames(self) -> int | None:
        return self.cfg.prefix_frames

    @torch.no_grad()
    def project(self, x: Tensor, prefix_frames: int | None = None) -> tuple[Tensor, Tensor]:
        """(W+ latents, G(I(x))) of normalised motions x."""
        self.encoder.eval()
        dev = next(self.encoder.parameters()).device
        wplus = encode(self.encoder, x.to(dev).float(), prefix_frames)
        return wplus, synthesize(self.g, wplus)


def load_encoder(path: str | os.PathLike | dict, device: str | torch.device = "cpu") -> EncoderBundle:
    """Read an encoder checkpoint (``CheckpointError`` for anything else) and rebuild encoder + generator."""
    def foreign(st: Any) -> str:
        generator = isinstance(st, dict) and st.get("format") == CHECKPOINT_FORMAT
        return " (this is a generator checkpoint; train an encoder with 'modi encoder train')" if generator else ""

    st, where = read_tagged(path, "encoder checkpoint", ENCODER_FORMAT, ENCODER_VERSION, label="encoder checkpoint",
                            foreign=foreign)
    g, codec, gcfg = load_model(st["generator"], device=device)
    try:
        cfg = EncoderConfig.from_dict(st["encoder_config"], generator_inplace_convs=g.cfg.n_inplace_convs)
        enc = MotionEncoder(g.cfg, g.levels, cfg).to(device)
        enc.load_state_dict(st["encoder"])
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{where}: encoder state does not match its config ({exc})") from None
    enc.eval()
    return EncoderBundle(enc, g, codec, gcfg, cfg, dict(st.get("train_config", {})),
                         {k: st.get(k) for k in ("step", "data_source", "data_info", "metrics")})


# =============================================================================================== trainer
class EncoderTrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during ``EncoderTrainer.train``: the checkpoint was saved at a step boundary (resumable);
    ``exit_code`` is 130 / 143."""

    def __init__(self, checkpoint: Path, signum: int | None = None) -> None:
        super().__init__(f"checkpoint saved to {checkpoint}")
        self.checkpoint = checkpoint
        self.signum = signum
        self.exit_code = faults.exit_code(signum)


def hold_output(out: str | os.PathLike):
    """The lock of an encoder checkpoint ``out``: ``.NAME.lock`` beside it (other encoders may share the folder)."""
    out = Path(out)
    return faults.hold_run_folder(out.parent, f".{out.name}.lock", what=str(out))


@dataclass
class EncoderTrainResult:
    step: int
    checkpoint: Path
    seconds: float
    last_losses: dict[str, float]
    metrics: dict[str, Any] | None


class EncoderTrainer:
    """Trains an encoder for a frozen generator on ``data.train``; writes ``out`` (the checkpoint) and
    ``out`` + ``.log.jsonl`` (losses, and test metrics every ``eval_every`` steps)."""

    def __init__(self, model: tuple, data: EncoderData, out: str | os.PathLike, cfg: EncoderTrainConfig | None = None,
                 *, generator_state: dict[str, Any] | None = None, resume: str | os.PathLike | None = None,
                 progress: bool = True, log: Callable[[str], None] | None = None):
        g, codec, gcfg = model
        self.g, self.codec, self.gcfg = g, codec, gcfg
        self.cfg = (cfg or EncoderTrainConfig()).validate()
        self.data = data
        self.out = Path(out)
        self.progress = progress
        self.log = log or (lambda msg: print(msg, flush=True))
        self.device = next(g.parameters()).device
        k, e, t = g.output_shape
        if data.train.ndim != 4 or tuple(data.train.shape[1:]) != (k, e, t):
            raise UserError(f"training windows are {tuple(data.train.shape[1:])}, the generator makes {(k, e, t)}")
        if data.train.shape[0] == 0:
            raise UserError("no training windows")
        for p in g.parameters():
            p.requires_grad_(False)
        g.eval()
        self.generator_state = generator_state or generator_bundle(g, codec, gcfg)
        torch.manual_seed(self.cfg.seed)
        self.encoder = build_encoder(g, self.cfg.channel_multiplier, self.cfg.prefix_frames,
                                     hidden=self.cfg.hidden, head=self.cfg.head)
        self.root_entity = root_rotation_entity(codec)
        self.encoder.train()
        self.optim = torch.optim.Adam(self.encoder.parameters(), lr=self.cfg.lr, betas=(self.cfg.beta1, self.cfg.beta2))
        self.scale = position_scale(codec)
        self.rng = torch.Generator().manual_seed(self.cfg.seed * 7919 + 3)
        self.gen_rng = torch.Generator().manual_seed(self.cfg.seed * 104729 + 11)
        self.w_std = None
        if self.cfg.generated > 0:
            self.w_std = random_w(g, 4096, seed=self.cfg.seed + 5).std(0).clamp_min(1e-3)
        self.step = 0
        self._saved_step: int | None = None  # step of the checkpoint on disk (named by a disk-full error)
        self.last_losses: dict[str, float] = {}
        self.metrics: dict[str, Any] | None = None
        self.train_x = data.train.to(self.device)
        if resume is not None:
            self.load_state(resume)

    # ------------------------------------------------------------------------------------------- steps
    def train_step(self) -> dict[str, float]:
        n_gen = int(round(self.cfg.batch * self.cfg.generated))
        idx = torch.randint(self.train_x.shape[0], (self.cfg.batch - n_gen,), generator=self.rng)
        real = self.train_x[idx.to(self.device)]
        target_w = None
        if n_gen:
            target_w = self._generated_latents(n_gen)
            with torch.no_grad():
                fake = self.g.synthesis(target_w, noise_mode="const")
            real = torch.cat([real, fake])
        wplus = encode(self.encoder, real)
        pred = self.g.synthesis(wplus, noise_mode="const")
        with torch.no_grad():
            dt = {k: v.detach() for k, v in self.codec.decode(real).items()}
        losses = encoder_losses(self.codec, pred, real, self.cfg, self.scale, dt, root_entity=self.root_entity)
        if target_w is not None and self.cfg.lambda_latent > 0:
            lat = ((wplus[-n_gen:] - target_w) / self.w_std).pow(2).mean()
            losses["latent"] = lat
            losses["total"] = losses["total"] + self.cfg.lambda_latent * lat
        if not torch.isfinite(losses["total"]):
            vals = {k: round(float(v), 4) for k, v in losses.items()}
            raise UserError(f"non-finite encoder loss at step {self.step} ({vals}); "
                            "try a lower --lr")
        self.optim.zero_grad(set_to_none=True)
        losses["total"].backward()
        self.optim.step()
        self.step += 1
        return {k: float(v.detach()) for k, v in losses.items()}

    def _generated_latents(self, n: int) -> Tensor:
        """W+ of generator samples as in training: two mapped z, mixed at a random layer 90% of the time."""
        d, L = self.g.latent_dim, self.g.n_latent
        z = torch.randn(2, n, d, generator=self.gen_rng).to(self.device)
        cut = torch.randint(1, L, (n,), generator=self.gen_rng)
        mix = torch.rand(n, generator=self.gen_rng) < 0.9
        with torch.no_grad():
            w1, w2 = self.g.mapping(z[0]), self.g.mapping(z[1])
        layer = torch.arange(L).view(1, L)
        second = (mix.view(n, 1) & (layer >= cut.view(n, 1))).to(self.device).unsqueeze(-1)
        return torch.where(second, w2.unsqueeze(1), w1.unsqueeze(1)).contiguous()

    def evaluate(self, split: str = "test") -> dict[str, Any]:
        x = self.data.test if split == "test" else self.data.train
        return evaluate_encoder(self.encoder, self.g, self.codec, x, units=self.cfg.units)

    def train(self, iters: int | None = None) -> EncoderTrainResult:
        """Train to ``iters`` steps (default ``cfg.iters``). Ctrl-C or SIGTERM finishes the step, saves the
        checkpoint and raises ``EncoderTrainingInterrupted`` (``--resume`` continues); a second Ctrl-C aborts. A
        signal during the final evaluation does not stop it: the run is done, it is saved and returns."""
        target = self.cfg.iters if iters is None else int(iters)
        t0 = time.time()
        with hold_output(self.out), faults.stop_on_signals("step") as stop:
            faults.remove_stale_temps(self.out)
            bar = None
            if self.progress:
                bar = tqdm(total=target, initial=min(self.step, target), desc="encoder train", dynamic_ncols=True)
            try:
                self._train_to(target, bar, stop)
            finally:
                if bar is not None:
                    bar.close()
            self.metrics = self.evaluate()
            self._log({"step": self.step, "test": self.metrics["encoder"], "final": True})
            ckpt = self.save_checkpoint()
        return EncoderTrainResult(self.step, ckpt, time.time() - t0, dict(self.last_losses), self.metrics)

    def _train_to(self, target: int, bar: Any, stop: Any) -> None:
        while self.step < target:
            if stop:
                raise EncoderTrainingInterrupted(self.save_checkpoint(), stop.signum)
            losses = self.train_step()
            self.last_losses = losses
            if bar is not None:
                bar.update(1)
                bar.set_postfix(total=f"{losses['total']:.3f}", rec=f"{losses['rec']:.3f}",
                                pos=f"{losses['pos']:.2f}")
            if self.step % self.cfg.log_every == 0 or self.step == target:
                self._log({"step": self.step, **{k: round(v, 6) for k, v in losses.items()}})
            if self.cfg.eval_every and self.step % self.cfg.eval_every == 0:
                self.metrics = self.evaluate()
                self._log({"step": self.step, "test": self.metrics["encoder"]})
            if self.cfg.ckpt_every and self.step % self.cfg.ckpt_every == 0:
                self.save_checkpoint()

    def _log(self, rec: dict[str, Any]) -> None:
        path = self.out.with_name(self.out.name + ".log.jsonl")
        path.parent.mkdir(parents=True, exist_ok=True)
        faults.append_line(path, json.dumps(rec))

    # ------------------------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        return encoder_checkpoint_dict(
            encoder=self.encoder, generator=self.generator_state, step=self.step,
            optim=self.optim.state_dict(), train_config=asdict(self.cfg),
            rng={"data": self.rng.get_state(), "generated": self.gen_rng.get_state(),
                 "torch": torch.get_rng_state(),
                 **({"cuda": torch.cuda.get_rng_state_all()} if torch.cuda.is_available() else {})},
            data_source=self.data.source, data_info=self.data.info,
            metrics=self.metrics, last_losses=dict(self.last_losses))

    def save_checkpoint(self, path: str | os.PathLike | None = None) -> Path:
        """Atomic (``modi.faults``): a full disk is one line, and the previous checkpoint stays as it was."""
        path = Path(path) if path is not None else self.out
        main = path == self.out
        faults.atomic_torch_save(self.state_dict(), path, previous_step=self._saved_step if main else None)
        if main:
            self._saved_step = self.step
        return path

    def load_state(self, path: str | os.PathLike) -> None:
        p = Path(path)
        st = _read_resume_checkpoint(p)
        saved_enc = EncoderConfig.from_dict(st["encoder_config"], generator_inplace_convs=self.g.cfg.n_inplace_convs)
        differ = [k for k, v in saved_enc.to_dict().items() if self.encoder.cfg.to_dict().get(k) != v]
        if differ:
            flags = sorted({_ENCODER_FIELD_OPTIONS.get(k, k) for k in differ})
            raise CheckpointError(f"{p}: encoder was built differently ({', '.join(flags)}: the checkpoint has "
                                  f"{', '.join(f'{k}={getattr(saved_enc, k)!r}' for k in differ)}); resume with the "
                                  "same --head, --prefix, --channel-multiplier and --hidden")
        _refuse_changed_options(p, saved_train_options(st), asdict(self.cfg))
        gen = st.get("generator") or {}
        mine = self.generator_state
        if gen.get("config") != mine.get("config") or gen.get("step") != mine.get("step"):
            raise CheckpointError(f"{p}: was trained against a different generator checkpoint")
        try:
            self.encoder.load_state_dict(st["encoder"])
            self.optim.load_state_dict(st["optim"])
        except (RuntimeError, ValueError, KeyError) as exc:
            raise CheckpointError(f"{p}: encoder state does not match ({exc})") from None
        self.step = int(st["step"])
        self.rng.set_state(st["rng"]["data"])
        if "generated" in st["rng"]:
            self.gen_rng.set_state(st["rng"]["generated"])
        torch.set_rng_state(st["rng"]["torch"])
        if "cuda" in st["rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(st["rng"]["cuda"])
        self._saved_step = self.step if p == self.out else None
        self.metrics = st.get("metrics")
        self.last_losses = dict(st.get("last_losses") or {})


# the command-line option behind each EncoderConfig field (for messages)
_ENCODER_FIELD_OPTIONS = {"prefix_frames": "--prefix", "mask_channel": "--prefix", "channel_multiplier":
                          "--channel-multiplier", "hidden": "--hidden", "head": "--head", "inplace_convs": "--head",
                          "in_channels": "the generator", "n_latent": "the generator", "latent_dim": "the generator"}


def _option_name(name: str) -> str:
    """``lambda_rec`` -> ``--lambda-rec`` for options ``modi encoder train`` has, else the field's own name."""
    return name if name in ("beta1", "beta2", "generated", "lambda_latent") else "--" + name.replace("_", "-")


def _read_resume_checkpoint(p: Path) -> dict[str, Any]:
    if not p.is_file():
        raise CheckpointError(f"{p}: no encoder checkpoint to resume")
    st = load_data(p, "encoder checkpoint")  # as data only: code in the file is refused unrun
    if not isinstance(st, dict) or st.get("format") != ENCODER_FORMAT:
        raise CheckpointError(f"{p}: not a MoDi encoder checkpoint")
    return st


def saved_train_options(st: dict[str, Any]) -> dict[str, Any]:
    """The ``RESUMED_OPTIONS`` an encoder checkpoint (its state dict) was trained with; an option the checkpoint
    predates takes the value it was trained with (``_OLD_TRAIN_OPTIONS``), the head comes from its encoder."""
    tc = {**_OLD_TRAIN_OPTIONS, **dict(st.get("train_config") or {})}
    tc["head"] = EncoderConfig.from_dict(st["encoder_config"]).head
    return {k: tc.get(k) for k in RESUMED_OPTIONS}


def _refuse_changed_options(p: Path, saved: dict[str, Any], given: dict[str, Any]) -> None:
    def fmt(v: Any) -> str:
        return f"{v:g}" if isinstance(v, float) else str(v)

    differ = [k for k in RESUMED_OPTIONS if given.get(k) is not None and given[k] != saved[k]]
    if differ:
        was = ", ".join(f"{_option_name(k)} {fmt(saved[k])} (this run: {fmt(given[k])})" for k in differ)
        raise CheckpointError(f"{p} was trained with {was}; a resumed run keeps its loss form, weights, optimizer "
                              "and head: drop those options (or choose another --out)")


def resumed_train_options(path: str | os.PathLike, given: dict[str, Any]) -> dict[str, Any]:
    """The ``RESUMED_OPTIONS`` for resuming the encoder checkpoint ``path``: the checkpoint's, where ``given``
    (option -> value, None = not given) gives none; ``CheckpointError`` naming every given option that differs."""
    p = Path(path)
    saved = saved_train_options(_read_resume_checkpoint(p))
    _refuse_changed_options(p, saved, given)
    return {**saved, **{k: v for k, v in given.items() if k in saved and v is not None}}


__all__ = ["EncoderTrainConfig", "LOSS_WEIGHTS", "OPTIMIZERS", "RESUMED_OPTIONS", "saved_train_options",
           "resumed_train_options", "root_rotation_entity", "EncoderData", "load_encoder_data", "split_windows", "encoder_losses",
           "generator_bundle", "encoder_checkpoint_dict", "EncoderBundle", "load_encoder", "EncoderTrainer", "EncoderTrainResult",
           "EncoderTrainingInterrupted", "hold_output",
           "ENCODER_FORMAT", "ENCODER_VERSION"]
