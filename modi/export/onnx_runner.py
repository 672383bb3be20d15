"""Run a modi ONNX model with NumPy and onnxruntime only, and write its motion as BVH.

This file imports neither torch nor anything else of modi: copy it next to ``model.onnx`` and ``model.json`` (the
sidecar ``modi export onnx`` writes) and run::

    python onnx_runner.py model.onnx out.bvh                    # one motion, noise drawn with NumPy (--seed)
    python onnx_runner.py model.onnx out.bvh --frames 300       # GANimator: any length >= the sidecar's minimum
    python onnx_runner.py model.onnx out.bvh --noise noise.npy  # given inputs (NAME.npy per input: --input NAME=FILE)

or from Python: ``Runner("model.onnx")(noise=..., frames=...)`` returns the outputs by name.

The contract: every input is checked against the sidecar before the graph runs (names, dtypes, shapes, the
lengths that must agree with each other, value ranges, finiteness), and a violation raises :class:`ContractError`
with one line saying what was expected -- a wrong noise length or a NaN is refused, never turned into a silent
wrong motion.  Integrations that call the graph directly (Unity Sentis, Unreal NNE, onnxruntime-web) should apply
the same checks: they are all in :func:`check_inputs` and described by the sidecar's ``inputs`` and ``dims``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

SIDECAR_FORMAT = "modi.onnx/1"
_DTYPES = {"float32": np.float32, "int64": np.int64}


class ContractError(ValueError):
    """An input that breaks the model's contract (the sidecar's ``inputs`` and ``dims``)."""


# ------------------------------------------------------------------------------------------- the sidecar


def sidecar_path(model: str | Path) -> Path:
    """``model.onnx`` -> ``model.json``."""
    return Path(model).with_suffix(".json")


def read_sidecar(model: str | Path) -> dict:
    path = sidecar_path(model)
    if not path.is_file():
        raise ContractError(f"{path}: no sidecar beside {model} (export writes both; keep them together)")
    side = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(side, dict) or side.get("format") != SIDECAR_FORMAT:
        raise ContractError(f"{path}: not a modi ONNX sidecar (format {SIDECAR_FORMAT} expected)")
    return side


def ceil_div(a: int, b: int) -> int:
    return -(-int(a) // int(b))


def dim_rule(side: dict, name: str, frames: int) -> int:
    """The length a derived dimension (``coarse_frames``) must have for ``frames`` output frames."""
    rule = side["dims"][name]
    return ceil_div(frames * rule["numerator"], rule["denominator"])


def frames_of(side: dict, feeds: dict) -> int | None:
    """Output frames the inputs ask for: the ``frames`` input's value, or the dimension that carries it."""
    fr = side["dims"].get("frames", {})
    if "input" in fr and fr["input"] in feeds:
        return int(np.asarray(feeds[fr["input"]]).reshape(-1)[0])
    return fr.get("fixed")


# ------------------------------------------------------------------------------------------- the contract


