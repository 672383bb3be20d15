"""modi.core.kinematics: the reference FK, against hand-computed poses and an independent scipy FK on real files."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from modi.io import bvh as B
from modi.core.kinematics import bvh_global_quats, bvh_positions, forward_kinematics
from modi.core.rotations import axis_angle_to_quat, euler_to_quat, quat_identity, quat_normalize


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_hand_computed_chain():
    # root at (1,2,3) turned 90 deg about Z; child offset (0,1,0) turned 90 deg about X; grandchild offset (0,0,2)
    s = np.sqrt(0.5)
    quats = torch.tensor([[[s, 0, 0, s], [s, s, 0, 0], [1.0, 0, 0, 0]]], dtype=torch.float64)
    offsets = torch.tensor([[9.0, 9, 9], [0, 1, 0], [0, 0, 2]], dtype=torch.float64)  # root offset is ignored
    pos, rot = forward_kinematics(quats, offsets, [-1, 0, 1], torch.tensor([[1.0, 2, 3]], dtype=torch.float64))
    # Rz90 (0,1,0) = (-1,0,0); Rz90 Rx90 (0,0,2) = Rz90 (0,-2,0) = (2,0,0)
    np.testing.assert_allclose(pos[0].numpy(), [[1, 2, 3], [0, 2, 3], [2, 2, 3]], atol=1e-12)
    np.testing.assert_allclose(rot[0, 2].numpy(), [0.5, 0.5, 0.5, 0.5], atol=1e-12)  # Rz90 * Rx90


def test_branching_and_broadcasting():
    parents = [-1, 0, 1, 0, 3]
    offsets = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0]], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    q = quat_normalize(torch.randn(2, 7, 5, 4, generator=g, dtype=torch.float64))
    root = torch.randn(2, 7, 3, generator=g, dtype=torch.float64)
    pos, _ = forward_kinematics(q, offsets, parents, root)
    assert pos.shape == (2, 7, 5, 3)
    # same result with per-frame offsets (..., J, 3) and frame by frame
    pos2, _ = forward_kinematics(q, offsets.expand(2, 7, 5, 3).clone(), parents, root)
    torch.testing.assert_close(pos, pos2)
    one, _ = forward_kinematics(q[1, 3], offsets, parents, root[1, 3])
    torch.testing.assert_close(pos[1, 3], one)
    # identity rotations: positions are the rest pose (cumulative offsets) shifted by the root
    ident, _ = forward_kinematics(quat_identity((4, 5), torch.float64), offsets, parents, torch.zeros(4, 3, dtype=torch.float64))
    np.testing.assert_allclose(ident[0].numpy(), [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [0, 2, 0]])
    # bone lengths are the offsets' norms whatever the rotations
    lengths = (pos[..., 1:, :] - pos[..., [0, 1, 0, 3], :]).norm(dim=-1)
    torch.testing.assert_close(lengths, torch.ones_like(lengths))


def _scipy_fk(b: B.Bvh) -> tuple[np.ndarray, np.ndarray]:
    """Independent FK: scipy Rotation per joint, numpy translations."""
    euler = b.euler_degrees()
    trans = b.local_translations()
    orders = b.rotation_orders
    pos = np.zeros(trans.shape)
    glob: list[Rotation] = []
    for j, p in enumerate(b.parents):
        local = Rotation.from_euler(orders[j], euler[:, j], degrees=True)
        if p < 0:
            glob.append(local)
            pos[:, j] = trans[:, j]
        else:
            glob.append(glob[p] * local)
            pos[:, j] = pos[:, p] + glob[p].apply(trans[:, j])
    quats = np.stack([g.as_quat()[:, [3, 0, 1, 2]] for g in glob], axis=1)
    return pos, quats


@pytest.mark.parametrize("rel", [
    "ganimator/Xia/normal.bvh",  # ZYX order, root-only positions
    "ganimator/Elephant/idle1.bvh",  # 6 channels on every joint, animated bone translations
    "bandai-namco-1/data/dataset-1_bow_active_001.bvh",  # ZXY, position channels everywhere
])
def test_bvh_positions_match_independent_fk(shared_data, rel):
    b = B.load(shared_data / "bvh" / rel)
    ref_pos, ref_q = _scipy_fk(b)
    pos = bvh_positions(b)
    assert pos.shape == (b.n_frames, b.n_joints, 3) and pos.dtype == np.float64
    scale = np.ptp(ref_pos[0], axis=0).max()
    assert np.abs(pos - ref_pos).max() < 1e-9 * scale
    gq = bvh_global_quats(b)
    dots = np.abs((gq * ref_q).sum(-1))  # q and -q are the same rotation
    np.testing.assert_allclose(dots, 1.0, atol=1e-9)


def test_fk_matches_matrix_chain_float32():
    g = torch.Generator().manual_seed(1)
    parents = [-1, 0, 1, 2, 1]
    offsets = torch.randn(5, 3, generator=g)
    aa = torch.randn(10, 5, 3, generator=g)
    q = axis_angle_to_quat(aa)
    root = torch.randn(10, 3, generator=g)
    pos, _ = forward_kinematics(q, offsets, parents, root)
    assert pos.dtype == torch.float32
    mats = Rotation.from_rotvec(aa.double().reshape(-1, 3).numpy()).as_matrix().reshape(10, 5, 3, 3)
    ref = np.zeros((10, 5, 3))
    gm = [None] * 5
    for j, p in enumerate(parents):
        if p < 0:
            gm[j], ref[:, j] = mats[:, j], root.double().numpy()
        else:
            gm[j] = gm[p] @ mats[:, j]
            ref[:, j] = ref[:, p] + np.einsum("fij,j->fi", gm[p], offsets[j].double().numpy())
    np.testing.assert_allclose(pos.double().numpy(), ref, atol=1e-5)


def test_gradcheck():
    g = torch.Generator().manual_seed(2)
    parents = [-1, 0, 1, 0]
    q = quat_normalize(torch.randn(3, 4, 4, generator=g, dtype=torch.float64)).requires_grad_(True)
    off = torch.randn(4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    root = torch.randn(3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: forward_kinematics(a, b, parents, c)[0], (q, off, root))


def test_euler_quats_agree_with_bvh_convention():
    # a one-joint "file": the root's global rotation must be the intrinsic ZXY product
    text = ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\nJOINT c\n{\n"
            "OFFSET 0 1 0\nCHANNELS 0\n}\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n30 40 50\n")
    b = B.loads(text)
    expected = Rotation.from_euler("ZXY", [30, 40, 50], degrees=True).apply([0, 1, 0])
    np.testing.assert_allclose(bvh_positions(b)[0, 1], expected, atol=1e-12)
    q = euler_to_quat(torch.tensor([30.0, 40, 50], dtype=torch.float64), "ZXY")
    np.testing.assert_allclose(np.abs(bvh_global_quats(b)[0, 0] @ q.numpy()), 1.0, atol=1e-12)


def test_bad_arguments():
    q = quat_identity((2, 3), torch.float64)
    off = torch.zeros(3, 3, dtype=torch.float64)
    root = torch.zeros(2, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="parents must precede"):
        forward_kinematics(q, off, [-1, 2, 0], root)
    with pytest.raises(ValueError, match="parents has 2 entries"):
        forward_kinematics(q, off, [-1, 0], root)
    with pytest.raises(ValueError, match="offsets must be"):
        forward_kinematics(q, torch.zeros(4, 3), [-1, 0, 1], root)
    with pytest.raises(ValueError, match="local_quats must be"):
        forward_kinematics(torch.zeros(2, 3, 3), off, [-1, 0, 1], root)
    with pytest.raises(ValueError, match="root_positions"):
        forward_kinematics(q, off, [-1, 0, 1], torch.zeros(2, 2))


# ------------------------------------------------------------------------------------------- modi export positions

_TWO_JOINTS = ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation "
               "Yrotation\nJOINT c\n{\nOFFSET 0 2 0\nCHANNELS 3 Zrotation Xrotation Yrotation\nEnd Site\n{\n"
               "OFFSET 0 1 0\n}\n}\n}\nMOTION\nFrames: 2\nFrame Time: 0.5\n1 2 3 0 0 0 0 0 0\n0 0 0 90 0 0 0 0 0\n")


def test_export_positions_cli(tmp_path, capsys):
    from modi.cli import main

    src = tmp_path / "two.bvh"
    src.write_text(_TWO_JOINTS)
    out = tmp_path / "pos.npy"
    names = tmp_path / "names.txt"
    assert main(["export", "positions", str(src), str(out), "--names", str(names)]) == 0
    pos = np.load(out)
    assert pos.dtype == np.float32 and pos.shape == (2, 2, 3)
    # frame 0: root at (1,2,3), child 2 above; frame 1: root turned 90 deg about Z, child at Rz90 (0,2,0) = (-2,0,0)
    np.testing.assert_allclose(pos, [[[1, 2, 3], [1, 4, 3]], [[0, 0, 0], [-2, 0, 0]]], atol=1e-6)
    assert names.read_text().split("\n")[:2] == ["r", "c"]
    assert "2 frames x 2 joints" in capsys.readouterr().out


def test_export_positions_real_file(shared_data, tmp_path):
    from modi.cli import main

    src = shared_data / "bvh" / "ganimator" / "Xia" / "proud.bvh"
    out = tmp_path / "proud"  # no .npy suffix: written exactly as named
    assert main(["export", "positions", str(src), str(out)]) == 0
    pos = np.load(out)
    ref, _ = _scipy_fk(B.load(src))
    assert pos.shape == ref.shape and pos.dtype == np.float32
    np.testing.assert_allclose(pos, ref, atol=1e-6 * np.ptp(ref[0], axis=0).max() + 1e-5)


@pytest.mark.parametrize("case", ["missing", "folder", "malformed", "bad_out_dir"])
def test_export_positions_user_errors(tmp_path, capsys, case):
    from modi.cli import main

    src = tmp_path / "in.bvh"
    out = tmp_path / "out.npy"
    if case == "missing":
        src = tmp_path / "nope.bvh"
    elif case == "folder":
        src = tmp_path
    elif case == "malformed":
        src.write_text(_TWO_JOINTS.replace("0 0 0 90 0 0 0 0 0", "0 0 0 90 0 0 0 0"))
    else:
        src.write_text(_TWO_JOINTS)
        out = tmp_path / "no" / "such" / "out.npy"
    assert main(["export", "positions", str(src), str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("modi: error:") and "\n" not in err
    assert "Traceback" not in err
    if case == "malformed":
        assert ":20:" in err and "8 values" in err
    assert not out.exists()


def test_export_positions_help(capsys):
    from modi.cli import main

    with pytest.raises(SystemExit) as info:
        main(["export", "positions", "--help"])
    assert info.value.code == 0
    assert "float32" in capsys.readouterr().out
