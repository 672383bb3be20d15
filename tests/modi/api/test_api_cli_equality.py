"""Seed for seed, the Python API gives the motions the CLI writes: ``modi.load(ckpt).generate(n, seed=s)`` and
``modi generate CKPT --n n --seed s``; ``modi.load(run).generate(n, frames=F, seed=s)`` and ``modi ganimator generate
RUN --n n --frames F --seed s``. Compared as the BVH text each writes (6 decimals), which must be identical."""
from __future__ import annotations

import pytest

import modi
from modi.cli import main
from modi.io import bvh as bvh_io

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize("n, seed, batch, extra", [(3, 0, None, []), (3, 7, 2, ["--psi", "0.6", "--ik"])])
def test_modi_sample_equals_modi_generate(modi_run, tmp_path, n, seed, batch, extra):
    """(Both batch motions alike: the default, or the same ``batch``; across batch sizes a motion agrees only to
    float rounding.)"""
    out = tmp_path / "gen"
    assert main(["generate", str(modi_run / "checkpoint.pt"), "--n", str(n), "--seed", str(seed), "--out", str(out),
                 "--gif-max", "0", *(["--batch", str(batch)] if batch else []), *extra]) == 0
    psi = float(extra[1]) if extra else 1.0
    motions = modi.load(modi_run / "checkpoint.pt").generate(n, seed=seed, psi=psi, ik="--ik" in extra,
                                                           **({"batch": batch} if batch else {}))
    assert len(motions) == n
    for i, m in enumerate(motions):
        written = (out / f"motion_{i:04d}.bvh").read_text()
        assert bvh_io.dumps(m.to_bvh()) == written, f"motion {i}"


@pytest.mark.parametrize("n, frames, seed", [(1, None, 0), (3, 50, 5)])
def test_ganimator_generate_equals_modi_ganimator_generate(gan_run, tmp_path, n, frames, seed):
    out = tmp_path / "gen"
    args = ["ganimator", "generate", str(gan_run), "--n", str(n), "--seed", str(seed), "--out", str(out), "--no-gif"]
    assert main(args + (["--frames", str(frames)] if frames else [])) == 0
    # the CLI places several motions on a crowd grid 1.5 body sizes apart: spacing=None asks for the same
    motions = modi.load(gan_run).generate(n, frames=frames, seed=seed, spacing=None)
    names = ["sample.bvh"] if n == 1 else [f"sample_{i:03d}.bvh" for i in range(n)]
    for m, name in zip(motions, names):
        assert bvh_io.dumps(m.to_bvh()) == (out / name).read_text(), name


@pytest.mark.parametrize("mode", ["loop", "expand", "edit"])
def test_ganimator_applications_equal_their_cli(gan_run, tmp_path, mode):
    """The applications of docs/single_clip.md: the CLI writes what GanimatorRun.generate returns."""
    run = modi.load(gan_run)
    src = tmp_path / "src.bvh"
    run.write(run.generate(1, frames=run.n_frames, seed=9), tmp_path / "src", gif=False)
    (tmp_path / "src" / "sample.bvh").rename(src)
    keep = run.skeleton.names[1]
    cli = {"loop": ["--loop", "--frames", "60", "--loop-root", "return"],
           "expand": ["--expand", str(src), "--frames", str(run.n_frames + 20), "--at", "5"],
           "edit": ["--edit", str(src), "--keep", keep]}[mode]
    api = {"loop": dict(loop=True, frames=60, loop_root="return"),
           "expand": dict(expand=src, frames=run.n_frames + 20, at=5),
           "edit": dict(edit=src, keep=keep)}[mode]
    out = tmp_path / "gen"
    assert main(["ganimator", "generate", str(gan_run), "--seed", "4", "--out", str(out), "--no-gif", *cli]) == 0
    m = run.generate(1, seed=4, **api)[0]
    assert bvh_io.dumps(m.to_bvh()) == (out / "sample.bvh").read_text()
