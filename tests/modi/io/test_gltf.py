"""glTF 2.0 export (modi.io.gltf, --format, modi export gltf): the Khronos validator on files from every writing
command, read-back positions against BVH forward kinematics (random rigs and real files), Blender's importer, and
the refusals (non-finite motion, output = input, output under a file, unknown format)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from modi.cli import main
from modi.errors import UserError
from modi.io import bvh as bvh_io
from modi.io import gltf
from modi.io.formats import save_motion
from modi.core.kinematics import bvh_positions
from modi.data.procedural import generate_clip

pytestmark = pytest.mark.usefixtures("one_torch_thread")

REAL = {  # the four kinds of real rig the issue names, with the unit their authors used
    "bandai": ("bandai-namco-1/data/dataset-1_walk_normal_001.bvh", "centimetres"),
    "mixamo": ("ganimator/Joe/Walk-In-Circle.bvh", "centimetres"),
    "crab": ("ganimator/Crabnew/Crab-dance-long.bvh", "metres"),
    "elephant": ("ganimator/Elephant/idle1.bvh", "metres"),
}

VALIDATE_JS = r"""
const fs = require('fs'), path = require('path');
const validator = require(process.env.GLTF_VALIDATOR);
(async () => {
  const out = {};
  for (const f of process.argv.slice(2)) {
    const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)), {
      uri: path.basename(f), maxIssues: 20,
      externalResourceFunction: (uri) => Promise.resolve(
        new Uint8Array(fs.readFileSync(path.join(path.dirname(f), decodeURIComponent(uri))))),
    });
    out[f] = {errors: r.issues.numErrors, warnings: r.issues.numWarnings,
              messages: r.issues.messages.map(m => `${m.code} ${m.pointer || ''}: ${m.message}`)};
  }
  console.log(JSON.stringify(out));
})().catch(e => { console.error(String(e)); process.exit(1); });
"""

BLENDER_PY = r"""
import json, sys
import bpy  # no numpy patch and the import dialog's defaults: what a user does
jobs = json.load(open(sys.argv[sys.argv.index("--") + 1]))
out = {}
for job in jobs:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.fps = max(1, round(job["fps"]))  # the importer puts a key at time t on frame t * render.fps
    bpy.ops.import_scene.gltf(filepath=job["file"])
    arm = next(o for o in bpy.data.objects if o.type == "ARMATURE")
    frames = []
    for i in range(job["frames"]):
        f = i * sc.render.fps / job["fps"]
        sc.frame_set(int(f), subframe=f - int(f))
        mw = arm.matrix_world
        frames.append([list(mw @ arm.pose.bones[n].head) for n in job["names"]])
    out[job["file"]] = frames
json.dump(out, open(sys.argv[sys.argv.index("--") + 2], "w"))
"""


# ------------------------------------------------------------------------------------------------ helpers


def _validator() -> Path:
    node, npm = shutil.which("node"), shutil.which("npm")
    if not node or not npm:
        pytest.skip("node/npm absent: the Khronos validator is npm package gltf-validator (npm install -g gltf-validator)")
    root = subprocess.run([npm, "root", "-g"], capture_output=True, text=True).stdout.strip()
    mod = Path(root) / "gltf-validator"
    if not (mod / "package.json").is_file():
        pytest.skip("npm package gltf-validator is not installed (npm install -g gltf-validator)")
    return mod


def validate(files, tmp: Path) -> dict[str, dict]:
    """Khronos glTF-Validator report (errors, warnings, messages) of each file, in one node process."""
    mod = _validator()
    script = tmp / "validate.js"
    script.write_text(VALIDATE_JS)
    r = subprocess.run(["node", str(script), *map(str, files)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "GLTF_VALIDATOR": str(mod)})
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _height(b) -> float:
    return b.skeleton().height()


def random_bvh(rng: np.random.Generator, n_joints: int, n_frames: int) -> bvh_io.Bvh:
    """A random rig: random tree, OFFSETs, per-joint Euler orders and channel subsets (position channels on some
    non-root joints too), End Sites, angles over the whole circle and a wandering root."""
    parents = [-1] + [int(rng.integers(0, j)) for j in range(1, n_joints)]
    offsets = rng.normal(0, 10, (n_joints, 3))
    orders = ["".join(rng.permutation(list("XYZ"))) for _ in range(n_joints)]
    channels = []
    for j in range(n_joints):
        rot = [f"{a}rotation" for a in orders[j][: int(rng.integers(1, 4)) if rng.random() < 0.2 else 3]]
        pos = ["Xposition", "Yposition", "Zposition"] if j == 0 or rng.random() < 0.15 else []
        channels.append(list(rng.permutation(pos + rot)) if j and rng.random() < 0.3 else pos + rot)
    n_ch = sum(len(c) for c in channels)
    motion = rng.uniform(-180, 180, (n_frames, n_ch))
    start = 0
    for j, chans in enumerate(channels):
        for k, c in enumerate(chans):
            if c.endswith("position"):
                motion[:, start + k] = np.cumsum(rng.normal(0, 3, n_frames)) + offsets[j, "XYZ".index(c[0])]
        start += len(chans)
    leaves = [j for j in range(n_joints) if j not in parents]
    ends = {j: rng.normal(0, 5, 3) for j in leaves if rng.random() < 0.7}
    names = [f"j{j}_{rng.integers(1000)}" for j in range(n_joints)]
    return bvh_io.Bvh(names, parents, offsets, channels, ends, float(rng.uniform(1 / 120, 1 / 10)), motion)


def assert_reads_back(path: Path, b: bvh_io.Bvh, scale: float, tol: float = 1e-5) -> float:
    """load_positions(path) equals the BVH's FK positions x scale to ``tol`` of the body height; returns the error."""
    names, parents, pos, fps, _ = gltf.load_positions(path)
    ref = bvh_positions(b) * scale
    h = _height(b) * scale
    assert names == list(b.names) and parents == list(b.parents)
    assert pos.shape == ref.shape and fps == pytest.approx(b.fps, rel=1e-6)  # BVH text rounds the frame time
    err = float(np.abs(pos - ref).max() / h)
    assert err < tol, f"{path.name}: read-back error {err:.2e} of body height"
    return err


