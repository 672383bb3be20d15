"""Seconds to sample N MoDi motions in one batch: the authors' generator (their ``g_ema``, paper widths, their
layers), the same generator on the ``modi_ext`` drop-in, and modi's ``Generator`` holding the same
weights (``modi.interop.modi_released.convert_generator``, which ``tests/modi/interop/test_peers_modi.py`` proves
equal to theirs) -- same latents, same thread count, in one process, the arms alternated (A B C A B C ...).

    python3 benchmarks/peers/sample_speed.py --n 64 --reps 7 --threads 1 --core 1 \\
        --json benchmarks/results/peers_sample.json

Their model is built without ``--foot``: with it, their pooling leaves an entity of the Bandai skeleton unpooled,
which modi's converter refuses (so there would be no modi arm holding the same weights). The weights are their
random initialisation (``released_modi.random_init_checkpoint``; sampling costs the same
whatever the values). Each arm's output is compared with theirs (``max_rel_diff``: max |a - b| / max |b|), so a
figure is only reported for arms that computed the same motions. Reported: per arm the median and range of the
reps, and the ratios their ÷ arm with issue 41's goal (modi >= 60x their generator).

The process first applies ``modi.models.optim.retain_freed_memory`` (what the ``modi`` command does at start), so
every arm, theirs included, reuses freed blocks instead of page-faulting them in anew; ``--malloc default`` leaves
glibc's defaults for all three.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.peers import released_modi as R
from benchmarks.peers.modi_dropin import dropin
from benchmarks.peers.speed_released import prepare_data
from modi.interop import modi_released as M
from modi.models.optim import retain_freed_memory

GOAL = 60.0  # issue 41: sampling 64 motions, modi >= 60x their generator
SAME = 1e-3  # max relative difference (fp32) below which two arms computed the same motions


def max_rel_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double(), b.detach().double()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


def timed(fn: Callable[[], torch.Tensor]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=64, help="motions per batch (the issue's figure: 64)")
    ap.add_argument("--reps", type=int, default=7, help="alternated timed batches per arm (after one warm-up)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--core", type=int, default=None, help="pin this process to one core (with --threads 1)")
    ap.add_argument("--bvh", type=int, default=8, help="Bandai-Namco files for their statics (the first N)")
    ap.add_argument("--malloc", choices=("retain", "default"), default="retain",
                    help="retain: glibc keeps freed blocks (as the modi command sets it), for every arm")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "peers_sample.json")
    a = ap.parse_args(argv)
    if min(a.n, a.reps, a.threads) < 1:
        print("sample_speed: --n, --reps and --threads must be >= 1", file=sys.stderr)
        return 2
    try:
        R.require_peer()
        R.require_data()
    except R.PeerUnavailable as exc:
        print(f"sample_speed: {exc}", file=sys.stderr)
        return 2
    retained = retain_freed_memory() if a.malloc == "retain" else False
    if a.core is not None:
        os.sched_setaffinity(0, {a.core})
    torch.set_num_threads(a.threads)

    with tempfile.TemporaryDirectory(prefix="peers_sample_") as tmp:
        npy, _, names = prepare_data(Path(tmp), a.bvh)
        with R.peer_runtime() as peer:
            channels = list(peer.traits.SkeletonTraits.n_channels_max)  # their paper widths
        args = R.make_args(npy, channels=channels, extra=())  # paper latent and mapping; no --foot: see the docstring
        ck = R.load_released(R.random_init_checkpoint(args, Path(tmp) / "init.pt"))
        z = torch.randn(a.n, ck["args"].latent, generator=torch.Generator().manual_seed(0))
        levels = M.released_levels(ck["g_ema"], ck["args"])
        ours = M.convert_generator(ck["g_ema"], ck["args"], levels, 4).eval()

        times: dict[str, list[float]] = {"theirs": [], "ext": [], "modi": []}
        diffs: dict[str, float] = {}
        with R.peer_runtime() as peer, torch.no_grad():
            _, _, theirs, _ = R.models_from_checkpoint(peer, ck)
            with dropin(peer):
                _, _, theirs_ext, _ = R.models_from_checkpoint(peer, ck)
            arms = {"theirs": lambda: theirs([z])[0], "ext": lambda: theirs_ext([z])[0], "modi": lambda: ours(z)}
            outs = {name: fn() for name, fn in arms.items()}  # warm-up, and the outputs compared
            for name in ("ext", "modi"):
                diffs[name] = max_rel_diff(outs[name], outs["theirs"])
            for _ in range(a.reps):
                for name, fn in arms.items():
                    times[name].append(timed(fn))

    summary = {name: {"median_s": statistics.median(t), "range_s": [min(t), max(t)],
                      "motions_per_s": a.n / statistics.median(t), "max_rel_diff": diffs.get(name, 0.0)}
               for name, t in times.items()}
    ratios = {}
    for name in ("ext", "modi"):
        per_rep = [x / y for x, y in zip(times["theirs"], times[name])]
        same = diffs[name] <= SAME
        ratios[f"theirs/{name}"] = {
            "median": summary["theirs"]["median_s"] / summary[name]["median_s"] if same else None,
            "range": [min(per_rep), max(per_rep)] if same else None, "same_output": same,
            "goal": GOAL if name == "modi" else None}
    result = {"command": "python3 benchmarks/peers/sample_speed.py " + " ".join(argv if argv is not None
                                                                              else sys.argv[1:]),
              "config": {"n": a.n, "reps": a.reps, "threads": a.threads, "core": a.core, "bvh_files": names,
                         "entities_per_level": [int(lv.n_entities) for lv in levels],
                         "channels": channels, "retain_freed_memory": retained},
              "machine": {"cpu": platform.processor() or platform.machine(), "nproc": os.cpu_count(),
                          "torch": torch.__version__},
              "arms": summary, "ratios": ratios, "times_s": times}
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(result, indent=1))
    for name, s in summary.items():
        print(f"{name:7s} {s['median_s']:.3f} s per {a.n} motions ({s['range_s'][0]:.3f}-{s['range_s'][1]:.3f}), "
              f"{s['motions_per_s']:.1f} motions/s, max rel diff to theirs {s['max_rel_diff']:.1e}")
    for name, r in ratios.items():
        if r["median"] is None:
            print(f"{name}: outputs differ, no ratio")
            continue
        goal = f"; goal >= {r['goal']:.0f}x: {'met' if r['median'] >= r['goal'] else 'NOT met'}" if r["goal"] else ""
        print(f"{name}: {r['median']:.1f}x (per rep {r['range'][0]:.1f}-{r['range'][1]:.1f}x{goal})")
    print(f"wrote {a.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
