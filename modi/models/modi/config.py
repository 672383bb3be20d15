"""Dataclass configs for MoDi: model, data and training, with the paper preset and a small CPU preset.

Every checkpoint stores ``MoDiConfig.to_dict()`` so a run can be rebuilt and resumed from the file alone.
The ablation switches are the variants of the paper's Table 2 (and Table 6 for the root representation).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

from modi.data.representation import LEAF_ROTATIONS

PAPER_CHANNELS = (256, 128, 64, 64, 32)  # coarse -> fine, paper Table 3
CONTACT_LOSSES = ("released", "squared")

# Values a checkpoint's config takes for fields it predates: the behaviour it was trained with, not today's default.
LEGACY_DEFAULTS: dict[str, dict[str, Any]] = {
    "model": {"noise_injection": True},
    "train": {"contact_loss": "squared"},
    "data": {"drop_root_anchor": False, "leaf_rotations": "keep"},
}


@dataclass
class ModelConfig:
    """Generator/discriminator architecture.

    ``channels`` runs coarse -> fine. When the skeleton's pooling hierarchy has more levels than ``channels``,
    only the finest ``len(channels)`` levels are used (the coarsest used level then has more than one entity);
    when it has fewer, the finest channel widths are used (as the authors' code does).
    """

    latent_dim: int = 512
    n_mlp: int = 8
    lr_mlp: float = 0.01
    channels: tuple[int, ...] = PAPER_CHANNELS
    kernel_size: int = 3
    neighbor_distance: int = 1
    n_inplace_convs: int = 2  # ablation "remove one in-place conv per hierarchy" = 1
    scaler: str = "conv"  # "conv" (convolutional scaler, MoDi) | "pool" (skeletal pooling/unpooling ablation)
    skeleton_aware: bool = True  # False = the non-skeleton-aware pseudo-image ablation (dense 2D convs)
    noise_injection: bool = False  # released MoDi: none; True = StyleGAN2 per-frame noise in every styled conv
    # skeleton topology (modi.core.skeleton_graph.build_hierarchy): "siblings" = edges sharing a joint are
    # neighbours (ours), "tree" = self + parent + children (the released code); "merge" pooling goes down to one entity (ours),
    # "released" keeps the root edge unpooled and the root-motion/contact entities to the coarsest level (<= 2 edges)
    neighbors: str = "siblings"
    pooling: str = "merge"
    mbstd_group: int = 4
    # "weight": StyleGAN2 weight demodulation (the paper); "activations": the released code's, each styled conv's
    # output divided by its standard deviation over entities and frames (what imported released checkpoints use)
    demodulation: str = "weight"
    # frames beyond the clip's start at the conv scalers: "adjoint" (modi's up/down ops, each the other's exact
    # adjoint, read zeros there); "stylegan2" (StyleGAN2's upfirdn padding, the released code's: the generator's
    # upsampler keeps the transposed conv's first tap and the discriminator's downsampler one more blurred frame)
    time_padding: str = "adjoint"

    @property
    def inplace_convs_per_level(self) -> int:
        """The in-place convs of each level's generator block and discriminator residual block: ``n_inplace_convs``,
        one fewer with the skeletal pooling scaler, whose scaling conv is itself an in-place conv at the level
        (unpool, then conv), so both scalers build as many convs per level."""
        return self.n_inplace_convs - (1 if self.scaler == "pool" and self.skeleton_aware else 0)

    def validate(self) -> None:
        if self.scaler not in ("conv", "pool"):
            raise ValueError(f"model.scaler must be 'conv' or 'pool', not {self.scaler!r}")
        if self.n_inplace_convs < 1:
            raise ValueError(f"model.n_inplace_convs must be >= 1, not {self.n_inplace_convs}")
        if not self.channels or any(int(c) < 1 for c in self.channels):
            raise ValueError(f"model.channels must be positive widths, got {self.channels}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"model.kernel_size must be odd and positive, not {self.kernel_size}")
        if self.latent_dim < 1 or self.n_mlp < 1:
            raise ValueError("model.latent_dim and model.n_mlp must be positive")
        if self.neighbors not in ("siblings", "tree"):
            raise ValueError(f"model.neighbors must be 'siblings' or 'tree', not {self.neighbors!r}")
        if self.pooling not in ("merge", "released"):
            raise ValueError(f"model.pooling must be 'merge' or 'released', not {self.pooling!r}")
        if self.demodulation not in ("weight", "activations"):
            raise ValueError(f"model.demodulation must be 'weight' or 'activations', not {self.demodulation!r}")
        if self.time_padding not in ("adjoint", "stylegan2"):
            raise ValueError(f"model.time_padding must be 'adjoint' or 'stylegan2', not {self.time_padding!r}")


@dataclass
class DataConfig:
    """How BVH clips become training windows (the representation switches are ablations)."""

    n_frames: int = 64
    fps: float = 30.0
    stride: int = 8
    rotation: str = "quaternion"  # "quaternion" (MoDi) | "positions" (ablation: joint positions instead of rotations)
    root: str = "velocity"  # "velocity" (CVPR MoDi) | "position" (ablation, paper Table 6)
    feet: list[str] | None = None  # foot joint names; None = detect by name
    drop_patterns: list[str] | None = None  # joint-name regexes to drop; None = fingers/face (modi.data.dataset default)
    keep_joints: list[str] | None = None  # joints never dropped
    # True / "drop" = the released preprocessing: no root anchor that only repeats its child (Bandai's joint_Root), no
    # rotation for joints without children (they move nothing). Not the default: its one equal-budget run was the
    # worst arm (FID 40.6), though within the run-to-run spread measured so far (docs/results.md, "Equal-budget
    # arms"); needs more seeds
    drop_root_anchor: bool = False
    leaf_rotations: str = "keep"

    def validate(self) -> None:
        if self.rotation not in ("quaternion", "positions"):
            raise ValueError(f"data.rotation must be 'quaternion' or 'positions', not {self.rotation!r}")
        if self.root not in ("velocity", "position"):
            raise ValueError(f"data.root must be 'velocity' or 'position', not {self.root!r}")
        if self.leaf_rotations not in LEAF_ROTATIONS:
            raise ValueError(f"data.leaf_rotations must be one of {LEAF_ROTATIONS}, not {self.leaf_rotations!r}")
        if self.n_frames < 2:
            raise ValueError(f"data.n_frames must be >= 2, not {self.n_frames}")
        if self.stride < 1:
            raise ValueError(f"data.stride must be >= 1, not {self.stride}")


@dataclass
class TrainConfig:
    """Optimisation and bookkeeping. Defaults are the paper's (Appendix D.2) and StyleGAN2's lazy regularisation."""

    batch: int = 16
    iters: int = 80_000
    lr: float = 0.002
    beta1: float = 0.0
    beta2: float = 0.99
    r1_gamma: float = 10.0
    d_reg_every: int = 16
    path_weight: float = 2.0
    g_reg_every: int = 4
    path_batch_shrink: int = 2
    path_decay: float = 0.01
    mixing: float = 0.9
    touch_weight: float = 0.01
    contact_weight: float = 1.0
    # contact consistency: "released" = mean of s(c) * ||ankle displacement per frame|| in the data's units (the
    # authors' train.py / utils/foot.py); "squared" = s(c) * speed^2 in body heights per second on the contact
    # (toe) joints (the paper's eq. 3; this package's form before the released one became the default)
    contact_loss: str = "released"
    ema_kimg: float = 10.0  # EMA half-life in thousands of samples (StyleGAN2: 10)
    w_avg_beta: float = 0.995
    seed: int = 0
    log_every: int = 10
    sample_every: int = 1000
    ckpt_every: int = 500
    snapshot_every: int = 10_000  # also keep step_XXXXXX.pt every this many steps (0 = never)
    n_samples: int = 8

    def validate(self) -> None:
        if self.batch < 1 or self.iters < 0:
            raise ValueError("train.batch must be >= 1 and train.iters >= 0")
        for name in ("d_reg_every", "g_reg_every", "path_batch_shrink"):
            if getattr(self, name) < 1:
                raise ValueError(f"train.{name} must be >= 1")
        if not 0.0 <= self.mixing <= 1.0:
            raise ValueError(f"train.mixing must be in [0, 1], not {self.mixing}")
        if self.contact_loss not in CONTACT_LOSSES:
            raise ValueError(f"train.contact_loss must be one of {', '.join(CONTACT_LOSSES)}, not {self.contact_loss!r}")


@dataclass
class MoDiConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    preset: str = "paper"

    def validate(self) -> "MoDiConfig":
        self.model.validate()
        self.data.validate()
        self.train.validate()
        return self

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["model"]["channels"] = list(self.model.channels)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "MoDiConfig":
        """Rebuild from ``to_dict`` output; unknown keys are rejected so stale checkpoints fail loudly."""

        def build(sub_cls, values):
            names = {f.name for f in fields(sub_cls)}
            unknown = set(values) - names
            if unknown:
                raise ValueError(f"unknown {sub_cls.__name__} fields: {sorted(unknown)}")
            return sub_cls(**values)

        model = {**LEGACY_DEFAULTS["model"], **dict(d.get("model", {}))}
        data = {**LEGACY_DEFAULTS["data"], **dict(d.get("data", {}))}
        if "joints" in data:  # early drafts called keep_joints "joints"
            data.setdefault("keep_joints", data.pop("joints"))
        if "channels" in model:
            model["channels"] = tuple(int(c) for c in model["channels"])
        return cls(
            model=build(ModelConfig, model),
            data=build(DataConfig, data),
            train=build(TrainConfig, {**LEGACY_DEFAULTS["train"], **dict(d.get("train", {}))}),
            preset=str(d.get("preset", "custom")),
        ).validate()


def paper_preset() -> MoDiConfig:
    """The paper's model: channels 256,128,64,64,32, batch 16, 80k iterations, lr 0.002, mixing 0.9."""
    return MoDiConfig(preset="paper").validate()


def small_preset() -> MoDiConfig:
    """A CPU-sized model with the same structure: narrower channels, shorter mapping MLP, smaller batch."""
    return MoDiConfig(
        model=ModelConfig(latent_dim=128, n_mlp=4, channels=(96, 64, 32, 32, 16)),
        train=TrainConfig(batch=8, iters=5_000, sample_every=500, ckpt_every=250, snapshot_every=0, n_samples=6),
        preset="small",
    ).validate()


PRESETS = {"paper": paper_preset, "small": small_preset}

ABLATIONS = {
    "pool": {"model.scaler": "pool"},
    "one-conv": {"model.n_inplace_convs": 1},
    "pseudo-image": {"model.skeleton_aware": False},
    "positions": {"data.rotation": "positions"},
    "root-position": {"data.root": "position"},
    # this package's own choices, kept as ablations beside the released code's (the defaults), one at a time or
    # together
    "noise": {"model.noise_injection": True},
    "squared-contact": {"train.contact_loss": "squared"},
    "pre-release": {"model.noise_injection": True, "train.contact_loss": "squared"},
    # the released code's skeleton topology and representation (not the defaults: docs/results.md, "Equal-budget
    # arms")
    "tree-neighbors": {"model.neighbors": "tree"},
    "released-representation": {"data.drop_root_anchor": True, "data.leaf_rotations": "drop"},
    "released-pooling": {"model.pooling": "released"},
}


def make_config(preset: str = "small", ablations: list[str] | tuple[str, ...] = (), **overrides: Any) -> MoDiConfig:
    """A preset plus named ablations (see ``ABLATIONS``) plus dotted overrides like ``{"train.iters": 100}``."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    cfg = PRESETS[preset]()
    changes: dict[str, Any] = {}
    for name in ablations:
        if name not in ABLATIONS:
            raise ValueError(f"unknown ablation {name!r}; choose from {', '.join(ABLATIONS)}")
        changes.update(ABLATIONS[name])
    changes.update(overrides)
    for key, value in changes.items():
        section, _, attr = key.partition(".")
        target = getattr(cfg, section, None)
        if target is None or not attr or not hasattr(target, attr):
            raise ValueError(f"unknown config key {key!r}")
        if attr == "channels":
            value = tuple(int(c) for c in value)
        setattr(target, attr, value)
    return cfg.validate()
