"""glTF 2.0 out of a BVH motion (``.glb`` or ``.gltf``), and joint positions back out of a glTF file.

What a file holds: one node per BVH joint (named as the joint, translation = its OFFSET), a skin over those nodes
with inverse bind matrices for the rest pose (Blender makes it an armature), optionally (``mesh=True``) a small mesh
bound to the skin (a tapered box per bone, weighted to the bone's parent joint, for viewers that draw no skeleton;
off by default, see :func:`build`), and one animation: a LINEAR rotation sampler per joint, a
translation sampler for the root (and for any joint whose BVH position channels move), keys at the clip's frame
times. glTF is Y-up in metres: BVH is read as Y-up (its convention) and lengths are multiplied by ``scale`` (a guess
from the body height when not given, see :func:`guess_unit`). Contact labels go in the animation's ``extras``.

Why numpy + json and no glTF library: the file is a few typed arrays and one JSON document, so the package keeps no
extra dependency for it, and the parts a library would hide (alignment, accessor bounds, the GLB chunk layout) are
checked directly by the tests against the Khronos validator. Rotations come from :mod:`modi.core.rotations`, positions
from :func:`modi.core.kinematics.forward_kinematics`, both for writing and for reading back.
"""
from __future__ import annotations

import base64
import json
import math
import os
import struct
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping, Sequence
from urllib.parse import unquote

import numpy as np
import torch

from modi.core.body import Body, UnitGuess, guess_unit
from modi.core.kinematics import bvh_positions, forward_kinematics
from modi.core.rotations import (
    euler_to_quat,
    matrix_to_quat,
    quat_mul,
    quat_normalize,
    quat_slerp,
    quat_to_matrix,
    quat_unflip,
)
from modi.errors import UserError
from modi.faults import atomic_write

__all__ = ["UnitGuess", "guess_unit", "dumps", "save", "load_positions", "read_tracks", "Tracks", "SUFFIXES"]

SUFFIXES = (".glb", ".gltf")
_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
_DTYPES = {_FLOAT: np.float32, _UBYTE: np.uint8, _USHORT: np.uint16, _UINT: np.uint32, 5120: np.int8, 5122: np.int16}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
CONTACTS_KEY = "modi_contacts"


# ---------------------------------------------------------------------------------------------- units


def _body(bvh, up: str = "y"):
    """The :class:`modi.core.body.Body` of the clip (ground root, standing height), from its FK positions, Y up."""
    p = np.asarray(bvh_positions(bvh), dtype=np.float64)
    if up == "z":
        p = np.stack([p[..., 0], p[..., 2], -p[..., 1]], -1)
    return Body.of(p, bvh.parents, bvh.names)


def _unit_for(bvh, scale: float | None, up: str = "y") -> UnitGuess:
    height = bvh.skeleton().height()
    try:
        standing = _body(bvh, up).standing_height
    except (ValueError, IndexError):
        standing = None
    if scale is None:
        return replace(guess_unit(height), standing=standing)
    if not (math.isfinite(scale) and scale > 0):
        raise UserError(f"--scale must be a positive number, got {scale}")
    return UnitGuess(float(scale), "given", height, standing)


# ---------------------------------------------------------------------------------------------- writing


