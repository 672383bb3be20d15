"""What a modi file is, from its data alone: :func:`inspect` (``modi info``) and :class:`FileInfo`.

Before trusting a checkpoint someone shared, look at it: the file is read as data only (``modi.io.safe_load``),
no network is built, and a file that names code is refused with one line, so this is safe on any file.
"""
from __future__ import annotations

import json
import math
import os
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from modi.errors import UserError
from modi.interop.provenance import KINDS as SOURCE_KINDS
from modi.io.safe_load import earlier_modi_globals, load_data

_FOLDER_FILES = ("ganimator.ckpt", "checkpoint.pt")  # what a GANimator / MoDi run folder holds


def _resolve(path: Path) -> Path:
    if path.is_dir():
        for name in _FOLDER_FILES:
            if (path / name).is_file():
                return path / name
        raise UserError(f"{path}: a folder without a modi checkpoint ({' or '.join(_FOLDER_FILES)})")
    if not path.exists():
        raise UserError(f"{path}: no such file")
    return path


def _skeleton(d: dict | None, names: list | None = None, parents: list | None = None) -> dict[str, Any] | None:
    names = list(d["names"]) if d is not None else names
    parents = list(d["parents"]) if d is not None else parents
    if names is None:
        return None
    return {"joints": len(names), "root": names[0] if names else None, "names": names, "parents": parents}


def _written_by(st: dict) -> dict[str, Any]:
    return {"modi_version": st.get("modi_version"), "torch_version": st.get("torch_version")}


def _precision(st: dict) -> str:
    """The precision a checkpoint was trained in: its record, or fp32 for one written before modi recorded it (every
    run was fp32 then). Its weights are fp32 either way."""
    return str(st.get("precision", "fp32"))


def _imported(prov: Any) -> dict[str, Any] | None:
    """An import's record (``modi.interop.provenance``), or the bare path earlier imports kept."""
    if prov is None:
        return None
    if not isinstance(prov, dict):
        return {"kind": None, "source": {"path": str(prov)}}
    return prov


def _kind(kind: str, prov: dict | None) -> str:
    return kind + (" (imported from the authors' released code)" if prov is not None else "")


def _modi(st: dict) -> dict[str, Any]:
    prov = _imported(st.get("imported_from"))
    return {"kind": _kind("MoDi generator checkpoint", prov), "format": st.get("format"),
            "version": st.get("version"), "step": st.get("step"), "skeleton": _skeleton(st.get("skeleton")),
            "config": st.get("config"), "data": st.get("data_source"), **_written_by(st), "imported": prov,
            "precision": _precision(st)}


def _encoder(st: dict) -> dict[str, Any]:
    gen = st.get("generator") or {}
    prov = _imported(st.get("imported_from"))
    return {"kind": _kind("MoDi encoder checkpoint", prov), "format": st.get("format"), "version": st.get("version"),
            "step": st.get("step"), "skeleton": _skeleton(gen.get("skeleton")),
            "config": {"encoder": st.get("encoder_config"), "train": st.get("train_config"),
                       "generator": gen.get("config")}, "data": st.get("data_source"), **_written_by(st),
            "imported": prov}


def _features(st: dict) -> dict[str, Any]:
    cfg = dict(st.get("config") or {})
    info = st.get("info") or {}
    epochs = info.get("epochs") or []
    return {"kind": "feature-extractor file (ST-GCN)", "format": st.get("format"),
            "version": int(st["format"].rsplit("-v", 1)[1]) if "-v" in st["format"] else None,
            "step": f"{len(epochs)} epochs" + (f", validation top-1 {info['val_top1']:.3f}" if "val_top1" in info else ""),
            "skeleton": _skeleton(None, cfg.pop("joint_names", None), cfg.pop("parents", None)), "config": cfg,
            "data": info.get("data"), **_written_by(st)}


def _ganimator(st: dict) -> dict[str, Any]:
    m = st.get("model") or {}
    cfg = m.get("config") or {}
    state = st.get("state") or {}
    lengths = m.get("lengths") or [[]]
    n_levels = len(lengths[0])
    n_blocks = math.ceil(n_levels / max(int(cfg.get("group_size", 1)), 1)) if n_levels else 0
    b = int(state.get("block", 0))
    where = "fully trained" if b >= n_blocks else f"block {b + 1}/{n_blocks}, iteration {state.get('iteration', 0)}"
    clips = [f"{c['name']} ({c['features'].shape[-1]} frames at {c['fps']:g} fps; pyramid {'-'.join(map(str, l))})"
             for c, l in zip(m.get("clips", []), lengths)]
    first = (m.get("clips") or [{}])[0]
    prov = _imported(state.get("imported_from"))
    kind = "GANimator checkpoint" + (" (trajectory-conditioned)" if cfg.get("conditional") else "")
    return {"kind": _kind(kind, prov),
            "format": st.get("format"), "version": int(str(st.get("format")).rsplit("/", 1)[1]),
            "step": f"{where}; {state.get('levels_done', 0)} of {n_levels} levels trained",
            "skeleton": _skeleton(first.get("skeleton")), "config": cfg, "data": ", ".join(clips),
            **_written_by(st), "imported": prov, "precision": _precision(st)}


