"""Procedural motion on a built-in humanoid: the data the demo and the core tests need without any files.

Each clip kind (walk, run, jump, wave, squat, idle) is a parametric cycle whose parameters (speed, stride, cadence,
arm swing, depth, facing, turning rate, phase, small smooth noise) are drawn from a ``numpy.random.Generator``, so a
seed fixes the clip. Legs are placed by analytic two-bone IK on foot targets that stay planted during stance (with a
heel-strike / toe-off roll), and the root height is limited by what the legs can reach, so feet do not slide and the
pelvis bobs the way a compass gait does. Poses are built as numpy rotation matrices (cheap, vectorised over frames)
and converted once to the quaternions of a :class:`modi.data.motion.Motion`.

Conventions: Y up, character faces +Z at heading 0 (its left is +X), centimetres, ground at y = 0.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from modi.core.rotations import matrix_to_euler, matrix_to_quat, quat_canonical, quat_normalize
from modi.core.skeleton import Skeleton
from modi.data.motion import Motion
from modi.io import bvh as bvh_io
from modi.io.formats import save_motion

KINDS: tuple[str, ...] = ("walk", "run", "jump", "wave", "squat", "idle")

# name, parent, offset (T-pose, cm). Ankles sit 8 cm and toes 1 cm above the ground when the root is at 100.
_JOINTS: list[tuple[str, str | None, tuple[float, float, float]]] = [
    ("Hips", None, (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "Hips", (9.0, -7.0, 0.0)),
    ("LeftLeg", "LeftUpLeg", (0.0, -43.0, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -42.0, 0.0)),
    ("LeftToe", "LeftFoot", (0.0, -7.0, 13.0)),
    ("RightUpLeg", "Hips", (-9.0, -7.0, 0.0)),
    ("RightLeg", "RightUpLeg", (0.0, -43.0, 0.0)),
    ("RightFoot", "RightLeg", (0.0, -42.0, 0.0)),
    ("RightToe", "RightFoot", (0.0, -7.0, 13.0)),
    ("Spine", "Hips", (0.0, 8.0, -1.0)),
    ("Spine1", "Spine", (0.0, 12.0, 0.0)),
    ("Spine2", "Spine1", (0.0, 12.0, 1.0)),
    ("Neck", "Spine2", (0.0, 14.0, 0.0)),
    ("Head", "Neck", (0.0, 9.0, 2.0)),
    ("LeftShoulder", "Spine2", (3.0, 10.0, 0.0)),
    ("LeftArm", "LeftShoulder", (14.0, 0.0, 0.0)),
    ("LeftForeArm", "LeftArm", (28.0, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (25.0, 0.0, 0.0)),
    ("RightShoulder", "Spine2", (-3.0, 10.0, 0.0)),
    ("RightArm", "RightShoulder", (-14.0, 0.0, 0.0)),
    ("RightForeArm", "RightArm", (-28.0, 0.0, 0.0)),
    ("RightHand", "RightForeArm", (-25.0, 0.0, 0.0)),
]
_END_SITES = {"Head": (0.0, 17.0, 0.0), "LeftHand": (10.0, 0.0, 0.0), "RightHand": (-10.0, 0.0, 0.0),
              "LeftToe": (0.0, 0.0, 6.0), "RightToe": (0.0, 0.0, 6.0)}
_J = {name: i for i, (name, _, _) in enumerate(_JOINTS)}

_THIGH, _SHIN = 43.0, 42.0
_REACH = 0.985 * (_THIGH + _SHIN)   # legs never lock fully straight: keeps the IK (and the knee axis) well defined
_ANKLE_H = 8.0                      # ankle height above the ground with the foot flat
_HEEL = np.array([0.0, -_ANKLE_H, -4.0])   # heel contact point relative to the ankle (foot frame)
_BALL = np.array([0.0, -7.0, 13.0])       # toe joint (ball of the foot) relative to the ankle
_STAND_Y = _ANKLE_H + 7.0 + _REACH - 0.5  # root height when standing with nearly straight legs
_G = 981.0                                # gravity, cm/s^2
_UPPER = [_J[n] for n in ("Spine", "Spine1", "Spine2", "Neck", "Head", "LeftShoulder", "RightShoulder",
                          "LeftArm", "RightArm", "LeftForeArm", "RightForeArm", "LeftHand", "RightHand")]


def builtin_skeleton() -> Skeleton:
    """The 22-joint humanoid every procedural clip uses (T-pose, Y up, facing +Z, cm, ZXY Euler for BVH)."""
    names = [n for n, _, _ in _JOINTS]
    parents = [-1 if p is None else _J[p] for _, p, _ in _JOINTS]
    offsets = np.array([o for _, _, o in _JOINTS], dtype=np.float64)
    end_sites = {_J[n]: np.array(o, dtype=np.float64) for n, o in _END_SITES.items()}
    return Skeleton(names=names, parents=parents, offsets=offsets, end_sites=end_sites,
                    rotation_orders=["ZXY"] * len(names))


# ----------------------------------------------------------------------------- small numpy helpers (pose building)

def _rx(a: np.ndarray) -> np.ndarray:
    a = np.radians(np.asarray(a, dtype=np.float64))
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(a.shape + (3, 3))


def _ry(a: np.ndarray) -> np.ndarray:
    a = np.radians(np.asarray(a, dtype=np.float64))
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(a.shape + (3, 3))


def _rz(a: np.ndarray) -> np.ndarray:
    a = np.radians(np.asarray(a, dtype=np.float64))
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(a.shape + (3, 3))


def _euler(angles: np.ndarray) -> np.ndarray:
    """(..., 3) degrees (z, x, y) -> R = Rz Rx Ry, the skeleton's own order."""
    return _rz(angles[..., 0]) @ _rx(angles[..., 1]) @ _ry(angles[..., 2])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _smooth(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _hermite(t: np.ndarray, kt: list[float], kv: list[float], kd: list[float] | None = None) -> np.ndarray:
    """Piecewise cubic Hermite through keys (times kt, values kv, slopes kd; 0 = ease in/out); held outside."""
    kt_a, kv_a = np.asarray(kt, float), np.asarray(kv, float)
    kd_a = np.zeros_like(kv_a) if kd is None else np.asarray(kd, float)
    i = np.clip(np.searchsorted(kt_a, t, side="right") - 1, 0, len(kt_a) - 2)
    h = kt_a[i + 1] - kt_a[i]
    s = np.clip((t - kt_a[i]) / np.maximum(h, 1e-9), 0.0, 1.0)
    s2, s3 = s * s, s * s * s
    return ((2 * s3 - 3 * s2 + 1) * kv_a[i] + (s3 - 2 * s2 + s) * h * kd_a[i]
            + (-2 * s3 + 3 * s2) * kv_a[i + 1] + (s3 - s2) * h * kd_a[i + 1])


def _wobble(rng: np.random.Generator, t: np.ndarray, shape: tuple[int, ...], amp: float,
            fmin: float = 0.15, fmax: float = 1.2) -> np.ndarray:
    """Smooth band-limited noise (sum of three random sinusoids) of shape (T, *shape)."""
    f = rng.uniform(fmin, fmax, size=shape + (3,))
    ph = rng.uniform(0, 2 * np.pi, size=shape + (3,))
    a = rng.normal(0.0, amp / np.sqrt(3.0), size=shape + (3,))
    return np.sum(a * np.sin(2 * np.pi * f * t.reshape((-1,) + (1,) * (len(shape) + 1)) + ph), axis=-1)


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


# ----------------------------------------------------------------------------- clip description

class _Clip:
    """What a clip kind specifies; ``_assemble`` turns it into joint rotations.

    Feet are given as ground references (point under the ankle of the flat foot), yaw and pitch (deg, + = toe up,
    pivoting on the heel; - = heel up, pivoting on the ball), plus the toe joint's global pitch.
    """

    def __init__(self, t: np.ndarray):
        n = len(t)
        self.t = t
        self.root_xz = np.zeros((n, 2))
        self.root_y = np.full(n, _STAND_Y)
        self.heading = np.zeros(n)           # deg, yaw of the character's path
        self.twist = np.zeros(n)             # pelvis yaw on top of heading
        self.lean = np.zeros(n)              # pelvis pitch (forward +)
        self.roll = np.zeros(n)
        self.sway = np.zeros(n)              # lateral root offset (toward the character's left +)
        self.foot_g = np.zeros((2, n, 3))    # [left, right]
        self.foot_yaw = np.zeros((2, n))
        self.foot_pitch = np.zeros((2, n))
        self.toe_pitch = np.zeros((2, n))
        self.local = np.zeros((n, len(_JOINTS), 3))  # extra local Euler (z, x, y) per upper-body joint, degrees
        # arm pose per side [left, right]: abduction (0 hanging, 90 T-pose), forward raise, twist, elbow flexion
        self.arm_abd = np.full((2, n), 8.0)
        self.arm_fwd = np.zeros((2, n))
        self.arm_twist = np.zeros((2, n))
        self.elbow = np.full((2, n), 12.0)


def _left_of(yaw_deg: np.ndarray) -> np.ndarray:
    y = np.radians(yaw_deg)
    return np.stack([np.cos(y), np.zeros_like(y), -np.sin(y)], -1)


def _fwd_of(yaw_deg: np.ndarray) -> np.ndarray:
    y = np.radians(yaw_deg)
    return np.stack([np.sin(y), np.zeros_like(y), np.cos(y)], -1)


def _ankle_and_rot(g: np.ndarray, yaw: np.ndarray, pitch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ankle position and foot global rotation from ground reference, yaw and pitch (pivot heel or ball)."""
    ryaw = _ry(yaw)
    rfoot = ryaw @ _rx(-pitch)
    flat_ankle = g + np.array([0.0, _ANKLE_H, 0.0])
    pivot_off = np.where((pitch > 0)[:, None], _HEEL, _BALL)                  # (T,3) in foot frame, from ankle
    pivot = flat_ankle + np.einsum("tij,tj->ti", ryaw, pivot_off)
    ankle = pivot - np.einsum("tij,tj->ti", rfoot, pivot_off)
    return ankle, rfoot


def _assemble(c: _Clip) -> tuple[np.ndarray, np.ndarray]:
    """Local rotation matrices (T,J,3,3) and root positions (T,3) for a clip description."""
    n, nj = len(c.t), len(_JOINTS)
    offsets = builtin_skeleton().offsets
    r_root = _ry(c.heading + c.twist) @ _rx(c.lean) @ _rz(c.roll)
    left = _left_of(c.heading)
    root = np.stack([c.root_xz[:, 0], np.zeros(n), c.root_xz[:, 1]], -1) + c.sway[:, None] * left

    legs = []
    u_bounds = []
    for side, (hip_j, foot_sign) in enumerate(((_J["LeftUpLeg"], 1.0), (_J["RightUpLeg"], -1.0))):
        ankle, rfoot = _ankle_and_rot(c.foot_g[side], c.foot_yaw[side], c.foot_pitch[side])
        hip_off = np.einsum("tij,j->ti", r_root, offsets[hip_j])
        dxz = np.hypot(root[:, 0] + hip_off[:, 0] - ankle[:, 0], root[:, 2] + hip_off[:, 2] - ankle[:, 2])
        dxz = np.minimum(dxz, 0.97 * _REACH)
        u_bounds.append(ankle[:, 1] - hip_off[:, 1] + np.sqrt(_REACH ** 2 - dxz ** 2))
        legs.append((hip_j, foot_sign, ankle, rfoot, hip_off))
    # soft minimum (always <= the hard one): the root never asks more of a leg than it can reach, and stays smooth.
    k = 1.0
    stack = np.stack([c.root_y] + u_bounds)
    m = stack.min(0)
    root[:, 1] = m - k * np.log(np.exp(-(stack - m) / k).sum(0))

    local = np.broadcast_to(np.eye(3), (n, nj, 3, 3)).copy()
    local[:, 0] = r_root
    ups = _UPPER
    local[:, ups] = _euler(c.local[:, ups])
    for side, (arm, fore, sgn) in enumerate(((_J["LeftArm"], _J["LeftForeArm"], 1.0),
                                             (_J["RightArm"], _J["RightForeArm"], -1.0))):
        r_arm = _rx(-c.arm_fwd[side]) @ _rz(sgn * (c.arm_abd[side] - 90.0)) @ _rx(c.arm_twist[side])
        local[:, arm] = r_arm @ local[:, arm]
        local[:, fore] = _ry(-sgn * c.elbow[side]) @ local[:, fore]

    for side, (hip_j, foot_sign, ankle, rfoot, hip_off) in enumerate(legs):
        hip = root + hip_off
        d = ankle - hip
        dist = np.linalg.norm(d, axis=-1)
        dhat = d / np.maximum(dist, 1e-9)[:, None]
        dist = np.clip(dist, abs(_THIGH - _SHIN) + 1e-3, (_THIGH + _SHIN) * 0.9999)
        pole = _fwd_of(c.foot_yaw[side]) + 0.08 * foot_sign * _left_of(c.foot_yaw[side])
        nrm = _unit(pole - np.sum(pole * dhat, -1, keepdims=True) * dhat)
        x = (_THIGH ** 2 - _SHIN ** 2 + dist ** 2) / (2 * dist)
        h = np.sqrt(np.maximum(_THIGH ** 2 - x ** 2, 0.0))
        knee = hip + x[:, None] * dhat + h[:, None] * nrm
        foot_pos = hip + dist[:, None] * dhat
        lat = _unit(np.cross(nrm, dhat))

        def frame(bone: np.ndarray) -> np.ndarray:
            yv = -_unit(bone)
            return np.stack([lat, yv, np.cross(lat, yv)], -1)   # columns: rest X, Y, Z -> world

        r_thigh = frame(knee - hip)
        r_shin = frame(foot_pos - knee)
        r_toe = _ry(c.foot_yaw[side]) @ _rx(-c.toe_pitch[side])
        local[:, hip_j] = np.swapaxes(r_root, -1, -2) @ r_thigh
        local[:, hip_j + 1] = np.swapaxes(r_thigh, -1, -2) @ r_shin
        local[:, hip_j + 2] = np.swapaxes(r_shin, -1, -2) @ rfoot
        local[:, hip_j + 3] = np.swapaxes(rfoot, -1, -2) @ r_toe
    return local, root


# ----------------------------------------------------------------------------- clip kinds

def _upper_noise(c: _Clip, rng: np.random.Generator, amp: float) -> None:
    c.local[:, _UPPER] += _wobble(rng, c.t, (len(_UPPER), 3), amp)


def _stance(c: _Clip, rng: np.random.Generator, width: float, toe_out: float, heading: float,
            origin: np.ndarray) -> None:
    """Both feet planted either side of ``origin`` (xz) facing ``heading``."""
    left = _left_of(np.array([heading]))[0]
    for side, sgn in enumerate((1.0, -1.0)):
        p = np.array([origin[0], 0.0, origin[1]]) + sgn * width * left
        c.foot_g[side] = p + rng.normal(0, 0.8, 3) * np.array([1.0, 0.0, 1.0])
        c.foot_yaw[side] = heading + sgn * toe_out
        c.toe_pitch[side] = 0.0
    c.heading[:] = heading
    c.root_xz[:] = origin


def _locomotion(c: _Clip, rng: np.random.Generator, run: bool) -> None:
    t = c.t
    if run:
        f, stride, duty = _u(rng, 1.25, 1.5), _u(rng, 200, 280), _u(rng, 0.32, 0.40)
        clear, heel, toe_off, turn_max = _u(rng, 16, 30), _u(rng, 0, 10), _u(rng, 25, 45), 12.0
    else:
        f, stride, duty = _u(rng, 0.8, 1.05), _u(rng, 105, 150), _u(rng, 0.58, 0.64)
        clear, heel, toe_off, turn_max = _u(rng, 6, 12), _u(rng, 8, 20), _u(rng, 20, 35), 20.0
    v = f * stride
    width, toe_out = _u(rng, 6, 11), _u(rng, 0, 12)
    psi0 = _u(rng, -180, 180)
    omega = 0.0 if rng.random() < 0.3 else _u(rng, -turn_max, turn_max)
    start = rng.uniform(-60, 60, 2)
    phase0 = rng.random()

    def path(tt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        psi = psi0 + omega * tt
        if abs(omega) < 1e-6:
            dx = v * tt * np.sin(np.radians(psi0))
            dz = v * tt * np.cos(np.radians(psi0))
        else:
            w = np.radians(omega)
            dx = v / w * (np.cos(np.radians(psi0)) - np.cos(np.radians(psi)))
            dz = v / w * (np.sin(np.radians(psi)) - np.sin(np.radians(psi0)))
        return np.stack([start[0] + dx, start[1] + dz], -1), psi

    c.root_xz, c.heading = path(t)
    ph_l = f * t + phase0
    for side, (sgn, off) in enumerate(((1.0, 0.0), (-1.0, 0.5 + rng.normal(0, 0.01)))):
        cyc = ph_l + off
        k = np.floor(cyc)
        p = cyc - k

        def plant(kk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            tm = (kk - phase0 - off + duty / 2) / f
            xz, psi = path(tm)
            g = np.stack([xz[:, 0], np.zeros_like(tm), xz[:, 1]], -1) + sgn * width * _left_of(psi)
            return g, psi + sgn * toe_out

        g0, y0 = plant(k)
        g1, y1 = plant(k + 1)
        stance = p < duty
        q = p / duty
        s = np.clip((p - duty) / (1 - duty), 0, 1)
        ss = _smooth(s)
        lift = clear * np.sin(np.pi * s ** (0.7 if run else 0.9))
        g = np.where(stance[:, None], g0, g0 + (g1 - g0) * ss[:, None])
        g[:, 1] = np.where(stance, 0.0, lift)
        c.foot_g[side] = g
        c.foot_yaw[side] = np.where(stance, y0, y0 + (y1 - y0) * ss)
        pitch_stance = heel * (1 - _smooth(q / 0.15)) - toe_off * _smooth((q - 0.6) / 0.4)
        pitch_swing = -toe_off + (heel + toe_off) * _smooth(s / 0.85)
        c.foot_pitch[side] = np.where(stance, pitch_stance, pitch_swing)
        relax = _smooth(s / 0.3)
        c.toe_pitch[side] = np.where(stance, np.maximum(pitch_stance, 0.0),
                                     (1 - relax) * np.maximum(pitch_swing, 0.0) + relax * pitch_swing)

    wl = 2 * np.pi * (ph_l - duty / 2)          # left mid-stance at wl = 0
    w2 = 2 * np.pi * ph_l                        # left heel strike at 0
    if run:
        c.root_y = _STAND_Y - _u(rng, 3, 8) - _u(rng, 2, 5) * np.cos(2 * wl)
        c.lean = _u(rng, 6, 14) + _u(rng, 0, 2) * np.cos(2 * wl)
    else:
        c.root_y = np.full(len(t), _STAND_Y - _u(rng, 0, 2))
        c.lean = _u(rng, 1, 6) + np.zeros(len(t))
    c.sway = _u(rng, 1, 4) * np.cos(wl) * (0.4 if run else 1.0)
    tw = _u(rng, 3, 8)
    c.twist = -tw * np.cos(w2)
    c.roll = _u(rng, 1, 4) * np.sin(wl)
    for j in ("Spine", "Spine1", "Spine2"):
        c.local[:, _J[j], 2] += 0.3 * tw * np.cos(w2)        # shoulders counter-rotate the pelvis
    c.local[:, _J["Neck"], 1] -= 0.4 * c.lean
    c.local[:, _J["Head"], 1] -= 0.3 * c.lean
    swing = _u(rng, 20, 40) if run else _u(rng, 10, 28)
    for side, sgn in enumerate((1.0, -1.0)):
        c.arm_abd[side] = _u(rng, 8, 18) if run else _u(rng, 5, 12)
        c.arm_fwd[side] = (15.0 if run else 3.0) - sgn * swing * np.cos(w2)
        c.elbow[side] = (_u(rng, 70, 95) if run else _u(rng, 10, 30)) - sgn * 0.3 * swing * np.cos(w2)
    _upper_noise(c, rng, _u(rng, 0.5, 2.0))


def _jump(c: _Clip, rng: np.random.Generator) -> None:
    t = c.t
    heading = _u(rng, -180, 180)
    fwd = _fwd_of(np.array([heading]))[0]
    width, toe_out = _u(rng, 8, 12), _u(rng, 0, 12)
    kt: dict[str, list[float]] = {k: [] for k in ("ry", "rf", "lean", "arm", "elbow", "pitch")}
    kd: dict[str, list[float]] = {k: [] for k in kt}
    keys_t: list[float] = []
    flights: list[tuple[float, float, float, float]] = []   # (takeoff, landing, start offset, distance)

    def key(time: float, **vals: tuple[float, float]) -> None:
        keys_t.append(time)
        for name in kt:
            v, d = vals.get(name, (kt[name][-1] if kt[name] else 0.0, 0.0))
            kt[name].append(v)
            kd[name].append(d)

    t0 = -_u(rng, 0.0, 1.0)
    base = 0.0
    time = t0
    key(time, ry=(_STAND_Y, 0), rf=(0, 0), lean=(0, 0), arm=(0, 0), elbow=(12, 0), pitch=(0, 0))
    while time < t[-1] + 0.1:
        crouch, hj, dist = _u(rng, 15, 30), _u(rng, 12, 38), (0.0 if rng.random() < 0.35 else _u(rng, 15, 70))
        v0 = np.sqrt(2 * _G * hj)
        tf = 2 * v0 / _G
        vz = dist / tf
        y_to = _STAND_Y + 3.0
        time += _u(rng, 0.15, 0.5)
        key(time, ry=(_STAND_Y, 0), rf=(base, 0), lean=(0, 0), arm=(0, 0), elbow=(12, 0), pitch=(0, 0))
        time += _u(rng, 0.35, 0.55)
        key(time, ry=(_STAND_Y - crouch, 0), rf=(base - 0.25 * crouch, 0), lean=(_u(rng, 15, 30), 0),
            arm=(-_u(rng, 30, 55), 0), elbow=(25, 0), pitch=(0, 0))
        time += _u(rng, 0.18, 0.26)
        takeoff = time
        key(time, ry=(y_to, v0), rf=(base + 3, vz), lean=(2, 0), arm=(_u(rng, 90, 150), 0), elbow=(10, 0),
            pitch=(-_u(rng, 25, 40), 0))
        time += tf
        flights.append((takeoff, time, base, dist))
        key(time, ry=(y_to, -v0), rf=(base + 3 + dist, vz), lean=(5, 0), arm=(_u(rng, 40, 90), 0), elbow=(15, 0),
            pitch=(-_u(rng, 5, 15), 0))
        base += dist
        time += _u(rng, 0.15, 0.25)
        key(time, ry=(_STAND_Y - _u(rng, 10, 22), 0), rf=(base + 1, 0), lean=(_u(rng, 8, 20), 0),
            arm=(_u(rng, 10, 30), 0), elbow=(20, 0), pitch=(0, 0))
        time += _u(rng, 0.3, 0.5)
        key(time, ry=(_STAND_Y, 0), rf=(base, 0), lean=(0, 0), arm=(0, 0), elbow=(12, 0), pitch=(0, 0))

    keys = np.array(keys_t)
    ry = _hermite(t, keys, kt["ry"], kd["ry"])
    rf = _hermite(t, keys, kt["rf"], kd["rf"])
    c.root_y = ry
    c.root_xz = np.array([0.0, 0.0]) + rf[:, None] * fwd[[0, 2]]
    c.heading[:] = heading
    c.lean = _hermite(t, keys, kt["lean"])
    left = _left_of(np.array([heading]))[0]
    pitch = _hermite(t, keys, kt["pitch"])
    # feet: planted at the running base offset; in flight they travel with the root and tuck a little
    plant_f = np.zeros(len(t))
    lift = np.zeros(len(t))
    for takeoff, landing, b, dist in flights:
        plant_f = np.where(t >= landing, b + dist, plant_f)
        inside = (t > takeoff) & (t < landing)
        s = (t - takeoff) / (landing - takeoff)
        plant_f = np.where(inside, b + dist * _smooth(s), plant_f)
        tuck = _u(rng, 4, 14)
        lift = np.where(inside, np.maximum(ry - (_STAND_Y + 3.0), 0) + tuck * np.sin(np.pi * np.clip(s, 0, 1)), lift)
    for side, sgn in enumerate((1.0, -1.0)):
        g = plant_f[:, None] * fwd + sgn * width * left
        g[:, 1] = lift
        c.foot_g[side] = g
        c.foot_yaw[side] = heading + sgn * toe_out
        c.foot_pitch[side] = pitch
        c.toe_pitch[side] = np.where(lift > 0, pitch, np.maximum(pitch, 0))
    c.local[:, _J["Spine1"], 1] += 0.3 * c.lean
    c.local[:, _J["Neck"], 1] -= 0.6 * c.lean
    arm = _hermite(t, keys, kt["arm"])
    for side in range(2):
        c.arm_fwd[side] = arm
        c.arm_abd[side] = 8.0 + 0.1 * np.abs(arm)
        c.elbow[side] = _hermite(t, keys, kt["elbow"])
    _upper_noise(c, rng, _u(rng, 0.5, 1.5))


def _idle_base(c: _Clip, rng: np.random.Generator, width: tuple[float, float] = (8, 12)) -> None:
    heading = _u(rng, -180, 180)
    _stance(c, rng, _u(rng, *width), _u(rng, 0, 15), heading,
            rng.uniform(-50, 50, 2))
    t = c.t
    c.sway = _u(rng, 0.5, 3) * np.sin(2 * np.pi * _u(rng, 0.1, 0.35) * t + _u(rng, 0, 6.3))
    c.root_y = _STAND_Y - _u(rng, 0, 2.5) + 0.4 * np.sin(2 * np.pi * _u(rng, 0.2, 0.35) * t)
    c.twist = _u(rng, -8, 8) + _wobble(rng, t, (), 2.0, 0.05, 0.3)
    c.roll = 1.5 * np.sin(2 * np.pi * _u(rng, 0.1, 0.35) * t)
    c.local[:, _J["Spine1"], 1] += 1.0 * np.sin(2 * np.pi * _u(rng, 0.2, 0.35) * t)   # breathing
    c.local[:, _J["Head"], 2] += _u(rng, 0, 25) * np.sin(2 * np.pi * _u(rng, 0.05, 0.25) * t + _u(rng, 0, 6.3))
    for side in range(2):
        c.arm_abd[side] = _u(rng, 5, 14) + _wobble(rng, t, (), 2.0)
        c.arm_fwd[side] = _u(rng, -5, 10) + _wobble(rng, t, (), 3.0)
        c.elbow[side] = _u(rng, 8, 25)


def _idle(c: _Clip, rng: np.random.Generator) -> None:
    _idle_base(c, rng)
    _upper_noise(c, rng, _u(rng, 1.0, 3.0))


def _wave(c: _Clip, rng: np.random.Generator) -> None:
    _idle_base(c, rng)
    t = c.t
    side = int(rng.integers(2))
    if rng.random() < 0.5:      # raise the arm during the clip, otherwise it is already up
        t_up = _u(rng, 0.0, max(t[-1] / 3, 0.1))
        w = _smooth((t - t_up) / _u(rng, 0.35, 0.6))
    else:
        w = np.ones(len(t))
    fw = _u(rng, 1.5, 3.0)
    amp = _u(rng, 15, 35)
    wave_abd, wave_fwd = _u(rng, 95, 140), _u(rng, -10, 30)
    wave_twist, wave_elbow = -90 + _u(rng, -15, 15), _u(rng, 60, 100)
    osc = amp * np.sin(2 * np.pi * fw * t + _u(rng, 0, 6.3))
    c.arm_abd[side] = (1 - w) * c.arm_abd[side] + w * wave_abd
    c.arm_fwd[side] = (1 - w) * c.arm_fwd[side] + w * wave_fwd
    c.arm_twist[side] = w * wave_twist
    c.elbow[side] = (1 - w) * c.elbow[side] + w * (wave_elbow + osc)
    hand = _J["LeftHand"] if side == 0 else _J["RightHand"]
    c.local[:, hand, 0] += w * 0.4 * osc
    c.roll = c.roll + w * (2.0 if side == 1 else -2.0)
    _upper_noise(c, rng, _u(rng, 0.5, 2.0))


def _squat(c: _Clip, rng: np.random.Generator) -> None:
    t = c.t
    heading = _u(rng, -180, 180)
    _stance(c, rng, _u(rng, 13, 18), _u(rng, 10, 25), heading, rng.uniform(-50, 50, 2))
    fwd = _fwd_of(np.array([heading]))[0]
    period = _u(rng, 1.8, 3.2)
    depth = _u(rng, 25, 45)
    lean = _u(rng, 20, 35)
    arms = _u(rng, 50, 95)
    t0 = -_u(rng, 0, period)
    ph = np.mod(t - t0, period) / period
    down = _smooth(ph / 0.4) * (1 - _smooth((ph - 0.55) / 0.35))
    c.root_y = _STAND_Y - 0.5 - depth * down
    c.root_xz = c.root_xz - (0.3 * depth * down)[:, None] * fwd[[0, 2]]
    c.lean = lean * down
    c.local[:, _J["Spine1"], 1] += 0.2 * lean * down
    c.local[:, _J["Neck"], 1] -= 0.5 * lean * down
    c.local[:, _J["Head"], 1] -= 0.3 * lean * down
    for side in range(2):
        c.arm_fwd[side] = arms * down - 0.3 * c.lean
        c.arm_abd[side] = 8.0
        c.elbow[side] = 10 + 10 * down
    _upper_noise(c, rng, _u(rng, 0.5, 1.5))


_BUILDERS = {"walk": lambda c, r: _locomotion(c, r, run=False), "run": lambda c, r: _locomotion(c, r, run=True),
             "jump": _jump, "wave": _wave, "squat": _squat, "idle": _idle}


# ----------------------------------------------------------------------------- public API

def _rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)


def clip_arrays(kind: str, n_frames: int, fps: float = 30.0,
                rng: np.random.Generator | int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Local rotation matrices (T,J,3,3) and root positions (T,3) of one clip (numpy; no torch needed)."""
    if kind not in _BUILDERS:
        raise ValueError(f"unknown clip kind {kind!r}; choose from {', '.join(KINDS)}")
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    t = np.arange(int(n_frames), dtype=np.float64) / float(fps)
    c = _Clip(t)
    _BUILDERS[kind](c, _rng(rng))
    return _assemble(c)


def generate_clip(kind: str, n_frames: int = 128, fps: float = 30.0,
                  rng: np.random.Generator | int | None = None):
    """One procedural clip as a float64 :class:`modi.data.motion.Motion` on :func:`builtin_skeleton`.

    ``rng`` is a Generator (consumed) or a seed; the same seed gives the same clip.
    """
    local, root = clip_arrays(kind, n_frames, fps, rng)
    q = quat_normalize(matrix_to_quat(torch.from_numpy(local)))
    q = quat_canonical(q)
    return Motion(skeleton=builtin_skeleton(), rotations=q, root_positions=torch.from_numpy(root), fps=float(fps))


def write_dataset(out_dir: str | Path, n_clips: int = 32, frames: int = 128, seed: int = 0, fps: float = 30.0,
                  kinds: list[str] | tuple[str, ...] | None = None) -> list[Path]:
    """Write ``n_clips`` BVH files (kinds in turn) and ``labels.json`` ({file name: kind}) into ``out_dir``.

    Clip ``i`` is drawn from ``default_rng([seed, i])``, so a clip does not depend on how many others are written,
    and equals ``generate_clip(kind, frames, fps, np.random.default_rng([seed, i]))``. All clips' Euler angles
    are converted in one batched call: thousands of tiny torch calls would cost more than the generation.
    """
    kinds = tuple(KINDS if kinds is None else kinds)
    bad = [k for k in kinds if k not in _BUILDERS]
    if bad or not kinds:
        raise ValueError(f"unknown clip kind(s) {bad}; choose from {', '.join(KINDS)}")
    if int(n_clips) < 1:
        raise ValueError(f"n_clips must be >= 1, got {n_clips}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sk = builtin_skeleton()
    names = [kinds[i % len(kinds)] for i in range(int(n_clips))]
    arrays = [clip_arrays(kind, frames, fps, np.random.default_rng([int(seed), i])) for i, kind in enumerate(names)]
    local = torch.from_numpy(np.stack([a[0] for a in arrays]))
    orders = set(sk.rotation_orders)
    if len(orders) != 1:   # pragma: no cover - the built-in skeleton uses one order
        raise AssertionError("built-in skeleton must use one Euler order")
    order = orders.pop()
    euler = matrix_to_euler(local, order).numpy()                          # (N, T, J, 3)
    rot_channels = [f"{axis}rotation" for axis in order]
    channels = [["Xposition", "Yposition", "Zposition"] + rot_channels] + [rot_channels] * (sk.n_joints - 1)
    paths, labels = [], {}
    for i, kind in enumerate(names):
        motion = np.concatenate([arrays[i][1], euler[i].reshape(euler.shape[1], -1)], axis=1)
        b = bvh_io.Bvh(names=list(sk.names), parents=list(sk.parents), offsets=sk.offsets, channels=channels,
                       end_sites=dict(sk.end_sites), frame_time=1.0 / float(fps), motion=motion)
        path = save_motion(b, out / f"{i:04d}_{kind}.bvh", precision=4)
        paths.append(path)
        labels[path.name] = kind
    (out / "labels.json").write_text(json.dumps(labels, indent=1, sort_keys=True) + "\n")
    return paths
