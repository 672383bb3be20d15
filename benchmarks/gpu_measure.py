"""The stages of ``python -m modi_ext.validate --out DIR`` (measure first, in one command).

They live here, not in ``modi_ext``, because they drive ``modi``'s trainers and the authors' code (``modi_ext``
never imports ``modi``); ``modi_ext.validate`` runs this script as it runs compare.py and train_step.py.

Each stage is a function ``stage_<name>(ctx) -> dict``; :func:`run_stage` runs one and writes ``DIR/<name>.json``
(``<name>_tf32off.json`` for a ``--tf32 off`` pass) as soon as it finishes, with the precision settings it ran under
(``precision``: cuBLAS and cuDNN ``allow_tf32``, ``cudnn.benchmark``, torch's float32 matmul precision) before and
after its work.  On the GPU the orchestrator (``modi_ext.validate.measure``) runs every stage in a process of its
own, with its own timeout inside the budget; ``--dry-run`` runs them in one process on the CPU at tiny sizes (the
plumbing, not a figure).  A stage that cannot run on this machine says why (``status: skipped``, ``reason``).

    python benchmarks/gpu_measure.py STAGE --out DIR --work DIR [--device cuda] [--tf32 default|off] [--tiny]
    python benchmarks/gpu_measure.py all --out DIR --work DIR --device cpu --tiny    # the dry run, one process
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
# the checkout after PYTHONPATH's entries (as train_step.py), so a build on PYTHONPATH wins
sys.path.insert(1 + len([p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]), str(ROOT))

import modi_ext  # noqa: E402,F401  (before torch, as the modi command does)
import torch  # noqa: E402

from modi_ext.validate import (MEASURE_STAGES as STAGES, MEASURE_TIMEOUTS as TIMEOUTS,  # noqa: E402
                               _kill_group, _write_atomic, measure_file, run_group)
CUDA_TESTS = ROOT / "tests" / "modi_ext" / "runtime" / "test_cuda_ops.py"
N_BVH = 8  # the first N Bandai-Namco files, as benchmarks/peers/speed_released.py
CYCLE = 16  # one lazy-regularisation cycle: R1 at i % 16 == 0, path length at i % 4 == 0 (theirs and modi's)
# modi's config for the authors' data layout (as speed_released runs ``modi train``: released representation, tree
# neighbours, released pooling, 64-frame windows every 32 frames)
RELEASED = {"model.neighbors": "tree", "model.pooling": "released", "data.drop_root_anchor": True,
            "data.leaf_rotations": "drop", "data.n_frames": 64, "data.stride": 32}


class Skip(Exception):
    """This stage cannot run here; the message says why (the JSON's ``reason``)."""


# ------------------------------------------------------------------------------------------------ context
class Ctx:
    def __init__(self, out: Path, work: Path, device: str = "cuda", tf32: str = "default", tiny: bool = False,
                 limit: float | None = None):
        self.out, self.work, self.device, self.tf32, self.tiny = Path(out), Path(work), device, tf32, tiny
        self.limit = limit  # seconds the orchestrator gave this stage (its subprocesses must end before)
        self.cuda = device.startswith("cuda")

    def sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()


def precision() -> dict:
    """The settings that decide whether fp32 GEMMs/convs run on TF32, and cuDNN's autotuning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch >= 2.9 prefers fp32_precision; the flags still read
        res = {"matmul_allow_tf32": bool(torch.backends.cuda.matmul.allow_tf32),
               "cudnn_allow_tf32": bool(torch.backends.cudnn.allow_tf32),
               "cudnn_benchmark": bool(torch.backends.cudnn.benchmark),
               "float32_matmul_precision": torch.get_float32_matmul_precision()}
    return res


def set_precision(mode: str) -> None:
    """``default``: torch's defaults as they are (TF32 for cuDNN convs, not for matmul); ``off``: TF32 off for both."""
    if mode == "off":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.backends.cuda.matmul.allow_tf32 = False
            torch.backends.cudnn.allow_tf32 = False
    elif mode != "default":
        raise ValueError(f"--tf32 must be default or off, not {mode!r}")


stage_file = measure_file


def write_json(path: Path, obj: dict) -> None:
    _write_atomic(path, json.dumps(obj, indent=1, default=str) + "\n")


def environment() -> dict:
    from modi_ext.runtime import dispatch

    env = {"torch": torch.__version__, "cuda": torch.version.cuda, "python": sys.version.split()[0],
           "cpus": os.cpu_count(), "modi_ext_built": bool(modi_ext.HAS_EXT),
           "modi_ext_cuda_kernels": bool(torch.cuda.is_available() and dispatch.kernels_built("cuda"))}
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        env.update(gpu=p.name, sms=p.multi_processor_count, capability=f"{p.major}.{p.minor}")
    return env


def run_stage(name: str, ctx: Ctx) -> dict:
    """Run one stage and write its JSON (whatever happened: pass, skipped with the reason, or fail with the
    traceback).  Returns what was written."""
    set_precision(ctx.tf32)
    rec: dict[str, Any] = {"stage": name, "device": ctx.device, "tf32": ctx.tf32, "tiny": ctx.tiny,
                           "precision": precision(), **environment()}
    path = stage_file(ctx.out, name, ctx.tf32)
    t0 = time.perf_counter()
    partial = lambda body: write_json(path, {**rec, "status": "running", **body})  # noqa: E731
    try:
        body = STAGE_FUNCS[name](ctx, partial)
        rec.update(status=body.pop("status", "pass"), **body)
    except Skip as exc:
        rec.update(status="skipped", reason=str(exc))
    except Exception as exc:  # noqa: BLE001 -- the JSON says what failed; the next stage still runs
        rec.update(status="fail", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc()[-4000:])
    rec["seconds"] = round(time.perf_counter() - t0, 2)
    rec["precision_after"] = precision()  # their code (or ours) must not have changed them
    write_json(path, rec)
    return rec


# ------------------------------------------------------------------------------------------------ shared data
def shared_root() -> Path | None:
    """``../shared`` beside the checkout, or ``shared/`` inside it (what the device tool copies)."""
    for cand in (ROOT.parent / "shared", ROOT / "shared"):
        if (cand / "peers").is_dir() or (cand / "data").is_dir():
            return cand
    return None


def _peers():
    """benchmarks.peers.released_modi / released_ganimator, pointed at the shared folder that exists here."""
    from benchmarks.peers import released_ganimator as RG
    from benchmarks.peers import released_modi as RM

    sh = shared_root()
    if sh is not None and sh != ROOT.parent / "shared":
        RM.PEER, RM.BANDAI = sh / "peers" / "MoDi", sh / "data" / "bvh" / "bandai-namco-1" / "data"
        RG.PEER = sh / "peers" / "ganimator"
        RG.DATA = sh / "data" / "bvh" / "ganimator"
    return RM, RG


def bandai_files(ctx: Ctx) -> list[Path]:
    RM, _ = _peers()
    try:
        folder = RM.require_data()
    except RM.PeerUnavailable as exc:
        raise Skip(str(exc)) from None
    return sorted(folder.glob("*.bvh"))[:1 if ctx.tiny else N_BVH]


def bvh_folder(ctx: Ctx) -> Path:
    """Links to the Bandai files both sides train on (made once under the work folder)."""
    folder = ctx.work / ("bvh_tiny" if ctx.tiny else "bvh")
    folder.mkdir(parents=True, exist_ok=True)
    for f in bandai_files(ctx):
        if not (folder / f.name).exists():
            (folder / f.name).symlink_to(f)
    return folder


def modi_config(ctx: Ctx, batch: int):
    from modi.models.modi.config import make_config

    return make_config("small" if ctx.tiny else "paper", **{"train.batch": batch, **RELEASED})


def modi_trainer(ctx: Ctx, batch: int, **kw):
    """modi's trainer on the same data and config as the authors' side, seeded."""
    from modi.models.modi.training import Trainer, prepare_data

    cfg = modi_config(ctx, batch)
    data = prepare_data(bvh_folder(ctx), cfg, work_dir=ctx.work / "modi_data")
    torch.manual_seed(0)
    return Trainer(cfg, data, Path(tempfile.mkdtemp(dir=ctx.work, prefix="run_")), device=ctx.device,
                   progress=False, tensorboard=False, write_samples=False, log=lambda m: None, **kw)


def kind(i: int) -> str:
    return "r1+path" if i % 16 == 0 else "path" if i % 4 == 0 else "plain"


KINDS = {kind(i) for i in range(CYCLE)}  # the step kinds of one cycle (the trainer's names for them)


def cycle_summary(times: list[tuple[str, float]]) -> dict:
    kinds: dict[str, list[float]] = {}
    for k, t in times:
        kinds.setdefault(k, []).append(t)
    mean = round(statistics.fmean(t for _, t in times), 5) if times else None
    return {"iterations": len(times), "cycle_mean_s": mean,
            "per_kind_median_s": {k: round(statistics.median(v), 5) for k, v in kinds.items()}}


# ------------------------------------------------------------------------------------------------ build
def cuda_arch() -> str | None:
    """TORCH_CUDA_ARCH_LIST for the visible GPU ('9.0' on an H100/H200), or None without one."""
    if not torch.cuda.is_available():
        return None
    major, minor = torch.cuda.get_device_capability(0)
    return f"{major}.{minor}"


def build_commands(ctx: Ctx) -> dict:
    arch = cuda_arch() or "9.0"
    env = {"MODI_EXT_CUDA": "1", "MODI_EXT_EMU": "0", "TORCH_CUDA_ARCH_LIST": arch,
           "MAX_JOBS": str(os.cpu_count() or 4)}
    ours = [sys.executable, "setup.py", "build_ext", "--inplace"]
    # their op package JIT-compiles fused_bias_act and upfirdn2d on import (into ~/tmp/stylegan_lock, reused by
    # the peer stage's process)
    RM, _ = _peers()
    theirs = [sys.executable, "-c", f"import sys; sys.path.insert(0, {str(RM.PEER)!r}); import op; print('their "
                                    "ops:', op.fused_act.fused.__file__, op.upfirdn2d.upfirdn2d_op.__file__)"]
    return {"env": env, "ours": ours, "theirs": theirs}


def stage_build(ctx: Ctx, partial: Callable) -> dict:
    """``python setup.py build_ext --inplace`` (CUDA, this GPU's arch, no emulated module) and, at the same time on
    the other cores, the authors' JIT ops; then whether the fresh ``_C`` has CUDA kernels."""
    cmds = build_commands(ctx)
    shown = {"command": " ".join(f"{k}={v}" for k, v in cmds["env"].items()) + " " + " ".join(cmds["ours"][1:]),
             "their_ops_command": " ".join(cmds["theirs"][1:2]) + " '<import their op package>'"}
    if not ctx.cuda:
        raise Skip(f"no CUDA (device {ctx.device}): on a GPU this runs `{shown['command']}` and builds the "
                   "authors' JIT ops beside it")
    env = {**os.environ, **cmds["env"]}
    deadline = (ctx.limit or TIMEOUTS["build"]) - 15  # the kernel check after it
    theirs = subprocess.Popen(cmds["theirs"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env=env, start_new_session=True)
    t0 = time.perf_counter()
    rc, out, timed_out = run_group(cmds["ours"], deadline, env, ROOT)
    ours = {"status": "timeout" if timed_out else ("pass" if rc == 0 else "fail"), "rc": rc,
            "seconds": round(time.perf_counter() - t0, 1), "tail": out[-2500:]}
    try:
        tout, _ = theirs.communicate(timeout=max(5.0, deadline - (time.perf_counter() - t0)))
        their = {"status": "pass" if theirs.returncode == 0 else "fail", "rc": theirs.returncode}
    except subprocess.TimeoutExpired:
        _kill_group(theirs.pid)
        tout, _ = theirs.communicate()
        their = {"status": "timeout"}
    their.update(seconds=round(time.perf_counter() - t0, 1), tail=(tout or "")[-2500:])
    check = subprocess.run([sys.executable, "-c", "import json, modi_ext; from modi_ext.runtime import dispatch; "
                            "print(json.dumps({'has_ext': modi_ext.HAS_EXT, 'cuda_kernels': "
                            "dispatch.kernels_built('cuda'), 'fk_kernels': dispatch.kernels_built('cuda', 'fk')}))"],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
    try:
        kernels = json.loads(check.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        kernels = {"error": (check.stdout + check.stderr)[-1500:]}
    ok = ours["status"] == "pass" and kernels.get("cuda_kernels") is True
    return {"status": "pass" if ok else "fail", **shown, "arch": cmds["env"]["TORCH_CUDA_ARCH_LIST"], "ours": ours,
            "their_ops": their, "built": kernels}


# ------------------------------------------------------------------------------------------------ CUDA tests
def pytest_counts(text: str) -> dict:
    """{'passed': 3, 'failed': 1, ...} from pytest's last summary line."""
    counts = {}
    for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?|xfailed|xpassed|deselected)", text[-3000:]):
        counts["errors" if word.startswith("error") else word] = int(n)
    return counts


def stage_cuda_tests(ctx: Ctx, partial: Callable) -> dict:
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cuda", str(CUDA_TESTS)]
    shown = " ".join(["python"] + cmd[1:])
    if not ctx.cuda:
        raise Skip(f"no CUDA (device {ctx.device}): on a GPU this runs `{shown}`")
    rc, out, timed_out = run_group(cmd, (ctx.limit or TIMEOUTS["cuda_tests"]) - 5, None, ROOT)
    counts = pytest_counts(out)
    ok = rc == 0 and counts.get("passed", 0) > 0
    return {"status": "timeout" if timed_out else ("pass" if ok else "fail"), "command": shown, "rc": rc,
            "counts": counts, "failures": re.findall(r"^FAILED .*$", out, re.M)[:40], "tail": out[-3000:]}


# ------------------------------------------------------------------------------------------------ MoDi step
def graphed_support(trainer_cls) -> str | None:
    """The Trainer keyword that turns CUDA graphs on, or None when modi has no graphed training path."""
    import inspect

    params = inspect.signature(trainer_cls.__init__).parameters
    for name in ("cuda_graphs", "graphs"):
        if name in params:
            return name
    return None


def time_modi(ctx: Ctx, batch: int, iters: int, keep: dict | None = None, graph_warmup: int | None = None,
              **kw) -> dict:
    """modi's step timed over ``iters`` iterations after a warm-up. ``keep`` (a dict) gets every step's losses and
    the trainer's final state (for ``compare_cycles``); ``graph_warmup`` sets a graphed trainer's eager steps per
    kind before its capture."""
    tr = modi_trainer(ctx, batch, **kw)
    if graph_warmup is not None and tr.graphs is not None:
        tr.graphs.warmup = graph_warmup
    # a whole cycle: every kind's kernels, plans and allocations; graphed with a warm-up of 1 per kind, every kind
    # is captured by step CYCLE (r1+path: warmed at 0, captured at 16), so the runs compared time one step later
    warm = 2 if ctx.tiny else CYCLE + (1 if keep is not None else 0)
    losses = []
    for _ in range(warm):
        losses.append(tr.train_step())
    ctx.sync()
    times = []
    for _ in range(iters):
        k = kind(tr.step)
        ctx.sync()
        t = time.perf_counter()
        losses.append(tr.train_step())
        ctx.sync()
        times.append((k, time.perf_counter() - t))
    if keep is not None:
        keep.update(losses=losses, state=trainer_state(tr))
    res = {"batch": batch, "preset": tr.cfg.name if hasattr(tr.cfg, "name") else ("small" if ctx.tiny else "paper"),
           "windows": list(tr.data.windows.shape), **cycle_summary(times)}
    if tr.graphs is not None:
        res["graphs"] = tr.graphs_record()
    return res


def trainer_state(tr) -> dict[str, torch.Tensor]:
    """Every weight (G, D, G_ema), optimiser state and the mean path length of a trainer, copied."""
    out = {}
    for name, module in (("G", tr.G), ("D", tr.D), ("G_ema", tr.G_ema)):
        out.update({f"{name}.{k}": v.detach().clone() for k, v in module.state_dict().items()})
    for name, opt in (("g_opt", tr.g_optim), ("d_opt", tr.d_optim)):
        for pid, st in opt.state_dict()["state"].items():
            out.update({f"{name}.{pid}.{k}": torch.as_tensor(v).detach().clone() for k, v in st.items()})
    out["mean_path_length"] = tr.mean_path_length.detach().clone()
    return out


GRAPH_RTOL, GRAPH_ATOL = 1e-3, 1e-4  # float tolerance of graphed vs eager (GPU kernels need not be bit-reproducible)


def compare_cycles(eager: dict, graphed: dict, rtol: float = GRAPH_RTOL, atol: float = GRAPH_ATOL) -> dict:
    """Graphed against eager from the same seed: every step's losses and every tensor of the final state allclose
    (``equal``), with the largest differences and what differs."""
    worst_loss, bad_losses = 0.0, []
    for i, (a, b) in enumerate(zip(eager["losses"], graphed["losses"])):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                bad_losses.append(f"step {i} {k}: missing")
                continue
            d = abs(a[k] - b[k])
            worst_loss = max(worst_loss, d)
            if not d <= atol + rtol * abs(a[k]):  # a NaN on one side is a difference
                bad_losses.append(f"step {i} {k}: {a[k]:.6g} vs {b[k]:.6g}")
    worst_w, bad_state = 0.0, []
    sa, sb = eager["state"], graphed["state"]
    for k in sorted(set(sa) | set(sb)):
        if k not in sa or k not in sb or sa[k].shape != sb[k].shape:
            bad_state.append(f"{k}: missing or reshaped")
            continue
        x, y = sa[k].double(), sb[k].double()
        if x.numel():
            worst_w = max(worst_w, float((x - y).abs().max()))
        if not torch.allclose(x, y, rtol=rtol, atol=atol):
            bad_state.append(k)
    steps = len(eager["losses"])
    equal = steps == len(graphed["losses"]) and not bad_losses and not bad_state
    return {"equal": equal, "steps": steps, "rtol": rtol, "atol": atol, "max_abs_loss_diff": worst_loss,
            "max_abs_state_diff": worst_w, "losses_differ": bad_losses[:20], "state_differs": bad_state[:20]}


def stage_modi_step(ctx: Ctx, partial: Callable) -> dict:
    """modi's step eager, then (with CUDA graphs, on a GPU) graphed from the same seed: per batch the timings of
    both and ``graphed_equals_eager`` -- every loss of the two cycles and the final weights and optimiser states
    allclose, the proof that ``modi.models.modi.graphs.AUTO_ENABLES_GRAPHS`` waits for."""
    from modi.models.modi.training import Trainer

    batches = (2,) if ctx.tiny else (16, 64)
    iters = 2 if ctx.tiny else CYCLE
    res: dict[str, Any] = {"eager": {}, "config": RELEASED}
    kw = graphed_support(Trainer)
    if kw is None:
        res["graphed"] = {"status": "not available", "reason": "modi has no CUDA-graph training path yet"}
    elif not ctx.cuda:
        res["graphed"] = res["graphed_equals_eager"] = {"status": "skipped", "reason": "no CUDA"}
    else:
        res["graphed"], res["graphed_equals_eager"] = {}, {"status": "running", "equal": None}
    graphs = kw is not None and ctx.cuda
    for b in batches:
        eager: dict = {}
        res["eager"][str(b)] = time_modi(ctx, b, iters, keep=eager if graphs else None, **({kw: "off"} if kw else {}))
        partial(res)
        if not graphs:
            continue
        graphed: dict = {}
        # one eager step per kind before its capture: the proof and the timing fit the stage's budget, and the
        # warm-up's job (lazy initialisation, MODI_EXT_IMPL=auto's timing) is done by then (the eager run's too)
        res["graphed"][str(b)] = time_modi(ctx, b, iters, keep=graphed, graph_warmup=1, **{kw: "on"})
        cmp = compare_cycles(eager, graphed)
        # equal results prove nothing if the run fell back to eager: every kind of the cycle must have been replayed
        graphs = res["graphed"][str(b)].get("graphs", {})
        cmp["all_kinds_graphed"] = graphs.get("ran") == "on" and set(graphs.get("replays", {})) >= KINDS
        cmp["equal"] = cmp["equal"] and cmp["all_kinds_graphed"]
        res["graphed_equals_eager"][str(b)] = cmp
        del eager, graphed
        gc.collect()  # the graphed trainer (a trainer and its graphs refer to each other) and its memory pool
        torch.cuda.empty_cache()
        per = [v for k, v in res["graphed_equals_eager"].items() if k.isdigit()]
        res["graphed_equals_eager"].update(status="pass" if all(v["equal"] for v in per) else "fail",
                                           equal=all(v["equal"] for v in per))
        if res["eager"][str(b)]["cycle_mean_s"] and res["graphed"][str(b)]["cycle_mean_s"]:
            res["graphed"][str(b)]["speedup_over_eager"] = round(res["eager"][str(b)]["cycle_mean_s"]
                                                                 / res["graphed"][str(b)]["cycle_mean_s"], 3)
        partial(res)
    return res


# ------------------------------------------------------------------------------------------------ authors' MoDi
def their_data(ctx: Ctx) -> Path:
    """Their .npy from the same Bandai files (their preprocessing), made once under the work folder."""
    RM, _ = _peers()
    npy = ctx.work / ("their_tiny" if ctx.tiny else "their") / "edge_rot_bandai.npy"
    if not npy.is_file():
        RM.prepare_dataset(npy, bandai_files(ctx), clip_len=64, stride=32)
    return npy


def time_their_modi(ctx: Ctx, RM, peer, batch: int, iters: int) -> dict:
    """Their ``train.main`` for ``iters`` iterations, each timed from the batch leaving their loader to the end of
    their EMA ``accumulate`` (as speed_released.worker_theirs, with a device sync at both ends)."""
    tm = RM.train_module(peer)
    npy = their_data(ctx)
    if ctx.tiny:
        args = RM.make_args(npy, feet=True, extra=("--latent", "32", "--n_mlp", "2", "--batch", str(batch)))
    else:
        args = RM.make_args(npy, feet=True, channels=list(peer.traits.SkeletonTraits.n_channels_max),
                            extra=("--batch", str(batch)))
    args.peer_device = "cuda" if ctx.cuda else "cpu"
    starts: list[float] = []
    ends: list[float] = []
    seen: dict[str, Any] = {}
    old_sample, old_acc, old_save = tm.sample_data, tm.accumulate, torch.save

    def sample_data(loader):
        for item in old_sample(loader):
            ctx.sync()
            starts.append(time.perf_counter())
            yield item

    def accumulate(m1, m2, decay=0.999):
        old_acc(m1, m2, decay)
        if starts:
            ctx.sync()
            ends.append(time.perf_counter())
            seen.setdefault("their_g_ema_device", str(next(m1.parameters()).device))

    tm.sample_data, tm.accumulate = sample_data, accumulate
    torch.save = lambda obj, f, *a, **k: Path(f).write_bytes(b"")  # their report-step checkpoints: untimed
    try:
        RM.trained_checkpoint(args, ctx.work / f"their_run_{batch}", iters=iters)
    finally:
        tm.sample_data, tm.accumulate, torch.save = old_sample, old_acc, old_save
    times = [(kind(i), e - s) for i, (s, e) in enumerate(zip(starts, ends))]
    timed = times[1:] if len(times) > 1 else times  # iteration 0 pays their first-call costs
    return {"batch": batch, "channels": list(args.n_channels_max), "iterations_run": len(times), **seen,
            **cycle_summary(timed)}


def stage_peer_modi_step(ctx: Ctx, partial: Callable) -> dict:
    RM, _ = _peers()
    try:
        RM.require_peer()
    except RM.PeerUnavailable as exc:
        raise Skip(str(exc)) from None
    bandai_files(ctx)
    res: dict[str, Any] = {"same_as": "modi_step: the same Bandai files, batch, paper widths (their "
                                      "n_channels_max), latent 512, contact entities, one 16-iteration cycle"}
    calls = {"fused_bias_act": 0, "upfirdn2d": 0}
    with RM.peer_runtime(device=ctx.device) as peer:
        import op  # noqa: F401  (theirs on CUDA -- built by the build stage; our stand-in on the CPU)

        fa, up = sys.modules["op.fused_act"], sys.modules["op.upfirdn2d"]
        evidence: dict[str, Any] = {"op_module": getattr(sys.modules["op"], "__file__", None) or "modi stand-in",
                                    "op_doc": (sys.modules["op"].__doc__ or "").strip()[:100]}
        if ctx.cuda:  # count calls into their compiled kernels: their CUDA branch ran when these are > 0
            fused, upop = fa.fused, up.upfirdn2d_op
            evidence.update(fused_so=fused.__file__, upfirdn2d_so=upop.__file__)
            real_f, real_u = fused.fused_bias_act, upop.upfirdn2d

            def count_f(*a, **k):
                calls["fused_bias_act"] += 1
                return real_f(*a, **k)

            def count_u(*a, **k):
                calls["upfirdn2d"] += 1
                return real_u(*a, **k)

            fused.fused_bias_act, upop.upfirdn2d = count_f, count_u
        res["evidence"] = evidence
        batches = (2,) if ctx.tiny else (16, 64)
        iters = 2 if ctx.tiny else CYCLE + 1
        res["eager"] = {}
        for b in batches:
            res["eager"][str(b)] = time_their_modi(ctx, RM, peer, b, iters)
            res["evidence"]["their_kernel_calls"] = dict(calls)
            partial(res)
    if ctx.cuda and not (calls["fused_bias_act"] and calls["upfirdn2d"]):
        res.update(status="fail", reason="their CUDA ops were never called")
    return res


# ------------------------------------------------------------------------------------------------ sampling
def stage_sampling(ctx: Ctx, partial: Callable) -> dict:
    batch, reps = (4, 2) if ctx.tiny else (256, 10)
    tr = modi_trainer(ctx, 2 if ctx.tiny else 16)
    g = tr.G_ema
    z = torch.randn(batch, g.latent_dim, device=ctx.device)
    times = []
    with torch.no_grad():
        for _ in range(2):
            g(z)
        for _ in range(reps):
            ctx.sync()
            t = time.perf_counter()
            g(z)
            ctx.sync()
            times.append(time.perf_counter() - t)
    med = statistics.median(times)
    return {"batch": batch, "reps": reps, "median_s": round(med, 6), "motions_per_s": round(batch / med, 1),
            "graphed": {"status": "not available", "reason": "no CUDA-graph sampling path in modi"}}


# ------------------------------------------------------------------------------------------------ kernels
KERNEL_OPS = ("skeletal_conv", "modulated_conv")  # issue 52's GPU rows: the finest level's fwd+bwd
KERNEL_PATHS = ("ext", "ext_mma", "dense", "ref")


def _bench_cuda():
    """benchmarks/bench_cuda.py, loaded by path (it owns the cases: the ops called directly, on MoDi's levels)."""
    import importlib.util

    name = "_modi_bench_cuda"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / "bench_cuda.py")
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name]


def _mma(fn: Callable) -> Callable:
    """``fn`` with the tensor-core kernels asked for (``MODI_EXT_CUDA_MMA=1``, read by the C++ op at each call),
    backward included."""
    def run(*a):
        before = os.environ.get("MODI_EXT_CUDA_MMA")
        os.environ["MODI_EXT_CUDA_MMA"] = "1"
        try:
            return fn(*a)
        finally:
            if before is None:
                os.environ.pop("MODI_EXT_CUDA_MMA", None)
            else:
                os.environ["MODI_EXT_CUDA_MMA"] = before
    return run


def _fwd_bwd(fn: Callable, leaves: list[torch.Tensor], grad: list[torch.Tensor]) -> Callable[[], tuple]:
    def run():
        y = fn(*leaves)
        if not grad:
            grad.append(torch.randn_like(y))
        return (y.detach(),) + torch.autograd.grad(y, leaves, grad[0])
    return run


def _max_rel_diff(a: tuple, b: tuple) -> float:
    """Largest |a - b| over each tensor's largest |b|, over the output and every gradient."""
    return max(float((x.float() - y.float()).abs().max() / y.float().abs().max().clamp_min(1e-30))
               for x, y in zip(a, b))


def stage_kernels(ctx: Ctx, partial: Callable) -> dict:
    """The finest skeletal and modulated conv's fwd+bwd at batch 256 on every path: the SIMT kernels (``ext``), the
    tensor-core kernels (``ext_mma``: ``MODI_EXT_CUDA_MMA=1``; bf16, and TF32 for fp32 where this build has it and
    torch allows it), ``dense`` and the reference (one cuDNN conv), interleaved medians per dtype; and how far the
    tensor-core results lie from the SIMT kernels' (what the emulator checks in CI, here on the real units)."""
    bc = _bench_cuda()
    batch, reps, warmup = (2, 2, 1) if ctx.tiny else (256, 20, 3)
    dtypes = ("fp32", "bf16")
    res: dict[str, Any] = {"batch": batch, "reps": reps, "level": "finest", "cases": {}}
    for tag in dtypes:
        dtype = bc.DTYPES[tag]
        for op, level, ref, ext, leaves, meta, dense_fn in bc._skeletal_defs(dtype, batch, ctx.device):
            if level != "finest" or op not in KERNEL_OPS:
                continue
            key = f"{op}.finest.b{batch}.{tag}.fwd_bwd"
            row: dict[str, Any] = {**meta, "dtype": tag}
            try:
                leaves_i = [t.detach().clone().requires_grad_(True) for t in leaves]
                grad: list[torch.Tensor] = []
                fns = {"ext": _fwd_bwd(ext, leaves_i, grad), "ext_mma": _fwd_bwd(_mma(ext), leaves_i, grad),
                       "dense": _fwd_bwd(dense_fn, leaves_i, grad), "ref": _fwd_bwd(ref, leaves_i, grad)}
                outs = {p: fns[p]() for p in KERNEL_PATHS}
                row["mma_vs_ext_max_rel_diff"] = _max_rel_diff(outs["ext_mma"], outs["ext"])
                row["ext_vs_ref_max_rel_diff"] = _max_rel_diff(outs["ext"], outs["ref"])
                times: dict[str, list[float]] = {p: [] for p in KERNEL_PATHS}
                for i in range(warmup + reps):
                    for p in KERNEL_PATHS:
                        ctx.sync()
                        t = time.perf_counter()
                        fns[p]()
                        ctx.sync()
                        if i >= warmup:
                            times[p].append((time.perf_counter() - t) * 1e3)
                ms = {p: round(statistics.median(v), 4) for p, v in times.items()}
                best_ext = min(ms["ext"], ms["ext_mma"])
                other = min(ms["dense"], ms["ref"])
                row.update(ms=ms, spread_ms={p: [round(min(v), 4), round(max(v), 4)] for p, v in times.items()},
                           best_ext="ext" if ms["ext"] <= ms["ext_mma"] else "ext_mma",
                           fastest_other="dense" if ms["dense"] <= ms["ref"] else "ref",
                           speedup_best_ext_vs_fastest_other=round(other / best_ext, 3))
            except Exception as exc:  # noqa: BLE001 -- one case's failure is recorded; the others still run
                row.update(status="fail", error=f"{type(exc).__name__}: {exc}")
            res["cases"][key] = row
            partial(res)
    if any(r.get("status") == "fail" for r in res["cases"].values()):
        res["status"] = "fail"
    return res


# ------------------------------------------------------------------------------------------------ GANimator
def ganimator_clip(ctx: Ctx) -> Path:
    _, RG = _peers()
    clip = RG.DATA / "Joe" / "Salsa-Dancing-6.bvh"
    if not clip.is_file():
        raise Skip(f"GANimator clip {clip} not found (../shared/data)")
    return clip


def time_our_ganimator(ctx: Ctx, clip: Path, iters: int) -> dict:
    """modi's iteration (``Trainer._iteration``: 5 D steps with WGAN-GP, 1 G step, 1 reconstruction) on each block
    of levels in turn, ``iters`` timed after one warm-up; seconds per iteration per block."""
    from modi.models.ganimator import config as gconfig
    from modi.models.ganimator.data import load_sequence
    from modi.models.ganimator.training import Trainer

    cfg = gconfig.preset("tiny" if ctx.tiny else "paper", device=ctx.device, seed=0, checkpoint_every=1e9)
    seq = load_sequence(clip, cfg)
    torch.manual_seed(0)
    tr = Trainer([seq], cfg, Path(tempfile.mkdtemp(dir=ctx.work, prefix="gan_")))
    n_sub = cfg.d_steps + cfg.g_steps + 1
    blocks = tr.blocks[-1:] if ctx.tiny else tr.blocks
    per_block = []
    for levels in blocks:
        for lv in levels:
            tr._make_opts(lv)
        for lv in range(tr.model.n_levels):
            for p in tr.model.gens[lv].parameters():
                p.requires_grad_(lv in levels)
        cache: dict = {}
        tr._iteration(levels, 1, n_sub, cache)
        ctx.sync()
        t = time.perf_counter()
        for _ in range(iters):
            tr._iteration(levels, 1, n_sub, cache)
        ctx.sync()
        per_block.append({"levels": list(levels), "s_per_iter": round((time.perf_counter() - t) / iters, 5)})
    return {"preset": cfg.preset, "d_steps": cfg.d_steps, "g_steps": cfg.g_steps, "iters_per_block": iters,
            "blocks": per_block, "mean_s_per_iter": round(statistics.fmean(b["s_per_iter"] for b in per_block), 5)}


def time_their_ganimator(ctx: Ctx, RG, clip: Path, iters: int) -> dict:
    """Their ``train.py`` (``released_ganimator.train_released``, ``--device=cuda`` on a GPU), every block's
    ``joint_train`` timed (device-synced) and divided by its iterations."""
    per_block: list[dict] = []
    devices: set[str] = set()
    with RG.peer_runtime() as peer:
        arch = peer.architecture
        real = arch.joint_train

        def joint_train(reals, gens, gan_models, lengths, z_star, amps, args, *rest, **kw):
            devices.update(str(next(g.parameters()).device) for g in gens if any(True for _ in g.parameters()))
            ctx.sync()
            t = time.perf_counter()
            out = real(reals, gens, gan_models, lengths, z_star, amps, args, *rest, **kw)
            ctx.sync()
            per_block.append({"levels": len(gan_models), "s_per_iter": round((time.perf_counter() - t)
                                                                             / max(1, args.num_iters), 5)})
            return out

        arch.joint_train = joint_train
        old_train_jt = getattr(peer.train, "joint_train", None)
        if old_train_jt is not None:
            peer.train.joint_train = joint_train
        try:
            RG.train_released(clip, ctx.work / "their_ganimator", iters,
                              extra=("--device=cuda",) if ctx.cuda else ())
        finally:
            arch.joint_train = real
            if old_train_jt is not None:
                peer.train.joint_train = old_train_jt
    if not per_block:
        raise RuntimeError("their joint_train was never called")
    return {"iters_per_block": iters, "blocks": per_block, "their_generator_devices": sorted(devices),
            "mean_s_per_iter": round(statistics.fmean(b["s_per_iter"] for b in per_block), 5)}


def stage_ganimator(ctx: Ctx, partial: Callable) -> dict:
    clip = ganimator_clip(ctx)
    iters = 1 if ctx.tiny else 15
    res: dict[str, Any] = {"clip": str(clip), "ours": time_our_ganimator(ctx, clip, iters)}
    partial(res)
    _, RG = _peers()
    if ctx.tiny:
        res["theirs"] = {"status": "skipped", "reason": "dry run: the authors' whole GANimator run is not cheap on the "
                                                        "CPU (benchmarks/peers/ganimator_speed.py times it there)"}
        return res
    try:
        RG.require_peer()
    except RG.PeerUnavailable as exc:
        res["theirs"] = {"status": "skipped", "reason": str(exc)}
        return res
    res["theirs"] = time_their_ganimator(ctx, RG, clip, iters)
    res["theirs_over_ours"] = round(res["theirs"]["mean_s_per_iter"] / res["ours"]["mean_s_per_iter"], 3)
    return res


# ------------------------------------------------------------------------------------------------ profile
def busy_fraction(intervals: list[tuple[float, float]], start: float, end: float) -> float | None:
    """The share of [start, end] covered by the union of ``intervals`` (kernels may overlap)."""
    if end <= start:
        return None
    covered, cur_s, cur_e = 0.0, None, None
    for s, e in sorted(intervals):
        if cur_e is None or s > cur_e:
            if cur_e is not None:
                covered += cur_e - cur_s
            cur_s, cur_e = s, e
        else:
            cur_e = max(cur_e, e)
    if cur_e is not None:
        covered += cur_e - cur_s
    return round(covered / (end - start), 4)


def profile_summary(prof, wall_s: float) -> dict:
    from torch.autograd import DeviceType

    events = list(prof.events())
    on_gpu = [e for e in events if e.device_type == DeviceType.CUDA]
    kernels = [e for e in on_gpu if not e.name.startswith(("Memcpy", "Memset"))]
    cpu_ops = [e for e in events if e.device_type == DeviceType.CPU]
    res = {"wall_ms": round(wall_s * 1e3, 3), "kernels": len(kernels), "memcpy_memset": len(on_gpu) - len(kernels),
           "aten_events": sum(1 for e in cpu_ops if e.name.startswith("aten::")),  # nested ones included
           "launches": sum(1 for e in cpu_ops if e.name in ("cudaLaunchKernel", "cudaLaunchKernelExC",
                                                              "cuLaunchKernel", "cuLaunchKernelEx")),
           "local_scalar_dense": sum(1 for e in cpu_ops if e.name == "aten::_local_scalar_dense"),
           "h2d_or_d2h_copies": sum(1 for e in cpu_ops if e.name == "cudaMemcpyAsync")}
    if kernels:
        spans = [(e.time_range.start, e.time_range.end) for e in events]
        start, end = min(s for s, _ in spans), max(e for _, e in spans)
        res["gpu_busy_fraction"] = busy_fraction([(e.time_range.start, e.time_range.end) for e in kernels],
                                                 start, end)
        res["kernel_ms"] = round(sum(e.time_range.end - e.time_range.start for e in kernels) / 1e3, 3)
    else:
        res["gpu_busy_fraction"] = None
        res["note"] = "no CUDA kernels (CPU run): aten ops counted instead"
    return res


def stage_profile(ctx: Ctx, partial: Callable) -> dict:
    """One step of each kind (plain, path, r1+path) of modi's paper step at batch 16 under torch.profiler:
    kernels, launches, aten ops, syncs, and the GPU-busy fraction of the step's span."""
    from torch.profiler import ProfilerActivity, profile

    tr = modi_trainer(ctx, 2 if ctx.tiny else 16)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if ctx.cuda else [])
    res: dict[str, Any] = {"batch": tr.cfg.train.batch, "kinds": {}}
    want = ("r1+path", "plain", "path")
    if ctx.tiny:
        want = ("plain",)  # step 1 (after step 0 unprofiled): the plumbing, cheaply
    for _ in range(2 * CYCLE + 1):
        if all(x in res["kinds"] for x in want):
            break
        k = kind(tr.step)
        if k in res["kinds"] or k not in want or (not ctx.tiny and tr.step < CYCLE):  # warm-up cycle on the GPU
            tr.train_step()
            continue
        ctx.sync()
        with profile(activities=acts) as prof:
            t = time.perf_counter()
            tr.train_step()
            ctx.sync()
            wall = time.perf_counter() - t
        res["kinds"][k] = profile_summary(prof, wall)
        partial(res)
    return res


STAGE_FUNCS: dict[str, Callable[[Ctx, Callable], dict]] = {
    "build": stage_build, "cuda_tests": stage_cuda_tests, "modi_step": stage_modi_step,
    "peer_modi_step": stage_peer_modi_step, "kernels": stage_kernels, "sampling": stage_sampling,
    "ganimator": stage_ganimator, "profile": stage_profile}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/gpu_measure.py")
    ap.add_argument("stage", choices=STAGES + ("all",))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--tf32", choices=("default", "off"), default="default")
    ap.add_argument("--tiny", action="store_true")
    ap.add_argument("--limit", type=float, default=None, help="seconds this stage was given")
    a = ap.parse_args(argv)
    ctx = Ctx(a.out, a.work, a.device, a.tf32, a.tiny, a.limit)
    bad = 0
    for name in STAGES if a.stage == "all" else (a.stage,):
        rec = run_stage(name, ctx)
        print(f"{name}: {rec['status']} {rec.get('reason', '')}{rec.get('error', '')}", flush=True)
        bad += rec["status"] not in ("pass", "skipped")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
