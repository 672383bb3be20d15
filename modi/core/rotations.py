"""All rotation math in one torch module: quaternions, matrices, 6D, Euler angles, axis-angle.

Conventions (shared by the whole package):

* Quaternions are ``(w, x, y, z)``; every function broadcasts over leading dimensions.
* Matrices rotate column vectors (``v' = R @ v``); ``quat_to_matrix(q) @ v == quat_apply(q, v)``.
* 6D is the first two *columns* of the matrix, ``[c0, c1]`` (Zhou et al. 2019); ``layout="rows"`` selects the
  first two *rows* ``[r0, r1]`` instead (the GANimator authors' code). Both decode with the same Gram-Schmidt (a
  rows vector is the columns vector of the transposed matrix), and both round-trip a rotation exactly.
* Euler ``order`` is the BVH channel order and is *intrinsic*: ``"ZXY"`` means
  ``R = Rz(a[..., 0]) @ Rx(a[..., 1]) @ Ry(a[..., 2])`` — the same as scipy's uppercase
  ``Rotation.from_euler("ZXY", a)``.

Everything is differentiable and NaN-free at the identity (and at small angles): functions with
a removable singularity (slerp, axis-angle) switch to a series expansion there, and the branches
that are not used are fed safe inputs so their gradients are finite (the "double where" trick).
"""
from __future__ import annotations

import torch
from torch import Tensor

from modi_ext.fk.reference import quat_apply, quat_mul

__all__ = [
    "EULER_ORDERS",
    "SIXD_LAYOUTS",
    "quat_normalize",
    "quat_canonical",
    "quat_mul",
    "quat_conjugate",
    "quat_inverse",
    "quat_apply",
    "quat_to_matrix",
    "matrix_to_quat",
    "matrix_to_6d",
    "sixd_to_matrix",
    "quat_to_6d",
    "sixd_to_quat",
    "euler_to_matrix",
    "matrix_to_euler",
    "euler_to_quat",
    "quat_to_euler",
    "quat_slerp",
    "quat_identity",
    "axis_angle_to_quat",
    "quat_to_axis_angle",
    "axis_angle_to_matrix",
    "quat_angle",
    "quat_between",
    "quat_unflip",
]

EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
_AXIS = {"X": 0, "Y": 1, "Z": 2}


def _check_last(x: Tensor, n: int, name: str, what: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"{name}: expected {what} with last dimension {n}, got shape {tuple(x.shape)}")


def _check_matrix(m: Tensor, name: str) -> None:
    if not isinstance(m, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(m).__name__}")
    if m.ndim < 2 or m.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: expected rotation matrices of shape (..., 3, 3), got {tuple(m.shape)}")


def _check_order(order: str) -> str:
    if not isinstance(order, str) or order.upper() not in EULER_ORDERS:
        raise ValueError(f"Euler order must be one of {', '.join(EULER_ORDERS)}, got {order!r}")
    return order.upper()


def _tiny(x: Tensor) -> float:
    return float(torch.finfo(x.dtype).eps) if x.is_floating_point() else 1e-12


