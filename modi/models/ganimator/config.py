"""GANimator hyper-parameters as one dataclass, saved inside every checkpoint.

Defaults are the published ones (Li et al. 2022 and the authors' public code): skeleton-aware convolutions with
neighbour distance 2, kernel 5 and reflect padding; a pyramid whose coarsest level is 1/5 of the sequence and whose
levels grow by 1/0.75; WGAN-GP (lambda 1), L1 reconstruction (lambda 50), contact consistency (lambda 5);
Adam 1e-4; 5 discriminator steps per generator step; 15,000 iterations per level, two consecutive levels trained
together as a block. Every preset keeps the 5:1 ratio; the ``fast`` preset keeps the architecture and cuts the
iterations so a CPU run finishes in minutes per level, spending 3x more of them on the coarsest block (only level 0
receives noise when sampling, so the content of random samples is decided there).

Loss-level details follow the authors' released code by default, each with our earlier form as a named option:
contact consistency measured per level frame (``contact_rescale=False``; ``True`` rescales it to per-source-frame
velocities, which makes it ~rate times weaker at coarse levels), the first frame's contact label 0
(``contact_first_frame="zero"``; ``"copy"`` copies the second frame's), biases uniform in +-1/sqrt(fan-in)
(``bias_init="uniform"``; ``"zeros"``), and 6D rotations from the first two *rows* of the matrix
(``sixd="rows"``; ``"columns"``). Checkpoints written before these options existed load with the forms they were
trained with (:data:`LEGACY`).
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
    contact_first_frame: str = "zero" # first frame's label: "zero" (released code) or "copy" (the second frame's)
    sixd: str = "rows"                # 6D rotation = first two "rows" (released code) or "columns" of the matrix
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
    bias_init: str = "uniform"        # "uniform" +-1/sqrt(fan-in) per entity (released code, nn.Conv1d) or "zeros"
    # --- losses -----------------------------------------------------------------------------------
    lambda_gp: float = 1.0
    lambda_rec: float = 50.0
    lambda_contact: float = 5.0
    contact_rescale: bool = False     # True: consistency on per-source-frame velocities (ours before; ~rate x weaker)
    # --- optimisation -----------------------------------------------------------------------------
    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    iterations: int = 15000           # per block of levels
    block_iterations: list[int] | None = None  # per-block budgets (block b: [min(b, len-1)]); overrides the next two
    coarse_multiplier: float = 1.0    # the coarsest block trains round(iterations * this) iterations
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
        if self.block_iterations is not None:
            self.block_iterations = [int(n) for n in self.block_iterations]
            if not self.block_iterations or any(n < 0 for n in self.block_iterations):
                raise UserError("block_iterations must be a non-empty list of counts >= 0, "
                                f"got {self.block_iterations}")
        if not self.coarse_multiplier > 0:
            raise UserError(f"coarse_multiplier must be > 0, got {self.coarse_multiplier}")
        if self.contact_first_frame not in ("zero", "copy"):
            raise UserError(f"contact_first_frame must be zero or copy, got {self.contact_first_frame!r}")
        if self.sixd not in ("rows", "columns"):
            raise UserError(f"sixd must be rows or columns, got {self.sixd!r}")
        if self.bias_init not in ("uniform", "zeros"):
            raise UserError(f"bias_init must be uniform or zeros, got {self.bias_init!r}")

    def block_budget(self, block: int) -> int:
        """Iterations of block ``block`` (0 = the coarsest levels)."""
        if self.block_iterations is not None:
            return self.block_iterations[min(block, len(self.block_iterations) - 1)]
        if block == 0:
            return max(0, int(round(self.iterations * self.coarse_multiplier)))
        return self.iterations

    def block_budgets(self, n_blocks: int) -> list[int]:
        return [self.block_budget(b) for b in range(n_blocks)]

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "GanimatorConfig":
        """A saved config; options it predates take the form that checkpoint was trained with (:data:`LEGACY`)."""
        known = {f.name for f in fields(cls)}
        kw = {k: v for k, v in LEGACY.items() if k not in d}
        kw.update({k: v for k, v in d.items() if k in known})
        return cls(**kw)

    def replace(self, **kw: Any) -> "GanimatorConfig":
        return replace(self, **kw)


# The forms of the loss-level options in checkpoints written before the options existed (the released code's forms
# are the defaults of new runs).
LEGACY: dict[str, Any] = {"contact_rescale": True, "contact_first_frame": "copy", "bias_init": "zeros",
                          "sixd": "columns"}


def preset(name: str, **overrides: Any) -> GanimatorConfig:
    """``paper``: the published schedule (15,000 iterations per block). ``fast``: same networks and the same 5:1
    discriminator ratio, 300 iterations per block and 900 on the coarsest (a CPU run). ``tiny``: a smoke-test
    schedule for tests and demos (20 iterations per block, narrow networks). ``None`` overrides are ignored."""
    if name == "paper":
        cfg = GanimatorConfig(preset="paper")
    elif name == "fast":
        cfg = GanimatorConfig(preset="fast", iterations=300, coarse_multiplier=3.0)
    elif name == "tiny":
        cfg = GanimatorConfig(preset="tiny", iterations=20, base_channels=32, fake_pool=0)
    else:
        raise UserError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return replace(cfg, **overrides) if overrides else cfg


__all__ = ["GanimatorConfig", "preset", "PRESETS", "LEGACY"]