def _tiny_generator_checkpoint(path: Path, frames: int = 16, nan: bool = False) -> None:
    """An untrained tiny MoDi generator on the built-in humanoid: enough for every MoDi writing command."""
    from modi.models.modi.encoder.training import generator_bundle
    from modi.models.modi.config import ModelConfig
    from modi.models.modi.levels import build_levels
    from modi.models.modi.networks import Generator
    from modi.models.modi.training import MotionCodec
    from modi.data.normalization import Normalizer
    from modi.data.procedural import KINDS, builtin_skeleton, generate_clip
    from modi.data.representation import modi_representation
    from modi.core.skeleton_graph import build_hierarchy

    torch.manual_seed(0)
    sk = builtin_skeleton()
    feet = sk.detect_feet()
    rep = modi_representation(sk, feet)
    raw = torch.cat([rep.encode(generate_clip(k, 40, 30.0, np.random.default_rng(i))).unfold(-1, frames, 8)
                     .permute(2, 0, 1, 3) for i, k in enumerate(KINDS)]).float()
    codec = MotionCodec(rep, Normalizer.fit(raw, skip_entities=rep.contacts), 30.0)
    cfg = ModelConfig(latent_dim=16, n_mlp=2, channels=(8, 8, 8))
    g = Generator(cfg, build_levels(build_hierarchy(sk, feet), cfg, frames), rep.K).eval()
    if nan:  # a diverged model: every motion it makes is NaN
        with torch.no_grad():
            for prm in g.parameters():
                prm.fill_(float("nan"))
    torch.save(generator_bundle(g, codec), path)


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict[str, Path]:
    """Output folders of every command that writes motion, each run with glTF among its formats."""
    w = tmp_path_factory.mktemp("writers")
    ckpt = w / "tiny.pt"
    _tiny_generator_checkpoint(ckpt)
    clip = w / "synth" / "0000_walk.bvh"
    runs = {
        "synth": ["synth", str(w / "synth"), "--n", "2", "--frames", "40", "--format", "bvh,glb,gltf"],
        "generate": ["generate", str(ckpt), "--n", "2", "--out", str(w / "generate"), "--gif-max", "0",
                     "--format", "bvh,glb"],
        "latent": ["latent", "interpolate", str(ckpt), "--out", str(w / "latent"), "--steps", "1",
                   "--format", "bvh,gltf"],
        "crowd": ["latent", "crowd", str(ckpt), "--out", str(w / "crowd"), "--k", "1", "--format", "bvh,glb"],
        "ganimator": ["ganimator", "generate", str(w / "gan"), "--out", str(w / "ganimator"), "--no-gif",
                      "--format", "bvh,glb"],
        "apply": ["apply", "edit", str(w / "enc.pt"), str(clip), "--out", str(w / "apply"), "--format", "bvh,glb"],
        "export": ["export", "gltf", str(clip), str(w / "export" / "walk.glb")],
    }
    for name, argv in runs.items():
        if name == "ganimator":
            assert main(["ganimator", "train", str(clip), "--out", str(w / "gan"), "--preset", "tiny",
                         "--iterations", "1", "--quiet"]) == 0
        if name == "apply":
            assert main(["encoder", "train", str(ckpt), str(w / "synth"), "--out", str(w / "enc.pt"), "--iters", "1",
                         "--batch", "2", "--eval-every", "0", "--quiet", "--no-cache"]) == 0
        if name == "export":
            (w / "export").mkdir()
        assert main(argv) == 0, name
    return {name: Path(argv[-1]).parent if name == "export" else w / name for name, argv in runs.items()}


