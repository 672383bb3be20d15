"""Bad input across the whole CLI: one ``error:`` line naming the problem, exit 2, no traceback, nothing written.

A table of user mistakes, several per command and every class of issue 15 (out-of-range and non-finite numbers,
unbounded sizes, too-short motion for GANimator, output paths that are files or inputs, devices that do not
exist, feet and joints, wrong or empty checkpoints, misleading messages), each run in-process through
``modi.cli.main``. Every case names the substring its message must contain, so the last-resort "internal error"
handler never passes a case. Separate tests cover Ctrl-C (before any command runs, and during ``ganimator train`` /
``encoder train``, which must leave a resumable checkpoint), the last-resort handler and the dataset's bone offsets.
"""
from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from modi.cli import main

pytestmark = pytest.mark.usefixtures("one_torch_thread")

T = 16  # frames of the tiny MoDi generator


def _tiny_generator_checkpoint(path: Path) -> None:
    """A tiny untrained MoDi generator on the built-in humanoid (what ``modi train`` would save, minus training)."""
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
    raw = torch.cat([rep.encode(generate_clip(k, 40, 30.0, np.random.default_rng(i))).unfold(-1, T, 8)
                     .permute(2, 0, 1, 3) for i, k in enumerate(KINDS)]).float()
    codec = MotionCodec(rep, Normalizer.fit(raw, skip_entities=rep.contacts), 30.0)
    cfg = ModelConfig(latent_dim=16, n_mlp=2, channels=(8, 8, 8))
    g = Generator(cfg, build_levels(build_hierarchy(sk, feet), cfg, T), rep.K).eval()
    torch.save(generator_bundle(g, codec), path)


def _cut_frames(src: Path, dst: Path, n: int, root_offset: str | None = None) -> None:
    """Copy of a BVH keeping its first ``n`` frames (and optionally another ROOT OFFSET line)."""
    lines = src.read_text().splitlines()
    m = lines.index("MOTION")
    head = lines[:m]
    if root_offset is not None:
        i = next(k for k, line in enumerate(head) if line.strip().startswith("OFFSET"))
        head[i] = f"\tOFFSET {root_offset}"
    frame_time = next(line for line in lines[m:] if line.startswith("Frame Time"))
    body = [line for line in lines[m + 3:] if line.strip()][:n]
    dst.write_text("\n".join(head + ["MOTION", f"Frames: {n}", frame_time] + body) + "\n")


def _single_joint_bvh(path: Path, frames: int = 40) -> None:
    rows = [f"{0.5 * i:.3f} {90 + np.sin(i / 5):.3f} 0 0 {2 * i:.3f} 0" for i in range(frames)]
    path.write_text("\n".join(["HIERARCHY", "ROOT Hips", "{", "\tOFFSET 0 0 0",
                               "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
                               "\tEnd Site", "\t{", "\t\tOFFSET 0 10 0", "\t}", "}", "MOTION",
                               f"Frames: {frames}", "Frame Time: 0.0333333"] + rows) + "\n")


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> dict[str, str]:
    """Inputs of every case: procedural clips, short clips, a single-joint rig, checkpoints of each kind."""
    from modi.data.procedural import write_dataset

    w = tmp_path_factory.mktemp("inputs")
    d = w / "d"
    write_dataset(d, n_clips=3, frames=40, seed=0)
    clip = d / "0000_walk.bvh"
    _cut_frames(clip, w / "short1.bvh", 1)
    _cut_frames(clip, w / "short2.bvh", 2)
    _cut_frames(clip, w / "clip10.bvh", 10)
    _single_joint_bvh(w / "one.bvh")
    big = w / "big"  # the same rig with every bone 10% longer
    big.mkdir()
    for f in sorted(d.glob("*.bvh")):
        (big / f.name).write_text(re.sub(r"OFFSET ([-\d. ]+)", lambda m: "OFFSET " + " ".join(
            f"{1.1 * float(v):.4f}" for v in m.group(1).split()), f.read_text()))
    _tiny_generator_checkpoint(w / "tiny.pt")
    (w / "empty.pt").write_bytes(b"")
    torch.save({"a": 1}, w / "dict.pt")
    np.save(w / "nan.npy", np.full(16, np.nan, dtype=np.float32))
    gan = w / "gan"
    rc = main(["ganimator", "train", str(clip), "--out", str(gan), "--preset", "tiny", "--iterations", "1",
               "--quiet"])
    assert rc == 0
    rc = main(["encoder", "train", str(w / "tiny.pt"), str(d), "--out", str(w / "enc.pt"), "--iters", "1",
               "--batch", "2", "--eval-every", "0", "--quiet", "--no-cache"])
    assert rc == 0
    return {"d": str(d), "clip": str(clip), "clip2": str(d / "0001_run.bvh"), "file": str(d / "labels.json"),
            "short1": str(w / "short1.bvh"), "short2": str(w / "short2.bvh"), "clip10": str(w / "clip10.bvh"),
            "one": str(w / "one.bvh"), "tiny": str(w / "tiny.pt"), "empty": str(w / "empty.pt"),
            "dict": str(w / "dict.pt"), "nan": str(w / "nan.npy"), "gan": str(gan), "enc": str(w / "enc.pt"),
            "big": str(big), "root": str(w)}


