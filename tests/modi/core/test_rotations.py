"""modi.core.rotations against scipy.spatial.transform.Rotation, round trips, and gradients."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from modi.core import rotations as R

ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]
DTYPES = [torch.float32, torch.float64]


def tol(dtype):
    return 2e-5 if dtype == torch.float32 else 1e-10


def rand_quats(n, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return R.quat_normalize(torch.randn(n, 4, generator=g, dtype=torch.float64)).to(dtype)


def scipy_rot(q):  # (w,x,y,z) -> scipy (x,y,z,w)
    q = q.detach().double().numpy()
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_to_matrix_matches_scipy(dtype):
    q = rand_quats(500, dtype)
    m = R.quat_to_matrix(q)
    assert m.dtype == dtype and m.shape == (500, 3, 3)
    np.testing.assert_allclose(m.double().numpy(), scipy_rot(q).as_matrix(), atol=tol(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_matrix_to_quat_matches_scipy_and_is_canonical(dtype):
    q = rand_quats(500, dtype, seed=1)
    m = torch.from_numpy(scipy_rot(q).as_matrix()).to(dtype)
    q2 = R.matrix_to_quat(m)
    assert (q2[:, 0] >= 0).all()
    ref = scipy_rot(q).as_quat(canonical=True)[:, [3, 0, 1, 2]]
    np.testing.assert_allclose(q2.double().numpy(), ref, atol=5 * tol(dtype))


def test_matrix_to_quat_at_every_branch():
    """180-degree turns about each axis (trace -1) and the identity exercise all four Shepperd branches."""
    mats = np.stack([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])
    mats = np.concatenate([mats, Rotation.from_rotvec([[0, 0, 3.14159], [2.0, -1.0, 0.5]]).as_matrix()])
    q = R.matrix_to_quat(torch.from_numpy(mats))
    np.testing.assert_allclose(R.quat_to_matrix(q).numpy(), mats, atol=1e-12)
    np.testing.assert_allclose(q[:4].abs().numpy(), np.eye(4), atol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("order", ORDERS)
def test_euler_to_matrix_and_quat_match_scipy(order, dtype):
    g = torch.Generator().manual_seed(2)
    ang = (torch.rand(300, 3, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([180.0, 180.0, 180.0])
    ref = Rotation.from_euler(order, ang.numpy(), degrees=True)
    m = R.euler_to_matrix(ang.to(dtype), order)
    np.testing.assert_allclose(m.double().numpy(), ref.as_matrix(), atol=tol(dtype) * 5)
    q = R.euler_to_quat(ang.to(dtype), order)
    np.testing.assert_allclose(R.quat_to_matrix(q).double().numpy(), ref.as_matrix(), atol=tol(dtype) * 5)
    rad = R.euler_to_matrix(torch.deg2rad(ang).to(dtype), order, degrees=False)
    np.testing.assert_allclose(rad.double().numpy(), ref.as_matrix(), atol=tol(dtype) * 5)


@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_euler_matches_scipy(order):
    mats = Rotation.random(400, random_state=3).as_matrix()
    ang = R.matrix_to_euler(torch.from_numpy(mats), order)
    ref = Rotation.from_matrix(mats).as_euler(order, degrees=True)
    diff = (ang.numpy() - ref + 180.0) % 360.0 - 180.0  # +-180 are the same angle
    assert np.abs(diff).max() < 1e-8
    assert (ang[:, 1].abs() <= 90.0 + 1e-9).all()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("order", ORDERS)
def test_euler_round_trip_including_gimbal_lock(order, dtype):
    ang = torch.tensor(
        [[10.0, 20.0, 30.0], [-170.0, 80.0, 100.0], [45.0, 90.0, 0.0], [30.0, -90.0, 60.0], [0.0, 0.0, 0.0]],
        dtype=dtype,
    )
    m = R.euler_to_matrix(ang, order)
    back = R.matrix_to_euler(m, order)
    assert torch.isfinite(back).all()
    torch.testing.assert_close(R.euler_to_matrix(back, order), m, atol=50 * tol(dtype), rtol=0)
    torch.testing.assert_close(back[:2], ang[:2], atol=1e-3 if dtype == torch.float32 else 1e-9, rtol=0)
    q = R.euler_to_quat(ang, order)
    torch.testing.assert_close(R.euler_to_matrix(R.quat_to_euler(q, order), order), m, atol=50 * tol(dtype), rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_6d_round_trip_and_layout(dtype):
    q = rand_quats(200, dtype, seed=4)
    m = R.quat_to_matrix(q)
    d6 = R.matrix_to_6d(m)
    torch.testing.assert_close(d6[:, :3], m[:, :, 0])
    torch.testing.assert_close(d6[:, 3:], m[:, :, 1])
    torch.testing.assert_close(R.sixd_to_matrix(d6), m, atol=tol(dtype), rtol=0)
    torch.testing.assert_close(R.sixd_to_quat(R.quat_to_6d(q)), R.quat_canonical(q), atol=5 * tol(dtype), rtol=0)
    # an arbitrary 6-vector becomes a proper rotation
    raw = torch.randn(100, 6, dtype=dtype, generator=torch.Generator().manual_seed(5))
    mm = R.sixd_to_matrix(raw)
    eye = torch.eye(3, dtype=dtype).expand(100, 3, 3)
    torch.testing.assert_close(mm.transpose(-1, -2) @ mm, eye, atol=10 * tol(dtype), rtol=0)
    torch.testing.assert_close(torch.linalg.det(mm), torch.ones(100, dtype=dtype), atol=10 * tol(dtype), rtol=0)


def test_quat_algebra_matches_scipy():
    a, b = rand_quats(300, seed=6), rand_quats(300, seed=7)
    ab = R.quat_mul(a, b)
    np.testing.assert_allclose(R.quat_to_matrix(ab).numpy(), (scipy_rot(a) * scipy_rot(b)).as_matrix(), atol=1e-12)
    v = torch.randn(300, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(8))
    np.testing.assert_allclose(R.quat_apply(a, v).numpy(), scipy_rot(a).apply(v.numpy()), atol=1e-12)
    # broadcasting: one quaternion against many vectors
    np.testing.assert_allclose(R.quat_apply(a[:1], v).numpy(), scipy_rot(a[0]).apply(v.numpy()), atol=1e-12)
    ident = R.quat_identity((300,), dtype=torch.float64)
    torch.testing.assert_close(R.quat_canonical(R.quat_mul(a, R.quat_inverse(a))), ident, atol=1e-12, rtol=0)
    torch.testing.assert_close(R.quat_conjugate(a), R.quat_inverse(a), atol=1e-12, rtol=0)
    scaled = 3.0 * a  # inverse is a true inverse even for non-unit input
    torch.testing.assert_close(R.quat_mul(scaled, R.quat_inverse(scaled)), ident, atol=1e-12, rtol=0)


def test_canonical_and_normalize():
    q = torch.tensor([[-0.5, 0.5, -0.5, 0.5], [0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]])
    c = R.quat_canonical(q)
    torch.testing.assert_close(c[0], torch.tensor([0.5, -0.5, 0.5, -0.5]))
    n = R.quat_normalize(q)
    assert torch.isfinite(n).all()
    torch.testing.assert_close(n[2], torch.tensor([1.0, 0.0, 0.0, 0.0]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_slerp_matches_scipy(dtype):
    q0, q1 = rand_quats(50, seed=9), rand_quats(50, seed=10)
    ts = torch.tensor([0.0, 0.25, 0.5, 0.9, 1.0], dtype=torch.float64)
    for i in range(0, 50, 7):
        ref = Slerp([0.0, 1.0], scipy_rot(torch.stack([q0[i], q1[i]])))(ts.numpy()).as_matrix()
        got = R.quat_slerp(q0[i].to(dtype).expand(5, 4), q1[i].to(dtype).expand(5, 4), ts.to(dtype))
        np.testing.assert_allclose(R.quat_to_matrix(got).double().numpy(), ref, atol=10 * tol(dtype))
    # shorter arc: -q1 is the same rotation, so the result must be too
    mid = R.quat_slerp(q0, -q1, 0.5)
    np.testing.assert_allclose(R.quat_to_matrix(mid).numpy(), R.quat_to_matrix(R.quat_slerp(q0, q1, 0.5)).numpy(),
                               atol=1e-12)
    same = R.quat_slerp(q0, q0, 0.3)
    torch.testing.assert_close(same, q0, atol=1e-12, rtol=0)


def test_axis_angle_matches_scipy():
    rv = torch.randn(300, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(11))
    rv = rv / rv.norm(dim=-1, keepdim=True) * torch.rand(300, 1, dtype=torch.float64) * 3.1
    q = R.axis_angle_to_quat(rv)
    np.testing.assert_allclose(R.quat_to_matrix(q).numpy(), Rotation.from_rotvec(rv.numpy()).as_matrix(), atol=1e-12)
    torch.testing.assert_close(R.quat_to_axis_angle(q), rv, atol=1e-10, rtol=0)
    tiny = torch.tensor([[1e-9, -2e-9, 0.5e-9], [0.0, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(R.quat_to_axis_angle(R.axis_angle_to_quat(tiny)), tiny, atol=1e-15, rtol=0)


def test_quat_between():
    u = torch.randn(100, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(12))
    v = torch.randn(100, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(13))
    v[0] = -u[0]  # antiparallel
    q = R.quat_between(u, v)
    got = R.quat_apply(q, u / u.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(got, v / v.norm(dim=-1, keepdim=True), atol=1e-10, rtol=0)


def test_batched_shapes():
    q = R.quat_normalize(torch.randn(2, 3, 5, 4, dtype=torch.float64))
    assert R.quat_to_matrix(q).shape == (2, 3, 5, 3, 3)
    assert R.matrix_to_quat(R.quat_to_matrix(q)).shape == (2, 3, 5, 4)
    assert R.quat_to_6d(q).shape == (2, 3, 5, 6)
    assert R.quat_to_euler(q, "ZXY").shape == (2, 3, 5, 3)
    assert R.quat_identity((2, 3)).shape == (2, 3, 4)


def test_bad_input_raises_clear_errors():
    with pytest.raises(ValueError, match="Euler order"):
        R.euler_to_matrix(torch.zeros(3), "XYX")
    with pytest.raises(ValueError, match="last dimension 4"):
        R.quat_to_matrix(torch.zeros(5, 3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        R.matrix_to_quat(torch.zeros(5, 3, 4))


def test_gradients_finite_at_identity():
    fns = [
        lambda q: R.matrix_to_quat(R.quat_to_matrix(q)),
        lambda q: R.quat_to_axis_angle(q),
        lambda q: R.quat_slerp(q, q.detach(), 0.4),
        lambda q: R.sixd_to_quat(R.quat_to_6d(q)),
        lambda q: R.quat_to_euler(q, "ZXY"),
    ]
    for fn in fns:
        q = R.quat_identity((3,), dtype=torch.float64).requires_grad_(True)
        fn(q).sum().backward()
        assert torch.isfinite(q.grad).all()
    aa = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    R.axis_angle_to_quat(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
    ang = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    R.matrix_to_euler(R.euler_to_matrix(ang, "YXZ"), "YXZ").sum().backward()
    assert torch.isfinite(ang.grad).all()


def test_gradcheck():
    q = rand_quats(6, seed=14).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: R.matrix_to_quat(R.quat_to_matrix(x)), (q,))
    d6 = torch.randn(6, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(R.sixd_to_matrix, (d6,))
    ang = (torch.rand(6, 3, dtype=torch.float64) * 120 - 60).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: R.euler_to_quat(a, "ZXY"), (ang,))
    assert torch.autograd.gradcheck(lambda a: R.matrix_to_euler(R.euler_to_matrix(a, "XZY"), "XZY"), (ang,))
    q1 = rand_quats(6, seed=15)
    t = torch.rand(6, 1, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: R.quat_slerp(a, q1, t), (q,))
    aa = (torch.randn(6, 3, dtype=torch.float64) * 0.7).requires_grad_(True)
    assert torch.autograd.gradcheck(R.axis_angle_to_quat, (aa,))


def test_quat_unflip_makes_sequences_continuous():
    q = rand_quats(50, seed=16)
    q = R.quat_slerp(q[:1].expand(50, 4), q[1:2].expand(50, 4), torch.linspace(0, 1, 50, dtype=torch.float64))
    flipped = q * torch.where(torch.rand(50, 1, generator=torch.Generator().manual_seed(17)) < 0.5, -1.0, 1.0).double()
    flipped[0] = q[0]
    fixed = R.quat_unflip(flipped, dim=0)
    torch.testing.assert_close(fixed, q)
    batch = R.quat_unflip(torch.stack([flipped, -flipped], dim=1), dim=0)  # (T, 2, 4), time first
    torch.testing.assert_close(batch[:, 1], -q)
    with pytest.raises(ValueError, match="quaternion dimension"):
        R.quat_unflip(q, dim=-1)