def _gltf_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.suffix in (".glb", ".gltf"))


# ------------------------------------------------------------------------------------------------ tests


def test_unit_guess_picks_the_unit_nearest_a_human_body():
    assert [gltf.guess_unit(h).unit for h in (0.45, 1.75, 2.8, 27.0, 68.0, 150.0, 230.0, 1750.0)] == [
        "metres", "metres", "metres", "inches", "inches", "centimetres", "centimetres", "millimetres"]
    assert gltf.guess_unit(150.0).scale == 0.01 and gltf.guess_unit(68.0).scale == 0.0254


def test_every_writing_command_writes_gltf_the_validator_accepts(written, tmp_path, capsys):
    files = {name: _gltf_files(folder) for name, folder in written.items()}
    assert all(files.values()), {k: v for k, v in files.items() if not v}
    report = validate([f for fs in files.values() for f in fs], tmp_path)
    bad = {f: r for f, r in report.items() if r["errors"] or r["warnings"]}
    assert not bad, json.dumps(bad, indent=1)[:3000]
    # the box body (--mesh) validates too, and the check can fail: a file whose POSITION bounds are wrong is reported
    meshed = tmp_path / "meshed.gltf"
    gltf.save(bvh_io.load(written["synth"] / "0000_walk.bvh"), meshed, mesh=True)
    r = validate([meshed], tmp_path)[str(meshed)]
    assert r["errors"] == 0 and r["warnings"] == 0, r
    doc = json.loads(meshed.read_text())
    pos = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    doc["accessors"][pos]["max"] = [v + 1.0 for v in doc["accessors"][pos]["max"]]
    broken = tmp_path / "broken.gltf"
    broken.write_text(json.dumps(doc))
    assert validate([broken], tmp_path)[str(broken)]["errors"] > 0


def test_files_of_every_command_read_back_as_their_bvh(written):
    checked = 0
    for name, folder in written.items():
        for f in _gltf_files(folder):
            src = written["synth"] / "0000_walk.bvh" if name == "export" else f.with_suffix(".bvh")
            # the built-in humanoid is in centimetres (a 1.9 m body), so every file is scaled by 0.01
            assert_reads_back(f, bvh_io.load(src), 0.01)
            checked += 1
    assert checked >= 11


def test_contact_labels_are_kept_as_extras(written):
    from modi.models.modi.sampling import generate_tensors

    _, codec = generate_tensors(str(written["generate"].parent / "tiny.pt"), 1)
    for i in range(2):
        names, _, _, _, contacts = gltf.load_positions(written["generate"] / f"motion_{i:04d}.glb")
        labels = np.load(written["generate"] / f"motion_{i:04d}_contacts.npy").astype(bool)
        assert contacts is not None and contacts.shape == (labels.shape[0], len(names))
        feet = [names.index(codec.skeleton.names[f]) for f in codec.feet]
        assert np.array_equal(contacts[:, feet], labels)
        assert not np.delete(contacts, feet, axis=1).any()
    names, _, _, _, contacts = gltf.load_positions(written["latent"] / "step_00.gltf")
    assert contacts is None  # no labels were given: none invented


def test_random_skeletons_read_back_exactly(tmp_path):
    rng = np.random.default_rng(21)
    files, worst = [], 0.0
    for i in range(12):
        b = random_bvh(rng, int(rng.integers(1, 30)), int(rng.integers(1, 25)))
        scale = float(rng.uniform(0.001, 2.0))
        path = tmp_path / f"r{i}{'.glb' if i % 2 else '.gltf'}"
        gltf.save(b, path, scale=scale, side_buffer=(i % 4 == 2))
        worst = max(worst, assert_reads_back(path, b, scale))
        files.append(path)
    assert (tmp_path / "r2.bin").is_file()
    if shutil.which("node"):
        report = validate(files, tmp_path)
        assert all(r["errors"] == 0 and r["warnings"] == 0 for r in report.values()), report