def check_inputs(side: dict, feeds: dict) -> dict[str, np.ndarray]:
    """``feeds`` as the graph's dtypes, after checking each against the sidecar; raises :class:`ContractError`."""
    specs = {s["name"]: s for s in side["inputs"]}
    unknown = sorted(set(feeds) - set(specs))
    if unknown:
        raise ContractError(f"unknown input(s) {', '.join(unknown)}; this model takes {', '.join(specs)}")
    missing = [n for n in specs if n not in feeds]
    if missing:
        raise ContractError(f"missing input(s) {', '.join(missing)}; this model takes {', '.join(specs)}")
    out: dict[str, np.ndarray] = {}
    bound: dict[str, tuple[int, str]] = {}
    for name, spec in specs.items():
        a = np.asarray(feeds[name])
        want = spec["dtype"]
        if want == "int64":
            if a.dtype.kind not in "iu" and not (a.dtype.kind == "f" and np.all(np.isfinite(a)) and
                                                np.all(a == np.round(a))):
                raise ContractError(f"{name}: expected whole numbers (int64), got dtype {a.dtype}")
        elif a.dtype.kind not in "fiu":
            raise ContractError(f"{name}: expected numbers ({want}), got dtype {a.dtype}")
        shape = spec["shape"]
        if a.ndim != len(shape):
            raise ContractError(f"{name}: expected {len(shape)} dimensions {_shape_text(shape)}, got shape "
                                f"{tuple(a.shape)}")
        for axis, (d, n) in enumerate(zip(shape, a.shape)):
            if isinstance(d, int):
                if n != d:
                    raise ContractError(f"{name}: dimension {axis} must be {d} {_shape_text(shape)}, got shape "
                                        f"{tuple(a.shape)}")
            elif d in bound and bound[d][0] != n:
                raise ContractError(f"{name}: dimension {axis} ({d}) is {n} but {bound[d][1]} has {d} = "
                                    f"{bound[d][0]}; they must agree")
            else:
                bound.setdefault(d, (int(n), name))
        if spec.get("finite", True) and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
            raise ContractError(f"{name}: {bad} value(s) are NaN or infinite; every value must be finite")
        lo, hi = spec.get("min"), spec.get("max")
        if a.size and lo is not None and float(a.min()) < lo:
            raise ContractError(f"{name}: values must be >= {lo:g} ({spec.get('values', '')}), got {a.min():g}")
        if a.size and hi is not None and float(a.max()) > hi:
            raise ContractError(f"{name}: values must be <= {hi:g} ({spec.get('values', '')}), got {a.max():g}")
        out[name] = a.astype(_DTYPES[want], copy=False)
    frames = frames_of(side, out)
    if frames is None and "frames" in bound:  # a trajectory's length
        frames = bound["frames"][0]
    elif frames is not None:
        bound.setdefault("frames", (frames, "frames"))
    for d, rule in side.get("dims", {}).items():
        if d not in bound:
            continue
        n, who = bound[d]
        if "min" in rule and n < rule["min"]:
            raise ContractError(f"{who}: {d} = {n} is below the model's minimum of {rule['min']} "
                                f"({rule.get('why', '')})".replace(" ()", ""))
        if "max" in rule and n > rule["max"]:
            raise ContractError(f"{who}: {d} = {n} is above the model's maximum of {rule['max']}")
        if "numerator" in rule and frames is not None:
            want = dim_rule(side, d, frames)
            if n != want:
                raise ContractError(f"{who}: {d} must be {want} for {frames} output frames "
                                    f"(ceil({frames} * {rule['numerator']} / {rule['denominator']})), got {n}")
    return out


def _shape_text(shape: list) -> str:
    return "(" + ", ".join(str(d) for d in shape) + ")"


def draw_inputs(side: dict, frames: int | None = None, batch: int = 1, seed: int = 0,
                psi: float | None = None, skip: tuple | list | set = ()) -> dict[str, np.ndarray]:
    """Inputs for ``batch`` motions: standard-normal noise / latents from NumPy's generator ``seed`` (not torch's:
    the same seed gives other motions than ``modi``'s own sampler), ``frames`` frames where the length is free;
    the inputs named in ``skip`` are left out (given by the caller)."""
    rng = np.random.default_rng(seed)
    fr = side["dims"].get("frames", {})
    if frames is None:
        frames = fr.get("fixed", fr.get("default"))
    sizes = {"batch": batch, "frames": frames}
    for d in side["dims"]:
        if "numerator" in side["dims"][d]:
            sizes[d] = dim_rule(side, d, frames)
    feeds: dict[str, np.ndarray] = {}
    for spec in side["inputs"]:
        if spec["name"] in skip:
            continue
        shape = [sizes.get(d, d) if isinstance(d, str) else d for d in spec["shape"]]
        if any(isinstance(d, str) for d in shape):
            raise ContractError(f"{spec['name']}: no default for dimensions {shape}; pass the input")
        kind = spec.get("draw", "normal")
        if kind == "normal":
            feeds[spec["name"]] = rng.standard_normal(shape).astype(np.float32)
        elif kind == "frames":
            feeds[spec["name"]] = np.full(shape, frames, dtype=np.int64)
        elif kind == "psi":
            feeds[spec["name"]] = np.full(shape, 1.0 if psi is None else psi, dtype=np.float32)
        else:
            raise ContractError(f"{spec['name']}: cannot be drawn ({kind}); pass it")
    return feeds


