"""Seconds per GANimator training iteration on one pinned core: the authors' ``train.py`` (``../shared/peers/
ganimator``, on the CPU through ``released_ganimator.train_released``) against ``modi ganimator train --preset
paper`` (the released schedule: 5 discriminator steps per generator step, the released defaults) on the same clip.

    python3 benchmarks/peers/ganimator_speed.py --iters 20,60 --reps 2 --core 1 \\
        --json benchmarks/results/peers_ganimator.json

Each arm is a whole run of its own process (data, pyramid, every block of levels, files), with ``--iters`` iterations
per block; a run at two counts gives the per-iteration cost as the slope, (wall(high) - wall(low)) / (blocks x
(high - low)), free of the start-up both pay once (imports, data, writing). A whole run of I iterations per block is
then setup + blocks x I x slope on each side; the figure is the slopes' ratio, their ÷ modi (issue 41's goal:
>= 5x). Runs are alternated (theirs low, modi low, theirs high, modi high, per rep); each process's peak RSS is
recorded as in ``speed_released.py``.
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
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.peers import released_ganimator as R
from benchmarks.peers.speed_released import measured, peak_rss_mb, pinned, run_group

GOAL = 5.0  # issue 41: GANimator whole run >= 5x the authors' code
CLIP = R.DATA / "Joe" / "Salsa-Dancing-6.bvh"


def worker_theirs(bvh: Path, iters: int, out: Path) -> None:
    import torch

    torch.set_num_threads(1)
    R.train_released(bvh, out, iters)


def run_arm(arm: str, bvh: Path, iters: int, core: int | None, work: Path, timeout: float) -> dict:
    out = work / f"{arm}_{iters}"
    rss = work / f"{arm}_{iters}.rss"
    if arm == "theirs":
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(bvh), "--iters", str(iters),
               "--worker-out", str(out)]
    else:
        cmd = ["modi", "ganimator", "train", str(bvh), "--out", str(out), "--preset", "paper", "--iterations",
               str(iters), "--threads", "1", "--quiet", "--seed", "0"]
    t0 = time.perf_counter()
    proc = run_group(measured(pinned(cmd, core), rss), timeout)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{arm} ({iters} iterations per block) failed ({proc.returncode}): "
                           f"{proc.stderr.strip()[-2000:]}")
    return {"arm": arm, "iters": iters, "wall_s": wall, "peak_rss_mb": peak_rss_mb(rss)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iters", default="20,60", help="two iteration counts per block, low,high")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--core", type=int, default=None)
    ap.add_argument("--blocks", type=int, default=4,
                    help="blocks of levels of the clip's pyramid (Salsa: 4); scales both slopes, not their ratio")
    ap.add_argument("--max-minutes", type=float, default=40.0)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "peers_ganimator.json")
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        worker_theirs(a.worker, int(a.iters), a.worker_out)
        return 0
    try:
        R.require_peer()
        R.require_data(CLIP)
    except R.PeerUnavailable as exc:
        print(f"ganimator_speed: {exc}", file=sys.stderr)
        return 2
    lo, hi = (int(x) for x in a.iters.split(","))
    if not 1 <= lo < hi or a.reps < 1:
        print("ganimator_speed: --iters needs two counts low < high, --reps >= 1", file=sys.stderr)
        return 2
    t0, budget = time.perf_counter(), a.max_minutes * 60
    runs: list[dict] = []
    stopped = None
    with tempfile.TemporaryDirectory(prefix="peers_ganimator_") as tmp:
        work = Path(tmp)
        for rep in range(a.reps):
            for iters in (lo, hi):
                for arm in ("theirs", "modi"):
                    left = budget - (time.perf_counter() - t0)
                    if left <= 0:
                        stopped = f"--max-minutes {a.max_minutes} reached"
                        break
                    print(f"[{time.perf_counter() - t0:7.1f} s] rep {rep} {arm} {iters}", file=sys.stderr)
                    r = run_arm(arm, CLIP, iters, a.core, work / f"rep{rep}", left)
                    r["rep"] = rep
                    runs.append(r)
                if stopped:
                    break
            if stopped:
                break
    slopes: dict[str, list[float]] = {"theirs": [], "modi": []}
    for rep in range(a.reps):
        for arm, per_rep in slopes.items():
            w = {r["iters"]: r["wall_s"] for r in runs if r["rep"] == rep and r["arm"] == arm}
            if lo in w and hi in w:
                per_rep.append((w[hi] - w[lo]) / (a.blocks * (hi - lo)))
    summary: dict = {}
    for arm, s in slopes.items():
        if s:
            summary[arm] = {"s_per_iteration": statistics.median(s), "per_rep": s,
                            "peak_rss_mb": max(r["peak_rss_mb"] for r in runs if r["arm"] == arm)}
    if len(slopes["theirs"]) and len(slopes["modi"]):
        per_rep = [x / y for x, y in zip(slopes["theirs"], slopes["modi"])]
        summary["theirs/modi"] = {"median": summary["theirs"]["s_per_iteration"] / summary["modi"]["s_per_iteration"],
                                  "range": [min(per_rep), max(per_rep)], "goal": GOAL}
    result = {"command": "python3 benchmarks/peers/ganimator_speed.py " + " ".join(argv if argv is not None
                                                                                 else sys.argv[1:]),
              "config": {"clip": CLIP.name, "iters": [lo, hi], "reps": a.reps, "core": a.core, "blocks": a.blocks},
              "machine": {"cpu": platform.processor() or platform.machine(), "nproc": os.cpu_count()},
              "stopped": stopped, "wall_s": time.perf_counter() - t0, "summary": summary, "runs": runs}
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(result, indent=1))
    for arm in ("theirs", "modi"):
        if arm in summary:
            s = summary[arm]
            print(f"{arm:7s} {s['s_per_iteration']:.3f} s per iteration (per rep "
                  f"{', '.join(f'{x:.3f}' for x in s['per_rep'])}), peak RSS {s['peak_rss_mb']:.0f} MB")
    if "theirs/modi" in summary:
        r = summary["theirs/modi"]
        print(f"their train.py / modi: {r['median']:.2f}x (per rep {r['range'][0]:.2f}-{r['range'][1]:.2f}x; goal "
              f">= {GOAL:.0f}x: {'met' if r['median'] >= GOAL else 'NOT met'})")
    print(f"wrote {a.json}{'; ' + stopped if stopped else ''}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