NO_CUDA = not torch.cuda.is_available()

# (command line with {placeholders}, a substring the single error line must contain)
CASES: list[tuple[str, str]] = [
    # --- non-finite / out-of-range numbers, named at the argument boundary
    ("synth {out} --fps 1e9", "argument --fps"),
    ("synth {out} --fps nan", "argument --fps: must be a finite number"),
    ("synth {out} --n 0", "argument --n"),
    ("synth {out} --seed -1", "argument --seed"),
    ("data info {d} --fps inf", "argument --fps"),
    ("data info {d} --window 0", "argument --window"),
    ("data info {d} --test-fraction 1.5", "argument --test-fraction"),
    ("render {clip} {out}.gif --azimuth nan", "argument --azimuth"),
    ("render {clip} {out}.gif --fps 0", "argument --fps"),
    ("render {clip} {out}.gif --max-frames 0", "argument --max-frames"),
    ("train {d} --out {out} --fps nan", "argument --fps"),
    ("train {d} --out {out} --lr nan", "argument --lr"),
    ("train {d} --out {out} --lr -0.8", "argument --lr"),
    ("train {d} --out {out} --log-every 0", "argument --log-every"),
    ("train {d} --out {out} --frames 65", "multiple of 16"),
    ("train {d} --out {out} --threads -2", "argument --threads"),
    ("train {d} --out {out} --seed -1", "argument --seed"),
    ("train {d} --out {out} --mixing 2", "argument --mixing"),
    ("train {d} --out {out} --representation edges", "argument --representation: invalid choice"),
    ("train {d} --out {out} --precision fp16", "argument --precision: invalid choice"),
    ("train {d} --out {out} --precision nan", "argument --precision: invalid choice"),
    ("ganimator train {clip} --out {out} --precision bfloat16", "argument --precision: invalid choice"),
    ("train {d} --out {out} --cuda-graphs yes", "argument --cuda-graphs: invalid choice"),
    ("generate {tiny} --out {out} --psi 1e30", "argument --psi"),
    ("generate {tiny} --out {out} --psi inf", "argument --psi"),
    ("generate {tiny} --out {out} --batch 0", "argument --batch"),
    ("latent interpolate {tiny} --out {out} --steps 0", "argument --steps"),
    ("latent interpolate {tiny} --out {out} --from {nan}", "NaN"),
    ("latent interpolate {tiny} --out {out} --to -1", "--to: a seed must be"),
    ("latent edit {tiny} --out {out} --alphas nan 1", "argument --alphas"),
    ("latent edit {tiny} --out {out} --alphas 1 0", "--alphas must be increasing"),
    ("latent edit {tiny} --out {out} --ratio 0.7", "argument --ratio"),
    ("latent edit {tiny} --out {out} --ratio 0", "argument --ratio"),
    ("latent crowd {tiny} --out {out} --sigma nan", "argument --sigma"),
    ("latent crowd {tiny} --out {out} --spacing -1", "argument --spacing"),
    ("latent invert {tiny} {clip} --out {out} --lr nan", "argument --lr"),
    ("encoder train {tiny} {d} --out {out}.pt --lr nan", "argument --lr"),
    ("encoder train {tiny} {d} --out {out}.pt --iters -1", "argument --iters"),
    ("apply denoise {empty} {clip} --out {out} --sigma nan", "argument --sigma"),
    ("ganimator train {clip} --out {out} --fps 0", "argument --fps"),
    ("ganimator train {clip} --out {out} --fps -30", "argument --fps"),
    ("ganimator train {clip} --out {out} --base-channels -4", "argument --base-channels"),
    ("ganimator train {clip} --out {out} --max-minutes 0", "argument --max-minutes"),
    ("ganimator train {clip} --out {out} --coarse-ratio 0", "argument --coarse-ratio"),
    ("ganimator train {clip} --out {out} --coarse-multiplier inf", "argument --coarse-multiplier"),
    ("encoder train {tiny} {d} --out {out}.pt --lambda-rec -1", "argument --lambda-rec"),
    ("ganimator generate {gan} --out {out} --crowd-spacing nan", "argument --crowd-spacing"),
    ("ganimator generate {gan} --out {out} --crowd-spacing -1", "argument --crowd-spacing"),
    ("blender install --blender {root}/no_blender", "Blender not found"),
    ("blender install --blender /bin/true --modi {root}/no_modi", "not an executable modi command"),
    ("blender install --blender /bin/true --modi {file}", "not an executable modi command"),
    ("blender addon --out {root}/no_folder/modi_blender.zip", "no such folder"),
    ("blender addon --out {d}", "is a folder, expected the .zip file"),
    ("ganimator generate {gan} --out {out} --n 0", "argument --n"),
    ("eval plausibility {clip} --ground nan", "argument --ground"),
    ("eval single --source {clip} {clip2} --threshold nan", "argument --threshold"),
    ("eval train-features {d} --out {out}.pt --holdout 1", "argument --holdout"),
    ("demo --out {out} --threads 0", "argument --threads"),
    # --- unbounded sizes, refused before any work
    ("data info {d} --fps 1e6", "argument --fps"),
    ("synth {out} --frames 10000000", "argument --frames"),
    ("train {d} --out {out} --batch 100000", "argument --batch"),
    ("generate {tiny} --out {out} --n 100000000", "argument --n"),
    ("latent cluster {tiny} --out {out} --n 100000000", "argument --n"),
    ("ganimator generate {gan} --out {out} --frames 10000000", "argument --frames"),
    ("encoder train {tiny} {d} --out {out}.pt --batch 100000", "argument --batch"),
    # --- too-short motion for GANimator: the minimum length and why
    ("ganimator train {short2} --out {out}", "needs at least 15 frames"),
    ("ganimator train {clip10} --out {out}", "reflect padding"),
    ("ganimator generate {gan} --out {out} --frames 10", "--frames 10 is too short for this run: at least"),
    ("ganimator generate {gan} --out {out} --content {short2}", "--content"),
    ("ganimator generate {gan} --out {out} --keyframes {short1}", "at least 2 key-frames"),
    ("ganimator generate {gan} --out {out} --loop --frames 3", "a loop needs at least"),
    ("ganimator generate {gan} --out {out} --loop --frames nan", "argument --frames"),
    ("ganimator generate {gan} --out {out} --loop --loop-root back", "argument --loop-root"),
    ("ganimator generate {gan} --out {out} --inbetween {d}/nope.bvh {clip} --frames 20", "no such BVH file"),
    ("ganimator generate {gan} --out {out} --inbetween {clip}@999 {clip} --frames 20", "is outside the clip"),
    ("ganimator generate {gan} --out {out} --inbetween {clip} {clip}", "--inbetween needs --frames"),
    ("ganimator generate {gan} --out {out} --inbetween {clip} {clip} --frames 0", "argument --frames"),
    ("ganimator generate {gan} --out {out} --expand {clip} --frames 20", "must be longer than the clip"),
    ("ganimator generate {gan} --out {out} --expand {clip} --frames 900 --at -1", "argument --at"),
    ("ganimator generate {gan} --out {out} --edit {clip} --keep Tail", "no joint named 'Tail'"),
    ("ganimator generate {gan} --out {out} --edit {clip}", "--edit needs --keep"),
    ("ganimator generate {gan} --out {out} --keep lower", "--keep goes with --edit"),
    ("ganimator generate {gan} --out {out} --content {clip} --content-level 63", "--content-level 63"),
    ("ganimator generate {gan} --out {out} --content-level -1", "argument --content-level"),
    ("ganimator generate {gan} --out {out} --loop --edit {clip} --keep lower", "use only one of"),
    # --- output paths: a file, under a file, an input
    ("synth {file}", "is a file, expected a folder"),
    ("synth {file}/sub", "which is a file, not a folder"),
    ("export positions {clip} {clip}", "refusing to write over an input"),
    ("export positions {clip} {file}/x.npy", "which is a file, not a folder"),
    ("export positions {clip} {d}", "is a folder, expected a file"),
    ("export positions {clip} {out}.npy --names {clip}", "refusing to write over an input"),
    ("render {clip} {file}/o.gif", "which is a file, not a folder"),
    ("train {d} --out {file}", "is a file, expected a folder"),
    ("generate {tiny} --out {file}", "is a file, expected a folder"),
    ("latent mean {tiny} --out {file}/x", "which is a file, not a folder"),
    ("ganimator train {clip} --out {file}", "is a file, expected a folder"),
    ("ganimator generate {gan} --out {clip}", "is a file, expected a folder"),
    ("encoder train {tiny} {d} --out {d}", "is a folder, expected a file"),
    ("eval plausibility {clip} --json {d}", "is a folder, expected a file"),
    ("eval plausibility {clip} --json {clip}", "refusing to write over an input"),
    ("encoder eval {tiny} --json {tiny}", "refusing to write over an input"),
    ("ganimator eval {gan} --json {gan}/ganimator.ckpt", "refusing to write over an input"),
    ("eval train-features {d} --out {out}.pt --json {out}.pt", "is also --out"),
    # --- glTF export, the viewer and --format
    ("export gltf {d}/nope.bvh {out}.glb", "no such BVH file"),
    ("export gltf {clip} {out}.txt", "must end in .glb or .gltf"),
    ("export gltf {clip} {out}.glb --scale 0", "argument --scale"),
    ("export gltf {clip} {out}.glb --scale nan", "argument --scale"),
    ("view {d}/nope.bvh --out {out}.html", "no such file"),
    ("view {clip} --out {clip}", "the page must end in .html"),
    ("synth {out} --format bvh,fbx", "unknown format 'fbx'"),
    # --- devices: say which exist
    ("train {d} --out {out} --device gpu7", "devices here: cpu"),
    ("generate {tiny} --out {out} --device cuda:99", "devices here: cpu"),
    ("ganimator train {clip} --out {out} --device gpu7", "devices here: cpu"),
    ("latent mean {tiny} --out {out} --device tpu", "devices here: cpu"),
    ("encoder eval {empty} --device gpu7", "devices here: cpu"),
    *([("generate {tiny} --out {out} --device cuda", "this torch has no CUDA device"),
       ("ganimator train {clip} --out {out} --device cuda", "this torch has no CUDA device")] if NO_CUDA else []),
    # --- feet and joints
    ("data info {d} --window 16 --feet LeftToe LeftToe", "joint 'LeftToe' is given twice"),
    ("data info {d} --window 16 --feet Hips", "the root joint Hips cannot be a foot"),
    ("data info {d} --window 16 --feet Nope", "Nope"),
    ("train {d} --out {out} --feet LeftToe LeftToe", "given twice"),
    ("ganimator train {clip} --out {out} --feet LeftToe,LeftToe", "given twice"),
    ("ganimator train {clip} --out {out} --feet Hips,LeftToe", "root joint Hips cannot be a foot"),
    ("eval plausibility {clip} --feet Hips", "root joint Hips cannot be a foot"),
    ("eval plausibility {clip} --feet LeftToe LeftToe", "given twice"),
    ("eval plausibility {one}", "name them with --feet"),
    # --- checkpoints: empty, foreign, the wrong kind
    ("encoder eval {empty} {d}", "not a readable encoder checkpoint"),
    ("encoder eval {tiny} {d}", "this is a generator checkpoint"),
    ("encoder eval {dict} {d}", "not a MoDi encoder checkpoint"),
    ("apply invert {empty} {clip} --out {out}", "not a readable encoder checkpoint"),
    ("apply fuse {tiny} {clip} {clip2} --out {out}", "this is a generator checkpoint"),
    ("generate {empty} --out {out}", "not a readable MoDi checkpoint"),
    ("generate {dict} --out {out}", "not a MoDi checkpoint"),
    ("latent mean {empty} --out {out}", "not a readable MoDi checkpoint"),
    ("encoder train {dict} {d} --out {out}.pt", "not a MoDi checkpoint"),
    ("encoder train {tiny} {big} --out {out}.pt", "same joints, but bone offsets differ"),
    ("train {d} --out {out} --resume {empty}", "not a readable MoDi checkpoint"),
    ("ganimator generate {tiny} --out {out}", "not a GANimator checkpoint"),
    ("ganimator generate {empty} --out {out}", "cannot read checkpoint"),
    ("ganimator generate {root}/X.pt --out {out}", "no such GANimator run folder or checkpoint file"),
    ("ganimator train {clip} --out {out} --conditional-from {root}/nope", "--conditional-from"),
    # --- found only after the output folder was made: it is removed again
    ("apply fuse {enc} {clip} {clip2} --out {out}/x --frame 1000", "fusion frame must be in"),
    ("apply edit {enc} {clip} --out {out} --from-frame 1000", "edit start frame"),
    ("apply prefix {enc} {clip} --out {out}", "--prefix"),
    ("apply invert {enc} test:999 --out {out}", "the test split has windows"),
    ("train {d} --out {out} --preset small", "no training windows"),
    ("ganimator generate {gan} --out {out} --trajectory {clip}", "needs a trajectory-conditioned run"),
    ("latent edit {tiny} --out {out} --boundary {file}", "not a boundary file"),
    ("encoder train {tiny} {d} --out {out}.pt --units furlongs", "argument --units"),
    # --- misleading messages, now saying what is wrong
    ("render {d} {out}.gif", "is a folder, expected a BVH file"),
    ("eval plausibility {d}", "is a folder, expected a BVH file"),
    ("ganimator train {d} --out {out}", "is a folder, expected a BVH file"),
    ("export positions {d} {out}.npy", "is a folder, expected a .bvh file"),
    ("latent invert {tiny} {d} --out {out}", "is a folder, expected a BVH file"),
    ("generate {gan} --out {out}", "is a folder, expected a MoDi checkpoint file"),
    ("encoder eval {gan}", "is a folder, expected an encoder checkpoint file"),
    ("train {d} --out {out} --resume {gan}", "--resume"),
    ("train {d} --out {out} --preset nope", "argument --preset: invalid choice"),
]