class Runner:
    """An onnxruntime session of ``model.onnx`` with its sidecar; calls check every input first."""

    def __init__(self, model: str | Path, providers: list[str] | None = None) -> None:
        try:
            import onnxruntime as ort  # the one optional dependency: imported only when a model is run
        except ImportError:
            raise ImportError("running an ONNX model needs onnxruntime: pip install onnxruntime") from None
        self.path = Path(model)
        if not self.path.is_file():
            raise ContractError(f"{model}: no such model file")
        self.sidecar = read_sidecar(model)
        self.session = ort.InferenceSession(str(self.path), providers=providers or ["CPUExecutionProvider"])
        self.output_names = [o.name for o in self.session.get_outputs()]

    def __call__(self, **feeds) -> dict[str, np.ndarray]:
        checked = check_inputs(self.sidecar, feeds)
        return dict(zip(self.output_names, self.session.run(None, checked)))


# ------------------------------------------------------------------------------------------- BVH output


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (w, x, y, z) -> rotation matrices ``(..., 3, 3)``."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(angle.shape + (3, 3))
    a, b = (axis + 1) % 3, (axis + 2) % 3
    m[..., axis, axis] = 1.0
    m[..., a, a], m[..., a, b], m[..., b, a], m[..., b, b] = c, -s, s, c
    return m


def matrix_to_euler(m: np.ndarray, order: str) -> np.ndarray:
    """Rotation matrices -> intrinsic Euler angles in degrees for a BVH channel ``order`` (``R = R_0 R_1 R_2``).

    The middle angle from one entry, the first from two, the last from what remains after undoing the first two
    (exact at gimbal lock too)."""
    i, j, k = ("XYZ".index(c) for c in order.upper())
    even = (i, j, k) in ((0, 1, 2), (1, 2, 0), (2, 0, 1))
    sign = 1.0 if even else -1.0
    beta = np.arcsin(np.clip(sign * m[..., i, k], -1.0, 1.0))
    alpha = np.arctan2(-sign * m[..., j, k], m[..., k, k])
    rest = np.swapaxes(_axis_rotation(i, alpha) @ _axis_rotation(j, beta), -1, -2) @ m  # = R_k(gamma)
    a, b = (k + 1) % 3, (k + 2) % 3
    gamma = np.arctan2(rest[..., b, a], rest[..., a, a])
    return np.degrees(np.stack([alpha, beta, gamma], -1))


def _depth_first(parents: list[int]) -> list[int]:
    children: dict[int, list[int]] = {j: [] for j in range(len(parents))}
    for j, p in enumerate(parents[1:], 1):
        children[p].append(j)
    order, stack = [], [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children[j]))
    return order


def bvh_text(side: dict, rotations: np.ndarray, root_position: np.ndarray, precision: int = 6) -> str:
    """One motion (``rotations (T, J, 4)``, ``root_position (T, 3)``, the sidecar's units) as BVH text on the
    sidecar's rig: root with 6 channels, other joints 3, each joint's rotation order as the source file had it."""
    sk = side["skeleton"]
    names, parents, offsets = sk["names"], sk["parents"], np.asarray(sk["offsets"], dtype=np.float64)
    orders = sk["rotation_orders"]
    ends = {names.index(n): v for n, v in sk.get("end_sites", {}).items()}
    T, J = rotations.shape[:2]
    if J != len(names) or root_position.shape != (T, 3):
        raise ContractError(f"rotations {rotations.shape} / root {root_position.shape} do not fit the {len(names)}-"
                            "joint rig")
    mats = quat_to_matrix(rotations.astype(np.float64))
    order = _depth_first(parents)
    fmt = lambda v: " ".join(f"{float(x):.{precision}f}" for x in v)  # noqa: E731
    depth = {0: 0}
    lines = ["HIERARCHY"]
    open_joints: list[int] = []
    cols = []
    for j in order:
        if j:
            depth[j] = depth[parents[j]] + 1
        while open_joints and parents[j] != open_joints[-1]:
            _close(lines, open_joints.pop(), depth, ends, fmt)
        ind = "\t" * depth[j]
        rot = [f"{c.upper()}rotation" for c in orders[j]]
        chans = (["Xposition", "Yposition", "Zposition"] if j == 0 else []) + rot
        lines += [f"{ind}{'ROOT' if j == 0 else 'JOINT'} {names[j]}", f"{ind}{{", f"{ind}\tOFFSET {fmt(offsets[j])}",
                  f"{ind}\tCHANNELS {len(chans)} " + " ".join(chans)]
        open_joints.append(j)
        if j == 0:
            cols.append(root_position.astype(np.float64))
        cols.append(matrix_to_euler(mats[:, j], orders[j]))
    while open_joints:
        _close(lines, open_joints.pop(), depth, ends, fmt)
    motion = np.concatenate(cols, axis=1)
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / float(side['fps']):.8f}"]
    row = " ".join([f"%.{precision}f"] * motion.shape[1])
    lines += [row % tuple(r) for r in motion.tolist()]
    return "\n".join(lines) + "\n"


