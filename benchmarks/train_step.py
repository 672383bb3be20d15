"""Seconds per training step, split by kind (plain / R1 / path length), on several kernel paths, in one process.

    python benchmarks/train_step.py --preset paper --threads 2 --json benchmarks/results/train_step_paper.json
    python benchmarks/train_step.py --preset small --sides ref,ext_refgrad,ext --json ...
    python benchmarks/train_step.py --model ganimator --threads 1 --json benchmarks/results/train_step_ganimator.json
    python benchmarks/train_step.py --device cuda --json benchmarks/results/train_step_cuda.json
    python benchmarks/train_step.py --model ganimator --block 0 --busy 1   # with one core kept busy (compare.py --busy)

Sides (``--sides``, comma separated):

* ``ref``          the pure-torch reference everywhere (``MODI_EXT_IMPL=ref``: MoDi's grouped per-sample form);
* ``dense``        the dense form everywhere (``MODI_EXT_IMPL=dense``: one shared conv, style/demod as scales --
                   what the package runs without the extension);
* ``ext_refgrad``  the C++ kernels for forward and first-order backward, but the graph of a gradient (R1, path
                   length, WGAN-GP) built through the dense reference (``MODI_EXT_DOUBLE=ref``: how the extension
                   worked before ``modi_ext.skeletal.gradfix``);
* ``ext``          the kernels for every order;
* ``ext_torchdemod`` as ``ext``, with the demodulation coefficients from torch ops (``MODI_EXT_DEMOD=torch``: how
                   the extension worked before ``modi_ext.demod``).

MoDi: one trainer per side, identical weights and seeds, on Bandai-Namco-1 (../shared/data) or the procedural clips.
The sides advance in interleaved chunks of one lazy-regularisation cycle (16 iterations: one R1 step, four path-length
steps) so machine load hits them alike; every iteration is timed and filed by what it ran (``plain``, ``path`` =
plain + path length, ``r1+path`` = plain + R1 + path length). Reported: the median of each kind, the mean over a
cycle (what a run pays per iteration), and the path-length / plain ratio. Generation times the EMA generator.

GANimator: one trainer per side on one clip (default Joe/Salsa-Dancing-6, fast preset: 5 D steps with the WGAN-GP,
1 G step, 1 reconstruction step per iteration) inside one block (default the finest); median seconds per iteration.

Roofline (``benchmarks/roofline.py``): the FLOPs of each step kind (MoDi) or of one iteration (GANimator) are counted
once during the warm-up on the extension's path (``flops``: the sparse per-pair formulas for the modi_ext ops, torch's
for the rest, every order of backward as it runs), and sgemm (``torch.mm`` 1024^3, same threads) is timed in this
process at the start and the end; every time gets GF/s and its fraction of the faster sgemm figure.

The process keeps freed blocks in glibc's heap, as the ``modi`` command does (``retain_freed_memory``);
``--malloc default`` leaves glibc's defaults.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The checkout's packages, after PYTHONPATH's entries (``python -m modi_ext.validate --build`` points PYTHONPATH at a
# fresh build: inserted first, the checkout's unbuilt modi_ext would shadow it) and before site-packages.
sys.path.insert(1 + len([p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]), str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from busy import busy_cores, start_early  # noqa: E402  (benchmarks/busy.py: no torch)

# --busy N starts the other job first; then modi_ext before torch, as the modi command does
# (modi_ext/runtime/omp_wait.py)
_EARLY_BUSY = start_early(sys.argv) if __name__ == "__main__" else None
import modi_ext  # noqa: E402

import torch  # noqa: E402

from compare import forced_env, machine, write_json  # noqa: E402  (benchmarks/compare.py)
from roofline import Sgemm, count_flops  # noqa: E402  (benchmarks/roofline.py)
from modi_ext import HAS_EXT  # noqa: E402
from modi.models.optim import retain_freed_memory  # noqa: E402

SIDES = {"ref": {"MODI_EXT_IMPL": "ref", "MODI_EXT_DOUBLE": "ext"},
         "dense": {"MODI_EXT_IMPL": "dense", "MODI_EXT_DOUBLE": "ext"},
         "ext_refgrad": {"MODI_EXT_IMPL": "ext", "MODI_EXT_DOUBLE": "ref"},
         "ext": {"MODI_EXT_IMPL": "ext", "MODI_EXT_DOUBLE": "ext"},
         "ext_torchdemod": {"MODI_EXT_IMPL": "ext", "MODI_EXT_DOUBLE": "ext", "MODI_EXT_DEMOD": "torch"}}


def side_env(side: str):
    """The environment of one side for the code run inside the block."""
    return forced_env(SIDES[side])


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _kind(step: int, tc) -> str:
    r1 = tc.r1_gamma > 0 and step % tc.d_reg_every == 0
    path = tc.path_weight > 0 and step % tc.g_reg_every == 0
    return "r1+path" if r1 and path else ("path" if path else ("r1" if r1 else "plain"))


def bench_modi(args, sides: list[str], device: torch.device) -> dict:
    from modi.models.modi.config import make_config
    from modi.models.modi.training import Trainer, prepare_data

    data_dir = args.data
    if data_dir is None:
        bandai = ROOT.parent / "shared" / "data" / "bvh" / "bandai-namco-1"
        data_dir = str(bandai) if bandai.is_dir() else "procedural"
    cfg = make_config(args.preset, **{"train.batch": args.batch})
    tc = cfg.train
    cycle = max(tc.d_reg_every, tc.g_reg_every)
    work = Path(tempfile.mkdtemp(prefix="modi_bench_"))
    data = prepare_data(data_dir, cfg, work_dir=work)
    trainers = {}
    for side in sides:
        with side_env(side):
            torch.manual_seed(0)
            trainers[side] = Trainer(cfg, data, work / side, device=device, progress=False, tensorboard=False,
                                     write_samples=False, log=lambda m: None)
    flops: dict[str, int] = {}  # step kind -> FLOPs, counted on the first trainer's warm-up on the ext path
    cycle_kinds = []
    for side, tr in trainers.items():  # warm-up: one full cycle each (allocator, oneDNN plans, kernel caches)
        with side_env(side):
            for _ in range(cycle):
                kind = _kind(tr.step, tc)
                if side == sides[0]:
                    cycle_kinds.append(kind)
                if side == sides[0] and kind not in flops and device.type == "cpu":
                    with side_env("ext"):
                        flops[kind], _ = count_flops(tr.train_step)
                else:
                    tr.train_step()
    per_kind: dict[str, dict[str, list[float]]] = {s: {} for s in sides}
    cycle_means: dict[str, list[float]] = {s: [] for s in sides}
    for _ in range(args.reps):
        for side, tr in trainers.items():
            with side_env(side):
                total = 0.0
                for _ in range(cycle):
                    kind = _kind(tr.step, tc)
                    _sync(device)
                    t = time.perf_counter()
                    tr.train_step()
                    _sync(device)
                    dt = time.perf_counter() - t
                    total += dt
                    per_kind[side].setdefault(kind, []).append(dt)
                cycle_means[side].append(total / cycle)
    res: dict = {"preset": args.preset, "batch": args.batch, "data": str(data_dir),
                 "windows": list(data.windows.shape), "cycle_iterations": cycle, "cycles": args.reps,
                 "hierarchy": [lv.n_entities for lv in trainers[sides[0]].levels], "sides": {}}
    sgemm = args.sgemm
    if sgemm is not None:
        sgemm.remeasure()
    cycle_flops = sum(flops.get(k, 0) for k in cycle_kinds) / cycle if flops else 0
    if flops:
        res["flops"] = {**flops, "cycle_mean": int(cycle_flops)}
    print(f"# MoDi preset {args.preset}, batch {args.batch}, data {data_dir}; median s per step of each kind")
    if flops:
        print("# GFLOP per step: " + ", ".join(f"{k} {v / 1e9:.2f}" for k, v in flops.items())
              + f", cycle mean {cycle_flops / 1e9:.2f}; sgemm {', '.join(f'{g:.1f}' for g in sgemm.samples)} GF/s "
              f"(start, end): fractions of {sgemm.gflops:.1f}")
    print(f"{'side':12s} {'plain':>8s} {'path':>8s} {'r1+path':>8s} {'cycle mean':>11s} {'path/plain':>11s} "
          f"{'GF/s':>6s} {'frac':>5s}  (GF/s, frac per kind: plain / path / r1+path)")
    for side in sides:
        med = {k: statistics.median(v) for k, v in per_kind[side].items()}
        mean = statistics.median(cycle_means[side])
        ratio = med.get("path", float("nan")) / med["plain"]
        res["sides"][side] = {"s_per_step": {k: round(v, 4) for k, v in med.items()}, "cycle_mean_s": round(mean, 4),
                              "path_over_plain": round(ratio, 3),
                              "r1_extra_s": round(med.get("r1+path", float("nan")) - med.get("path", float("nan")), 4)}
        roof = ""
        if flops:
            rates = {k: sgemm.rate(flops[k], v * 1e3) for k, v in med.items() if k in flops}
            gf, frac = sgemm.rate(cycle_flops, mean * 1e3)
            res["sides"][side].update(
                gflops={k: round(r[0], 3) for k, r in rates.items()},
                frac_sgemm={k: round(r[1], 4) for k, r in rates.items()},
                cycle_mean_gflops=round(gf, 3), cycle_mean_frac_sgemm=round(frac, 4))
            roof = f" {gf:6.1f} {frac:5.2f}  " + " / ".join(f"{rates[k][0]:.1f}, {rates[k][1]:.2f}"
                                                           for k in ("plain", "path", "r1+path") if k in rates)
        print(f"{side:12s} {med['plain']:8.3f} {med.get('path', float('nan')):8.3f} "
              f"{med.get('r1+path', float('nan')):8.3f} {mean:11.3f} {ratio:11.2f}{roof}")
    for a, b in (("ext_refgrad", "ext"), ("ref", "ext"), ("dense", "ext"), ("ref", "dense")):
        if a in sides and b in sides:
            sp = res["sides"][a]["cycle_mean_s"] / res["sides"][b]["cycle_mean_s"]
            res[f"cycle_speedup_{b}_vs_{a}"] = round(sp, 3)
            print(f"cycle mean: {b} is {sp:.2f}x faster than {a}")

    gen_sides = [s for s in ("ref", "dense", "ext") if s in sides]
    if args.gen_batch > 0 and gen_sides:
        z = torch.randn(args.gen_batch, trainers[gen_sides[0]].G_ema.latent_dim, device=device)
        times: dict[str, list[float]] = {s: [] for s in gen_sides}
        with torch.no_grad():
            for s in gen_sides:
                with side_env(s):
                    trainers[s].G_ema(z)
            for _ in range(args.gen_reps):
                for s in gen_sides:
                    with side_env(s):
                        _sync(device)
                        t = time.perf_counter()
                        trainers[s].G_ema(z)
                        _sync(device)
                        times[s].append(time.perf_counter() - t)
        res["generate"] = {"batch": args.gen_batch,
                           **{f"{s}_motions_per_s": round(args.gen_batch / statistics.median(times[s]), 1)
                              for s in gen_sides}}
        if device.type == "cpu":
            with torch.no_grad(), side_env("ext"):
                gen_flops, _ = count_flops(lambda: trainers[gen_sides[0]].G_ema(z))
            res["generate"]["flops"] = gen_flops
            for s in gen_sides:
                gf, frac = args.sgemm.rate(gen_flops, statistics.median(times[s]) * 1e3)
                res["generate"][f"{s}_gflops"], res["generate"][f"{s}_frac_sgemm"] = round(gf, 3), round(frac, 4)
        print("generate     " + "   ".join(f"{s} {res['generate'][f'{s}_motions_per_s']:.1f} motions/s"
                                           for s in gen_sides) + f"  (batch {args.gen_batch})")
    return res


def bench_ganimator(args, sides: list[str], device: torch.device) -> dict:
    from modi.models.ganimator import config as gconfig
    from modi.models.ganimator.data import load_sequence
    from modi.models.ganimator.training import Trainer

    clip = Path(args.clip or ROOT.parent / "shared" / "data" / "bvh" / "ganimator" / "Joe" / "Salsa-Dancing-6.bvh")
    if not clip.is_file():
        raise SystemExit(f"train_step: GANimator clip {clip} not found (--clip)")
    cfg = gconfig.preset(args.ganimator_preset, device=str(device), seed=0, checkpoint_every=1e9)
    seq = load_sequence(clip, cfg)
    work = Path(tempfile.mkdtemp(prefix="ganimator_bench_"))
    trainers = {}
    for side in sides:
        with side_env(side):
            torch.manual_seed(0)
            tr = Trainer([seq], cfg, work / side)
            b = args.block if args.block >= 0 else len(tr.blocks) + args.block
            levels = tr.blocks[b]
            for l in levels:
                tr._make_opts(l)
            for l in range(tr.model.n_levels):
                for p in tr.model.gens[l].parameters():
                    p.requires_grad_(l in levels)
            trainers[side] = (tr, levels, {})
    n_sub = cfg.d_steps + cfg.g_steps + 1
    times: dict[str, list[float]] = {s: [] for s in sides}
    it_flops = 0
    for side, (tr, levels, cache) in trainers.items():  # warm-up (the first side's counts the FLOPs, ext path)
        with side_env(side):
            if side == sides[0] and device.type == "cpu":
                with side_env("ext"):
                    it_flops, _ = count_flops(lambda: tr._iteration(levels, 1, n_sub, cache))
            else:
                tr._iteration(levels, 1, n_sub, cache)
    for _ in range(args.reps):
        for side, (tr, levels, cache) in trainers.items():
            with side_env(side):
                _sync(device)
                t = time.perf_counter()
                for _ in range(args.iters):
                    tr._iteration(levels, 1, n_sub, cache)
                _sync(device)
                times[side].append((time.perf_counter() - t) / args.iters)
    tr0, levels0, _ = trainers[sides[0]]
    lengths = tr0.model.level_lengths(seq.n_frames)
    res = {"clip": str(clip), "preset": args.ganimator_preset, "d_steps": cfg.d_steps, "g_steps": cfg.g_steps,
           "block_levels": levels0, "level_frames": lengths, "entities": seq.n_entities,
           "iters_per_chunk": args.iters, "chunks": args.reps, "sides": {}}
    sgemm = args.sgemm
    roof_note = ""
    if sgemm is not None:
        sgemm.remeasure()
        roof_note = (f"; {it_flops / 1e9:.3f} GFLOP per iteration; sgemm {', '.join(f'{g:.1f}' for g in sgemm.samples)}"
                     f" GF/s (start, end): fractions of {sgemm.gflops:.1f}")
    print(f"# GANimator {clip.name}, preset {args.ganimator_preset} (d_steps {cfg.d_steps}, WGAN-GP on every D step),"
          f" block levels {levels0}; median s per iteration{roof_note}")
    if it_flops:
        res["flops_per_iter"] = it_flops
    for side in sides:
        med = statistics.median(times[side])
        res["sides"][side] = {"s_per_iter": round(med, 4)}
        roof = ""
        if it_flops:
            gf, frac = sgemm.rate(it_flops, med * 1e3)
            res["sides"][side].update(gflops=round(gf, 3), frac_sgemm=round(frac, 4))
            roof = f"  {gf:6.1f} GF/s  {frac:5.2f} of sgemm"
        print(f"{side:12s} {med:8.3f} s/it{roof}")
    for a in ("ref", "dense", "ext_refgrad"):
        if a in sides and "ext" in sides:
            sp = res["sides"][a]["s_per_iter"] / res["sides"]["ext"]["s_per_iter"]
            res[f"speedup_ext_vs_{a}"] = round(sp, 3)
            print(f"ext is {sp:.2f}x faster than {a}")
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="modi", choices=["modi", "ganimator"])
    ap.add_argument("--sides", default=None,
                    help="comma-separated among ref, dense, ext_refgrad, ext (default: MoDi ext_refgrad,ext; "
                         "GANimator ref,ext_refgrad,ext)")
    ap.add_argument("--data", default=None, help="MoDi BVH folder (default: ../shared/data/bvh/bandai-namco-1, "
                    "else 'procedural')")
    ap.add_argument("--preset", default="paper", choices=["paper", "small"], help="MoDi preset")
    ap.add_argument("--batch", type=int, default=16, help="MoDi batch")
    ap.add_argument("--reps", type=int, default=3, help="timed chunks per side (MoDi: 16-iteration cycles)")
    ap.add_argument("--gen-batch", type=int, default=256, help="MoDi generation batch (0: skip)")
    ap.add_argument("--gen-reps", type=int, default=5)
    ap.add_argument("--clip", default=None, help="GANimator BVH (default: Joe/Salsa-Dancing-6 from ../shared/data)")
    ap.add_argument("--ganimator-preset", default="fast")
    ap.add_argument("--block", type=int, default=-1, help="GANimator block to time (negative: from the end)")
    ap.add_argument("--iters", type=int, default=8, help="GANimator iterations per timed chunk")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    ap.add_argument("--malloc", choices=("retain", "default"), default="retain",
                    help="retain: glibc keeps freed blocks, as the modi command sets it")
    ap.add_argument("--busy", type=int, default=0, metavar="N",
                    help="keep N cores busy with spinning helper processes while timing (compare.py --busy)")
    args = ap.parse_args(argv)

    if not HAS_EXT:
        print("modi_ext is not built: nothing to compare (python setup.py build_ext --inplace)", file=sys.stderr)
        return 2
    default = "ext_refgrad,ext" if args.model == "modi" else "ref,ext_refgrad,ext"
    sides = [s.strip() for s in (args.sides or default).split(",") if s.strip()]
    bad = [s for s in sides if s not in SIDES]
    if bad or not sides:
        ap.error(f"--sides: unknown {bad}; choose among {', '.join(SIDES)}")
    retained = retain_freed_memory() if args.malloc == "retain" else False
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda":
        from bench_cuda import device_description

        desc = device_description()
    else:
        desc = machine()
    print(f"# {desc}")
    args.sgemm = Sgemm() if device.type == "cpu" else None
    with (_EARLY_BUSY or busy_cores(args.busy)) as taken:
        if args.busy:
            print(f"# {args.busy} core(s) kept busy by spinning helper processes (pinned to {taken})")
        body = bench_modi(args, sides, device) if args.model == "modi" else bench_ganimator(args, sides, device)
    res = {"machine": desc, "date": time.strftime("%Y-%m-%d"), "device": str(device), "model": args.model,
           "retain_freed_memory": retained,
           "omp_wait": modi_ext.omp_wait_policy(), "busy": args.busy, **body}
    if args.sgemm is not None:
        res["roofline"] = args.sgemm.describe()
    write_json(Path(args.json) if args.json else None, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
