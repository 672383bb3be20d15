"""One place that writes a motion in the formats a command was asked for (``--format bvh,glb``).

Every writer of motion in the package (``modi generate``, ``ganimator generate``, ``latent …``, ``apply …``,
``synth``) calls :func:`save_motion`, not ``bvh.save``, so each writes every format asked for. The formats and the glTF scale are set once
per command by the CLI (:func:`requested`, from ``--format`` / ``--gltf-scale``) rather than passed down through every
library function: the writers stay as they were, and code that calls the library directly gets BVH as before (or
passes ``formats=`` itself). The glTF unit guess is printed once per command, not once per file.
"""
from __future__ import annotations

import argparse
import contextvars
import math
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np
import torch

from modi.errors import UserError
from modi.faults import atomic_write
from modi.io import bvh as bvh_io
from modi.io import gltf

__all__ = ["FORMATS", "parse_formats", "add_format_options", "requested", "save_motion", "check_motion",
           "check_finite"]

FORMATS = {"bvh": ".bvh", "glb": ".glb", "gltf": ".gltf"}


@dataclass
class _Request:
    formats: tuple[str, ...] = ("bvh",)
    scale: float | None = None
    inputs: tuple[Path, ...] = ()
    announced: set = field(default_factory=set)


_CURRENT: contextvars.ContextVar[_Request] = contextvars.ContextVar("modi_output_formats", default=_Request())


def parse_formats(text: str) -> tuple[str, ...]:
    """``"bvh,glb"`` -> ``("bvh", "glb")``; an argparse type (unknown, empty or repeated names are refused)."""
    names = [t.strip().lower() for t in str(text).split(",")]
    if not names or any(not n for n in names):
        raise argparse.ArgumentTypeError(f"{text!r}: give a comma list of {', '.join(FORMATS)}")
    bad = [n for n in names if n not in FORMATS]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown format {bad[0]!r}; choose from {', '.join(FORMATS)}")
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"{text!r} names a format twice")
    return tuple(names)


parse_formats.__name__ = "format list"  # argparse names the type in its message


def _scale(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text} must be a positive number")
    return v


_scale.__name__ = "scale"


def add_format_options(parser: argparse.ArgumentParser) -> None:
    """``--format`` and ``--gltf-scale`` on a command that writes motion."""
    parser.add_argument("--format", type=parse_formats, default="bvh", metavar="LIST",
                        help="motion file formats, a comma list of bvh, glb (binary glTF 2.0), gltf (JSON glTF), "
                             "e.g. bvh,glb")
    parser.add_argument("--gltf-scale", type=_scale, default=None, metavar="S",
                        help="glTF: multiply lengths by S to get metres (default: guessed from the body height "
                             "and printed)")


def _input_files(values) -> tuple[Path, ...]:
    """The existing files among a command's argument values (strings, or lists of them)."""
    found = []
    for v in values:
        for item in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(item, (str, os.PathLike)) and str(item) and os.path.isfile(item):
                found.append(Path(item))
    return tuple(found)


@contextmanager
def requested(formats: Sequence[str] | None = None, scale: float | None = None, inputs=()) -> Iterator[None]:
    """Within this block :func:`save_motion` writes ``formats`` (default BVH) with glTF ``scale``, and refuses to
    write over any of ``inputs`` (argument values; those naming existing files are the command's inputs)."""
    token = _CURRENT.set(_Request(tuple(formats) if formats else ("bvh",), scale, _input_files(inputs)))
    try:
        yield
    finally:
        _CURRENT.reset(token)


def check_finite(x, what: str = "the generated motions") -> None:
    """``UserError`` when a batch (tensor or list of tensors) holds NaN or inf: checked before any file is written,
    so a broken model leaves no partial output."""
    parts = x if isinstance(x, (list, tuple)) else [x]
    if not all(bool(torch.isfinite(torch.as_tensor(p)).all()) for p in parts):
        raise UserError(f"{what} contain NaN or inf (a diverged or corrupt model?); nothing written")


def check_motion(bvh, path: str | os.PathLike) -> None:
    """``UserError`` for a motion that cannot be written (no frames, NaN or inf anywhere)."""
    if bvh.n_frames < 1:
        raise UserError(f"{path}: the motion has no frames; nothing written")
    if not (np.isfinite(bvh.motion).all() and np.isfinite(bvh.offsets).all()
            and all(np.isfinite(v).all() for v in bvh.end_sites.values())):
        raise UserError(f"{path}: the motion contains NaN or inf; nothing written")


def save_motion(bvh, path: str | os.PathLike, *, contacts: Mapping[str, object] | None = None,
                precision: int = 6, formats: Sequence[str] | None = None, scale: float | None = None) -> Path:
    """Write ``bvh`` as ``path`` with each requested format's suffix (``walk.bvh`` -> ``walk.bvh``, ``walk.glb``).

    ``contacts`` ({joint name: (T,) labels}) go into the glTF's extras. Every file is checked before any is written
    and goes through :func:`modi.faults.atomic_write`. Returns the first format's path (the BVH one by default).
    """
    req = _CURRENT.get()
    formats = tuple(formats) if formats else req.formats
    scale = scale if scale is not None else req.scale
    base = Path(path)
    if base.suffix.lower() in FORMATS.values():
        base = base.with_suffix("")
    check_motion(bvh, path)
    blobs = []
    for fmt in formats:
        out = base.parent / (base.name + FORMATS[fmt])
        for inp in req.inputs:
            if out.exists() and os.path.samefile(out, inp):
                raise UserError(f"{out} is an input of this command; refusing to write over it (choose another --out)")
        if fmt == "bvh":
            blobs.append((out, bvh_io.dumps(bvh, precision)))
        else:
            data, unit = gltf.dumps(bvh, FORMATS[fmt], scale, contacts)
            blobs.append((out, data))
            key = (unit.unit, unit.scale)
            if key not in req.announced:
                req.announced.add(key)
                print(f"modi: glTF units: {unit.describe().replace('--scale', '--gltf-scale')}")
    for out, data in blobs:
        atomic_write(out, data)
    return blobs[0][0]
