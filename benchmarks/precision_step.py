"""Training in bf16 against fp32 (docs/precision.md): what a step costs, and how exact the regularisers stay.

    python benchmarks/precision_step.py step --threads 1 --reps 7 --json benchmarks/results/precision_step.json
    python benchmarks/precision_step.py regularisers --threads 1 --json benchmarks/results/precision_regularisers.json
    python benchmarks/precision_step.py regularisers --ckpt RUN/checkpoint.pt   # on trained weights

``step``: two MoDi trainers (``--preset``, default small; Bandai-Namco-1 from ../shared/data, else the procedural
clips), identical weights, seeds and data order, one with ``precision="fp32"`` and one with ``"bf16"``. After one
warm-up cycle each, they advance in interleaved cycles of 16 iterations (one R1 step, four path-length steps: what a
run pays per iteration), ``--reps`` cycles each; reported are the median seconds per iteration of each precision over
the cycles, their min-max spread, and the bf16 / fp32 ratio of each pair of cycles (median, min, max).

``regularisers``: one batch through the same MoDi model in float64 (the reference), fp32 and bf16 autocast (the
networks' forward passes under autocast, every loss from their outputs cast to fp32, as the trainer does), and the
relative error of each against float64: the plain D and G losses, R1 and the path-length penalty, each as its value
and as its gradient on the weights (||g - g64|| / ||g64||). The path-length penalty is
``modi.models.modi.losses.path_length_penalty``'s formula with its random projection drawn once (float64, cast to
each side), and its running mean set to the float64 lengths' mean (a converged run's; at init the mean is 0 and the
penalty is the mean square length, far less sensitive). With ``--ganimator`` the same for GANimator's WGAN-GP on the
finest block of one clip (fast preset). bf16's unit roundoff is 2^-8 = 0.0039; fp32's 2^-24.
"""
from __future__ import annotations

