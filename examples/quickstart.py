"""modi from Python, end to end, in a couple of minutes on a laptop CPU (CI runs this file: tests/modi/api).

    python examples/quickstart.py --out quickstart_out [--bvh my_clip.bvh] [--modi-ckpt runs/modi/checkpoint.pt]

1. read a BVH clip (yours, or a built-in procedural walk) and look at it in metres;
2. train a tiny GANimator on it and generate new motions;
3. load a MoDi checkpoint (yours, or one trained here for two steps) and sample, interpolate;
4. write BVH and glTF, and the 3D viewer page;
5. build a network of one's own from modi_ext layers on the clip's skeleton and compile it with torch.compile.

The tiny schedules make the motions meaningless; the calls are the ones real runs use.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from torch import nn

import modi
from modi_ext.layers import SkeletalConv, SkeletalDownsample, SkeletalUpsample


def builtin_clip(folder: Path) -> Path:
    """A stand-in for your own BVH: the package's procedural humanoid walking (what ``modi synth`` writes)."""
    from modi.models.modi.training import write_procedural_data

    return sorted(write_procedural_data(folder, n_clips=6, frames=40, seed=1).glob("*.bvh"))[0]


class TinyAutoencoder(nn.Module):
    """Skeleton-aware conv -> pool to the next level of the skeleton's hierarchy -> unpool -> conv, on the
    (B, 4, J, T) joint rotations of a clip: a network of one's own on any rig."""

    def __init__(self, topo: modi.Topology, width: int = 16) -> None:
        super().__init__()
        self.enc = SkeletalConv(4, width, topo.neighbors(0))
        self.down = SkeletalDownsample(width, width, topo.pooling(0))
        self.up = SkeletalUpsample(width, width, topo.pooling(0))
        self.dec = SkeletalConv(width, 4, topo.neighbors(0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = torch.nn.functional.leaky_relu(self.enc(x), 0.2)
        h = torch.nn.functional.leaky_relu(self.down(h), 0.2)
        return self.dec(torch.nn.functional.leaky_relu(self.up(h), 0.2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="quickstart_out", help="output folder (created)")
    ap.add_argument("--bvh", default=None, help="a BVH clip (default: a built-in procedural walk)")
    ap.add_argument("--modi-ckpt", default=None, help="a MoDi checkpoint (default: train a tiny one here)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)

    # 1. a clip: one Motion type, fps and length unit always known
    bvh = Path(args.bvh) if args.bvh else builtin_clip(out / "data")
    clip = modi.load(bvh)
    print(clip)
    height = float(clip.positions(unit="m")[0, :, 1].max() - clip.positions(unit="m")[0, :, 1].min())
    print(f"  {clip.duration:.2f} s, about {height:.2f} m tall in its first frame (file unit: {clip.unit})")

    # 2. GANimator: train (tiny schedule) and generate
    run = modi.train_ganimator(bvh, out / "ganimator", preset="tiny", iterations=5, max_levels=2, coarse_ratio=0.5,
                               resume=True, progress=lambda p: None)
    print(run)
    variations = run.generate(2, frames=2 * clip.n_frames, seed=0)
    edited = run.generate(1, keyframes=bvh, seed=1)  # any BVH on the rig serves as coarse key-frames here
    print(f"  GANimator: {len(variations)} motions of {variations[0].n_frames} frames, key-frame edit "
          f"{edited[0].n_frames} frames")

    # 3. MoDi: load a checkpoint (or train a tiny one) and sample
    if args.modi_ckpt:
        gen = modi.load(args.modi_ckpt)
    else:
        tiny = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
                "data.stride": 8, "train.batch": 2, "train.sample_every": 0, "train.ckpt_every": 0}
        gen = modi.train_modi(bvh.parent, out / "modi", config=tiny, iters=2, resume=(out / "modi" /
                                                                                 "checkpoint.pt").exists())
    print(gen)
    samples = gen.generate(4, seed=0, psi=0.7)
    blend = gen.interpolate(0, 1, steps=4)
    print(f"  MoDi: {len(samples)} samples, an interpolation of {len(blend)} motions; feet {gen.feet}")
    print(f"  what modi info says: {modi.inspect(gen.path).kind}")

    # 4. files: BVH, glTF (metres, contact labels inside), the viewer page
    variations[0].to_bvh(out / "ganimator_0.bvh")
    variations[0].to_gltf(out / "ganimator_0.glb")
    samples[0].to_bvh(out / "modi_0.bvh")
    samples[0].to_gltf(out / "modi_0.gltf")
    modi.show([clip, *variations, samples[0]], titles=["source", "GANimator 0", "GANimator 1", "MoDi 0"],
              out=out / "view.html")
    print(f"  wrote {out / 'ganimator_0.glb'}, {out / 'modi_0.gltf'}, {out / 'view.html'}")

    # 5. layers of one's own on the clip's skeleton, compiled
    topo = modi.Topology(clip.skeleton)  # joints only: one entity per joint
    print(f"  {topo!r}")
    net = TinyAutoencoder(topo)
    frames = clip.n_frames - clip.n_frames % 2
    x = clip.rotations[:frames].float().permute(2, 1, 0).unsqueeze(0).contiguous()  # (1, 4, J, T)
    t0 = time.perf_counter()
    compiled = torch.compile(net)
    y = compiled(x)
    seconds = time.perf_counter() - t0
    torch.testing.assert_close(y, net(x), rtol=1e-4, atol=1e-4)
    loss = (y - x).square().mean()
    loss.backward()  # gradients flow through the compiled graph and the extension's kernels
    loss = loss.detach()
    print(f"  torch.compile'd skeletal autoencoder: {tuple(x.shape)} -> {tuple(y.shape)}, first call "
          f"{seconds:.1f} s (compilation), loss {loss.item():.3f}")
    print("done")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
