"""Convert a checkpoint of the released MoDi encoder (``train_encoder.py``) into a modi encoder run.

The released encoder is their ``Discriminator`` class (built with one in-place conv per block) whose
``LatentPrediction`` head reads the features at ``latent_rec_idx`` 4 -- one level before the coarsest -- through
two linear layers of width n_latent x latent_dim and predicts W+ in the released row layout. modi's encoder with
the ``released`` head is that network; its last linear layer's output rows are reordered at import so it predicts
modi's W+ layout directly (``modi_released.released_style_index``). The layers the released head never reads
(the coarsest block, final conv and score head of the discriminator class) are dropped.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from modi.errors import CheckpointError
from modi.interop.modi_released import check_masks, convert_checkpoint, released_style_index, reverse_hierarchy_state
from modi.interop.provenance import file_record, record, released_iterations
from modi.interop.released_files import load_released_file
from modi.models.modi.checkpoint import atomic_torch_save
from modi.models.modi.encoder.model import EncoderConfig, MotionEncoder
from modi.models.modi.encoder.training import encoder_checkpoint_dict, generator_bundle
from modi.models.modi.latent.space import mean_w
from modi.models.modi.sampling import load_generator


def read_encoder_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The released encoder checkpoint's dict, checked for what conversion supports (as data)."""
    st = load_released_file(path, "released MoDi encoder checkpoint")
    if "e" not in st or "args" not in st:
        raise CheckpointError(f"{path}: not a released MoDi encoder checkpoint (no 'e' and 'args')")
    args = st["args"]
    if int(getattr(args, "encoder_latent_rec_idx", 4)) != 4:
        raise CheckpointError(f"{path}: encoder_latent_rec_idx {args.encoder_latent_rec_idx}: only the released "
                              "default (4, one level before the coarsest) imports")
    if int(getattr(args, "n_frames", 0)) < 0 or getattr(args, "keep_loc", 0) or getattr(args, "keep_rot", 0):
        raise CheckpointError(f"{path}: in-between or keep_loc/keep_rot masking has no modi encoder form")
    if "latent_predictor.linear2.weight" not in st["e"]:
        raise CheckpointError(f"{path}: the encoder has no two-layer latent head (extra_linear 1) to import")
    return st


def encoder_state(e_sd: dict[str, torch.Tensor], enc: Any, index: list[int], power: int = 1) -> dict[str, Tensor]:
    """The state dict of modi encoder ``enc`` for released encoder tensors ``e_sd`` (``power`` as in
    ``modi_released.generator_state``); the head's W+ rows gathered into modi's layout by ``index``."""
    sd = reverse_hierarchy_state(e_sd, enc.from_motion.net.conv, "from_motion.net", enc.blocks,
                                 int(enc.cfg.inplace_convs), power)
    sd["fc.weight"] = e_sd["latent_predictor.linear1.weight"].clone()
    sd["fc.bias"] = e_sd["latent_predictor.linear1.bias"].clone()
    n, dim = enc.cfg.n_latent, enc.cfg.latent_dim
    w = e_sd["latent_predictor.linear2.weight"].reshape(n, dim, -1)
    b = e_sd["latent_predictor.linear2.bias"].reshape(n, dim)
    sd["head.weight"] = w[index].reshape(n * dim, -1).clone()
    sd["head.bias"] = b[index].reshape(n * dim).clone()
    sd["w_avg"] = enc.w_avg.clone()
    return sd


def convert_encoder(st: dict[str, Any], g: Any) -> Any:
    """A modi ``MotionEncoder`` (released head) holding the released encoder's function, for modi generator ``g``."""
    args = st["args"]
    e_sd = st["e"]
    check_masks(e_sd, "e")
    k, _, _ = g.output_shape
    n_pred = int(e_sd["latent_predictor.linear2.bias"].numel()) // g.latent_dim
    if n_pred != g.n_latent:
        raise CheckpointError(f"the encoder predicts {n_pred} latent rows, its generator has {g.n_latent}: "
                              "W-space encoders (n_latent_predict 1) and other generators are not supported")
    n_frames = int(getattr(args, "n_frames", 0))
    cfg = EncoderConfig(in_channels=k, n_latent=g.n_latent, latent_dim=g.latent_dim, mask_channel=False,
                        prefix_frames=n_frames or None, head="released", inplace_convs=1)
    enc = MotionEncoder(g.cfg, g.levels, cfg, w_avg=mean_w(g).cpu())
    index = released_style_index(len(g.levels), g.cfg.n_inplace_convs)
    enc.load_state_dict(encoder_state(e_sd, enc, index))
    return enc


def import_checkpoint(ckpt: Path | str, generator: Path | str, data: Path | str, out: Path | str,
                      fps: float = 30.0) -> Path:
    """Write ``out/encoder.pt``, a modi encoder run (the released encoder with the released generator it
    inverts, converted as ``modi import modi-released`` does); returns its path."""
    st = read_encoder_checkpoint(ckpt)
    gen_state = convert_checkpoint(generator, data, fps)
    g, codec, gcfg = load_generator(gen_state)
    enc = convert_encoder(st, g)
    gen_prov = gen_state["imported_from"]
    iterations, known = released_iterations(ckpt, st.get("e_optim"))
    prov = record("encoder-released", file_record(ckpt), iterations=iterations, iterations_from=known,
                  args=st["args"], data=gen_prov["data"], seed=None, generator=gen_prov)
    bundle = {**generator_bundle(g, codec, gcfg, step=gen_state["step"]), "imported_from": gen_prov}
    state = encoder_checkpoint_dict(encoder=enc, generator=bundle, step=iterations or 0, imported_from=prov)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "encoder.pt"
    atomic_torch_save(state, path)
    return path


Tensor = torch.Tensor

__all__ = ["read_encoder_checkpoint", "encoder_state", "convert_encoder", "import_checkpoint"]