@pytest.fixture(scope="module")
def real_files(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("real")
    res = {}
    for key, (rel, unit) in REAL.items():
        src = shared_data / "bvh" / rel
        if not src.is_file():
            pytest.skip(f"{src} absent")
        b = bvh_io.load(src)
        assert main(["export", "gltf", str(src), str(out / f"{key}.glb")]) == 0
        res[key] = (out / f"{key}.glb", b, unit)
    return res


def test_real_bvh_reads_back_and_validates(real_files, tmp_path):
    for key, (path, b, unit) in real_files.items():
        guess = gltf.guess_unit(_height(b))
        assert guess.unit == unit, key
        assert_reads_back(path, b, guess.scale)
    if shutil.which("node"):
        report = validate([p for p, _, _ in real_files.values()], tmp_path)
        assert all(r["errors"] == 0 and r["warnings"] == 0 for r in report.values()), report


def test_blender_imports_the_same_positions(real_files, written, tmp_path):
    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("Debian package blender (with python3-numpy for its glTF importer) is not installed")
    n_frames = 24
    cases = {key: (p, b, gltf.guess_unit(_height(b)).scale) for key, (p, b, _) in real_files.items()}
    rng = np.random.default_rng(5)
    rb = random_bvh(rng, 12, n_frames)
    cases["random"] = (tmp_path / "random.glb", rb, 0.05)
    gltf.save(rb, cases["random"][0], scale=0.05)
    gb = bvh_io.load(written["ganimator"] / "sample.bvh")
    cases["ganimator"] = (written["ganimator"] / "sample.glb", gb, 0.01)
    jobs = [{"file": str(p), "fps": b.fps, "frames": min(n_frames, b.n_frames), "names": list(b.names)}
            for p, b, _ in cases.values()]
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    (tmp_path / "read.py").write_text(BLENDER_PY)
    # Blender's embedded Python takes its home from the first python3 on PATH: keep a pyenv/venv one out of it
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PYENV", "VIRTUAL_ENV"))}
    env["PATH"] = "/usr/local/bin:/usr/bin:/bin"
    r = subprocess.run([blender, "-b", "--factory-startup", "--python", str(tmp_path / "read.py"), "--",
                        str(tmp_path / "jobs.json"), str(tmp_path / "out.json")], capture_output=True, text=True,
                       timeout=300, env=env)
    assert (tmp_path / "out.json").is_file(), r.stdout[-2000:] + r.stderr[-2000:]
    got = json.loads((tmp_path / "out.json").read_text())
    for key, (p, b, scale) in cases.items():
        z_up = np.array(got[str(p)])                    # Blender is Z-up: glTF (x, y, z) = Blender (x, z, -y)
        pos = np.stack([z_up[..., 0], z_up[..., 2], -z_up[..., 1]], axis=-1)
        ref = bvh_positions(b)[: len(pos)] * scale
        err = float(np.abs(pos - ref).max() / (_height(b) * scale))
        assert err < 1e-3, f"{key}: Blender positions off by {err:.2e} of body height"


# ------------------------------------------------------------------------------------------------ refusals


def _nan_bvh(tmp: Path) -> Path:
    path = tmp / "nan.bvh"
    path.write_text("\n".join(["HIERARCHY", "ROOT Hips", "{", "\tOFFSET 0 0 0",
                               "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
                               "\tEnd Site", "\t{", "\t\tOFFSET 0 10 0", "\t}", "}", "MOTION", "Frames: 2",
                               "Frame Time: 0.0333333", "0 0 0 0 0 0", "0 nan 0 0 0 0"]) + "\n")
    return path


def test_refusals_are_one_line_exit_2_and_write_nothing(written, tmp_path, capsys):
    clip = written["synth"] / "0000_walk.bvh"
    before = clip.read_bytes()
    cases = [
        ["export", "gltf", str(_nan_bvh(tmp_path)), str(tmp_path / "o" / "nan.glb")],      # non-finite input
        ["export", "gltf", str(clip), str(clip)],                                           # output is the input
        ["export", "gltf", str(clip), str(clip / "x.glb")],                                 # under a file
        ["export", "gltf", str(clip), str(tmp_path / "o" / "x.fbx")],                       # not a glTF name
        ["synth", str(tmp_path / "s"), "--n", "1", "--format", "bvh,obj"],                   # unknown format
        ["synth", str(tmp_path / "s"), "--n", "1", "--format", "glb,glb"],                   # repeated format
        ["synth", str(clip), "--n", "1", "--format", "glb"],                                 # output folder is a file
    ]
    (tmp_path / "o").mkdir()
    for argv in cases:
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err and "\n" not in err, (argv, err)
    assert not any((tmp_path / "o").iterdir()) and not (tmp_path / "s").exists()
    assert clip.read_bytes() == before
    # a generating command whose output would land on its own input BVH (latent invert writes input.bvh)
    inv = tmp_path / "inv"
    inv.mkdir()
    (inv / "input.bvh").write_bytes(before)
    assert main(["latent", "invert", str(written["generate"].parent / "tiny.pt"), str(inv / "input.bvh"), "--out",
                 str(inv), "--steps", "1", "--format", "glb,bvh"]) == 2
    assert "is an input of this command" in capsys.readouterr().err
    assert sorted(p.name for p in inv.iterdir()) == ["input.bvh"] and (inv / "input.bvh").read_bytes() == before


def test_a_model_that_makes_nan_writes_nothing(tmp_path, capsys):
    ckpt = tmp_path / "nan.pt"
    _tiny_generator_checkpoint(ckpt, nan=True)
    for argv in (["generate", str(ckpt), "--n", "3", "--batch", "1", "--out", str(tmp_path / "g"), "--format", "glb"],
                 ["latent", "mean", str(ckpt), "--out", str(tmp_path / "m"), "--format", "bvh,glb"]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert "NaN or inf" in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nan.pt"]


def test_save_motion_refuses_nan_before_writing_any_format(tmp_path):
    b = random_bvh(np.random.default_rng(0), 4, 5)
    b.motion[3, 2] = np.inf
    with pytest.raises(UserError, match="NaN or inf"):
        save_motion(b, tmp_path / "m.bvh", formats=("bvh", "glb"))
    assert list(tmp_path.iterdir()) == []
    b.motion[3, 2] = 0.0
    assert save_motion(b, tmp_path / "m.bvh", formats=("glb", "bvh"), scale=1.0) == tmp_path / "m.glb"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.bvh", "m.glb"]


def test_unit_guess_is_printed_once_per_command(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "s"), "--n", "3", "--frames", "8", "--format", "glb"]) == 0
    out = capsys.readouterr().out
    assert out.count("glTF units:") == 1 and "centimetres" in out
    assert sorted(p.suffix for p in (tmp_path / "s").iterdir()) == [".glb"] * 3 + [".json"]
    assert main(["synth", str(tmp_path / "t"), "--n", "1", "--frames", "8", "--format", "glb", "--gltf-scale",
                 "0.5"]) == 0
    assert "x 0.5 to metres" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------------ what users see