# ----------------------------------------------------------------------------------------- quaternions


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Scale to unit length; a zero quaternion stays finite (returned unchanged) instead of NaN."""
    _check_last(q, 4, "quat_normalize", "quaternions")
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(eps)


def quat_canonical(q: Tensor) -> Tensor:
    """Pick the representative with ``w >= 0`` (q and -q are the same rotation)."""
    _check_last(q, 4, "quat_canonical", "quaternions")
    return torch.where(q[..., :1] < 0, -q, q)


def quat_conjugate(q: Tensor) -> Tensor:
    _check_last(q, 4, "quat_conjugate", "quaternions")
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_inverse(q: Tensor) -> Tensor:
    """True inverse (conjugate / |q|^2), so it is also right for non-unit quaternions."""
    _check_last(q, 4, "quat_inverse", "quaternions")
    return quat_conjugate(q) / (q * q).sum(-1, keepdim=True).clamp_min(1e-24)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    # Explicit components: broadcasts freely (torch.linalg.cross needs equal batch shapes on older torch).
    ax, ay, az = a.unbind(-1)
    bx, by, bz = b.unbind(-1)
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), dim=-1)


def quat_identity(shape: int | tuple[int, ...] | torch.Size = (), dtype: torch.dtype | None = None,
                  device: torch.device | str | None = None) -> Tensor:
    """Identity quaternions of shape ``(*shape, 4)``."""
    if isinstance(shape, int):
        shape = (shape,)
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def quat_unflip(q: Tensor, dim: int = 0) -> Tensor:
    """Flip signs along ``dim`` (time) so consecutive quaternions have a non-negative dot product.

    q and -q are the same rotation, but learned models and linear filters want the continuous choice.
    The first element keeps its sign.
    """
    _check_last(q, 4, "quat_unflip", "quaternions")
    dim = dim % q.ndim
    if dim == q.ndim - 1:
        raise ValueError("quat_unflip: dim must not be the quaternion dimension")
    n = q.shape[dim]
    if n < 2:
        return q
    dots = (q.narrow(dim, 1, n - 1) * q.narrow(dim, 0, n - 1)).sum(-1, keepdim=True)
    flips = torch.cumsum((dots < 0).to(torch.int64), dim=dim) % 2
    first = torch.zeros_like(flips.narrow(dim, 0, 1))
    sign = 1 - 2 * torch.cat((first, flips), dim=dim)
    return q * sign.to(q.dtype)


def quat_angle(q: Tensor) -> Tensor:
    """Rotation angle in radians, in [0, pi] (sign-invariant); NaN-free gradient away from the identity."""
    _check_last(q, 4, "quat_angle", "quaternions")
    n = torch.linalg.vector_norm(q[..., 1:], dim=-1)
    return 2.0 * torch.atan2(n, q[..., 0].abs())


# ----------------------------------------------------------------------------------------- matrices


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)``; non-unit input is normalised implicitly (s = 2/|q|^2)."""
    _check_last(q, 4, "quat_to_matrix", "quaternions")
    w, x, y, z = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1).clamp_min(1e-24)
    xx, yy, zz = x * x * s, y * y * s, z * z * s
    xy, xz, yz = x * y * s, x * z * s, y * z * s
    wx, wy, wz = w * x * s, w * y * s, w * z * s
    m = torch.stack(
        (
            1.0 - (yy + zz), xy - wz, xz + wy,
            xy + wz, 1.0 - (xx + zz), yz - wx,
            xz - wy, yz + wx, 1.0 - (xx + yy),
        ),
        dim=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(m: Tensor) -> Tensor:
    """Unit quaternions (canonical, w >= 0) from rotation matrices, robust at every angle.

    Shepperd's method: of the four algebraically equivalent formulas, use the one whose square
    root argument is largest (always >= 1 for a rotation), so nothing is divided by a small number.
    The unused branches get a clamped argument so their (discarded) gradients stay finite.
    """
    _check_matrix(m, "matrix_to_quat")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 w^2, 4 x^2, 4 y^2, 4 z^2 (for an exact rotation)
    v = torch.stack(
        (
            1.0 + m00 + m11 + m22,
            1.0 + m00 - m11 - m22,
            1.0 - m00 + m11 - m22,
            1.0 - m00 - m11 + m22,
        ),
        dim=-1,
    )
    r = 2.0 * torch.sqrt(v.clamp_min(0.1))  # r_i = 4 * |component i|; >= 2 on the chosen branch
    d21, d02, d10 = m21 - m12, m02 - m20, m10 - m01
    s01, s02, s12 = m01 + m10, m02 + m20, m12 + m21
    rw, rx, ry, rz = r.unbind(-1)
    cand = torch.stack(
        (
            torch.stack((rw * 0.25, d21 / rw, d02 / rw, d10 / rw), dim=-1),
            torch.stack((d21 / rx, rx * 0.25, s01 / rx, s02 / rx), dim=-1),
            torch.stack((d02 / ry, s01 / ry, ry * 0.25, s12 / ry), dim=-1),
            torch.stack((d10 / rz, s02 / rz, s12 / rz, rz * 0.25), dim=-1),
        ),
        dim=-2,
    )  # (..., 4 branches, 4 components)
    best = v.argmax(dim=-1, keepdim=True)  # (..., 1)
    q = torch.gather(cand, -2, best.unsqueeze(-1).expand(best.shape[:-1] + (1, 4))).squeeze(-2)
    return quat_canonical(quat_normalize(q))


SIXD_LAYOUTS = ("columns", "rows")


def _check_layout(layout: str) -> str:
    if layout not in SIXD_LAYOUTS:
        raise ValueError(f"6D layout must be 'columns' or 'rows', got {layout!r}")
    return layout


def matrix_to_6d(m: Tensor, *, layout: str = "columns") -> Tensor:
    """First two columns ``[c0, c1]`` (or, with ``layout="rows"``, first two rows ``[r0, r1]``) -> ``(..., 6)``."""
    _check_matrix(m, "matrix_to_6d")
    if _check_layout(layout) == "rows":
        return torch.cat((m[..., 0, :], m[..., 1, :]), dim=-1)
    return torch.cat((m[..., :, 0], m[..., :, 1]), dim=-1)


def sixd_to_matrix(d6: Tensor, *, layout: str = "columns") -> Tensor:
    """Gram-Schmidt on the two stored columns (or rows); any (non-degenerate) 6-vector maps to a rotation."""
    _check_last(d6, 6, "sixd_to_matrix", "6D rotations")
    _check_layout(layout)
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / torch.linalg.vector_norm(a1, dim=-1, keepdim=True).clamp_min(1e-12)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / torch.linalg.vector_norm(a2, dim=-1, keepdim=True).clamp_min(1e-12)
    b3 = _cross(b1, b2)
    # the third row of a rotation is the cross product of the first two, as its third column is of the first two
    return torch.stack((b1, b2, b3), dim=-2 if layout == "rows" else -1)


def quat_to_6d(q: Tensor, *, layout: str = "columns") -> Tensor:
    return matrix_to_6d(quat_to_matrix(q), layout=layout)


def sixd_to_quat(d6: Tensor, *, layout: str = "columns") -> Tensor:
    return matrix_to_quat(sixd_to_matrix(d6, layout=layout))


# ----------------------------------------------------------------------------------------- Euler


def _axis_matrix(axis: int, c: Tensor, s: Tensor) -> Tensor:
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    if axis == 0:
        rows = (one, zero, zero, zero, c, -s, zero, s, c)
    elif axis == 1:
        rows = (c, zero, s, zero, one, zero, -s, zero, c)
    else:
        rows = (c, -s, zero, s, c, zero, zero, zero, one)
    return torch.stack(rows, dim=-1).reshape(c.shape + (3, 3))


def _axis_quat(axis: int, c: Tensor, s: Tensor) -> Tensor:
    """Quaternion of a turn about ``axis`` given cos and sin of the *half* angle."""
    zero = torch.zeros_like(c)
    comps = [c, zero, zero, zero]
    comps[axis + 1] = s
    return torch.stack(comps, dim=-1)


def euler_to_matrix(angles: Tensor, order: str, degrees: bool = True) -> Tensor:
    """Intrinsic Euler angles ``(..., 3)`` in BVH channel ``order`` -> matrices ``(..., 3, 3)``."""
    order = _check_order(order)
    _check_last(angles, 3, "euler_to_matrix", "Euler angles")
    a = torch.deg2rad(angles) if degrees else angles
    c, s = torch.cos(a), torch.sin(a)  # one call each: sin/cos dominate on large batches
    m = _axis_matrix(_AXIS[order[0]], c[..., 0], s[..., 0])
    m = m @ _axis_matrix(_AXIS[order[1]], c[..., 1], s[..., 1])
    return m @ _axis_matrix(_AXIS[order[2]], c[..., 2], s[..., 2])


def euler_to_quat(angles: Tensor, order: str, degrees: bool = True) -> Tensor:
    """Intrinsic Euler angles -> unit quaternions (not sign-canonicalised: continuous in the angles)."""
    order = _check_order(order)
    _check_last(angles, 3, "euler_to_quat", "Euler angles")
    half = (torch.deg2rad(angles) if degrees else angles) * 0.5
    c, s = torch.cos(half), torch.sin(half)
    q = _axis_quat(_AXIS[order[0]], c[..., 0], s[..., 0])
    q = quat_mul(q, _axis_quat(_AXIS[order[1]], c[..., 1], s[..., 1]))
    return quat_mul(q, _axis_quat(_AXIS[order[2]], c[..., 2], s[..., 2]))


def matrix_to_euler(m: Tensor, order: str, degrees: bool = True) -> Tensor:
    """Matrices -> intrinsic Euler angles with the middle angle in [-90, 90], the others in (-180, 180].

    For ``R = Ri(a) Rj(b) Rk(c)`` with parity ``e`` (+1 for the cyclic orders XYZ/YZX/ZXY):
    ``sin b = e R[i,k]``, ``a = atan2(-e R[j,k], R[k,k])``, ``c = atan2(-e R[i,j], R[i,i])``.
    ``b`` uses atan2 against ``hypot(R[i,i], R[i,j]) = cos b``, which stays accurate near +-90
    where asin would not. At gimbal lock (cos b ~ 0) only a +- c is defined; like scipy we set c = 0.
    """
    order = _check_order(order)
    _check_matrix(m, "matrix_to_euler")
    i, j, k = (_AXIS[c] for c in order)
    e = 1.0 if (j - i) % 3 == 1 else -1.0
    rik = m[..., i, k]
    cb = torch.hypot(m[..., i, i], m[..., i, j])
    b = torch.atan2(e * rik, cb)
    a = torch.atan2(-e * m[..., j, k], m[..., k, k])
    c = torch.atan2(-e * m[..., i, j], m[..., i, i])
    lock = cb < 64 * _tiny(m)
    if bool(lock.any()):
        # R = Ri(a) Rj(+-90): column j of R is Ri(a) e_j = cos a e_j + e sin a e_k.
        a_lock = torch.atan2(e * m[..., k, j], m[..., j, j])
        a = torch.where(lock, a_lock, a)
        c = torch.where(lock, torch.zeros_like(c), c)
    out = torch.stack((a, b, c), dim=-1)
    return torch.rad2deg(out) if degrees else out


def quat_to_euler(q: Tensor, order: str, degrees: bool = True) -> Tensor:
    _check_last(q, 4, "quat_to_euler", "quaternions")
    return matrix_to_euler(quat_to_matrix(q), order, degrees)


# ----------------------------------------------------------------------------------------- interpolation, axis-angle


def quat_slerp(q0: Tensor, q1: Tensor, t: Tensor | float) -> Tensor:
    """Spherical linear interpolation along the shorter arc; ``t`` broadcasts (e.g. shape (..., 1) or scalar).

    Near-identical inputs fall back to normalised lerp, which is the limit and keeps gradients finite.
    """
    _check_last(q0, 4, "quat_slerp(q0)", "quaternions")
    _check_last(q1, 4, "quat_slerp(q1)", "quaternions")
    if not isinstance(t, Tensor):
        t = torch.tensor(t, dtype=q0.dtype, device=q0.device)
    else:
        t = t.to(q0.dtype)
    if t.ndim > 0 and t.shape[-1] != 1:
        t = t.unsqueeze(-1)  # t given per leading index, e.g. (T,) for (T, 4) quaternions
    d = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(d < 0, -q1, q1)
    d = d.abs()
    small = d > 1.0 - 1e-6
    d_safe = torch.where(small, torch.zeros_like(d), d).clamp(-1.0, 1.0)
    theta = torch.acos(d_safe)
    sin_theta = torch.sin(theta)
    w0 = torch.where(small, 1.0 - t, torch.sin((1.0 - t) * theta) / sin_theta)
    w1 = torch.where(small, t, torch.sin(t * theta) / sin_theta)
    return quat_normalize(w0 * q0 + w1 * q1)


def axis_angle_to_quat(aa: Tensor) -> Tensor:
    """Rotation vectors (axis * angle in radians) ``(..., 3)`` -> unit quaternions."""
    _check_last(aa, 3, "axis_angle_to_quat", "axis-angle vectors")
    a2 = (aa * aa).sum(-1, keepdim=True)
    small = a2 < 1e-8
    angle = torch.sqrt(torch.where(small, torch.ones_like(a2), a2))
    half = 0.5 * angle
    # sin(angle/2)/angle and cos(angle/2) with their Taylor series at 0
    k = torch.where(small, 0.5 - a2 / 48.0, torch.sin(half) / angle)
    w = torch.where(small, 1.0 - a2 / 8.0, torch.cos(half))
    return torch.cat((w, aa * k), dim=-1)


def quat_to_axis_angle(q: Tensor) -> Tensor:
    """Unit quaternions -> rotation vectors with angle in [0, pi]."""
    _check_last(q, 4, "quat_to_axis_angle", "quaternions")
    q = quat_canonical(q)
    w, v = q[..., :1], q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    small = n2 < 1e-12
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    angle = 2.0 * torch.atan2(n, w)
    w_safe = torch.where(small, w.clamp_min(1e-6), torch.ones_like(w))
    # angle / n -> 2/w * (1 - n^2/(3 w^2)) as n -> 0
    k = torch.where(small, 2.0 / w_safe * (1.0 - n2 / (3.0 * w_safe * w_safe)), angle / n)
    return v * k


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    return quat_to_matrix(axis_angle_to_quat(aa))


def quat_between(u: Tensor, v: Tensor) -> Tensor:
    """Shortest-arc unit quaternion rotating direction ``u`` onto direction ``v`` (both (..., 3)).

    Antiparallel inputs get a 180-degree turn about an axis perpendicular to ``u``.
    """
    _check_last(u, 3, "quat_between(u)", "vectors")
    _check_last(v, 3, "quat_between(v)", "vectors")
    u, v = torch.broadcast_tensors(u, v)
    un = u / torch.linalg.vector_norm(u, dim=-1, keepdim=True).clamp_min(1e-12)
    vn = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)
    w = 1.0 + (un * vn).sum(-1, keepdim=True)
    axis = _cross(un, vn)
    anti = w < 1e-6
    if bool(anti.any()):
        # any axis perpendicular to u: cross with the coordinate axis least aligned with u
        basis = torch.eye(3, dtype=u.dtype, device=u.device)[un.abs().argmin(-1)]
        perp = _cross(un, basis)
        perp = perp / torch.linalg.vector_norm(perp, dim=-1, keepdim=True).clamp_min(1e-12)
        axis = torch.where(anti, perp, axis)
        w = torch.where(anti, torch.zeros_like(w), w)
    return quat_normalize(torch.cat((w, axis), dim=-1))