_KINDS = {"modi-checkpoint": _modi, "modi-encoder": _encoder, "modi-features-v1": _features,
          "modi.ganimator/1": _ganimator}


def describe(path: str | Path) -> dict[str, Any]:
    """The description ``modi info`` prints, from the file's data alone (``UserError`` for anything else)."""
    p = _resolve(Path(path))
    st = load_data(p, "modi file", allowed=earlier_modi_globals())
    fmt = st.get("format") if isinstance(st, dict) else None
    if fmt not in _KINDS:
        raise UserError(f"{p}: not a modi checkpoint, encoder or feature-extractor file"
                        + (f" (format tag {fmt!r})" if fmt is not None else " (no format tag)"))
    try:
        return {"file": str(p), **_KINDS[fmt](st)}
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise UserError(f"{p}: a {fmt} file with missing or malformed fields ({type(exc).__name__}: {exc})") from None


def _flat(d: Any, prefix: str = "") -> list[str]:
    """``a.b=value`` pairs of a nested config, for one readable line per field group."""
    if not isinstance(d, dict):
        return [f"{prefix}={d!r}"] if prefix else [repr(d)]
    out: list[str] = []
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        out += _flat(v, key) if isinstance(v, dict) else [f"{key}={json.dumps(v)}"]
    return out


def describe_text(d: dict[str, Any]) -> str:
    """The text ``modi info`` prints for a :func:`describe` dict."""
    sk = d["skeleton"]
    names = ", ".join(sk["names"][:8]) + (", ..." if sk and len(sk["names"]) > 8 else "") if sk else ""
    wrote = (f"modi {d['modi_version']}" if d.get("modi_version")
             else "not recorded (written before modi recorded its version)")
    if d.get("torch_version"):
        wrote += f", torch {d['torch_version']}"
    rows = [("file", d["file"]), ("kind", d["kind"]), ("format", f"{d['format']} (version {d['version'] if d['version'] is not None else 'not recorded'})"),
            ("step", d["step"]),
            ("skeleton", f"{sk['joints']} joints, root {sk['root']}: {names}" if sk else "not recorded"),
            ("data", d.get("data") or "not recorded"), ("written by", wrote)]
    if d.get("precision") is not None:  # the checkpoints of training runs
        rows.append(("precision", f"trained in {d['precision']} (weights stored in fp32)"))
    lines = [f"{k + ':':12s} {v}" for k, v in rows]
    lines += imported_text(d.get("imported"))
    cfg = " ".join(_flat(d["config"])) if d.get("config") is not None else "not recorded"
    lines += textwrap.wrap(cfg, width=110, initial_indent=f"{'config:':12s} ", subsequent_indent=" " * 13)
    return "\n".join(lines)


def _source_text(src: dict, kind: str | None) -> str:
    name = src.get("name") or src.get("path") or "?"
    what = SOURCE_KINDS.get(kind or "", "released checkpoint")
    if src.get("files"):
        names = [f["name"] for f in src["files"]]
        gens = [n for n in names if n.startswith("gen")]
        shown = [n for n in names if not n.startswith("gen")] + ([f"{len(gens)} generators ({gens[0]}..{gens[-1]})"]
                                                                  if gens else [])
        return f"{what} {name}/ ({', '.join(shown)}; sha256 {src.get('sha256')} over the files' sha256)"
    return f"{what} {name}" + (f" (sha256 {src['sha256']})" if src.get("sha256") else "")


