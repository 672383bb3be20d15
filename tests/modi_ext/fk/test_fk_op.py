"""modi_ext.fk: the C++ FK kernel against the dense reference, hand-computed poses and modi.core.kinematics."""
from __future__ import annotations

import math
import random

import pytest
import torch

from modi_ext import HAS_EXT
from modi_ext.fk import check_parents, fk, fk_reference
from modi_ext.layers import ForwardKinematics

needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")

# Bandai-Namco 22-joint skeleton topology (root, hips, spine chain, two arms off the chest, two legs off the hips).
BANDAI_PARENTS = [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1, 14, 15, 16, 1, 18, 19, 20]


def random_tree(n_joints: int, seed: int) -> list[int]:
    """Random topologically sorted tree: mostly chains (like limbs) with random branch points."""
    rng = random.Random(seed)
    parents = [-1]
    for j in range(1, n_joints):
        parents.append(j - 1 if rng.random() < 0.6 else rng.randrange(j))
    return parents


def random_inputs(parents, lead=(3, 5), dtype=torch.float32, seed=0, unit=True, requires_grad=False):
    g = torch.Generator().manual_seed(seed)
    J = len(parents)
    q = torch.randn(*lead, J, 4, generator=g, dtype=torch.float64)
    if unit:
        q = q / q.norm(dim=-1, keepdim=True)
    off = torch.randn(J, 3, generator=g, dtype=torch.float64) * 10.0
    root = torch.randn(*lead, 3, generator=g, dtype=torch.float64) * 50.0
    out = [t.to(dtype).requires_grad_(requires_grad) for t in (q, off, root)]
    return out[0], out[1], out[2]


def _axis_quat(axis, degrees):
    h = math.radians(degrees) / 2
    return [math.cos(h)] + [math.sin(h) * a for a in axis]


@pytest.mark.parametrize("impl", ["ref", pytest.param("ext", marks=needs_ext)])
def test_hand_computed_chain(impl, monkeypatch):
    # Root turned 90 deg about z (x -> y), joint 1 turned 90 deg about x (y -> z): worked out by hand.
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    q = torch.tensor([[_axis_quat((0, 0, 1), 90), _axis_quat((1, 0, 0), 90), [1.0, 0, 0, 0]]], dtype=torch.float64)
    off = torch.tensor([[5.0, 5.0, 5.0], [1.0, 0, 0], [0, 2.0, 0]], dtype=torch.float64)
    root = torch.tensor([[10.0, 20.0, 30.0]], dtype=torch.float64)
    pos, rot = fk(q, off, [-1, 0, 1], root, return_rotations=True)
    expected = torch.tensor([[[10.0, 20, 30], [10, 21, 30], [10, 21, 32]]], dtype=torch.float64)
    torch.testing.assert_close(pos, expected, atol=1e-12, rtol=0)
    # global rotation of joint 2 = Rz(90) Rx(90): maps x -> y, y -> z, z -> x
    c = 0.5
    torch.testing.assert_close(rot[0, 2], torch.tensor([c, c, c, c], dtype=torch.float64), atol=1e-12, rtol=0)


@needs_ext
@pytest.mark.parametrize("n_joints,seed", [(2, 0), (3, 1), (7, 2), (16, 3), (29, 4), (40, 5), (40, 6)])
def test_forward_matches_reference_fp32(n_joints, seed):
    parents = random_tree(n_joints, seed)
    q, off, root = random_inputs(parents, lead=(4, 9), seed=seed)
    pos, rot = fk(q, off, parents, root, return_rotations=True)
    pos_ref, rot_ref = fk_reference(q.double(), off.double(), parents, root.double(), return_rotations=True)
    torch.testing.assert_close(pos, pos_ref.float(), rtol=1e-5, atol=2e-4)
    torch.testing.assert_close(rot, rot_ref.float(), rtol=1e-5, atol=1e-5)


@needs_ext
def test_bandai_shape_and_leading_dims():
    q, off, root = random_inputs(BANDAI_PARENTS, lead=(2, 3, 4), seed=7)
    pos = fk(q, off, BANDAI_PARENTS, root)
    assert pos.shape == (2, 3, 4, 22, 3)
    torch.testing.assert_close(pos, fk_reference(q, off, BANDAI_PARENTS, root), rtol=1e-5, atol=2e-4)
    # a single pose (no leading dims) works too
    pos1 = fk(q[0, 0, 0].contiguous(), off, BANDAI_PARENTS, root[0, 0, 0].contiguous())
    torch.testing.assert_close(pos1, pos[0, 0, 0])


