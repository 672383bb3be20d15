"""ONNX export of a GANimator run and of a MoDi generator, with a JSON sidecar that states the model's contract.

The graph runs the sampler and the decoding, so what comes out is a motion, not features: per-frame local joint
rotations in the rig's joint order, the root position and the foot contacts.  The sidecar (``model.json`` beside
``model.onnx``) holds what a program needs to use them and to call the graph correctly: joint names, parents,
offsets, end sites, Euler orders, fps and unit of the rig; every input's shape, dtype and value range; which
lengths are free and which are fixed; what each output means.  ``modi.export.onnx_runner`` checks inputs against it
(NumPy only) before running the graph.

**Exporter.** ``torch.onnx.export(..., dynamo=True)``: the exporter torch 2.13 recommends (and its default).  It
captures the model with ``torch.export`` and translates the ATen graph with onnxscript's function library; the
TorchScript exporter (``dynamo=False``) is deprecated and cannot express lengths computed from an input's value
(GANimator's level lengths follow the requested number of frames).  Two adjustments: onnxscript's translation of
``repeat_interleave`` does not take the ``output_size`` argument torch passes (our own one-line translation does),
and after export every weight-only subgraph (the skeletal layers' compact -> masked dense weight) is folded into a
constant, so the file holds plain dense weights and the graph only the per-sample work.

**Skeletal ops.** The export runs with ``MODI_EXT_IMPL=dense``: ``modi_ext``'s pure-torch form (one shared
convolution with the masked dense weight, style and demodulation as scales), which standard ONNX operators express.
The C++/CUDA kernels are custom operators no ONNX runtime has; ``ref`` is also plain torch but convolves each
sample with its own modulated weight (a grouped convolution whose group count is the batch), which would fix the
batch size.

**What is dynamic.**
GANimator: the batch and the number of frames (one graph, any length from the sidecar's ``dims.frames.min``): the
unconditional graph takes ``frames`` as an int64 input, a conditional one reads it from the trajectory's length;
``--frames N`` fixes it instead (static shapes, for runtimes that want them).
MoDi: the batch; the motion length is the model's (its coarsest level is a learned constant of fixed length).
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
from torch import Tensor, nn

from modi._version import __version__ as modi_version
from modi.core.body import guess_unit
from modi.errors import CheckpointError, OnnxExportError, UserError
from modi.export import onnx_runner
from modi.io.safe_load import earlier_modi_globals, load_data
from modi.models.ganimator.data import K, features_to_motion, resample
from modi.models.ganimator.networks import GanimatorModel, synthesize
from modi.models.ganimator.training import FORMAT as GANIMATOR_FORMAT
from modi.models.ganimator.training import checkpoint_path, load_model
from modi.models.modi.checkpoint import CHECKPOINT_FORMAT as MODI_FORMAT
from modi.models.modi.sampling import load_generator

OPSET = 18  # the opset onnxscript's torch library is written in: no version conversion after export
SIDECAR_FORMAT = onnx_runner.SIDECAR_FORMAT
PSI_RANGE = (-2.0, 2.0)  # what 'modi generate --psi' accepts
_EXAMPLE_BATCH = 2  # a batch of 1 would be specialised (torch.export treats sizes 0 and 1 as constants)


# ------------------------------------------------------------------------------------------- graphs


class GanimatorGraph(nn.Module):
    """A GANimator run as one function: level-0 noise (and a trajectory) -> rotations, root position, contacts.

    The sampler is ``modi.models.ganimator.networks.synthesize`` with the run's generators; decoding is
    ``features_to_motion`` as ``modi ganimator generate`` does it (first training clip's 6D layout and start
    position, contacts clamped to [0, 1]); lengths come out in the source file's units.  Noise enters at the
    coarsest level only (``fine_noise=False``, the default of ``generate`` and of the authors' demo).
    """

    def __init__(self, model: GanimatorModel, frames: int | None = None) -> None:
        super().__init__()
        seq = model.seqs[0]
        self.gens = model.gens
        self.rates = list(model.rates[0])
        self.train_lengths = list(model.lengths[0])
        self.amp = float(model.amps[0][0])
        self.n_entities = int(model.n_entities)
        self.n_joints = int(model.n_joints)
        self.sixd = seq.sixd
        self.cond = list(model.cond_entities)
        self.fixed = frames
        self.inv_scale = 1.0 / float(seq.scale)
        self.min_frames = ganimator_min_frames(model)
        self.register_buffer("root_start", seq.root_start.detach().to(torch.float32).clone(), persistent=False)
        # trajectory input in file units: the root-motion entity's dx, y, dz times the run's scale
        ts = torch.ones(1, K, max(len(self.cond), 1), 1)
        if self.cond:
            ts[0, :3, 0] = float(seq.scale)
        self.register_buffer("traj_scale", ts, persistent=False)

    def level_lengths(self, n):
        """``ceil(n * L_l / L_last)``: ``GanimatorModel.level_lengths`` in integers (exact for ints and SymInts)."""
        b = self.train_lengths[-1]
        return [(n * a + b - 1) // b for a in self.train_lengths]

    def forward(self, noise: Tensor, frames_or_trajectory: Tensor | None = None):
        traj = None
        if self.cond:
            traj = frames_or_trajectory * self.traj_scale
            n = traj.shape[-1]
        elif self.fixed is not None:
            n = self.fixed
        else:
            n = frames_or_trajectory.reshape(-1)[0].item()
            torch._check(n >= self.min_frames)
        lengths = self.level_lengths(n)
        # level 0 takes the noise's own length: the contract (onnx_runner.check_inputs) makes it equal lengths[0],
        # and no relation between two input sizes has to be traced
        lengths[0] = noise.shape[1]
        B = noise.shape[0]
        noises = [noise.reshape(B, 1, 1, lengths[0]) * self.amp] + [None] * (len(lengths) - 1)
        conds = None
        if traj is not None:  # modi.models.ganimator.generate.trajectory_conditions (the last level: the input)
            conds = [resample(traj, L, 1.0 / r) for L, r in zip(lengths[:-1], self.rates[:-1])] + [traj]
        feats = synthesize(self.gens, self.rates, lengths, noises, self.n_entities, conds=conds, batch=B)[-1]
        quats, root, contacts = features_to_motion(feats, self.n_joints, self.root_start, sixd=self.sixd)
        return quats, root * self.inv_scale, contacts.clamp(0.0, 1.0)


def ganimator_min_frames(model: GanimatorModel) -> int:
    """The fewest output frames the graph takes: every level long enough for its reflect padding, and (for a
    conditional run) every coarser level shorter than the output, as ``trajectory_conditions`` assumes."""
    h = model.cfg.kernel_size // 2 if model.cfg.padding_mode == "reflect" else 0
    lengths = model.lengths[0]
    b = lengths[-1]
    n = 1
    while True:
        ls = [-(-n * a // b) for a in lengths]
        if min(ls) > h and (not model.cond_entities or all(L < n for L in ls[:-1])):
            return n
        n += 1


class ModiGraph(nn.Module):
    """A MoDi generator as one function: z or w (truncation ``psi``, the noise maps) -> rotations, root, contacts.

    ``Generator.forward`` then the codec's decoding, as ``modi generate`` does it (contacts on the label scale: on
    when > 0.5).  Truncation is always applied (``w_avg + psi (w - w_avg)``; modi skips it at ``psi = 1``, where
    it is the identity up to rounding)."""

    def __init__(self, g: nn.Module, codec: Any, input_kind: str = "z") -> None:
        super().__init__()
        if input_kind not in ("z", "w"):
            raise ValueError(f"input must be 'z' or 'w', got {input_kind!r}")
        if codec.positions_mode:
            raise OnnxExportError("this MoDi model generates joint positions (the 'positions' ablation), not "
                                  "rotations: it has no rotations to export")
        self.g = g
        self.input_kind = input_kind
        self.rep = codec.rep
        self.register_buffer("mean", codec.normalizer.mean.detach().to(torch.float32)[..., None], persistent=False)
        self.register_buffer("std", codec.normalizer.std.detach().to(torch.float32)[..., None], persistent=False)
        self.noise_shapes = list(g.noise_shapes())

    def forward(self, latent: Tensor, psi: Tensor, noise: Tensor | None = None):
        g = self.g
        w = g.mapping(latent) if self.input_kind == "z" else latent
        w = g.w_avg + psi * (w - g.w_avg)
        maps = None
        if self.noise_shapes:
            maps, pos = [], 0
            for e, t in self.noise_shapes:
                maps.append(noise[:, pos:pos + e * t].reshape(-1, 1, e, t))
                pos += e * t
        x = g.synthesis(g.make_wplus(w), noise=maps)
        quats, root, contacts = self.rep.decode_parts(x * self.std + self.mean)
        return quats, root, contacts


# ------------------------------------------------------------------------------------------- export


@contextlib.contextmanager
def plain_torch_ops() -> Iterator[None]:
    """``MODI_EXT_IMPL=dense`` for the duration (read by ``modi_ext`` on every call): the skeletal layers run as
    plain torch ops, which the exporter can translate."""
    before = os.environ.get("MODI_EXT_IMPL")
    os.environ["MODI_EXT_IMPL"] = "dense"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("MODI_EXT_IMPL", None)
        else:
            os.environ["MODI_EXT_IMPL"] = before


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence what the exporter says that is not about the model: its optional torchvision operators, torch's own
    deprecation notices, and its note that two inputs share the batch dimension (they do, on purpose)."""
    log = logging.getLogger("torch.onnx")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*LeafSpec.*", category=FutureWarning)
            warnings.filterwarnings("ignore", message=".*shares the same shape constraints.*", category=UserWarning)
            yield
    finally:
        log.setLevel(level)


