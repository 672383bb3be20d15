"""pytest-benchmark suite for the skeletal ops (same cases as compare.py; run ``pytest benchmarks/bench_skeletal.py``).

Benchmarks are not tests: they assert nothing about speed.  ``compare.py`` reports the ref/ext ratios.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

# the environment as the user gave it, before compare.py's import of modi_ext records its own OpenMP-wait decision
# (MODI_EXT_OMP_WAIT, ...) there: every compare.py run below must look at its own machine (quiet or busy)
_USER_ENV = dict(os.environ)

import pytest  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from compare import skeletal_cases  # noqa: E402

from modi_ext import HAS_EXT  # noqa: E402

_CASES, _INFO, _SOURCE = skeletal_cases() if HAS_EXT else ({}, {}, "")
SELECTED = [name for name in _CASES if name.split(".")[1] in ("finest", "level1") or name.endswith("coarsest.fwd")]


@pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
@pytest.mark.parametrize("impl", ["ext", "ref"])
@pytest.mark.parametrize("case", SELECTED or ["none"])
def test_skeletal(benchmark, case, impl):
    ref_fn, ext_fn = _CASES[case]
    fn = ext_fn if impl == "ext" else ref_fn
    benchmark.group = case
    benchmark.extra_info.update(_INFO.get(case, {}))
    benchmark(fn)


# ---------------------------------------------------------------------------------------------- quiet vs busy
# python benchmarks/bench_skeletal.py --json benchmarks/results/cpu_busy.json [--repeats 5] [--reps 3] [--ab-reps 40]
#
# Runs compare.py (each run its own process) on a quiet machine and with one core kept busy (compare --busy 1), the
# two alternated within every repeat so drift hits them alike.  Every run is at 2 threads with --thread-ab 1: the
# extension alone at 2 and at 1 thread, alternated call by call inside the process, gives the thread ratios (busy
# 2t / 1t, quiet scaling, backward scaling) without comparing separate processes.  Writes median / min / max over
# the repeats of each run's figure, side by side, with the issue-23 targets.
BUSY_CASES = (r"\.finest\.(fwd|fwd_bwd|bwd)$|^skeletal_conv\.finest\.double$|^ganimator_conv\.salsa\.(fwd|fwd_bwd)$"
              r"|^fk\.")
CONDITIONS = [(0, 2), (1, 2)]  # (busy cores, threads)
AB_THREADS = 1
MODI_FINEST = ["skeletal_conv", "modulated_conv", "scaler_up", "scaler_down", "modulated_up"]


def _cond(busy: int, threads: int) -> str:
    return f"{'busy' if busy else 'quiet'}_{threads}t"


def _spread(values: list[float]) -> dict:
    import statistics

    return {"median": round(statistics.median(values), 4), "min": round(min(values), 4),
            "max": round(max(values), 4), "runs": len(values)}


def _compare_run(root: Path, busy: int, threads: int, args, out: Path) -> dict:
    import json
    import subprocess

    cmd = [sys.executable, str(root / "benchmarks" / "compare.py"), "--threads", str(threads), "--busy", str(busy),
           "--only", args.only, "--reps", str(args.reps), "--min-time", "0", "--thread-ab", str(AB_THREADS),
           "--ab-reps", str(args.ab_reps), "--json", str(out)]
    print("#", " ".join(cmd[1:]), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=_USER_ENV)
    return json.loads(out.read_text(encoding="utf-8"))


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a is not None and b else None


def busy_report(argv: list[str] | None = None) -> int:
    import argparse
    import datetime
    import tempfile

    from compare import machine, write_json

    ap = argparse.ArgumentParser(description="quiet vs one-core-busy figures of compare.py cases, 1 and 2 threads")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--repeats", type=int, default=5, help="compare.py runs per condition (spread over runs)")
    ap.add_argument("--reps", type=int, default=3, help="timed runs per side (reference / extension) in each run")
    ap.add_argument("--ab-reps", type=int, default=40, help="extension calls per thread count in each run")
    ap.add_argument("--only", default=BUSY_CASES, help="regex of compare.py cases")
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1],
                    help="checkout whose compare.py (and extension) runs (default: this one)")
    args = ap.parse_args(argv)
    runs: dict[str, list[dict]] = {_cond(*c): [] for c in CONDITIONS}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for busy, threads in (CONDITIONS if r % 2 == 0 else CONDITIONS[::-1]):
                out = Path(tmp) / f"{r}_{busy}_{threads}.json"
                runs[_cond(busy, threads)].append(_compare_run(args.root, busy, threads, args, out))
    names = sorted({n for rs in runs.values() for r in rs for n in r})
    cases: dict[str, dict] = {}
    for name in names:
        entry: dict = {}
        per: dict[str, list[dict]] = {c: [r[name] for r in rs if name in r] for c, rs in runs.items()}
        for cond, got in per.items():
            if not got:
                continue
            e = {side: _spread([g[side] for g in got]) for side in ("ref_ms", "ext_ms", "dense_ms")
                 if all(side in g for g in got)}
            if all("ext_ms_threads" in g for g in got):
                for n in got[0]["ext_ms_threads"]:
                    e[f"ext_ms_{n}t_alternated"] = _spread([g["ext_ms_threads"][n] for g in got])
                e["ext_2t_over_1t_alternated"] = _spread([g["ext_thread_ratio"] for g in got])
            e["speedup_ref_over_ext"] = _spread([g["ref_ms"] / g["ext_ms"] for g in got])
            entry[cond] = e
        q, b = entry.get("quiet_2t", {}), entry.get("busy_2t", {})
        med = lambda e, k: e[k]["median"] if k in e else None  # noqa: E731
        entry["ext_busy_2t_over_busy_1t"] = med(b, "ext_2t_over_1t_alternated")
        entry["ext_slowdown_quiet_to_busy_2t"] = _ratio(med(b, "ext_ms_2t_alternated"), med(q, "ext_ms_2t_alternated"))
        entry["ref_slowdown_quiet_to_busy_2t"] = _ratio(med(b, "ref_ms"), med(q, "ref_ms"))
        entry["speedup_ref_over_ext_quiet_2t"] = med(q, "speedup_ref_over_ext")
        r = med(q, "ext_2t_over_1t_alternated")
        entry["ext_scaling_quiet_1t_to_2t"] = round(1.0 / r, 3) if r else None
        cases[name] = entry
    targets = {}
    for op in MODI_FINEST:
        e = cases.get(f"{op}.finest.fwd_bwd")
        if e and e["ext_busy_2t_over_busy_1t"] is not None:
            targets[f"{op}.finest.fwd_bwd busy 2t <= 1.2x busy 1t"] = e["ext_busy_2t_over_busy_1t"] <= 1.2
            if e["ext_slowdown_quiet_to_busy_2t"] is not None and e["ref_slowdown_quiet_to_busy_2t"] is not None:
                targets[f"{op}.finest.fwd_bwd ext slowdown <= ref slowdown"] = (
                    e["ext_slowdown_quiet_to_busy_2t"] <= e["ref_slowdown_quiet_to_busy_2t"])
    for kind in ("fwd_bwd", "double"):
        e = cases.get(f"skeletal_conv.finest.{kind}")
        if e and e["speedup_ref_over_ext_quiet_2t"] is not None:
            targets[f"skeletal_conv.finest.{kind} quiet 2t >= 5x ref"] = e["speedup_ref_over_ext_quiet_2t"] >= 5.0
    e = cases.get("skeletal_conv.finest.bwd", {})
    if e.get("ext_scaling_quiet_1t_to_2t") is not None:
        targets["skeletal_conv.finest backward scaling 1t->2t >= 1.8x"] = e["ext_scaling_quiet_1t_to_2t"] >= 1.8
    report = {"machine": machine(), "date": datetime.date.today().isoformat(),
              "command": "python benchmarks/bench_skeletal.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "root": str(args.root), "repeats": args.repeats, "reps_per_run": args.reps,
              "conditions": {_cond(*c): {"busy_cores": c[0], "threads": c[1]} for c in CONDITIONS},
              "omp_wait": sorted({row.get("omp_wait", "?") for rs in runs.values() for r in rs for row in r.values()}),
              "ab_reps_per_run": args.ab_reps,
              "note": ("each figure: median / min / max over `repeats` compare.py runs of that run's median (ms) or "
                       "ratio; *_alternated: the extension alone at 2 and 1 threads, alternated call by call"),
              "targets": targets, "cases": cases}
    write_json(args.json, report)
    for k, v in targets.items():
        print(f"{'MET ' if v else 'MISS'} {k}")
    return 0


if __name__ == "__main__":
    raise SystemExit(busy_report())