def _data_text(data: dict, kind: str | None) -> str:
    if not data:
        return "not recorded"
    head = f"{data.get('name')} (sha256 {data.get('sha256')})"
    if kind == "ganimator-released":
        text = (f"{head}: {data.get('frames')} frames, Frame Time {data.get('frame_time'):.9g} "
                f"({data.get('fps'):.9g} fps); their frame stride {data.get('stride')}: a clip of "
                f"{data.get('clip_frames')} frames at {data.get('clip_fps'):.9g} fps, pyramid "
                f"{'-'.join(map(str, data.get('pyramid') or []))}; units x{data.get('scale'):g}, contact threshold "
                f"{data.get('threshold'):g} on {', '.join(data.get('contacts') or []) or 'no joints'}")
        if data.get("floor_root"):
            text += f"; root track from the static floor root {(data.get('joints') or ['?'])[0]}" \
                if (data.get("joints") or [""])[0] == "joint_Root" else "; the file's static floor root left out"
        flips = [f"frame {f.get('frame')} {f.get('joint')}" for f in data.get("flipped_labels") or []]
        if flips:
            text += (f"; {len(flips)} contact label(s) within float32 rounding of the threshold settled by amps.pt "
                     f"({', '.join(flips)})")
        return text
    window, stride = data.get("window"), data.get("stride")
    return (f"{head}: {data.get('clips')} clips, windows of {window} frames every "
            f"{stride if stride is not None else '? (no two windows overlap)'}, at {data.get('fps'):g} fps")


def imported_text(prov: dict | None) -> list[str]:
    """The ``imported`` rows: what the source file says, marked as theirs."""
    if prov is None:
        return []
    kind = prov.get("kind")
    src = prov.get("source") or {}
    rows = [("imported", _source_text(src, kind) + (f", by modi {prov['imported_by']}" if prov.get("imported_by")
                                                    else ""))]
    if kind is None:
        return [f"{'imported:':12s} {src.get('path')} (recorded before modi kept what the file says)"]
    its = prov.get("iterations")
    rows.append(("their step", f"{its} iterations, {prov.get('iterations_from')}" if its is not None
                 else f"not recorded ({prov.get('iterations_from')})"))
    rows.append(("their data", _data_text(prov.get("data") or {}, kind)))
    rows.append(("their seed", prov["seed"] if prov.get("seed") is not None
                 else "none (their training scripts set no seed)"))
    if prov.get("generator"):
        rows.append(("generator", _source_text((prov["generator"] or {}).get("source") or {}, "modi-released")))
    lines = []
    for k, v in rows:
        lines += textwrap.wrap(str(v), width=110, initial_indent=f"{k + ':':12s} ", subsequent_indent=" " * 13)
    args = prov.get("args") or {}
    text = " ".join(f"--{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in args.items()) or "none"
    lines += textwrap.wrap(text, width=110, initial_indent=f"{'their args:':12s} ", subsequent_indent=" " * 13,
                           break_on_hyphens=False)
    return lines


@dataclass
class FileInfo:
    """What ``modi info FILE`` prints, as an object: ``kind``, ``format`` and ``version``, training ``step``, the
    ``skeleton`` (joints, root, names, parents), the ``config``, the ``data`` it was trained on, the modi and
    torch versions that wrote it and, for a MoDi or GANimator checkpoint, the ``precision`` it was trained in
    (``fp32`` or ``bf16``; None for other files). ``str()`` is the text ``modi info`` prints; :meth:`to_dict` its
    ``--json``."""

    file: str
    kind: str
    format: Any
    version: Any
    step: Any
    skeleton: dict[str, Any] | None
    config: Any
    data: Any
    modi_version: str | None = None
    torch_version: str | None = None
    imported: dict[str, Any] | None = None
    precision: str | None = None
    text: str = field(default="", repr=False, compare=False)

    @classmethod
    def from_dict(cls, d: dict[str, Any], text: str = "") -> "FileInfo":
        return cls(d["file"], d["kind"], d.get("format"), d.get("version"), d.get("step"), d.get("skeleton"),
                   d.get("config"), d.get("data"), d.get("modi_version"), d.get("torch_version"), d.get("imported"),
                   d.get("precision"), text)

    def to_dict(self) -> dict[str, Any]:
        """The ``modi info --json`` object."""
        return {"file": self.file, "kind": self.kind, "format": self.format, "version": self.version,
                "step": self.step, "skeleton": self.skeleton, "config": self.config, "data": self.data,
                "modi_version": self.modi_version, "torch_version": self.torch_version, "imported": self.imported,
                "precision": self.precision}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, default=str)

    def __str__(self) -> str:
        return self.text or self.to_json()


def inspect(path: str | os.PathLike) -> FileInfo:
    """What ``modi info PATH`` prints, as a :class:`FileInfo`: kind, format and version, training step, skeleton,
    config, training data and the modi that wrote a MoDi / GANimator checkpoint (or run folder), an encoder or a
    feature-extractor file. The file is read as data only (nothing in it runs: safe on a file someone sent);
    cost: reading it, no network is built. ``UserError`` for anything else."""
    d = describe(path)
    return FileInfo.from_dict(d, describe_text(d))


__all__ = ["inspect", "FileInfo", "describe", "describe_text"]
