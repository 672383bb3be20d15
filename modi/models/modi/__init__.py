"""MoDi (Raab et al., CVPR 2023): skeleton-aware StyleGAN2 for unconditional motion synthesis.

* ``config``   -- dataclass configs, the paper and small presets, ablation switches
* ``networks`` -- mapping network, synthesis network (conv scaler, skip outputs), discriminator
* ``losses``   -- non-saturating, R1, path length, foot touch and contact consistency
* ``training`` -- data preparation, ``Trainer`` (checkpoints, resume, DDP)
* ``codec``    -- the normalised-tensor <-> motion codec
* ``checkpoint`` -- checkpoint format, validated reading, atomic writing
* ``sampling`` -- checkpoints -> motions (truncation, deterministic seeds, IK cleanup, BVH/GIF output)

Submodules are imported lazily so ``import modi.models.modi`` stays cheap.
"""
from __future__ import annotations

from modi._lazy import lazy_exports

_EXPORTS = {
    "MoDiConfig": ".config", "ModelConfig": ".config", "DataConfig": ".config", "TrainConfig": ".config",
    "make_config": ".config", "paper_preset": ".config", "small_preset": ".config", "PRESETS": ".config",
    "ABLATIONS": ".config",
    "Generator": ".networks", "Discriminator": ".networks", "LevelSpec": ".networks", "build_levels": ".networks",
    "MappingNetwork": ".networks",
    "Trainer": ".training", "TrainingData": ".training", "MotionCodec": ".codec", "prepare_data": ".training",
    "NonFiniteLossError": ".training", "init_distributed_from_env": ".training",
    "load_checkpoint": ".checkpoint", "load_generator": ".sampling", "sample_motions": ".sampling",
    "sample_positions": ".sampling", "generate_tensors": ".sampling", "write_outputs": ".sampling",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