def test_matches_modi_kinematics():
    kin = pytest.importorskip("modi.core.kinematics")
    for n_joints, seed in [(5, 10), (22, 11), (35, 12)]:
        parents = random_tree(n_joints, seed)
        q, off, root = random_inputs(parents, lead=(6,), dtype=torch.float64, seed=seed)
        pos, rot = fk(q, off, parents, root, return_rotations=True)
        pos_k, rot_k = kin.forward_kinematics(q, off, parents, root)
        torch.testing.assert_close(pos, pos_k, rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(rot, rot_k, rtol=1e-12, atol=1e-12)


@needs_ext
@pytest.mark.parametrize("n_joints,seed", [(1, 0), (2, 1), (6, 2), (13, 3), (22, 4)])
def test_gradcheck_float64(n_joints, seed):
    parents = BANDAI_PARENTS if n_joints == 22 else random_tree(n_joints, seed)
    # Non-unit quaternions on purpose: the gradient must be exact off the unit sphere too.
    lead = (2, 3) if n_joints < 10 else (2,)
    q, off, root = random_inputs(parents, lead=lead, dtype=torch.float64, seed=seed, unit=False, requires_grad=True)
    off = (off / 10).detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c: fk(a, b, parents, c, return_rotations=True), (q, off, root))
    assert torch.autograd.gradcheck(lambda a, c: fk(a, off.detach(), parents, c), (q, root))


@needs_ext
def test_gradient_through_one_output_only():
    # Only the rotations (or only the positions) feed the loss: the other output's gradient is absent.
    parents = random_tree(9, 8)
    q, off, root = random_inputs(parents, lead=(3,), dtype=torch.float64, seed=8, requires_grad=True)
    for pick in (0, 1):
        got = torch.autograd.grad(fk(q, off, parents, root, return_rotations=True)[pick].sin().sum(), (q, off),
                                  allow_unused=True)
        want = torch.autograd.grad(fk_reference(q, off, parents, root, True)[pick].sin().sum(), (q, off),
                                   allow_unused=True, materialize_grads=True)
        torch.testing.assert_close(got[0], want[0])
        torch.testing.assert_close(got[1], want[1])


@needs_ext
def test_meta_tensors_give_shapes():
    q, off, root = (torch.empty(2, 5, 7, 4, device="meta"), torch.empty(7, 3, device="meta"),
                    torch.empty(2, 5, 3, device="meta"))
    pos, rot = fk(q, off, random_tree(7, 0), root, return_rotations=True)
    assert pos.shape == (2, 5, 7, 3) and rot.shape == (2, 5, 7, 4) and pos.device.type == "meta"


@needs_ext
def test_gradients_match_reference_fp32():
    parents = BANDAI_PARENTS
    q, off, root = random_inputs(parents, lead=(8, 16), seed=3, requires_grad=True)
    g = torch.Generator().manual_seed(1)
    w_pos = torch.randn(8, 16, 22, 3, generator=g)
    w_rot = torch.randn(8, 16, 22, 4, generator=g)
    grads = []
    for fn in (fk, fk_reference):
        pos, rot = fn(q, off, parents, root, return_rotations=True)
        grads.append(torch.autograd.grad((pos * w_pos).sum() + (rot * w_rot).sum(), (q, off, root)))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3)


@needs_ext
@pytest.mark.parametrize("requires_grad", [False, True])
def test_opcheck(requires_grad):
    for n_joints, seed in [(4, 0), (22, 1)]:
        parents = random_tree(n_joints, seed)
        q, off, root = random_inputs(parents, lead=(2, 3), seed=seed, requires_grad=requires_grad)
        torch.library.opcheck(torch.ops.modi_ext.fk.default, (q, off, parents, root))