import argparse
import copy
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(1 + len([p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]), str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import modi_ext  # noqa: E402,F401  (before torch, as the modi command does)
import torch  # noqa: E402

from compare import machine, write_json  # noqa: E402  (benchmarks/compare.py)
from modi.models.modi.config import make_config  # noqa: E402
from modi.models.precision import precision_autocast, widened  # noqa: E402
from modi.models.modi.losses import d_logistic_loss, d_r1_penalty, g_nonsaturating_loss  # noqa: E402
from modi.models.modi.training import Trainer, prepare_data  # noqa: E402

BANDAI = ROOT.parent / "shared" / "data" / "bvh" / "bandai-namco-1"
SALSA = ROOT.parent / "shared" / "data" / "bvh" / "ganimator" / "Joe" / "Salsa-Dancing-6.bvh"
CYCLE = 16  # iterations: one R1 step (d_reg_every 16) and four path-length steps (g_reg_every 4)


def _data_dir(arg: str | None) -> str:
    return arg if arg is not None else (str(BANDAI) if BANDAI.is_dir() else "procedural")


def _trainer(cfg, data, work: Path, precision: str, resume=None) -> Trainer:
    torch.manual_seed(0)
    return Trainer(cfg, data, work / precision, progress=False, tensorboard=False, write_samples=False,
                   log=lambda m: None, precision=precision, resume=resume)


# =============================================================================================== step time
def bench_step(args) -> dict:
    cfg = make_config(args.preset, **({"train.batch": args.batch} if args.batch else {}))
    data_dir = _data_dir(args.data)
    work = Path(tempfile.mkdtemp(prefix="modi_precision_"))
    data = prepare_data(data_dir, cfg, work_dir=work)
    trainers = {p: _trainer(cfg, data, work, p) for p in ("fp32", "bf16")}
    for tr in trainers.values():  # warm-up: one cycle each (allocator, oneDNN plans, kernel choices)
        for _ in range(CYCLE):
            tr.train_step()
    cycles: dict[str, list[float]] = {p: [] for p in trainers}
    for _ in range(args.reps):
        for p, tr in trainers.items():
            t = time.perf_counter()
            for _ in range(CYCLE):
                tr.train_step()
            cycles[p].append((time.perf_counter() - t) / CYCLE)
    ratios = [b / a for a, b in zip(cycles["fp32"], cycles["bf16"])]
    res = {"machine": machine(), "preset": args.preset, "batch": cfg.train.batch, "data": data_dir,
           "cycle_iterations": CYCLE, "reps": args.reps,
           "s_per_iter": {p: {"median": round(statistics.median(v), 4), "min": round(min(v), 4),
                              "max": round(max(v), 4), "all": [round(x, 4) for x in v]} for p, v in cycles.items()},
           "bf16_over_fp32": {"median": round(statistics.median(ratios), 3), "min": round(min(ratios), 3),
                              "max": round(max(ratios), 3)}}
    print(f"# {res['machine']}\n# MoDi preset {args.preset}, batch {cfg.train.batch}, {data_dir}: seconds per "
          f"iteration over {args.reps} interleaved {CYCLE}-iteration cycles")
    for p, v in res["s_per_iter"].items():
        print(f"{p:5s} median {v['median']:.4f}  min {v['min']:.4f}  max {v['max']:.4f}")
    r = res["bf16_over_fp32"]
    print(f"bf16 / fp32 per cycle pair: median {r['median']:.3f}  min {r['min']:.3f}  max {r['max']:.3f}")
    return res


# =============================================================================================== regularisers
def _flat_grad(out: torch.Tensor, params: list[torch.Tensor]) -> torch.Tensor:
    grads = torch.autograd.grad(out, params, allow_unused=True)
    return torch.cat([(g if g is not None else torch.zeros_like(p)).double().flatten() for g, p in zip(grads, params)])


def _rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    return float((a.double() - ref).norm() / ref.norm().clamp_min(1e-300))


def _path_terms(G, zs, inject, noise, mean, amp) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``path_length_penalty`` with the projection ``noise`` given: (penalty, lengths, gradient on G's weights)."""
    with amp:
        fake, wplus = G(zs, inject_index=inject, return_latents=True)
    (grad,) = torch.autograd.grad((fake.to(noise.dtype) * noise).sum(), wplus, create_graph=True)
    lengths = torch.sqrt(grad.pow(2).sum(2).mean(1))
    penalty = (lengths - mean).pow(2).mean()
    return penalty, lengths, _flat_grad(penalty, [p for p in G.parameters() if p.requires_grad])


def _modi_terms(G, D, real, zs, inject) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """{name: (value, gradient on the weights)} of the plain losses and R1 under the current autocast state."""
    out = {}
    dparams = list(D.parameters())
    with torch.no_grad():
        fake = G(zs, inject_index=inject)
    d = d_logistic_loss(widened(D(real)), widened(D(fake)))
    out["d_loss"] = (d.detach(), _flat_grad(d, dparams))
    real_r = real.detach().requires_grad_(True)
    r1 = d_r1_penalty(widened(D(real_r)), real_r)
    out["r1"] = (r1.detach(), _flat_grad(r1, dparams))
    g = g_nonsaturating_loss(widened(D(G(zs, inject_index=inject))))
    out["g_loss"] = (g.detach(), _flat_grad(g, list(G.parameters())))
    return out


def bench_regularisers(args) -> dict:
    cfg = make_config(args.preset, **({"train.batch": args.batch} if args.batch else {}))
    data_dir = _data_dir(args.data)
    work = Path(tempfile.mkdtemp(prefix="modi_precision_"))
    data = prepare_data(data_dir, cfg, work_dir=work)
    tr = _trainer(cfg, data, work, "fp32", resume=args.ckpt)
    G, D = tr.G, tr.D
    for p in (*G.parameters(), *D.parameters()):
        p.requires_grad_(True)
    gen = torch.Generator().manual_seed(args.seed)
    b = cfg.train.batch
    real = data.windows[torch.randperm(data.windows.shape[0], generator=gen)[:b]]
    zs = [torch.randn(b, cfg.model.latent_dim, generator=gen)]
    zp = [z[: max(1, b // cfg.train.path_batch_shrink)] for z in zs]
    G64, D64 = copy.deepcopy(G).double(), copy.deepcopy(D).double()
    with torch.no_grad():
        n_frames = G(zp, inject_index=None).shape
    noise = torch.randn(n_frames, generator=gen, dtype=torch.float64) / math.sqrt(n_frames[2] * n_frames[3])
    _, lengths64, _ = _path_terms(G64, [z.double() for z in zp], None, noise, 0.0, precision_autocast("fp32", "cpu"))
    mean = float(lengths64.detach().mean())
    ref = _modi_terms(G64, D64, real.double(), [z.double() for z in zs], None)
    # the path-length terms take the path batch (zp), the others the full batch
    ref_path = _path_terms(G64, [z.double() for z in zp], None, noise, mean, precision_autocast("fp32", "cpu"))
    ref["path"], ref["path_lengths"] = (ref_path[0].detach(), ref_path[2]), (ref_path[1].detach(), ref_path[2][:0])
    res: dict = {"machine": machine(), "preset": args.preset, "batch": b, "data": data_dir,
                 "weights": str(args.ckpt) if args.ckpt else "initial (seed 0)", "path_mean": mean, "terms": {}}
    sides = {}
    for prec in ("fp32", "bf16"):
        with precision_autocast(prec, "cpu"):
            got = _modi_terms(G, D, real, zs, None)
        pth = _path_terms(G, zp, None, noise.float(), mean, precision_autocast(prec, "cpu"))
        got["path"], got["path_lengths"] = (pth[0].detach(), pth[2]), (pth[1].detach(), pth[2][:0])
        sides[prec] = got
    print(f"# {res['machine']}\n# MoDi preset {args.preset}, batch {b}, {data_dir}, weights: {res['weights']}; "
          f"relative error against float64 (value / gradient on the weights)")
    print(f"{'term':14s} {'value (f64)':>12s} {'fp32 value':>11s} {'bf16 value':>11s} {'fp32 grad':>10s} "
          f"{'bf16 grad':>10s}")
    for name, (v64, g64) in ref.items():
        row = {"value_f64": float(v64.double().norm()) if v64.ndim else float(v64)}
        for prec in sides:
            v, g = sides[prec][name]
            row[f"{prec}_value"] = _rel(v, v64.double())
            row[f"{prec}_grad"] = _rel(g, g64) if g64.numel() else None
        res["terms"][name] = row
        fmt = lambda x: f"{x:10.2e}" if x is not None else f"{'-':>10s}"  # noqa: E731
        print(f"{name:14s} {row['value_f64']:12.4e} {row['fp32_value']:11.2e} {row['bf16_value']:11.2e} "
              f"{fmt(row['fp32_grad'])} {fmt(row['bf16_grad'])}")
    if args.ganimator:
        res["ganimator"] = bench_gp(args)
    return res


def bench_gp(args) -> dict:
    """The WGAN-GP and the plain WGAN loss of GANimator's finest block, float64 / fp32 / bf16 autocast."""
    from modi.models.ganimator import config as gconfig
    from modi.models.ganimator.data import load_sequence
    from modi.models.ganimator.training import Trainer as GTrainer
    from modi.models.ganimator.training import gradient_penalty

    cfg = gconfig.preset("fast", seed=0, checkpoint_every=1e9)
    seq = load_sequence(SALSA, cfg)
    torch.manual_seed(0)
    tr = GTrainer([seq], cfg, Path(tempfile.mkdtemp(prefix="ganimator_precision_")))
    levels = tr.blocks[-1]
    fakes = tr._forward(0, levels, "random", False, {})
    out = {"clip": str(SALSA), "levels": levels, "terms": {}}
    print(f"# GANimator {SALSA.name}, fast preset, levels {levels} (initial weights)")
    for l, fake in zip(levels, fakes):
        disc, real = tr.model.discs[l], tr.reals[0][l]
        d64 = copy.deepcopy(disc).double()
        rows = {}
        sides = (("f64", d64, torch.float64), ("fp32", disc, torch.float32), ("bf16", disc, torch.float32))
        for prec, net, dt in sides:
            amp = precision_autocast("fp32" if prec == "f64" else prec, "cpu")
            params = list(net.parameters())
            with amp:
                scores = net(torch.cat([fake.to(dt), real.to(dt)]))
            loss = 0.5 * (scores[:1].to(dt).mean() - scores[1:].to(dt).mean())
            torch.manual_seed(1)  # the same interpolation weight on every side
            with amp:
                gp = gradient_penalty(net, real.to(dt), fake.to(dt))
            rows[prec] = {"wgan": (loss.detach(), _flat_grad(loss, params)),
                          "gp": (gp.detach(), _flat_grad(gp, params))}
        for name in ("wgan", "gp"):
            v64, g64 = rows["f64"][name]
            row = {"value_f64": float(v64)}
            for prec in ("fp32", "bf16"):
                v, g = rows[prec][name]
                row[f"{prec}_value"], row[f"{prec}_grad"] = _rel(v, v64), _rel(g, g64)
            out["terms"][f"level{l}.{name}"] = row
            print(f"level {l} {name:5s} {row['value_f64']:12.4e} {row['fp32_value']:11.2e} {row['bf16_value']:11.2e} "
                  f"{row['fp32_grad']:10.2e} {row['bf16_grad']:10.2e}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("step", "regularisers"))
    ap.add_argument("--preset", default="small", choices=("small", "paper"))
    ap.add_argument("--batch", type=int, default=None, help="MoDi batch (default: the preset's)")
    ap.add_argument("--data", default=None, help="BVH folder (default: ../shared/data/bvh/bandai-namco-1, else "
                                                 "procedural)")
    ap.add_argument("--reps", type=int, default=7, help="step: timed cycles per precision (at least 5)")
    ap.add_argument("--ckpt", default=None, help="regularisers: a MoDi checkpoint of the preset (default: the "
                                                 "initial weights of seed 0)")
    ap.add_argument("--seed", type=int, default=0, help="regularisers: the batch, latents and projection")
    ap.add_argument("--ganimator", action="store_true", help="regularisers: GANimator's WGAN-GP too")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.what == "step" and args.reps < 5:
        ap.error("--reps must be at least 5 (medians of fewer say little)")
    torch.set_num_threads(args.threads)
    res = bench_step(args) if args.what == "step" else bench_regularisers(args)
    write_json(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
