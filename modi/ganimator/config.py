"""GANimator hyper-parameters as one dataclass, saved inside every checkpoint.

Defaults are the published ones (Li et al. 2022 and the authors' public code): skeleton-aware convolutions with
neighbour distance 2, kernel 5 and reflect padding; a pyramid whose coarsest level is 1/5 of the sequence and whose
levels grow by 1/0.75; WGAN-GP (lambda 1), L1 reconstruction (lambda 50), contact consistency (lambda 5);
Adam 1e-4; 15,000 iterations per level, two consecutive levels trained together as a block.
The ``fast`` preset keeps the architecture and cuts the iterations so a CPU run finishes in minutes per level.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from modi.errors import UserError

PRESETS = ("paper", "fast", "tiny")


@dataclass
class GanimatorConfig:
    """Everything that defines a GANimator run (data, pyramid, networks, losses, optimisation)."""

    # --- data -------------------------------------------------------------------------------------
    fps: float | None = 30.0          # integer-stride downsampling towards this rate (None keeps the file rate)
    joint_reduction: bool = True      # drop finger / head-top detail joints automatically
    keep_joints: list[str] | None = None   # explicit joint names to keep (overrides joint_reduction)
    feet: list[str] | None = None     # explicit contact joints (default: detected from the motion)
    contacts: bool = True             # contact labels as virtual joints + consistency loss
    contact_velocity: float = 0.0125  # contact when foot speed < this * skeleton height per 1/30 s
    # --- pyramid ----------------------------------------------------------------------------------
    coarse_ratio: float = 0.2         # coarsest level length / sequence length
    scale_factor: float = 1.0 / 0.75  # length growth between consecutive levels
    max_levels: int | None = None     # keep only the first N levels (debugging)
    # --- networks ---------------------------------------------------------------------------------
    neighbor_distance: int = 2
    kernel_size: int = 5
    padding_mode: str = "reflect"
    base_channels: int = 128          # total channels of the first hidden layer (split over entities)
    n_layers: int = 4                 # convolutions per generator / discriminator
    # --- losses -----------------------------------------------------------------------------------
    lambda_gp: float = 1.0
    lambda_rec: float = 50.0
    lambda_contact: float = 5.0
    # --- optimisation -----------------------------------------------------------------------------
    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    iterations: int = 15000           # per block of levels
    group_size: int = 2               # consecutive levels trained together
    d_steps: int = 5                  # discriminator updates per iteration
    g_steps: int = 1                  # adversarial generator updates per iteration (+1 reconstruction update)
    fake_pool: int = 50               # history of fakes shown to D (0 disables)
    # --- conditional (trajectory) generation --------------------------------------------------------
    conditional: bool = False         # generator levels take root trajectory as a hard constraint
    # --- bookkeeping ------------------------------------------------------------------------------
    seed: int = 0
    device: str = "cpu"
    checkpoint_every: float = 120.0   # seconds between checkpoint writes inside a block
    preset: str = "paper"

    def __post_init__(self) -> None:
        self.betas = tuple(float(b) for b in self.betas)  # type: ignore[assignment]
        if self.kernel_size % 2 != 1 or self.kernel_size < 1:
            raise UserError(f"kernel_size must be a positive odd number, got {self.kernel_size}")
        if not 0.0 < self.coarse_ratio <= 1.0:
            raise UserError(f"coarse_ratio must be in (0, 1], got {self.coarse_ratio}")
        if self.scale_factor <= 1.0:
            raise UserError(f"scale_factor must be > 1, got {self.scale_factor}")
        if self.padding_mode not in ("reflect", "zeros", "replicate"):
            raise UserError(f"padding_mode must be reflect, zeros or replicate, got {self.padding_mode!r}")
        if self.group_size < 1 or self.iterations < 0 or self.n_layers < 2:
            raise UserError("group_size >= 1, iterations >= 0 and n_layers >= 2 are required")
        if self.d_steps < 0 or self.g_steps < 0:
            raise UserError("d_steps and g_steps must be >= 0")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "GanimatorConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def replace(self, **kw: Any) -> "GanimatorConfig":
        return replace(self, **kw)


def preset(name: str, **overrides: Any) -> GanimatorConfig:
    """``paper``: the published schedule. ``fast``: same networks, ~10x fewer iterations (a CPU run).
    ``tiny``: a smoke-test schedule for tests and demos."""
    if name == "paper":
        cfg = GanimatorConfig(preset="paper")
    elif name == "fast":
        cfg = GanimatorConfig(preset="fast", iterations=300, d_steps=2)
    elif name == "tiny":
        cfg = GanimatorConfig(preset="tiny", iterations=20, d_steps=1, base_channels=32, fake_pool=0)
    else:
        raise UserError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return replace(cfg, **overrides) if overrides else cfg


__all__ = ["GanimatorConfig", "preset", "PRESETS"]