class _Bin:
    """The binary buffer under construction: each ``add`` is one 4-byte-aligned buffer view + accessor."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, data: np.ndarray, kind: str, target: int | None = None, bounds: bool = False) -> int:
        data = np.ascontiguousarray(data)
        comp = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint8): _UBYTE, np.dtype(np.uint16): _USHORT,
                np.dtype(np.uint32): _UINT}[data.dtype]
        raw = data.tobytes()
        view: dict[str, Any] = {"buffer": 0, "byteOffset": self.size, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        pad = (-len(raw)) % 4
        self.chunks.append(raw + b"\0" * pad)
        self.size += len(raw) + pad
        n = _NCOMP[kind]
        acc: dict[str, Any] = {"bufferView": len(self.views) - 1, "componentType": comp,
                               "count": int(data.size // n), "type": kind}
        if bounds:
            flat = data.reshape(-1, n)
            acc["min"] = [_num(v) for v in flat.min(axis=0)]
            acc["max"] = [_num(v) for v in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def bytes(self) -> bytes:
        return b"".join(self.chunks)


def _num(v) -> float | int:
    """A JSON number that reads back as exactly the stored float32 (repr of the float64 of the float32)."""
    return int(v) if np.issubdtype(type(v), np.integer) else float(v)


def _local_motion(bvh) -> tuple[np.ndarray, np.ndarray]:
    """(local quaternions (F, J, 4) w,x,y,z; local translations (F, J, 3)) in file units, float64."""
    euler = torch.from_numpy(bvh.euler_degrees())
    orders = bvh.rotation_orders
    quats = torch.empty(euler.shape[:-1] + (4,), dtype=torch.float64)
    for order in set(orders):
        idx = [j for j, o in enumerate(orders) if o == order]
        quats[:, idx] = euler_to_quat(euler[:, idx], order)
    quats = quat_unflip(quats, dim=0)  # the continuous sign, so a viewer's slerp between keys takes the short arc
    return quats.numpy(), bvh.local_translations()


def _bone_boxes(starts: np.ndarray, ends: np.ndarray, owner: Sequence[int], height: float):
    """A tapered box around each segment start->end: (positions (V,3), normals (V,3), joints (V,), indices (I,))."""
    pos, nrm, jnt, idx = [], [], [], []
    for a, b, j in zip(starts, ends, owner):
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 1e-4 * height:
            continue  # coincident joints: no bone to draw
        d = d / length
        ref = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(d, ref)
        u /= np.linalg.norm(u)
        v = np.cross(d, u)
        w0 = min(0.15 * length, 0.04 * height)
        w1 = 0.5 * w0
        ring = [(1, 1), (-1, 1), (-1, -1), (1, -1)]
        corners = np.array([a + w0 * (s * u + t * v) for s, t in ring] + [b + w1 * (s * u + t * v) for s, t in ring])
        centre = corners.mean(axis=0)
        faces = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
        for f in faces:
            quad = corners[list(f)]
            n = np.cross(quad[1] - quad[0], quad[2] - quad[0])
            if np.dot(n, quad.mean(axis=0) - centre) < 0:  # wind counter-clockwise seen from outside
                quad, n = quad[::-1], -n
            n = n / np.linalg.norm(n)
            base = len(pos)
            pos.extend(quad)
            nrm.extend([n] * 4)
            jnt.extend([j] * 4)
            idx.extend([base, base + 1, base + 2, base, base + 2, base + 3])
    return np.array(pos).reshape(-1, 3), np.array(nrm).reshape(-1, 3), np.array(jnt, dtype=np.int64), \
        np.array(idx, dtype=np.int64)


def _contact_extras(contacts: Mapping[str, np.ndarray] | None, names: Sequence[str], n_frames: int) -> dict | None:
    """``{"joints": [names], "labels": ["0110...", ...]}``: one 0/1 character per frame and labelled joint."""
    if not contacts:
        return None
    joints, labels = [], []
    for name, lab in contacts.items():
        if name not in names:
            raise ValueError(f"contact labels for {name!r}, which is not a joint of the motion")
        lab = np.asarray(lab).reshape(-1)
        if lab.shape[0] != n_frames:
            raise ValueError(f"contact labels of {name!r} have {lab.shape[0]} frames, the motion {n_frames}")
        joints.append(name)
        labels.append("".join("1" if x else "0" for x in (lab > 0.5)))
    return {"joints": joints, "labels": labels}


def build(bvh, scale: float, contacts: Mapping[str, np.ndarray] | None = None, mesh: bool = False,
          up: str = "y") -> tuple[dict, bytes]:
    """The glTF JSON document (buffer 0 without ``uri``) and its binary buffer for ``bvh`` at ``scale``.

    ``mesh``: also a box-per-bone body bound to the skin, for viewers that draw no skeleton. Off by default
    because Debian's Blender 3.4 fails on any mesh with its default import (Shading "Use Normals" reaches
    ``numpy.bool``, which numpy 1.24 removed); without a mesh it imports the armature and its action.
    The boxes follow :class:`modi.core.body.Body`: none on a static ground root or its link to the hips, none for
    End Sites (leaf joints get a small cube instead, so a head top is not drawn twice).
    ``up="z"``: the BVH is Z-up; its root is turned -90 degrees about X into glTF's Y-up."""
    J, F = bvh.n_joints, bvh.n_frames
    if F < 1:
        raise UserError("the motion has no frames; nothing written")
    quats, trans = _local_motion(bvh)
    if up == "z":   # (x, y, z) -> (x, z, -y): the root's rotation and translation turn, everything below follows

        half = math.sqrt(0.5)
        turn = torch.tensor([half, -half, 0.0, 0.0], dtype=torch.float64)
        quats[:, 0] = quat_mul(turn.expand(F, 4), torch.from_numpy(quats[:, 0])).numpy()
        trans = trans.copy()
        trans[:, 0] = np.stack([trans[:, 0, 0], trans[:, 0, 2], -trans[:, 0, 1]], -1)
    elif up != "y":
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    trans = trans * scale
    offsets = bvh.offsets * scale
    if not (np.isfinite(quats).all() and np.isfinite(trans).all() and np.isfinite(offsets).all()):
        raise UserError("the motion contains NaN or inf; nothing written")
    # bind pose: every rotation identity, the root at its OFFSET; the mesh is built in it
    ident = torch.zeros(J, 4, dtype=torch.float64)
    ident[:, 0] = 1.0
    rest, _ = forward_kinematics(ident, torch.from_numpy(offsets), bvh.parents, torch.from_numpy(offsets[0]))
    rest = rest.numpy()
    pos = nrm = jnt = idx = np.zeros(0)
    if mesh:
        body = _body(bvh, up)
        h = max(body.standing_height * scale, 1e-9)
        seg_a, seg_b, owner = [], [], []
        for j in body.bones():
            seg_a.append(rest[bvh.parents[j]])
            seg_b.append(rest[j])
            owner.append(bvh.parents[j])
        ground = set(body.ground)
        has_kids = {q for q in bvh.parents if q >= 0}
        for j in range(J):  # a leaf's tip: a small cube on the joint (End Site offsets are no body part)
            if j not in has_kids and j not in ground and not bvh.names[j].lower().endswith("end"):
                seg_a.append(rest[j] - [0.0, 0.03 * h, 0.0])
                seg_b.append(rest[j] + [0.0, 0.03 * h, 0.0])
                owner.append(j)
        pos, nrm, jnt, idx = _bone_boxes(np.array(seg_a).reshape(-1, 3), np.array(seg_b).reshape(-1, 3), owner, h)

    b = _Bin()
    nodes: list[dict] = []
    children: list[list[int]] = [[] for _ in range(J)]
    for j in range(1, J):
        children[bvh.parents[j]].append(j)
    moving = [j for j in range(J) if j == 0 or np.ptp(trans[:, j], axis=0).max() > 0]
    for j in range(J):
        node: dict[str, Any] = {"name": bvh.names[j]}
        node["translation"] = [float(x) for x in trans[0, j]]  # frame 0 (constant when not animated)
        q0 = quats[0, j]
        node["rotation"] = [float(q0[1]), float(q0[2]), float(q0[3]), float(q0[0])]
        if children[j]:
            node["children"] = children[j]
        nodes.append(node)
    mesh_node = J
    if mesh:
        nodes.append({"name": "body", "mesh": 0, "skin": 0})

    ibm = np.zeros((J, 4, 4))
    ibm[:] = np.eye(4)
    ibm[:, :3, 3] = -rest  # bind rotations are identity: the inverse is a translation
    ibm_acc = b.add(ibm.transpose(0, 2, 1).astype(np.float32), "MAT4")  # glTF matrices are column-major
    attrs = {}
    primitive: dict[str, Any] = {}
    if not mesh:
        pass
    elif len(idx):
        attrs["POSITION"] = b.add(pos.astype(np.float32), "VEC3", _ARRAY_BUFFER, bounds=True)
        attrs["NORMAL"] = b.add(nrm.astype(np.float32), "VEC3", _ARRAY_BUFFER)
        joints = np.zeros((len(jnt), 4), dtype=np.uint8 if J < 256 else np.uint16)
        joints[:, 0] = jnt
        attrs["JOINTS_0"] = b.add(joints, "VEC4", _ARRAY_BUFFER)
        weights = np.zeros((len(jnt), 4), dtype=np.float32)
        weights[:, 0] = 1.0
        attrs["WEIGHTS_0"] = b.add(weights, "VEC4", _ARRAY_BUFFER)
        ind = b.add(idx.astype(np.uint16 if len(pos) < 65535 else np.uint32), "SCALAR", _ELEMENT_ARRAY_BUFFER)
        primitive = {"attributes": attrs, "indices": ind, "material": 0}
    else:  # a skeleton with no visible bone (all joints coincide): one point so the mesh stays valid
        attrs["POSITION"] = b.add(rest[:1].astype(np.float32), "VEC3", _ARRAY_BUFFER, bounds=True)
        attrs["JOINTS_0"] = b.add(np.zeros((1, 4), dtype=np.uint8), "VEC4", _ARRAY_BUFFER)
        attrs["WEIGHTS_0"] = b.add(np.array([[1, 0, 0, 0]], dtype=np.float32), "VEC4", _ARRAY_BUFFER)
        primitive = {"attributes": attrs, "mode": 0, "material": 0}

    times = (np.arange(F, dtype=np.float64) * bvh.frame_time).astype(np.float32)
    t_acc = b.add(times, "SCALAR", bounds=True)
    samplers, channels = [], []
    for j in range(J):
        q = quats[:, j]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        out = b.add(q[:, [1, 2, 3, 0]].astype(np.float32), "VEC4")
        samplers.append({"input": t_acc, "output": out, "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": j, "path": "rotation"}})
        if j in moving:
            out = b.add(trans[:, j].astype(np.float32), "VEC3")
            samplers.append({"input": t_acc, "output": out, "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": j, "path": "translation"}})
    animation: dict[str, Any] = {"name": "motion", "samplers": samplers, "channels": channels}
    extras = _contact_extras(contacts, bvh.names, F)
    if extras:
        animation["extras"] = {CONTACTS_KEY: extras}

    data = b.bytes()
    doc = {
        "asset": {"version": "2.0", "generator": "modi (modi.io.gltf)"},
        "scene": 0,
        "scenes": [{"name": "motion", "nodes": [0, mesh_node] if mesh else [0],
                    "extras": {"modi": {"fps": float(bvh.fps), "frames": F, "scale_to_metres": float(scale)}}}],
        "nodes": nodes,
        "skins": [{"name": "skeleton", "joints": list(range(J)), "skeleton": 0, "inverseBindMatrices": ibm_acc}],
        "animations": [animation],
        "buffers": [{"byteLength": len(data)}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    }
    if mesh:
        doc["meshes"] = [{"name": "body", "primitives": [primitive]}]
        doc["materials"] = [{"name": "body", "pbrMetallicRoughness": {
            "baseColorFactor": [0.75, 0.78, 0.85, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.8}}]
    return doc, data


def _glb(doc: dict, data: bytes) -> bytes:
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * ((-len(text)) % 4)
    data += b"\0" * ((-len(data)) % 4)
    total = 12 + 8 + len(text) + 8 + len(data)
    return (struct.pack("<III", _GLB_MAGIC, 2, total) + struct.pack("<II", len(text), _JSON_CHUNK) + text
            + struct.pack("<II", len(data), _BIN_CHUNK) + data)


def dumps(bvh, suffix: str = ".glb", scale: float | None = None, contacts: Mapping[str, np.ndarray] | None = None,
          mesh: bool = False, up: str = "y") -> tuple[bytes, UnitGuess]:
    """(file bytes, unit guess): ``.glb`` binary, or ``.gltf`` JSON with the buffer embedded as a data URI."""
    unit = _unit_for(bvh, scale, up)
    doc, data = build(bvh, unit.scale, contacts, mesh, up)
    if suffix == ".glb":
        return _glb(doc, data), unit
    if suffix == ".gltf":
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")
        return json.dumps(doc, indent=1).encode("utf-8"), unit
    raise ValueError(f"glTF suffix must be .glb or .gltf, not {suffix!r}")


def save(bvh, path: str | os.PathLike, scale: float | None = None, contacts: Mapping[str, np.ndarray] | None = None,
         side_buffer: bool = False, mesh: bool = False, up: str = "y") -> UnitGuess:
    """Write ``bvh`` as glTF to ``path`` (``.glb``, or ``.gltf`` with its buffer embedded, or beside it as
    ``NAME.bin`` with ``side_buffer``); every file goes through :func:`modi.faults.atomic_write`."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise UserError(f"{path}: a glTF file name ends in .glb or .gltf")
    if side_buffer and suffix == ".gltf":
        unit = _unit_for(bvh, scale, up)
        doc, data = build(bvh, unit.scale, contacts, mesh, up)
        bin_path = path.with_suffix(".bin")
        doc["buffers"][0]["uri"] = bin_path.name
        atomic_write(bin_path, data)
        atomic_write(path, json.dumps(doc, indent=1))
        return unit
    blob, unit = dumps(bvh, suffix, scale, contacts, mesh, up)
    atomic_write(path, blob)
    return unit


# ---------------------------------------------------------------------------------------------- reading


def _parse(path: Path) -> tuple[dict, list[bytes]]:
    """(JSON document, bytes of each buffer) of a ``.glb`` or ``.gltf`` file."""
    raw = path.read_bytes()
    binary = None
    if raw[:4] == b"glTF":
        magic, version, total = struct.unpack_from("<III", raw, 0)
        if version != 2:
            raise UserError(f"{path}: GLB version {version}; only glTF 2.0 is read")
        off, doc = 12, None
        while off + 8 <= min(total, len(raw)):
            length, kind = struct.unpack_from("<II", raw, off)
            chunk = raw[off + 8: off + 8 + length]
            if kind == _JSON_CHUNK and doc is None:
                doc = json.loads(chunk.decode("utf-8"))
            elif kind == _BIN_CHUNK and binary is None:
                binary = chunk
            off += 8 + length
        if doc is None:
            raise UserError(f"{path}: GLB without a JSON chunk")
    else:
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise UserError(f"{path}: not a glTF file ({exc})") from None
    buffers = []
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            if binary is None:
                raise UserError(f"{path}: buffer {i} has no uri and the file has no binary chunk")
            buffers.append(binary)
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            side = path.parent / unquote(uri)
            if not side.is_file():
                raise UserError(f"{path}: buffer file {side} is missing")
            buffers.append(side.read_bytes())
    return doc, buffers


def _accessor(doc: dict, buffers: list[bytes], i: int) -> np.ndarray:
    """Accessor ``i`` as a float64 array (count, components); normalised integers are mapped to [0, 1] / [-1, 1]."""
    acc = doc["accessors"][i]
    if "sparse" in acc or "bufferView" not in acc:
        raise UserError(f"accessor {i}: sparse or view-less accessors are not read")
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(_DTYPES[acc["componentType"]]).newbyteorder("<")
    n = _NCOMP[acc["type"]]
    count = int(acc["count"])
    start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
    stride = int(view.get("byteStride", 0)) or dtype.itemsize * n
    buf = buffers[view["buffer"]]
    arr = np.ndarray((count, n), dtype=dtype, buffer=buf, offset=start, strides=(stride, dtype.itemsize))
    out = arr.astype(np.float64)
    if acc.get("normalized"):
        info = np.iinfo(dtype)
        out = np.maximum(out / info.max, -1.0)
    return out


def _sample(times: np.ndarray, keys: np.ndarray, values: np.ndarray, mode: str, rotation: bool) -> np.ndarray:
    """A sampler's value at each of ``times`` (LINEAR: lerp/slerp, STEP, CUBICSPLINE: Hermite), clamped at the ends."""
    n = len(keys)
    if mode == "CUBICSPLINE":
        tan_in, vals, tan_out = values[0::3], values[1::3], values[2::3]
    else:
        vals = values
    if n == 1:
        return np.repeat(vals[:1], len(times), axis=0)
    k = np.clip(np.searchsorted(keys, times, side="right") - 1, 0, n - 2)
    dt = keys[k + 1] - keys[k]
    s = np.clip((times - keys[k]) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
    if mode == "STEP":
        return np.where((s >= 1.0)[:, None], vals[k + 1], vals[k])
    if mode == "CUBICSPLINE":
        s2, s3 = s * s, s * s * s
        h = [2 * s3 - 3 * s2 + 1, (s3 - 2 * s2 + s) * dt, -2 * s3 + 3 * s2, (s3 - s2) * dt]
        out = (h[0][:, None] * vals[k] + h[1][:, None] * tan_out[k] + h[2][:, None] * vals[k + 1]
               + h[3][:, None] * tan_in[k + 1])
        return quat_normalize(torch.from_numpy(out)).numpy() if rotation else out
    if rotation:  # glTF stores x,y,z,w: slerp in w,x,y,z
        a = torch.from_numpy(vals[k][:, [3, 0, 1, 2]])
        b = torch.from_numpy(vals[k + 1][:, [3, 0, 1, 2]])
        return quat_slerp(a, b, torch.from_numpy(s)[:, None]).numpy()[:, [1, 2, 3, 0]]
    return vals[k] + s[:, None] * (vals[k + 1] - vals[k])


def _node_static(node: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translation, rotation x,y,z,w, scale) of a node, from ``matrix`` when it has one."""
    if "matrix" in node:
        m = np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
        t = m[:3, 3].copy()
        s = np.linalg.norm(m[:3, :3], axis=0)
        r = m[:3, :3] / s
        if np.linalg.det(r) < 0:
            s[0], r[:, 0] = -s[0], -r[:, 0]


        q = matrix_to_quat(torch.from_numpy(r)).numpy()
        return t, q[[1, 2, 3, 0]], s
    return (np.array(node.get("translation", [0, 0, 0]), dtype=np.float64),
            np.array(node.get("rotation", [0, 0, 0, 1]), dtype=np.float64),
            np.array(node.get("scale", [1, 1, 1]), dtype=np.float64))


@dataclass
class Tracks:
    """A glTF file's skeleton animation, sampled at its key times: joint ``names`` and ``parents``, local
    ``rotations`` (T, J, 4) w,x,y,z and ``translations`` (T, J, 3) of every joint node, the static transform
    ``above`` (4x4) of the nodes above the root joint, the frame rate and the contact labels (T, J) or None."""

    names: list[str]
    parents: list[int]
    rotations: torch.Tensor
    translations: torch.Tensor
    above: np.ndarray
    fps: float
    contacts: np.ndarray | None


def read_tracks(path: str | os.PathLike) -> Tracks:
    """The :class:`Tracks` of a glTF file (what :func:`load_positions` turns into positions); see there for which
    nodes are joints and which frames are read."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such glTF file")
    doc, buffers = _parse(path)
    nodes = doc.get("nodes", [])
    if not nodes:
        raise UserError(f"{path}: the glTF file has no nodes")
    parent_of = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}
    skins = doc.get("skins", [])
    members = set(skins[0]["joints"]) if skins else set(range(len(nodes)))
    scene = doc.get("scenes", [{}])[doc.get("scene", 0)] if doc.get("scenes") else {}
    roots = scene.get("nodes") or [i for i in range(len(nodes)) if i not in parent_of]
    order: list[int] = []
    stack = list(reversed(roots))
    while stack:  # depth-first over the scene: parents before children
        i = stack.pop()
        if i in members:
            order.append(i)
        stack.extend(reversed(nodes[i].get("children", [])))
    if not order:
        raise UserError(f"{path}: no joint node is in the scene")
    skin_order = list(skins[0]["joints"]) if skins else []
    if sorted(skin_order) == sorted(order) and all(
            parent_of.get(i) not in members or skin_order.index(parent_of[i]) < k for k, i in enumerate(skin_order)):
        order = skin_order  # the writer's own order (a BVH's file order) whenever parents already come first
    index = {n: k for k, n in enumerate(order)}

    def joint_parent(i: int) -> int:
        p = parent_of.get(i)
        while p is not None and p not in index:
            p = parent_of.get(p)
        return -1 if p is None else index[p]

    parents = [joint_parent(i) for i in order]
    if parents.count(-1) != 1:
        raise UserError(f"{path}: the skin's joints form {parents.count(-1)} trees; one skeleton is read")

    anims = doc.get("animations", [])
    anim = anims[0] if anims else {"samplers": [], "channels": []}
    tracks: dict[tuple[int, str], int] = {}
    for ch in anim["channels"]:
        node = ch["target"].get("node")
        if node in index and ch["target"]["path"] in ("translation", "rotation", "scale"):
            tracks[(node, ch["target"]["path"])] = ch["sampler"]
    keys = [_accessor(doc, buffers, anim["samplers"][s]["input"])[:, 0] for s in set(tracks.values())]
    times = np.unique(np.concatenate(keys)) if keys else np.zeros(1)
    T, J = len(times), len(order)
    trs = {"translation": np.zeros((T, J, 3)), "rotation": np.zeros((T, J, 4)), "scale": np.ones((T, J, 3))}
    for k, i in enumerate(order):
        t, r, s = _node_static(nodes[i])
        for what, val in (("translation", t), ("rotation", r), ("scale", s)):
            sampler = tracks.get((i, what))
            if sampler is None:
                trs[what][:, k] = val
                continue
            sm = anim["samplers"][sampler]
            trs[what][:, k] = _sample(times, _accessor(doc, buffers, sm["input"])[:, 0],
                                      _accessor(doc, buffers, sm["output"]), sm.get("interpolation", "LINEAR"),
                                      what == "rotation")
    if np.abs(trs["scale"] - 1.0).max() > 1e-4:
        raise UserError(f"{path}: joints are scaled; only rotation and translation are read")
    # what sits above the root joint (non-joint ancestors, e.g. an armature node): one static similarity transform
    above = np.eye(4)
    p = parent_of.get(order[0])
    while p is not None:
        t, r, s = _node_static(nodes[p])
        if np.ptp(s) > 1e-6 * abs(s).max():
            raise UserError(f"{path}: node {nodes[p].get('name', p)} scales unevenly above the skeleton")
        m = np.eye(4)

        m[:3, :3] = quat_to_matrix(torch.from_numpy(r[[3, 0, 1, 2]])).numpy() * s[0]
        m[:3, 3] = t
        above = m @ above
        p = parent_of.get(p)
    quats = torch.from_numpy(trs["rotation"][..., [3, 0, 1, 2]])
    quats = quats / quats.norm(dim=-1, keepdim=True)
    offs = torch.from_numpy(trs["translation"])
    extras = (scene.get("extras") or {}).get("modi") or {}
    if "fps" in extras:  # ours: exact (key times are float32)
        fps = float(extras["fps"])
    else:
        fps = float(1.0 / np.median(np.diff(times))) if T > 1 else 30.0
    contacts = None
    labels = (anim.get("extras") or {}).get(CONTACTS_KEY)
    names = [nodes[i].get("name", f"joint_{i}") for i in order]
    if labels:
        contacts = np.zeros((T, J), dtype=bool)
        for name, lab in zip(labels["joints"], labels["labels"]):
            if name in names and len(lab) == T:
                contacts[:, names.index(name)] = np.frombuffer(lab.encode("ascii"), dtype=np.uint8) == ord("1")
    return Tracks(names, parents, quats, offs, above, fps, contacts)


def load_positions(path: str | os.PathLike) -> tuple[list[str], list[int], np.ndarray, float, np.ndarray | None]:
    """``(names, parents, positions (T, J, 3) in the file's units -- metres for glTF --, fps, contacts)`` of a glTF.

    Joints are the first skin's joints (all nodes when there is no skin), in the skin's order when parents come first
    there, else depth first; frames are
    the first animation's key times (the union over its samplers). Each frame's TRS is sampled from the accessors
    and turned into positions by :func:`modi.core.kinematics.forward_kinematics`. ``contacts`` is ``(T, J)`` bool from
    the ``modi_contacts`` extra, or None. Joint scale other than 1 is refused (motion files do not animate it).
    """
    tr = read_tracks(path)
    pos, _ = forward_kinematics(tr.rotations, tr.translations, tr.parents, tr.translations[:, 0])
    pos = pos.numpy() @ tr.above[:3, :3].T + tr.above[:3, 3]
    return tr.names, tr.parents, pos, tr.fps, tr.contacts