def _bad_cases():
    parents = [-1, 0, 1, 1]
    ok = dict(local_quats=torch.randn(2, 4, 4), offsets=torch.randn(4, 3), parents=parents, root_positions=torch.randn(2, 3))
    cases = [
        ("local_quats", dict(local_quats=torch.randn(2, 4, 3)), ValueError, "local_quats.*\\(\\.\\.\\., J, 4\\)"),
        ("local_quats", dict(local_quats=torch.randn(4)), ValueError, "local_quats"),
        ("local_quats", dict(local_quats=torch.randn(2, 4, 4).half()), ValueError, "local_quats.*float32 or float64"),
        ("local_quats", dict(local_quats=torch.randn(0, 4, 4), root_positions=torch.randn(0, 3)), ValueError, "empty"),
        ("local_quats", dict(local_quats=torch.randn(4, 2, 4).transpose(0, 1)), ValueError, "local_quats must be contiguous"),
        ("offsets", dict(offsets=torch.randn(3, 3)), ValueError, "offsets must have shape"),
        ("offsets", dict(offsets=torch.randn(4, 3).double()), ValueError, "offsets has dtype"),
        ("offsets", dict(offsets=torch.randn(3, 4).t()), ValueError, "offsets must be contiguous"),
        ("root_positions", dict(root_positions=torch.randn(3, 3)), ValueError, "root_positions must have shape"),
        ("root_positions", dict(root_positions=torch.randn(2, 2)), ValueError, "root_positions must have shape"),
        ("root_positions", dict(root_positions=torch.randn(2, 3, dtype=torch.float64)), ValueError, "root_positions has dtype"),
        ("root_positions", dict(root_positions=[[0.0, 0, 0]] * 2), TypeError, "root_positions must be a torch.Tensor"),
        ("parents", dict(parents=[-1, 0, 1]), ValueError, "parents has 3 entries"),
        ("parents", dict(parents=[0, 0, 1, 1]), ValueError, "parents\\[0\\] must be -1"),
        ("parents", dict(parents=[-1, 0, 3, 1]), ValueError, "parents\\[2\\] = 3 is out of range"),
        ("parents", dict(parents=[-1, 0, -1, 1]), ValueError, "parents\\[2\\] = -1 is out of range"),
        ("parents", dict(parents=[-1, 0, 7, 1]), ValueError, "parents\\[2\\] = 7"),
        ("parents", dict(parents=[-1, 0, 0.5, 1]), ValueError, "parents must be"),
        ("parents", dict(parents=torch.tensor([-1.0, 0, 1, 1])), ValueError, "parents must be a 1-D integer"),
        ("parents", dict(parents=[]), ValueError, "parents"),
    ]
    return [pytest.param({**ok, **change}, exc, match, id=f"{name}-{i}") for i, (name, change, exc, match) in enumerate(cases)]


@pytest.mark.parametrize("impl", ["ref", pytest.param("ext", marks=needs_ext)])
@pytest.mark.parametrize("kwargs,exc,match", _bad_cases())
def test_bad_input_names_the_argument(kwargs, exc, match, impl, monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    with pytest.raises(exc, match=match):
        fk(**kwargs)


@needs_ext
def test_cpp_op_rejects_bad_input_without_crashing():
    op = torch.ops.modi_ext.fk
    q, off, root = torch.randn(2, 3, 4), torch.randn(3, 3), torch.randn(2, 3)
    with pytest.raises(RuntimeError, match=r"parents\[2\] = 5 is out of range"):
        op(q, off, [-1, 0, 5], root)
    with pytest.raises(RuntimeError, match="parents has 2 entries"):
        op(q, off, [-1, 0], root)
    with pytest.raises(RuntimeError, match="offsets must be contiguous"):
        op(q, torch.randn(3, 3).t(), [-1, 0, 1], root)
    with pytest.raises(RuntimeError, match="root_positions has dtype"):
        op(q, off, [-1, 0, 1], root.double())
    with pytest.raises(RuntimeError, match="local_quats is empty"):
        op(torch.randn(0, 3, 4), off, [-1, 0, 1], torch.randn(0, 3))
    with pytest.raises(RuntimeError, match="grad_positions must have shape"):
        torch.ops.modi_ext.fk_backward(torch.randn(2, 3), None, q, q, off, [-1, 0, 1], False)


@needs_ext
def test_reference_path_forced_by_env(monkeypatch):
    q, off, root = random_inputs(BANDAI_PARENTS, seed=5)
    ext = fk(q, off, BANDAI_PARENTS, root)
    monkeypatch.setenv("MODI_EXT_IMPL", "ref")
    ref = fk(q, off, BANDAI_PARENTS, root)
    torch.testing.assert_close(ext, ref, rtol=1e-5, atol=2e-4)


@needs_ext
def test_impl_argument_selects_the_path(monkeypatch):
    q, off, root = random_inputs(BANDAI_PARENTS, seed=6, requires_grad=True)
    ext = fk(q, off, BANDAI_PARENTS, root, impl="ext")
    ref = fk(q, off, BANDAI_PARENTS, root, impl="ref")
    kernel_nodes = ("modi_ext_fk", "fk_eager")  # the registered op, or its eager Function (kernels.launch)
    assert any(n in ext.grad_fn.name() for n in kernel_nodes)
    assert not any(n in ref.grad_fn.name() for n in kernel_nodes)
    torch.testing.assert_close(ext, ref, rtol=1e-5, atol=2e-4)
    with pytest.raises(ValueError, match="impl must be"):
        fk(q, off, BANDAI_PARENTS, root, impl="cuda")


def test_check_parents_accepts_tensor_and_tuple():
    assert check_parents(torch.tensor([-1, 0, 0, 2])) == (-1, 0, 0, 2)
    assert check_parents((-1, 0), 2) == (-1, 0)


def test_module_handles_layout_and_dtype():
    off = torch.randn(22, 3, dtype=torch.float64)
    m = ForwardKinematics(BANDAI_PARENTS, off)
    assert m.offsets.dtype == torch.get_default_dtype() and "offsets" in m.state_dict()
    q, _, root = random_inputs(BANDAI_PARENTS, lead=(2, 5), seed=2)
    # permuted network output: (B, J, 4, T) -> (B, T, J, 4) is not contiguous
    q_nc = q.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    assert not q_nc.is_contiguous()
    out = m(q_nc, root)
    torch.testing.assert_close(out, fk_reference(q, off.float(), BANDAI_PARENTS, root), rtol=1e-5, atol=2e-4)
    out64, rot64 = m(q.double(), root.double(), return_rotations=True)
    assert out64.dtype == torch.float64 and rot64.shape == (2, 5, 22, 4)
    with pytest.raises(ValueError, match="22"):
        m(q[..., :5, :].contiguous(), root)
    with pytest.raises(ValueError, match="offsets"):
        ForwardKinematics([-1, 0], torch.randn(2, 4))
    with pytest.raises(ValueError, match="parents"):
        ForwardKinematics([-1, 2, 0], torch.randn(3, 3))


def test_compile_fullgraph_matches_eager():
    torch._dynamo.reset()
    m = ForwardKinematics(BANDAI_PARENTS, torch.randn(22, 3))
    compiled = torch.compile(m, fullgraph=True, dynamic=False)
    q, _, root = random_inputs(BANDAI_PARENTS, lead=(2, 8), seed=9, requires_grad=True)
    out = compiled(q, root)
    ref = m(q, root)
    torch.testing.assert_close(out, ref)
    g_c = torch.autograd.grad(out.square().sum(), (q, root))
    g_e = torch.autograd.grad(ref.square().sum(), (q, root))
    for a, b in zip(g_c, g_e):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3)