def _need_onnx() -> None:
    missing = []
    for name in ("onnx", "onnxscript"):
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise OnnxExportError(f"ONNX export needs {' and '.join(missing)}: pip install 'modi[onnx]' "
                              "(onnx, onnxscript, onnxruntime)")


def _translations() -> dict:
    """Our translation of ``aten.repeat_interleave.Tensor`` (onnxscript's does not take ``output_size``)."""
    from onnxscript import opset18 as op  # optional dependency (the 'onnx' extra): only an export needs it

    def repeat_interleave(repeats, output_size=None):
        # index j repeated repeats[j] times: out[p] = #{j : cumsum(repeats)[j] <= p}, p < output_size
        ends = op.CumSum(repeats, op.Constant(value_int=0))
        if output_size is None:
            total = op.ReduceSum(repeats, keepdims=1)
        else:
            total = op.Constant(value_ints=[int(output_size)])
        pos = op.Range(op.Constant(value_int=0), op.Squeeze(total), op.Constant(value_int=1))
        hit = op.LessOrEqual(op.Unsqueeze(ends, op.Constant(value_ints=[0])),
                             op.Unsqueeze(pos, op.Constant(value_ints=[1])))
        return op.ReduceSum(op.Cast(hit, to=7), op.Constant(value_ints=[1]), keepdims=0)

    return {torch.ops.aten.repeat_interleave.Tensor: repeat_interleave}