def test_mesh_has_no_end_site_boxes_nor_ground_root_plank(shared_data):
    """Mixamo: the mesh top is the head top (no End Site box doubling the head); Bandai: no vertex is skinned to
    the static floor root (its 'bone' to the hips is a translation)."""
    joe = shared_data / "bvh" / REAL["mixamo"][0]
    bandai = shared_data / "bvh" / REAL["bandai"][0]
    if not joe.is_file() or not bandai.is_file():
        pytest.skip("Mixamo or Bandai clip absent from ../shared/data")
    b = bvh_io.load(joe)
    doc, data = gltf.build(b, 0.01, mesh=True)
    prim = doc["meshes"][0]["primitives"][0]["attributes"]
    top = doc["accessors"][prim["POSITION"]]["max"][1]
    ident = torch.zeros(b.n_joints, 4, dtype=torch.float64)
    ident[:, 0] = 1.0
    from modi.core.kinematics import forward_kinematics

    off = torch.from_numpy(b.offsets * 0.01)
    rest = forward_kinematics(ident, off, b.parents, off[0])[0].numpy()
    assert top <= rest[:, 1].max() + 0.02, (top, rest[:, 1].max())   # within 2 cm of the head-top joint
    bb = bvh_io.load(bandai)
    doc, data = gltf.build(bb, 0.01, mesh=True)
    joints = gltf._accessor(doc, [data], doc["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"])
    assert bb.names[0] == "joint_Root" and not (joints[:, 0] == 0).any()
    assert "meshes" not in gltf.build(bb, 0.01)[0]   # the default file has no mesh (Blender 3.4's default import)


def test_up_z_turns_the_file_into_y_up(tmp_path):
    path = tmp_path / "walk.bvh"
    generate_clip("walk", 20, 30.0, rng=4).save(path)
    b = bvh_io.load(path)
    assert main(["export", "gltf", "--up", "z", "--scale", "1", str(path), str(tmp_path / "z.glb")]) == 0
    _, _, pos, _, _ = gltf.load_positions(tmp_path / "z.glb")
    ref = bvh_positions(b)
    turned = np.stack([ref[..., 0], ref[..., 2], -ref[..., 1]], -1)    # Z-up (x, y, z) -> Y-up (x, z, -y)
    assert np.abs(pos - turned).max() < 1e-4 * np.abs(ref).max()
