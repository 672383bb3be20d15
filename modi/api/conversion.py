"""Files in, files out: what ``modi export positions``, ``modi export gltf|onnx`` and ``modi import`` do, from
Python. Each call checks its paths (one-line ``UserError``: missing input, missing output folder, an output that
is one of the inputs) before any work."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from modi.core.contacts import feet_of, preview_contacts
from modi.core.kinematics import bvh_positions
from modi.errors import UserError
from modi.export.onnx import export_onnx as _export_onnx
from modi.export.onnx_runner import sidecar_path
from modi.faults import atomic_save_npy, atomic_write, existing_file, refuse_overwrite
from modi.interop import encoder_released, ganimator_released, modi_released
from modi.io import bvh as bvh_io
from modi.io import gltf
from modi.io.bvh import Bvh
from modi.io.formats import check_motion


def _output_folder(output: str | os.PathLike) -> Path:
    out = Path(output)
    if not out.absolute().parent.is_dir():
        raise UserError(f"{output}: folder {out.absolute().parent} does not exist")
    return out


def export_positions(bvh: str | os.PathLike, output: str | os.PathLike, *,
                     names: str | os.PathLike | None = None) -> tuple[np.ndarray, Bvh]:
    """``modi export positions``: forward kinematics of a BVH as the file means it, saved as a float32 ``.npy``
    ``(T, J, 3)`` in the file's units and joint order (and the joint names, one a line, to ``names``). Returns the
    array and the BVH read. Cost: one pass of FK (milliseconds)."""
    if os.path.isdir(bvh):
        raise UserError(f"{bvh}: is a folder, expected a .bvh file")
    if not os.path.exists(bvh):
        raise UserError(f"{bvh}: no such file")
    out_dir = os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(out_dir):
        raise UserError(f"{output}: folder {out_dir} does not exist")
    refuse_overwrite(output, [bvh])
    if names:
        refuse_overwrite(names, [bvh], "--names")
        if os.path.abspath(names) == os.path.abspath(output):
            raise UserError(f"--names {names} is the output array's file; choose another name")
    b = bvh_io.load(bvh)
    pos = bvh_positions(b).astype(np.float32)
    atomic_save_npy(output, pos)
    if names:
        atomic_write(names, "\n".join(b.names) + "\n")
    return pos, b


@dataclass
class GltfExport:
    """What :func:`export_gltf` wrote: the BVH it read and the unit it scaled by (``unit.describe()``)."""

    bvh: Bvh
    unit: Any


def export_gltf(bvh: str | os.PathLike, output: str | os.PathLike, *, scale: float | None = None, up: str = "y",
                mesh: bool = False, contacts: bool = True, side_buffer: bool = False) -> GltfExport:
    """``modi export gltf``: a BVH as glTF 2.0 (``.glb``, or ``.gltf`` with the buffer embedded or beside it as
    ``.bin`` with ``side_buffer``), Y-up in metres (``scale`` None: the unit guessed from the body size), with the
    preview's foot-contact labels as extras unless ``contacts=False``. Cost: milliseconds for a clip."""
    out = Path(output)
    if out.suffix.lower() not in gltf.SUFFIXES:
        raise UserError(f"{output}: the output name must end in .glb or .gltf")
    if side_buffer and out.suffix.lower() != ".gltf":
        raise UserError("--side-buffer needs an output ending in .gltf")
    existing_file(bvh)
    _output_folder(output)
    refuse_overwrite(output, [bvh])
    if side_buffer:
        refuse_overwrite(out.with_suffix(".bin"), [bvh], "buffer file")
    b = bvh_io.load(bvh)
    check_motion(b, bvh)
    labels = None
    if contacts:  # the same labels as the GIF and the viewer page (modi.core.contacts.preview_contacts)
        p = np.asarray(bvh_positions(b), dtype=np.float64)
        if up == "z":
            p = np.stack([p[..., 0], p[..., 2], -p[..., 1]], -1)
        feet = feet_of(b)
        lab = preview_contacts(p, feet, b.fps, b.parents, b.names)
        labels = {b.names[f]: lab[:, f] for f in feet}
    unit = gltf.save(b, out, scale=scale, side_buffer=side_buffer, contacts=labels, mesh=mesh, up=up)
    return GltfExport(b, unit)


def export_onnx(source: str | os.PathLike, output: str | os.PathLike, *, frames: int | None = None,
                input_kind: str = "z", ema: bool = True, opset: int = 18) -> dict[str, Any]:
    """``modi export onnx``: the generator of a GANimator run (folder or ``.ckpt``) or a MoDi checkpoint as an
    ONNX graph plus its JSON sidecar beside it (:func:`modi.export.onnx.export_onnx`); returns the sidecar. Cost:
    one ``torch.onnx.export`` (seconds to a minute); needs ``pip install 'modi[onnx]'``. The sidecar's path is
    :func:`sidecar_path` of ``output``."""
    src = Path(source)
    if not src.exists():
        raise UserError(f"{source}: no such run folder or checkpoint file")
    out = _output_folder(output)
    refuse_overwrite(out, [src])
    refuse_overwrite(sidecar_path(out), [src], "sidecar")
    return _export_onnx(src, out, frames=frames, input_kind=input_kind, ema=ema, opset=opset)


def _exists(path: str | os.PathLike, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise UserError(f"{path}: no such {what}")
    return p


def import_released(kind: str, ckpt: str | os.PathLike, out: str | os.PathLike, *,
                    data: str | os.PathLike | None = None, generator: str | os.PathLike | None = None,
                    fps: float = 30.0) -> Path:
    """``modi import KIND``: a checkpoint of the authors' released code as a modi run, read as data only.

    ``kind``: ``"modi-released"`` (``data``: their ``edge_rot_*.npy`` or its folder; returns RUN/checkpoint.pt),
    ``"encoder-released"`` (also ``generator``, the released MoDi checkpoint it inverts) or
    ``"ganimator-released"`` (``data``: the training BVH, None: the path in its ``args.txt``). Cost: reading and
    converting the weights (seconds)."""
    if kind == "modi-released":
        if data is None:
            raise UserError("modi-released needs the released training data (data=)")
        return modi_released.import_checkpoint(_exists(ckpt, "checkpoint file"), _exists(data, "data file or folder"),
                                               Path(out), fps=fps)
    if kind == "encoder-released":
        if data is None or generator is None:
            raise UserError("encoder-released needs the generator checkpoint (generator=) and the data (data=)")
        return encoder_released.import_checkpoint(_exists(ckpt, "checkpoint file"),
                                                  _exists(generator, "checkpoint file"),
                                                  _exists(data, "data file or folder"), Path(out), fps=fps)
    if kind == "ganimator-released":
        bvh = _exists(data, "BVH file") if data is not None else None
        return ganimator_released.import_checkpoint(_exists(ckpt, "checkpoint file"), bvh, Path(out))
    raise UserError(f"unknown kind {kind!r}; choose from modi-released, encoder-released, ganimator-released")


__all__ = ["export_positions", "export_gltf", "GltfExport", "export_onnx", "sidecar_path", "import_released"]