def _fold_weights(model_proto):
    """Fold every subgraph that depends on constants only (onnxscript's default keeps ``ConstantOfShape`` and
    large tensors unfolded; the skeletal layers' dense weights are such a subgraph), then tidy up."""
    import onnxscript.optimizer as oo  # optional dependency (the 'onnx' extra)

    oo.fold_constants(model_proto, should_fold=lambda node: True)
    return oo.optimize(model_proto)


def _export(module: nn.Module, args: tuple, out: Path, input_names: list[str], dynamic: dict | None,
            opset: int) -> None:
    import onnx  # optional dependency (the 'onnx' extra)

    module.eval()
    with plain_torch_ops(), torch.no_grad(), _quiet_exporter():
        prog = torch.onnx.export(module, args, dynamo=True, input_names=input_names,
                                 output_names=["rotations", "root_position", "contacts"], opset_version=opset,
                                 dynamic_shapes=dynamic, custom_translation_table=_translations(),
                                 external_data=False, verbose=False)
    proto = _fold_weights(prog.model_proto)
    for o in proto.graph.output:  # name the traced length symbol of the outputs (u0, s1, ...) as the sidecar does
        dim = o.type.tensor_type.shape.dim
        if len(dim) > 1 and dim[1].dim_param:
            dim[1].dim_param = "frames"
    onnx.checker.check_model(proto)
    tmp = out.with_name(out.name + ".tmp")
    onnx.save(proto, str(tmp))
    os.replace(tmp, out)


