"""GANimator (Li et al., SIGGRAPH 2022): neural motion synthesis from a single sequence of any skeleton.

A coarse-to-fine pyramid of small skeleton-aware GANs (``modi_ext`` skeletal convolutions) is trained on one clip
(or a few clips of one character, "mixing"); sampling is fully convolutional, so motions of any length, crowds,
style transfer, key-frame editing and trajectory-conditioned / streaming generation all use the same generators.

Typical use::

    from modi.models.ganimator import load_sequences, preset, train, load_model
    clips = load_sequences(["Salsa-Dancing-6.bvh"], preset("fast"))
    model = train(clips, preset("fast"), "runs/salsa")
    motion = model.sample(900)          # (1, 6, E, 900) features; see modi.models.ganimator.generate to decode / write

or ``modi ganimator train`` / ``modi ganimator generate`` on the command line.
"""
from modi.models.ganimator.config import PRESETS, GanimatorConfig, preset
from modi.models.ganimator.data import Sequence, load_sequence, load_sequences, sequence_from_clip
from modi.models.ganimator.networks import GanimatorModel, LevelGenerator, PatchDiscriminator, ganimator_neighbors
from modi.models.ganimator.training import Trainer, load_model, run_summary, train

__all__ = ["GanimatorConfig", "preset", "PRESETS", "Sequence", "load_sequence", "load_sequences",
           "sequence_from_clip", "GanimatorModel", "LevelGenerator", "PatchDiscriminator", "ganimator_neighbors",
           "Trainer", "train", "load_model", "run_summary"]
