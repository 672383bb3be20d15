"""What a MoDi training step asks of the host: device->host syncs and ATen ops per step, counted on the CPU.

    python benchmarks/step_ops.py --preset small --threads 1 [--steps 17] [--json out.json]

The steps run through the training loop (``Trainer.train``, ``log_every`` past the last counted step, so no counted
step is a log step), from step 1 of a trainer on the built-in procedural clips, after step 0 (the first use of
every layer: modi_ext checks the index maps and runs its self-check once). A step is everything from one call of
the loop's step to the next. Two counts of each step:

* ``dispatch``: a ``TorchDispatchMode`` sees every ATen op called from Python or autograd, with its input shapes.
  ``syncs`` are ``aten::_local_scalar_dense`` calls (``.item()``, ``float(t)``, ``bool(t)``: on CUDA each one waits
  for the device); ``h2d`` are copies from the CPU to another device and tensors made from host data
  (``lift_fresh``); ``work`` are the ops that are not views or aliases (on CUDA they are the launches); ``seq`` is
  the (op, shapes) sequence, equal from step to step of a kind when no step's ops depend on random host draws.
  A dispatch mode turns modi_ext's eager shortcut off (``modi_ext.runtime.eager.usable``), so these are the
  registered-op path's ops.
* ``profiler``: ``torch.profiler`` as production runs (the eager shortcut on): the ATen and modi_ext ops that have
  no op below them and are not views (``leaf_work``), and ``aten::_local_scalar_dense`` events.

Step kinds: ``plain``, ``path`` (lazy path length), ``r1`` (lazy R1), ``r1+path``; ``cycle mean`` weighs them as
one lazy-regularisation cycle of the preset does (small: 16 steps, 1 r1+path, 3 path, 12 plain).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(1 + len([p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]), str(ROOT))

import modi_ext  # noqa: E402,F401  (before torch, as the modi command: the OpenMP spin)

import torch  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

SYNC_OPS = frozenset({"aten::_local_scalar_dense"})
ALIAS_OPS = frozenset({"aten::detach", "aten::alias", "aten::lift_fresh", "aten::_unsafe_view", "aten::view",
                       "aten::_reshape_alias", "aten::_reshape_alias_copy"})


def step_kind(step: int, tc: Any) -> str:
    r1 = tc.r1_gamma > 0 and step % tc.d_reg_every == 0
    path = tc.path_weight > 0 and step % tc.g_reg_every == 0
    return "r1+path" if r1 and path else "r1" if r1 else "path" if path else "plain"


def _name(func: Any) -> str:
    return f"{func.namespace}::{func._opname}"


def _shapes(args: Any) -> tuple:
    out = []
    for a in args:
        if isinstance(a, torch.Tensor):
            out.append(tuple(a.shape))
        elif isinstance(a, (list, tuple)) and a and isinstance(a[0], torch.Tensor):
            out.append(tuple(tuple(t.shape) for t in a if isinstance(t, torch.Tensor)))
    return tuple(out)


class OpCounter(TorchDispatchMode):
    """Records every ATen op (name, input shapes), per step (``mark()`` starts a step)."""

    def __init__(self):
        super().__init__()
        self.steps: list[dict[str, Any]] = []
        self.view_ops: set[str] = set()

    def mark(self, **info: Any) -> None:
        self.steps.append({**info, "seq": [], "syncs": 0, "h2d": 0, "work": 0, "ops": 0})

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        if self.steps:
            name = _name(func)
            rec = self.steps[-1]
            rec["ops"] += 1
            rec["seq"].append((name, _shapes(args)))
            view = func.is_view or name in ALIAS_OPS
            if view:
                self.view_ops.add(name)
            else:
                rec["work"] += 1
            if name in SYNC_OPS:
                rec["syncs"] += 1
            if name in ("aten::lift_fresh", "aten::lift_fresh_copy"):
                rec["h2d"] += 1
            elif name in ("aten::_to_copy", "aten::copy_"):
                src = args[1] if name == "aten::copy_" else args[0]
                dst = args[0].device if name == "aten::copy_" else kwargs.get("device", src.device)
                if isinstance(src, torch.Tensor) and src.device.type == "cpu" and torch.device(dst).type != "cpu":
                    rec["h2d"] += 1
        return out


def _step_method(tr: Any) -> str:
    """The method the training loop calls once per step (``run_step``; ``train_step`` in modi before 0.2)."""
    return "run_step" if hasattr(tr, "run_step") else "train_step"


def count_loop(tr: Any, n: int, on_step: Callable[[int], None]) -> None:
    """Run ``n + 1`` steps of the training loop from ``tr.step``; ``on_step(step)`` is called as each step starts
    (the last step, followed by the loop's final log and checkpoint, is not to be counted)."""
    name = _step_method(tr)
    original = getattr(tr, name)

    def marked(*a, **k):
        on_step(tr.step)
        return original(*a, **k)

    setattr(tr, name, marked)
    try:
        tr.train(tr.step + n + 1)
    finally:
        delattr(tr, name)


def dispatch_counts(tr: Any, n: int) -> tuple[list[dict[str, Any]], set[str]]:
    counter = OpCounter()
    tc = tr.cfg.train
    with counter:
        count_loop(tr, n, lambda s: counter.mark(step=s, kind=step_kind(s, tc)))
    return counter.steps[:n], counter.view_ops


def profiler_counts(tr: Any, n: int, view_ops: set[str]) -> list[dict[str, Any]]:
    from torch.profiler import ProfilerActivity, profile, record_function

    tc = tr.cfg.train
    marks: list[Any] = []

    def on_step(s: int) -> None:
        if marks:
            marks[-1].__exit__(None, None, None)
        rf = record_function(f"modi::step{s}")
        rf.__enter__()
        marks.append(rf)

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        count_loop(tr, n, on_step)
        if marks:
            marks[-1].__exit__(None, None, None)
    start = tr.step - n - 1
    rows = {s: {"step": s, "kind": step_kind(s, tc), "leaf_work": 0, "syncs": 0} for s in range(start, start + n)}

    def step_of(ev) -> int | None:
        while ev is not None:
            if ev.name.startswith("modi::step"):
                return int(ev.name[len("modi::step"):])
            ev = ev.cpu_parent
        return None

    for ev in prof.events():
        if not ev.name.startswith(("aten::", "modi_ext::")):
            continue
        s = step_of(ev)
        if s not in rows:
            continue
        if ev.name in SYNC_OPS:
            rows[s]["syncs"] += 1
        below = any(c.name.startswith(("aten::", "modi_ext::")) for c in ev.cpu_children)
        if not below and ev.name not in view_ops and ev.name not in ALIAS_OPS:
            rows[s]["leaf_work"] += 1
    return [rows[s] for s in sorted(rows)]


def cycle_weights(tc: Any) -> dict[str, float]:
    cycle = math.lcm(tc.d_reg_every, tc.g_reg_every)
    w: dict[str, float] = defaultdict(float)
    for s in range(cycle):
        w[step_kind(s, tc)] += 1.0 / cycle
    return dict(w)


def summarise(rows: list[dict[str, Any]], fields: tuple[str, ...], tc: Any) -> dict[str, Any]:
    by_kind: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_kind[r["kind"]].append(r)
    out: dict[str, Any] = {}
    for kind, rs in by_kind.items():
        out[kind] = {f: round(sum(r[f] for r in rs) / len(rs), 2) for f in fields}
        out[kind]["n"] = len(rs)
    weights = cycle_weights(tc)
    if all(k in out for k in weights):
        out["cycle mean"] = {f: round(sum(w * out[k][f] for k, w in weights.items()), 1) for f in fields}
    return out


def make_trainer(preset: str, work: Path, overrides: dict[str, Any] | None = None) -> Any:
    from modi.models.modi import training
    from modi.models.modi.config import make_config

    cfg = make_config(preset, **{"train.log_every": 10 ** 6, "train.ckpt_every": 0, "train.sample_every": 0,
                                 **(overrides or {})})
    data = training.prepare_data("procedural", cfg, work_dir=work)
    return training.Trainer(cfg, data, work / "run", progress=False, tensorboard=False, write_samples=False,
                            log=lambda m: None)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small", choices=["small", "paper"])
    ap.add_argument("--steps", type=int, default=16, help="counted steps from step 1 (16: a small-preset cycle)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    work = Path(tempfile.mkdtemp(prefix="modi_step_ops_"))
    tr = make_trainer(args.preset, work / "a")
    tc = tr.cfg.train
    getattr(tr, _step_method(tr))()  # step 0: first use
    rows, view_ops = dispatch_counts(tr, args.steps)
    same: dict[str, bool] = {}
    first: dict[str, list] = {}
    n_windows = tr.windows.shape[0]
    for r in rows:  # (a step whose windows open an epoch also sends that epoch's order to the device: not compared)
        if (r["step"] * tc.batch) // n_windows != ((r["step"] - 1) * tc.batch) // n_windows:
            continue
        if r["kind"] in first:
            same[r["kind"]] = same.get(r["kind"], True) and r["seq"] == first[r["kind"]]
        else:
            first[r["kind"]] = r["seq"]
    tr2 = make_trainer(args.preset, work / "b")
    getattr(tr2, _step_method(tr2))()
    prof_rows = profiler_counts(tr2, args.steps, view_ops)
    res = {"preset": args.preset, "batch": tc.batch, "steps": args.steps, "threads": args.threads,
           "torch": torch.__version__,
           "dispatch": summarise(rows, ("syncs", "h2d", "work", "ops"), tc),
           "same_ops_within_kind": same,
           "profiler": summarise(prof_rows, ("syncs", "leaf_work"), tc),
           "per_step": [{k: r[k] for k in ("step", "kind", "syncs", "h2d", "work", "ops")} for r in rows]}
    print(f"# MoDi preset {args.preset}, batch {tc.batch}, steps 1..{args.steps}, {args.threads} thread(s), "
          f"torch {torch.__version__}")
    print(f"{'kind':12s} {'n':>3s} {'syncs':>6s} {'h2d':>5s} {'work ops':>9s} {'all ops':>8s}   "
          f"{'prof syncs':>10s} {'prof leaf work':>14s}  same ops")
    for kind in ("plain", "path", "r1", "r1+path", "cycle mean"):
        d, p = res["dispatch"].get(kind), res["profiler"].get(kind)
        if d is None:
            continue
        print(f"{kind:12s} {d.get('n', ''):>3} {d['syncs']:6.1f} {d['h2d']:5.1f} {d['work']:9.1f} {d['ops']:8.1f}   "
              f"{p['syncs']:10.1f} {p['leaf_work']:14.1f}  {same.get(kind, '')}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