def _close(lines: list[str], j: int, depth: dict, ends: dict, fmt) -> None:
    ind = "\t" * depth[j]
    if j in ends:
        lines += [f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {fmt(ends[j])}", f"{ind}\t}}"]
    lines.append(f"{ind}}}")


def write_bvh(side: dict, outputs: dict[str, np.ndarray], path: str | Path, index: int = 0) -> Path:
    """Motion ``index`` of a batch of outputs as a BVH file."""
    path = Path(path)
    path.write_text(bvh_text(side, outputs["rotations"][index], outputs["root_position"][index]), encoding="utf-8")
    return path


# ------------------------------------------------------------------------------------------- the script


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="onnx_runner.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("model", metavar="MODEL.onnx", help="the exported model (its sidecar MODEL.json beside it)")
    p.add_argument("output", metavar="OUT.bvh", help="BVH to write (a batch: OUT_000.bvh, OUT_001.bvh, ...)")
    p.add_argument("--frames", type=int, default=None, help="output frames (models with a free length)")
    p.add_argument("--batch", type=int, default=1, help="motions to draw when no input is given")
    p.add_argument("--seed", type=int, default=0, help="NumPy seed for the drawn noise / latents")
    p.add_argument("--psi", type=float, default=None, help="MoDi: truncation (1 = none)")
    p.add_argument("--input", action="append", default=[], metavar="NAME=FILE.npy",
                   help="an input from a .npy file (repeatable); others are drawn")
    p.add_argument("--noise", metavar="FILE.npy", default=None, help="shorthand for --input noise=FILE.npy")
    p.add_argument("--contacts", action="store_true", help="also write OUT_contacts.npy (T, F) per motion")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    try:
        runner = Runner(args.model)
        side = runner.sidecar
        given: dict[str, np.ndarray] = {}
        for item in args.input + ([f"noise={args.noise}"] if args.noise else []):
            name, _, file = item.partition("=")
            if not file:
                raise ContractError(f"--input {item}: expected NAME=FILE.npy")
            given[name] = np.load(file, allow_pickle=False)
        frames = args.frames
        if frames is None:
            frames = frames_of(side, given) or _frames_from_given(side, given)
        batch = next((int(np.shape(v)[0]) for n, v in given.items() if _first_dim(side, n) == "batch"), args.batch)
        feeds = {**draw_inputs(side, frames, batch, args.seed, args.psi, skip=set(given)), **given}
        out = runner(**feeds)
    except (ContractError, ImportError, OSError) as exc:
        print(f"onnx_runner: {exc}", file=sys.stderr)
        return 2
    n = out["rotations"].shape[0]
    base = Path(args.output)
    for i in range(n):
        path = base if n == 1 else base.with_name(f"{base.stem}_{i:03d}{base.suffix}")
        write_bvh(side, out, path, i)
        if args.contacts:
            np.save(path.with_name(path.stem + "_contacts.npy"), out["contacts"][i])
        print(f"{path}: {out['rotations'].shape[1]} frames x {out['rotations'].shape[2]} joints at "
              f"{side['fps']:g} fps")
    return 0


def _first_dim(side: dict, name: str):
    spec = next((s for s in side["inputs"] if s["name"] == name), None)
    return spec["shape"][0] if spec and spec["shape"] else None


def _frames_from_given(side: dict, given: dict) -> int | None:
    """The output length an input's shape fixes (a trajectory's frames), if any."""
    for spec in side["inputs"]:
        if spec["name"] in given and "frames" in spec["shape"]:
            return int(np.shape(given[spec["name"]])[spec["shape"].index("frames")])
    return None


if __name__ == "__main__":
    sys.exit(main())