@needs_ext
def test_real_skeletons_match_modi_kinematics(shared_data):
    bvh = pytest.importorskip("modi.io.bvh")
    kin = pytest.importorskip("modi.core.kinematics")
    rotations = pytest.importorskip("modi.core.rotations")
    files = sorted((shared_data / "bvh").rglob("*.bvh"))
    picked = [f for f in files if "bandai" in str(f)][:1] + [f for f in files if "ganimator" in str(f)][:2]
    if not picked:
        pytest.skip(f"no BVH files under {shared_data / 'bvh'}")
    for path in picked:
        b = bvh.load(path)
        euler = torch.from_numpy(b.euler_degrees()[:60])
        q = torch.empty(euler.shape[:-1] + (4,), dtype=torch.float64)
        for order in set(b.rotation_orders):
            idx = [j for j, o in enumerate(b.rotation_orders) if o == order]
            q[:, idx] = rotations.euler_to_quat(euler[:, idx], order)
        off = torch.from_numpy(b.offsets).double().contiguous()
        root = torch.from_numpy(b.local_translations()[:60, 0]).contiguous()
        pos = fk(q.contiguous(), off, b.parents, root)
        expected, _ = kin.forward_kinematics(q, off, b.parents, root)
        torch.testing.assert_close(pos, expected, rtol=1e-10, atol=1e-8, msg=f"{path.name}")
        pos32 = fk(q.float().contiguous(), off.float(), b.parents, root.float())
        scale = float(expected.abs().max())
        torch.testing.assert_close(pos32.double(), expected, rtol=0, atol=2e-6 * scale, msg=f"{path.name} fp32")


@needs_ext
def test_eager_function_and_registered_op_agree(monkeypatch):
    """``kernels.launch`` takes FK's eager Function; ``MODI_EXT_EAGER=0`` the registered op: the same values and
    gradients, first order and with a graph."""
    def run():
        q, off, root = random_inputs(BANDAI_PARENTS, seed=8, requires_grad=True)
        pos, rot = fk(q, off, BANDAI_PARENTS, root, return_rotations=True, impl="ext")
        (gq,) = torch.autograd.grad(pos.pow(2).sum() + rot.sum(), q, create_graph=True)
        gq.pow(2).sum().backward()
        return pos.grad_fn.name(), pos, gq, q.grad, root.grad
    eager_run = run()
    monkeypatch.setenv("MODI_EXT_EAGER", "0")
    op_run = run()
    assert "fk_eager" in eager_run[0] and "modi_ext_fk" in op_run[0]
    for a, b in zip(eager_run[1:], op_run[1:]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