_PROGRESS = re.compile(r"\d+%\|")  # a tqdm progress bar while data loads


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("line, expected", CASES, ids=[c[0].replace(" ", "_")[:70] for c in CASES])
def test_bad_input_is_one_line_exit_2(line, expected, work, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MODI_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("MODI_TRACEBACK", raising=False)
    out = tmp_path / "o" / "out"
    (tmp_path / "o").mkdir()
    argv = [a.format(out=out, **work) for a in shlex.split(line)]
    before_in, before_out = _snapshot(Path(work["root"])), _snapshot(tmp_path / "o")
    capsys.readouterr()
    rc = main(argv)
    captured = capsys.readouterr()
    err_lines = [line for line in captured.err.splitlines() if line.strip() and not _PROGRESS.search(line)]
    assert rc == 2, (argv, rc, captured.err[-2000:])
    assert len(err_lines) == 1, err_lines
    assert "error:" in err_lines[0] and expected in err_lines[0], err_lines[0]
    assert "Traceback" not in captured.err + captured.out and "internal error" not in err_lines[0]
    assert _snapshot(Path(work["root"])) == before_in, "an input was changed"
    assert _snapshot(tmp_path / "o") == before_out, "partial output left behind"


def test_table_covers_every_command():
    commands = {" ".join(c[0].split()[:2]) if c[0].split()[0] in ("data", "latent", "encoder", "apply", "ganimator",
                                                                   "eval", "export") else c[0].split()[0]
                for c in CASES}
    for cmd in ("synth", "data info", "render", "export positions", "train", "generate", "demo", "latent mean",
                "latent interpolate", "latent edit", "latent crowd", "latent cluster", "latent invert",
                "encoder train", "encoder eval", "apply invert", "ganimator train", "ganimator generate",
                "eval plausibility", "eval single", "eval train-features"):
        assert cmd in commands, cmd
    assert len(CASES) >= 100


def test_single_joint_rig_has_no_feet_and_works(work, tmp_path, monkeypatch, capsys):
    """IK / contacts on a single-joint skeleton: the root is never a foot, so there is nothing to pin."""
    monkeypatch.setenv("MODI_CACHE", str(tmp_path / "cache"))
    d = tmp_path / "one"
    d.mkdir()
    (d / "one.bvh").write_text(Path(work["one"]).read_text())
    assert main(["data", "info", str(d), "--window", "16"]) == 0
    assert "feet:        (none)" in capsys.readouterr().out


def test_rerunning_a_finished_ganimator_run_says_so(work, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(work["gan"], run)
    capsys.readouterr()
    assert main(["ganimator", "train", work["clip"], "--out", str(run), "--preset", "tiny", "--iterations", "1",
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "already fully trained" in out and "resuming" not in out


def test_last_resort_handler(monkeypatch, capsys):
    """A genuine bug: one line naming the exception and how to get the traceback; MODI_TRACEBACK=1 re-raises."""
    import modi.cli.commands.synth as proc

    def boom(args):
        raise RuntimeError("something inside broke\nsecond line")

    monkeypatch.setattr(proc, "run", boom)  # register() binds the module's run when the parser is built
    monkeypatch.delenv("MODI_TRACEBACK", raising=False)
    assert main(["synth", "x"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "internal error" in err[0] and "MODI_TRACEBACK=1" in err[0] and "RuntimeError" in err[0]
    monkeypatch.setenv("MODI_TRACEBACK", "1")
    with pytest.raises(RuntimeError):
        main(["synth", "x"])


def _ctrl_c_env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[3])}


def test_ctrl_c_at_start_is_not_a_traceback(tmp_path):
    """SIGINT while modi is still importing torch and building the parser: one line, exit 130.

    The child says when the interpreter's own start-up (``site``) is over, and the signal is sent ``delay`` later:
    a signal during the interpreter's start-up is CPython's to report, not modi's (on a loaded machine start-up can
    take longer than the delay)."""
    launcher = ("import runpy, sys; sys.stderr.write('ready\\n'); sys.stderr.flush(); "
                "sys.argv = ['modi'] + sys.argv[1:]; runpy.run_module('modi', run_name='__main__', alter_sys=True)")
    for delay in (0.05, 0.4):
        p = subprocess.Popen([sys.executable, "-c", launcher, "synth", str(tmp_path / f"s{delay}")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_ctrl_c_env(),
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        assert p.stderr.readline().strip() == "ready"
        try:
            p.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
        assert "Traceback" not in err, err
        if p.returncode != 0:  # a fast machine may finish first
            assert p.returncode in (130, -signal.SIGINT) and "interrupted" in err, (p.returncode, err)


def test_ctrl_c_during_ganimator_train_saves_a_resumable_checkpoint(work, tmp_path, monkeypatch, capsys):
    from modi.models.ganimator.training import Trainer, read_checkpoint

    real = Trainer._iteration
    calls = []

    def iteration(self, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            signal.raise_signal(signal.SIGINT)  # what Ctrl-C does, delivered in the middle of an iteration
        return real(self, *a, **k)

    monkeypatch.setattr(Trainer, "_iteration", iteration)
    run = tmp_path / "run"
    rc = main(["ganimator", "train", work["clip"], "--out", str(run), "--preset", "tiny", "--iterations", "50",
               "--quiet"])
    err = capsys.readouterr().err
    assert rc == 130 and "checkpoint saved" in err and "Traceback" not in err
    assert "stopping after this" in err
    st = read_checkpoint(run)["state"]
    assert (st["block"], st["iteration"]) == (0, 3)  # the interrupted iteration finished, then it saved
    monkeypatch.setattr(Trainer, "_iteration", real)
    assert main(["ganimator", "train", work["clip"], "--out", str(run), "--preset", "tiny", "--iterations", "50",
                 "--quiet", "--max-minutes", "0.001"]) == 0
    assert "resuming" in capsys.readouterr().out


def test_ctrl_c_during_encoder_train_saves_a_resumable_checkpoint(work, tmp_path, monkeypatch, capsys):
    from modi.models.modi.encoder.training import EncoderTrainer

    real = EncoderTrainer.train_step

    def step(self):
        if self.step == 2:
            signal.raise_signal(signal.SIGINT)
        return real(self)

    monkeypatch.setattr(EncoderTrainer, "train_step", step)
    monkeypatch.setenv("MODI_CACHE", str(tmp_path / "cache"))
    enc = tmp_path / "enc.pt"
    rc = main(["encoder", "train", work["tiny"], work["d"], "--out", str(enc), "--iters", "20", "--batch", "4",
               "--eval-every", "0", "--ckpt-every", "0", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 130 and "checkpoint saved" in err and "--resume" in err and "Traceback" not in err
    assert "stopping after this" in err
    assert torch.load(enc, map_location="cpu", weights_only=True)["step"] == 3


def test_stop_on_sigint_finishes_the_step_then_a_second_ctrl_c_aborts(capsys):
    """The one handler both GANimator and encoder training use: the first Ctrl-C sets the flag and says so on
    stderr, the second raises at once, and the previous handler is back afterwards."""
    from modi.faults import stop_on_signals

    before = signal.getsignal(signal.SIGINT)
    with stop_on_signals("iteration") as stop:
        assert not stop
        signal.raise_signal(signal.SIGINT)
        assert stop
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    out = capsys.readouterr()
    assert out.out == "" and "stopping after this iteration and saving a checkpoint" in out.err
    assert signal.getsignal(signal.SIGINT) is before


def test_dataset_offsets_do_not_come_from_one_odd_clip(work, tmp_path):
    """A 1-frame clip whose ROOT OFFSET is a world position must not set the skeleton, whatever the file order."""
    from modi.data.dataset import DatasetConfig, build_dataset

    clips = sorted(Path(work["d"]).glob("*.bvh"))
    offsets = []
    for name in ("0000_aaa_bind.bvh", "9999_zzz_bind.bvh"):
        d = tmp_path / name
        d.mkdir()
        for c in clips:
            (d / c.name).write_text(c.read_text())
        _cut_frames(clips[0], d / name, 1, root_offset="-1.7 90.3 -407.1")
        ds = build_dataset(d, DatasetConfig(window=16, stride=8), cache=False)
        assert abs(ds.skeleton.offsets[0]).max() < 1.0, ds.skeleton.offsets[0]
        offsets.append(ds.skeleton.offsets)
    np.testing.assert_array_equal(offsets[0], offsets[1])
    ref = build_dataset(work["d"], DatasetConfig(window=16, stride=8), cache=False).skeleton
    np.testing.assert_array_equal(offsets[0], ref.offsets)


def test_argument_types():
    import argparse

    from modi.cli import types as ct

    assert ct.positive_int("3") == 3 and ct.nonneg_int("0") == 0 and ct.multiple_of(16)("64") == 64
    assert ct.float_range(0, 1, lo_inclusive=False)("1") == 1.0 and ct.finite_float("-2.5") == -2.5
    bad = [(ct.positive_int, "0"), (ct.positive_int, "1.5"), (ct.multiple_of(16), "65"), (ct.multiple_of(16), "0"),
           (ct.float_range(0, 1, lo_inclusive=False), "0"), (ct.float_range(0, 1, hi_inclusive=False), "1"),
           (ct.finite_float, "nan"), (ct.finite_float, "-inf"), (ct.finite_float, "x"), (ct.fps_float, "1e6"),
           (ct.seed_int, "-1"), (ct.batch_int, "100000"), (ct.device, "gpu7")]
    for parse, text in bad:
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)
    assert ct.device("cpu") == "cpu" and ct.device_or_auto("auto") == "auto"


def test_a_reader_that_leaves_early_is_not_an_error(tmp_path):
    """`modi info RUN | head -1`: the reader closes the pipe; modi says nothing on stderr and exits as a shell tool
    killed by SIGPIPE would (141), instead of 'modi: error: Broken pipe'."""
    child = ("import sys; import modi.cli.commands.synth as p\n"
             "p.run = lambda args: [print('x' * 1000, flush=True) for _ in range(10000)]\n"
             "from modi.cli import main; sys.exit(main(['synth', sys.argv[1]]))\n")
    proc = subprocess.Popen([sys.executable, "-c", child, str(tmp_path / "out")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=_ctrl_c_env())
    assert proc.stdout.readline().startswith(b"xxx")
    proc.stdout.close()  # what `head -1` does after its line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert err == ""
