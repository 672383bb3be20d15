"""Seconds per training iteration on one pinned core: the authors' MoDi ``train.py`` with their layers, the same
script with the ``modi_ext`` drop-in (``modi_dropin``: their skeletal convs on modi_ext and their blur as modi's;
``ext_conv``: the convs only, the drop-in before the blur was patched), and ``modi train`` with the released
representation, neighbours and pooling -- same BVH files, same model (paper widths, latent 512, 8-layer mapping, contact
entities), same batch, whole lazy-regularisation cycles (16 iterations: R1 at i % 16 == 0, path length at
i % 4 == 0, their defaults and modi's), the arms alternated (A B C A B C ...).

    python3 benchmarks/peers/speed_released.py --batch 8 --cycles 1 --reps 2 --core 1 --max-minutes 25 \\
        --json benchmarks/results/peers_speed.json --md -
    python3 benchmarks/peers/speed_released.py --smoke 2 --json benchmarks/results/peers_speed_smoke.json

Each arm runs in its own process under ``taskset -c CORE`` with one torch/OpenMP thread. Their arms run their own
``train.main`` through ``released_modi.trained_checkpoint`` (on the CPU, patched at run time); an iteration is
timed from the batch leaving their loader to the end of their EMA ``accumulate`` (their report step -- checkpoint,
BVH -- is outside it; their checkpoint writes are replaced by an empty file in timing runs). ``modi train`` is
timed by its own ``log.jsonl`` (``--log-every 1``: wall time between consecutive steps; no samples or periodic
checkpoints). Per rep an arm's figure is its mean over whole cycles (what a run pays per iteration); reported are
the median and range over reps, per-kind medians, and the ratios with issue 41's goals (their script >= 12x faster
on the drop-in; modi's trainer >= 20x their script with their layers). ``--smoke N`` runs N iterations per arm, once:
a check that everything runs, not a figure.

Memory: every arm's process runs under a small wrapper whose only child it is, so the wrapper's
``RUSAGE_CHILDREN`` ``ru_maxrss`` is that process's peak resident set (data, model, optimiser, every iteration
kind). Beside it, the same figure for a process that only imports torch (the floor every arm pays), and the ratio
modi ÷ their script both raw and above that floor (the issue's goal: <= 1/3).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

CYCLE = 16  # lcm of their (and modi's) d_reg_every = 16 and g_reg_every = 4
ARMS = ("theirs", "ext", "ext_conv", "modi")
LABELS = {"theirs": "their train.py, their layers", "ext": "their train.py, modi_ext drop-in (convs and blur)",
          "ext_conv": "their train.py, modi_ext drop-in of the convs only (their blur)",
          "modi": "modi train (released representation, tree neighbours, released pooling)"}
GOALS = {"theirs/ext": 12.0, "theirs/ext_conv": None, "theirs/modi": 20.0}  # issue 41's goals
MEMORY_GOAL = 1 / 3  # issue 41: peak memory of modi's paper step <= 1/3 of their script's

# Runs argv[2:] as its only child and writes that child's peak RSS (kB, Linux ru_maxrss) to argv[1].
_PEAK_RSS = ("import resource, subprocess, sys\n"
             "p = subprocess.run(sys.argv[2:])\n"
             "open(sys.argv[1], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))\n"
             "sys.exit(p.returncode)\n")


def kind(i: int) -> str:
    """What their iteration ``i`` (0-based) runs besides the plain D and G steps."""
    return "r1+path" if i % 16 == 0 else "path" if i % 4 == 0 else "plain"


def one_thread_env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
            "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}


# --------------------------------------------------------------------------------------------- workers
def worker_theirs(npy: Path, batch: int, iters: int, arm: str, workdir: Path) -> dict[str, Any]:
    """Their ``train.main`` for ``iters`` iterations (in this process), each iteration timed; ``arm``: ``theirs``
    (their layers), ``ext`` (the drop-in) or ``ext_conv`` (the drop-in without its blur)."""
    import torch

    from benchmarks.peers import released_modi as R
    from benchmarks.peers.modi_dropin import dropin

    torch.set_num_threads(1)
    t_setup = time.perf_counter()
    starts: list[float] = []
    ends: list[float] = []
    with R.peer_runtime() as peer:
        tm = R.train_module(peer)
        channels = list(peer.traits.SkeletonTraits.n_channels_max)  # their paper widths
        args = R.make_args(npy, feet=True, channels=channels, extra=("--batch", str(batch)))
        statics = R.motion_statics(peer, args)
        entities = [int(n) for n in peer.traits.SkeletonAwareFastConvTraits.n_joints(statics)]
        old_sample, old_acc, old_save = tm.sample_data, tm.accumulate, torch.save

        def sample_data(loader):
            for item in old_sample(loader):
                starts.append(time.perf_counter())
                yield item

        def accumulate(m1, m2, decay=0.999):
            old_acc(m1, m2, decay)
            if starts:  # main()'s initial copy (decay 0) comes before the first batch
                ends.append(time.perf_counter())

        tm.sample_data, tm.accumulate = sample_data, accumulate
        torch.save = lambda obj, f, *a, **k: Path(f).write_bytes(b"")  # their report-step checkpoints: untimed
        try:
            with dropin(peer, blur=arm == "ext") if arm != "theirs" else contextlib.nullcontext():
                R.trained_checkpoint(args, workdir, iters=iters)
        finally:
            tm.sample_data, tm.accumulate, torch.save = old_sample, old_acc, old_save
    total = time.perf_counter() - t_setup
    times = [e - s for s, e in zip(starts, ends)]
    return {"iters": [{"i": i, "kind": kind(i), "s": t} for i, t in enumerate(times)],
            "wall_s": total, "channels": channels[-len(entities):], "entities_per_level": entities, "batch": batch}


def run_modi(bvh_dir: Path, batch: int, iters: int, core: int | None, workdir: Path, timeout: float) -> dict:
    """``modi train`` (paper preset, the released representation/neighbours/pooling) as a pinned process."""
    out = workdir / "modi_run"
    shutil.rmtree(out, ignore_errors=True)
    cmd = ["modi", "train", str(bvh_dir), "--out", str(out), "--preset", "paper", "--representation", "released",
           "--neighbors", "tree", "--pooling", "released", "--iters", str(iters), "--batch", str(batch),
           "--frames", "64", "--stride", "32", "--threads", "1", "--log-every", "1", "--sample-every", "0",
           "--ckpt-every", "0", "--no-tensorboard", "--seed", "0"]
    t0 = time.perf_counter()
    rss = workdir / "modi.rss"
    proc = run_group(measured(pinned(cmd, core), rss), timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"modi train failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    from modi.models.modi.checkpoint import load_checkpoint

    levels = load_checkpoint(out / "checkpoint.pt")["levels"]  # what it trained: entities and widths per level
    steps = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines() if line.strip()]
    steps = [s for s in steps if "sec_per_iter" in s]
    return {"iters": [{"i": int(s["step"]) - 1, "kind": kind(int(s["step"]) - 1), "s": float(s["sec_per_iter"])}
                      for s in steps], "wall_s": time.perf_counter() - t0, "batch": batch,
            "entities_per_level": [int(lv["n_entities"]) for lv in levels],
            "channels": [int(lv["channels"]) for lv in levels], "peak_rss_mb": peak_rss_mb(rss)}


def pinned(cmd: list[str], core: int | None) -> list[str]:
    return (["taskset", "-c", str(core)] + cmd) if core is not None else cmd


def measured(cmd: list[str], rss_file: Path) -> list[str]:
    """``cmd`` under the peak-RSS wrapper (``_PEAK_RSS``): after it exits, ``peak_rss_mb(rss_file)``."""
    return [sys.executable, "-c", _PEAK_RSS, str(rss_file)] + cmd


def run_group(cmd: list[str], timeout: float) -> subprocess.CompletedProcess:
    """``subprocess.run`` in a session of its own, whose timeout kills the whole group: the measured process is
    the wrapper's child, which killing the wrapper alone would leave running."""
    proc = subprocess.Popen(cmd, env=one_thread_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def peak_rss_mb(rss_file: Path) -> float:
    return int(rss_file.read_text()) / 1024.0


def torch_floor_mb(workdir: Path) -> float:
    """Peak RSS of a process that imports torch and exits: what every arm pays before any work."""
    rss = workdir / "floor.rss"
    proc = run_group(measured([sys.executable, "-c", "import torch"], rss), timeout=300)
    if proc.returncode != 0:
        raise RuntimeError(f"importing torch failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return peak_rss_mb(rss)


def run_theirs(arm: str, npy: Path, batch: int, iters: int, core: int | None, workdir: Path,
               timeout: float) -> dict:
    out = workdir / f"{arm}.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", arm, "--npy", str(npy), "--batch", str(batch),
           "--iters", str(iters), "--workdir", str(workdir / arm), "--worker-out", str(out)]
    rss = workdir / f"{arm}.rss"
    proc = run_group(measured(pinned(cmd, core), rss), timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"{arm} worker failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return {**json.loads(out.read_text()), "peak_rss_mb": peak_rss_mb(rss)}


# --------------------------------------------------------------------------------------------- data
def prepare_data(workdir: Path, n_bvh: int) -> tuple[Path, Path, list[str]]:
    """The first ``n_bvh`` Bandai-Namco files: their .npy (their preprocessing, 64-frame clips every 32 frames)
    and a folder of links to the same files for ``modi train``."""
    from benchmarks.peers import released_modi as R

    files = sorted(R.require_data().glob("*.bvh"))[:n_bvh]
    npy = R.prepare_dataset(workdir / "data" / "edge_rot_bandai.npy", files, clip_len=64, stride=32)
    bvh_dir = workdir / "bvh"
    bvh_dir.mkdir(parents=True, exist_ok=True)
    for f in files:
        link = bvh_dir / f.name
        if not link.exists():
            link.symlink_to(f)
    return npy, bvh_dir, [f.name for f in files]


# --------------------------------------------------------------------------------------------- summary
def summarise(runs: dict[str, list[dict]], whole_cycles: bool, floor_mb: float | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for arm, reps in runs.items():
        means = [statistics.fmean(x["s"] for x in r["iters"]) for r in reps if r["iters"]]
        kinds: dict[str, list[float]] = {}
        for r in reps:
            for x in r["iters"]:
                kinds.setdefault(x["kind"], []).append(x["s"])
        out[arm] = {"label": LABELS[arm], "per_rep_mean_s": means,
                    "median_s": statistics.median(means) if means else None,
                    "range_s": [min(means), max(means)] if means else None,
                    "per_kind_median_s": {k: statistics.median(v) for k, v in kinds.items()},
                    "n_iters_per_rep": [len(r["iters"]) for r in reps]}
        rss = [r["peak_rss_mb"] for r in reps if "peak_rss_mb" in r]
        if rss:
            out[arm]["peak_rss_mb"] = statistics.median(rss)
            out[arm]["peak_rss_mb_per_rep"] = rss
    ratios = {}
    for name, (num, den) in {"theirs/ext": ("theirs", "ext"), "theirs/ext_conv": ("theirs", "ext_conv"),
                             "theirs/modi": ("theirs", "modi")}.items():
        a, b = out.get(num, {}).get("per_rep_mean_s"), out.get(den, {}).get("per_rep_mean_s")
        if a and b:
            paired = [x / y for x, y in zip(a, b)]
            ratios[name] = {"median": out[num]["median_s"] / out[den]["median_s"], "per_rep": paired,
                            "range": [min(paired), max(paired)], "goal": GOALS[name],
                            "goal_met": (out[num]["median_s"] / out[den]["median_s"] >= GOALS[name])
                            if whole_cycles and GOALS[name] else None}
    memory = {}
    for name, num in {"modi/theirs": "modi", "ext/theirs": "ext"}.items():
        a, b = out.get(num, {}).get("peak_rss_mb"), out.get("theirs", {}).get("peak_rss_mb")
        if a and b:
            memory[name] = {"peak_rss": a / b, "goal": MEMORY_GOAL if num == "modi" else None,
                            "goal_met": a / b <= MEMORY_GOAL if num == "modi" else None}
            if floor_mb is not None and b > floor_mb:
                memory[name]["above_torch_floor"] = (a - floor_mb) / (b - floor_mb)
    return {"arms": out, "ratios": ratios, "memory": memory, "torch_floor_mb": floor_mb}


def markdown(result: dict[str, Any]) -> str:
    s = result["summary"]
    smoke = result["config"]["smoke"]
    unit = "s/iteration (mean of each rep's whole cycles)" if not smoke else "s/iteration (SMOKE: not a figure)"
    lines = [f"| arm | median {unit} | range over reps | plain / path / r1+path (median s) | peak RSS (MB) |",
             "|---|---|---|---|---|"]
    for arm, a in s["arms"].items():
        k = a["per_kind_median_s"]
        kinds = " / ".join(f"{k[n]:.2f}" if n in k else "—" for n in ("plain", "path", "r1+path"))
        rng = f"{a['range_s'][0]:.2f}–{a['range_s'][1]:.2f}" if a["range_s"] else "—"
        med = f"{a['median_s']:.2f}" if a["median_s"] is not None else "—"
        rss = f"{a['peak_rss_mb']:.0f}" if a.get("peak_rss_mb") else "—"
        lines.append(f"| {a['label']} | {med} | {rng} | {kinds} | {rss} |")
    for arm, reps in result["runs"].items():
        if reps and "entities_per_level" in reps[0]:
            lines.append(f"\n{arm}: entities per level {reps[0]['entities_per_level']}, widths {reps[0]['channels']}")
    for name, r in s["ratios"].items():
        met = {True: "met", False: "NOT met", None: "n/a (smoke)"}[r["goal_met"]]
        goal = f"; goal ≥ {r['goal']:.0f}×: {met}" if r["goal"] else ""
        lines.append(f"\n{name}: **{r['median']:.1f}×** (per rep {r['range'][0]:.1f}–{r['range'][1]:.1f}×{goal})")
    floor = s.get("torch_floor_mb")
    if floor:
        lines.append(f"\na process that only imports torch: {floor:.0f} MB peak RSS")
    for name, m in s.get("memory", {}).items():
        above = f"; above the torch floor {m['above_torch_floor']:.2f}" if "above_torch_floor" in m else ""
        goal = (f" (goal ≤ 1/3: {'met' if m['goal_met'] else 'NOT met'})" if m["goal"] else "")
        lines.append(f"\npeak RSS {name}: **{m['peak_rss']:.2f}**{above}{goal}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=16, help="batch (their default and the paper's: 16)")
    ap.add_argument("--cycles", type=int, default=1, help="whole 16-iteration regularisation cycles per arm and rep")
    ap.add_argument("--reps", type=int, default=2, help="alternated repetitions of every arm")
    ap.add_argument("--smoke", type=int, default=0, metavar="N",
                    help="N iterations per arm, one rep: a check that the arms run, not a measurement")
    ap.add_argument("--arms", default=",".join(ARMS), help=f"comma-separated subset of {','.join(ARMS)}")
    ap.add_argument("--core", type=int, default=None, help="CPU core every arm is pinned to (taskset -c)")
    ap.add_argument("--bvh", type=int, default=8, help="Bandai-Namco files used (the first N, sorted)")
    ap.add_argument("--max-minutes", type=float, default=25.0,
                    help="stop starting arms (and stop a running one) past this wall time")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "peers_speed.json")
    ap.add_argument("--md", default=None, help="also write the markdown table here ('-': stdout)")
    ap.add_argument("--worker", choices=("theirs", "ext", "ext_conv"), help=argparse.SUPPRESS)
    ap.add_argument("--npy", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--iters", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--workdir", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)

    if a.worker:
        res = worker_theirs(a.npy, a.batch, a.iters, a.worker, a.workdir)
        a.worker_out.write_text(json.dumps(res))
        return 0

    from benchmarks.peers import released_modi as R

    try:
        R.require_peer()
        R.require_data()
    except R.PeerUnavailable as exc:
        print(f"speed_released: {exc}", file=sys.stderr)
        return 2
    arms = [x for x in a.arms.split(",") if x]
    bad = [x for x in arms if x not in ARMS]
    problem = (f"unknown arm(s) {', '.join(bad)} (choose from {', '.join(ARMS)})" if bad or not arms
               else "--batch, --cycles and --reps must be >= 1" if min(a.batch, a.cycles, a.reps) < 1
               else "--smoke needs >= 2 iterations (their train() needs two)" if a.smoke in (1,) or a.smoke < 0
               else None)
    if problem:
        print(f"speed_released: {problem}", file=sys.stderr)
        return 2
    iters = a.smoke or CYCLE * a.cycles
    reps = 1 if a.smoke else a.reps
    t0 = time.perf_counter()
    budget = a.max_minutes * 60
    runs: dict[str, list[dict]] = {arm: [] for arm in arms}
    stopped = None
    with tempfile.TemporaryDirectory(prefix="peers_speed_") as tmp:
        work = Path(tmp)
        npy, bvh_dir, names = prepare_data(work, a.bvh)
        floor_mb = torch_floor_mb(work)
        for rep in range(reps):
            for arm in arms:
                left = budget - (time.perf_counter() - t0)
                if left <= 0:
                    stopped = f"--max-minutes {a.max_minutes} reached before rep {rep} of {arm}"
                    break
                print(f"[{time.perf_counter() - t0:7.1f} s] rep {rep} {arm}: {iters} iterations", file=sys.stderr)
                try:
                    if arm == "modi":
                        res = run_modi(bvh_dir, a.batch, iters, a.core, work, left)
                    else:
                        res = run_theirs(arm, npy, a.batch, iters, a.core, work, left)
                except subprocess.TimeoutExpired:
                    stopped = f"--max-minutes {a.max_minutes} reached during rep {rep} of {arm}"
                    break
                res["rep"] = rep
                runs[arm].append(res)
            if stopped:
                break
    result = {
        "command": "python3 benchmarks/peers/speed_released.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "config": {"batch": a.batch, "iters_per_arm_and_rep": iters, "cycles": 0 if a.smoke else a.cycles,
                   "reps": reps, "smoke": bool(a.smoke), "core": a.core, "bvh_files": names,
                   "their_flags": list(R.RELEASED_FLAGS) + ["--foot", "--v2_contact_loss", "--character", "bandai"],
                   "modi_flags": "--preset paper --representation released --neighbors tree --pooling released "
                                 "--frames 64 --stride 32 --threads 1"},
        "machine": {"cpu": platform.processor() or platform.machine(), "nproc": os.cpu_count(),
                    "python": platform.python_version()},
        "stopped": stopped, "wall_s": time.perf_counter() - t0,
        "summary": summarise(runs, whole_cycles=not a.smoke and stopped is None, floor_mb=floor_mb),
        "runs": runs}
    try:
        import torch

        result["machine"]["torch"] = torch.__version__
    except ImportError:  # pragma: no cover
        pass
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(result, indent=1))
    md = markdown(result)
    if a.md == "-":
        print(md)
    elif a.md:
        Path(a.md).write_text(md + "\n")
    print(f"wrote {a.json} ({result['wall_s']:.0f} s{'; ' + stopped if stopped else ''})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