def _write_sidecar(side: dict, out: Path) -> Path:
    path = onnx_runner.sidecar_path(out)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(side, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path


def _skeleton_json(names, parents, offsets, end_sites: dict, orders, height: float) -> dict:
    unit = guess_unit(height)
    return {"names": list(names), "parents": [int(p) for p in parents],
            "offsets": np.asarray(offsets, dtype=np.float64).round(9).tolist(),
            "end_sites": {names[int(j)]: np.asarray(v, dtype=np.float64).round(9).tolist()
                          for j, v in end_sites.items()},
            "rotation_orders": list(orders or ["ZYX"] * len(names)),
            "unit": unit.unit, "metres_per_unit": unit.scale}


def _outputs_json(J: int, feet: list[str], contact_rule: str) -> list[dict]:
    return [
        {"name": "rotations", "dtype": "float32", "shape": ["batch", "frames", J, 4],
         "meaning": "local rotation of every joint relative to its parent, unit quaternion (w, x, y, z) with w >= 0, "
                    "joints in skeleton.names order; BVH-style: child world rotation = parent world rotation x "
                    "local rotation, joint position = parent position + parent world rotation x offset"},
        {"name": "root_position", "dtype": "float32", "shape": ["batch", "frames", 3],
         "meaning": "position of the root joint (skeleton.names[0]) per frame, in skeleton.unit (as the BVH root's "
                    "position channels), Y up"},
        {"name": "contacts", "dtype": "float32", "shape": ["batch", "frames", len(feet)],
         "meaning": f"foot contact label per frame for each joint of 'feet' (in that order): {contact_rule}"},
    ]


def _provenance(source: Path, kind: str, opset: int) -> dict:
    return {"format": SIDECAR_FORMAT, "kind": kind, "source": str(source), "modi_version": modi_version,
            "torch_version": str(torch.__version__), "opset": opset,
            "exporter": "torch.onnx.export(dynamo=True), skeletal ops on modi_ext's dense pure-torch path"}


def export_ganimator(run: str | Path, out: str | Path, *, frames: int | None = None, opset: int = OPSET) -> dict:
    """Write ``out`` (``.onnx``) and its sidecar for the GANimator run ``run`` (a folder or ``.ckpt``)."""
    _need_onnx()
    out = Path(out)
    model = load_model(run)
    seq = model.seqs[0]
    graph = GanimatorGraph(model, frames)
    n_min = graph.min_frames
    if frames is not None and frames < n_min:
        raise OnnxExportError(f"--frames {frames}: this run needs at least {n_min} frames")
    N = frames or graph.train_lengths[-1]  # the run's own length (the training clip's)
    L0 = graph.level_lengths(N)[0]
    noise = torch.randn(_EXAMPLE_BATCH, L0)
    batch = torch.export.Dim("batch", min=1)
    dims: dict[str, dict] = {"batch": {"min": 1}}
    coarse = {"numerator": int(graph.train_lengths[0]), "denominator": int(graph.train_lengths[-1]),
              "rule": "ceil(frames * numerator / denominator): the coarsest level's length"}
    inputs = [{"name": "noise", "dtype": "float32", "shape": ["batch", "coarse_frames"], "finite": True,
               "draw": "normal",
               "values": f"standard normal N(0, 1), one value per coarse frame (the graph multiplies it by the "
                         f"level-0 amplitude {graph.amp:.6g}); what modi draws with torch.randn"}]
    noise_dims = {0: batch} if frames is not None else \
        {0: batch, 1: torch.export.Dim("coarse_frames", min=graph.level_lengths(n_min)[0])}
    dims["coarse_frames"] = coarse
    if model.cond_entities:
        traj = torch.zeros(_EXAMPLE_BATCH, K, 2, N)
        traj[:, 0, 1] = 1.0  # a valid 6D rotation for the root entity
        traj[:, 4, 1] = 1.0
        args = (noise, traj)
        names = ["noise", "trajectory"]
        dynamic = {"noise": noise_dims, "frames_or_trajectory": {0: batch} if frames is not None else
                   {0: batch, 3: torch.export.Dim("frames", min=n_min)}}
        inputs.append({"name": "trajectory", "dtype": "float32", "shape": ["batch", K, 2, "frames" if frames is None
                                                                            else N], "finite": True,
                       "values": f"the root trajectory the motion follows, as the run's features: [:, :, 0, t] = "
                                 f"[dx, y, dz, 0, 0, 0] (root displacement from frame t-1 to t in x and z, frame 0: "
                                 f"the displacement to frame 1; root height y; skeleton.unit), [:, :, 1, t] = the "
                                 f"root joint's rotation as 6D ({seq.sixd} of its rotation matrix: the first two)"})
        dims["frames"] = {"min": n_min, "default": N, "from": "trajectory"} if frames is None else {"fixed": N}
    elif frames is None:
        args = (noise, torch.tensor([N], dtype=torch.int64))
        names = ["noise", "frames"]
        dynamic = {"noise": noise_dims, "frames_or_trajectory": None}
        inputs.append({"name": "frames", "dtype": "int64", "shape": [1], "min": n_min, "draw": "frames",
                       "values": f"number of output frames, >= {n_min}"})
        dims["frames"] = {"min": n_min, "default": N, "input": "frames",
                          "why": "every level of the pyramid must be longer than its convolutions' padding"}
    else:
        args = (noise,)
        names = ["noise"]
        dynamic = {"noise": noise_dims}
        dims["frames"] = {"fixed": N}
    _export(graph, args, out, names, dynamic, opset)

    sk = seq.skeleton
    inv = 1.0 / seq.scale
    side = _provenance(Path(run), "ganimator", opset)
    side.update({
        "model": out.name,
        "fps": float(seq.fps),
        "skeleton": _skeleton_json(sk.names, sk.parents, sk.offsets * inv,
                                   {j: np.asarray(v) * inv for j, v in sk.end_sites.items()}, sk.rotation_orders,
                                   sk.height() * inv),
        "feet": [sk.names[f] for f in seq.feet],
        "inputs": inputs,
        "dims": dims,
        "outputs": _outputs_json(sk.n_joints, [sk.names[f] for f in seq.feet], "in [0, 1], on when > 0.5"),
        "fixed": ["the rig (joints, offsets)", "noise enters the coarsest level only (fine_noise off)",
                  "the root path starts at the first training clip's start (root_start, x and z)"]
                 + (["frames"] if frames is not None else []),
        "ganimator": {"train_lengths": [int(x) for x in graph.train_lengths], "noise_amplitude": graph.amp,
                      "root_start": (seq.root_start.double() * inv).tolist(), "conditional": bool(model.cond_entities),
                      "file_units_to_working": float(seq.scale), "training_clip": seq.name},
    })
    _write_sidecar(side, out)
    return side


def export_modi(ckpt: str | Path | dict, out: str | Path, *, input_kind: str = "z", ema: bool = True,
                opset: int = OPSET, source: str | Path | None = None) -> dict:
    """Write ``out`` (``.onnx``) and its sidecar for the MoDi checkpoint ``ckpt`` (EMA weights by default)."""
    _need_onnx()
    out = Path(out)
    g, codec, cfg = load_generator(ckpt, ema=ema)
    graph = ModiGraph(g, codec, input_kind)
    D = int(g.latent_dim)
    latent = torch.randn(_EXAMPLE_BATCH, D)
    psi = torch.ones(1)
    batch = torch.export.Dim("batch", min=1)
    args: tuple = (latent, psi)
    names = [input_kind, "psi"]
    dynamic: dict = {"latent": {0: batch}, "psi": None}
    S = sum(e * t for e, t in graph.noise_shapes)
    inputs = [
        {"name": input_kind, "dtype": "float32", "shape": ["batch", D], "finite": True,
         "draw": "normal" if input_kind == "z" else "none",
         "values": "latent z, standard normal N(0, 1) (the mapping network makes w of it)" if input_kind == "z"
         else "style w (the mapping network's output space; e.g. a projection of a motion into W)"},
        {"name": "psi", "dtype": "float32", "shape": [1], "min": PSI_RANGE[0], "max": PSI_RANGE[1], "draw": "psi",
         "values": "truncation: w_avg + psi (w - w_avg); 1 = none, 0 = the mean motion"},
    ]
    if S:
        args = args + (torch.randn(_EXAMPLE_BATCH, S),)
        names.append("noise")
        dynamic["noise"] = {0: batch}
        inputs.append({"name": "noise", "dtype": "float32", "shape": ["batch", S], "finite": True, "draw": "normal",
                       "values": "standard normal N(0, 1): the per-frame noise maps of the styled convolutions, "
                                 f"flattened and concatenated (entities x frames: {graph.noise_shapes})"})
    _export(graph, args, out, names, dynamic, opset)

    sk = codec.skeleton
    _, _, T = g.output_shape
    side = _provenance(Path(source) if source is not None else Path(str(ckpt)), "modi", opset)
    side.update({
        "model": out.name,
        "fps": float(codec.fps),
        "skeleton": _skeleton_json(sk.names, sk.parents, sk.offsets, sk.end_sites, sk.rotation_orders, codec.height),
        "feet": [sk.names[f] for f in codec.feet],
        "inputs": inputs,
        "dims": {"batch": {"min": 1}, "frames": {"fixed": int(T)}},
        "outputs": _outputs_json(sk.n_joints, [sk.names[f] for f in codec.feet],
                                 "the generated label (about 0 to 1), on when > 0.5"),
        "fixed": ["frames (the generator's coarsest level is a learned constant of fixed length)",
                  "the rig (joints, offsets)"],
        "modi": {"latent_dim": D, "input": input_kind, "weights": "G_ema" if ema else "G",
                 "noise_shapes": [list(s) for s in graph.noise_shapes]},
    })
    _write_sidecar(side, out)
    return side


def source_kind(source: str | Path) -> tuple[str, Any]:
    """``("ganimator", path)`` or ``("modi", checkpoint dict)`` for a run folder or checkpoint file."""
    p = Path(source)
    if p.is_dir():
        if checkpoint_path(p).is_file():
            return "ganimator", p
        if (p / "checkpoint.pt").is_file():
            p = p / "checkpoint.pt"
        else:
            raise UserError(f"{p}: no GANimator run ({checkpoint_path(p).name}) or MoDi checkpoint (checkpoint.pt) "
                            "in this folder")
    if not p.is_file():
        raise UserError(f"{p}: no such run folder or checkpoint file")
    st = load_data(p, "modi checkpoint", allowed=earlier_modi_globals())
    fmt = st.get("format") if isinstance(st, dict) else None
    if fmt == GANIMATOR_FORMAT:
        return "ganimator", p
    if fmt == MODI_FORMAT:
        return "modi", st
    raise CheckpointError(f"{p}: neither a GANimator run nor a MoDi checkpoint (format {fmt or '?'}); released "
                          "checkpoints convert first with 'modi import'")


def export_onnx(source: str | Path, out: str | Path, *, frames: int | None = None, input_kind: str = "z",
                ema: bool = True, opset: int = OPSET) -> dict:
    """Export a GANimator run or a MoDi checkpoint (told apart by the file's format tag); returns the sidecar."""
    if Path(out).suffix.lower() != ".onnx":
        raise UserError(f"{out}: the output name must end in .onnx")
    kind, what = source_kind(source)
    if kind == "ganimator":
        if input_kind != "z":
            raise UserError("--input applies to MoDi checkpoints; a GANimator run takes noise")
        return export_ganimator(what, out, frames=frames, opset=opset)
    if frames is not None:
        raise UserError("--frames applies to GANimator runs; a MoDi generator's length is fixed")
    return export_modi(what, out, input_kind=input_kind, ema=ema, opset=opset, source=source)


__all__ = ["export_onnx", "export_ganimator", "export_modi", "GanimatorGraph", "ModiGraph", "plain_torch_ops",
           "ganimator_min_frames", "source_kind", "OnnxExportError", "OPSET"]
