"""One command that validates modi_ext on a real GPU and records what it measured.

    python -m modi_ext.validate [--build] [--json FILE] [--budget SECONDS] [--emulated] [--dry-run] [--allow-skip]

What the CPU-only CI cannot prove (real concurrency, the hardware's own numerics, speed) is checked here, each step a
subprocess in its own process group with its own timeout so the whole run fits ``--budget`` (default 600 s: 10
minutes on one H100/H200).  A preflight first fails in one line when there is no GPU, torch has no CUDA, the built
extension has no CUDA kernels, or nvcc's CUDA major differs from torch's.  The report is ``ok`` only when every step
ran and passed; a skipped step makes it ``incomplete`` (exit 1) unless ``--allow-skip``:

1. ``dispatch``   first-use self-check of the kernels in fp32/bf16/fp16 and ``auto``'s ext-vs-dense choice on MoDi's
                  finest-level shapes (``modi_ext.dispatch_report()``);
2. ``cuda_tests`` ``pytest tests/modi_ext/runtime/test_cuda_ops.py`` (every op against the float64 reference, gradcheck,
                  opcheck, half precision, determinism, CUDA-graph capture); ``--emulated`` adds the ``cuda_emulated``
                  suite;
3. ``sanitizer_*`` ``compute-sanitizer`` memcheck / racecheck / synccheck / initcheck over one small call of every
                  kernel, forward and backward, filtered to modi_ext's kernels, with torch's caching allocator off
                  (the tool is looked for on PATH, in ``$CUDA_HOME/bin`` and in pip's ``nvidia`` package folders);
4. ``compare_fp32`` / ``compare_bf16``  ``benchmarks/compare.py --device cuda``: reference vs dense vs kernels;
5. ``train_step`` ``benchmarks/train_step.py --device cuda --preset paper``: seconds per MoDi training step on the
                  ref, dense and ext paths.

``--build`` (the default when the installed extension has no CUDA kernels and nvcc is found) first builds modi and
modi_ext with the CUDA kernels for this GPU into a temporary folder -- never the checkout -- inside the budget, and
every step then imports that build (``step_env``).

Writes ``benchmarks/results/cuda_<gpu>.json`` (or ``--json FILE``).  Without a visible GPU it says so and exits 2.

``--out DIR`` runs the GPU step measurements instead (``benchmarks/gpu_measure.py``, one process per stage, default
budget 330 s): ``build`` (``setup.py build_ext --inplace`` for this GPU's arch, the authors' JIT ops beside it),
``cuda_tests`` (``pytest -m cuda``), ``modi_step`` (MoDi's paper step, batch 16 and 64), ``peer_modi_step`` (the
authors' ``train.py`` on the same data, config and batch, on their CUDA ops), ``sampling`` (batch 256), ``ganimator``
(ours vs the authors' iteration) and ``profile`` (kernels and GPU-busy fraction per step kind); each writes
``DIR/<stage>.json`` as it ends, with the precision settings, and ``--tf32 both`` (default) reruns the timed stages
with TF32 off.  ``--out DIR --dry-run`` runs every stage on the CPU at tiny sizes (CI).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shutil
import signal
import site
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

import modi_ext
from modi_ext.layers import ModulatedSkeletalConv, SkeletalConv
from modi_ext.runtime import dispatch, kernels, payload

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_BUDGET_S = 600.0  # the whole command: ten minutes on one H100/H200
SUBSET = "finest|level1|fk"  # benchmark cases: the levels that dominate a training step, and FK


# ``--out DIR``: the GPU step measurements, one JSON per stage (benchmarks/gpu_measure.py runs each stage)
MEASURE_SCRIPT = ROOT / "benchmarks" / "gpu_measure.py"
MEASURE_BUDGET_S = 330.0  # a 6-minute device call: the budget plus start-up, with time left for a rerun
MEASURE_STAGES = ("build", "cuda_tests", "modi_step", "peer_modi_step", "kernels", "sampling", "ganimator",
                  "profile")
MEASURE_TIMED = ("modi_step", "peer_modi_step", "kernels", "ganimator")  # again with TF32 off on both sides, time allowing
# seconds per stage on one H100/H200; each gets min(this, what is left of --budget)
MEASURE_TIMEOUTS = {"build": 170, "cuda_tests": 75, "modi_step": 80, "peer_modi_step": 60, "kernels": 30,
                    "sampling": 20, "ganimator": 50, "profile": 30}
MEASURE_TIMEOUTS_TF32OFF = {"modi_step": 30, "peer_modi_step": 40, "kernels": 15, "ganimator": 35}


@dataclass
class Step:
    name: str
    cmd: list[str]
    timeout_s: float
    needs: list[Path] = field(default_factory=list)  # files that must exist (a source checkout)
    tool: str | None = None  # an executable that must be found (see ``find_sanitizer``)
    env: dict = field(default_factory=dict)  # extra environment for this step
    result_json: Path | None = None  # a file the step writes, loaded into the report


def gpu_slug(name: str) -> str:
    """'NVIDIA H200' -> 'nvidia_h200' (the results file name)."""
    return re.sub(r"[^a-z0-9]+", "_", name.lower()).strip("_") or "gpu"


SANITIZER = "compute-sanitizer"
SANITIZER_TOOLS = ("memcheck", "racecheck", "synccheck", "initcheck")
KERNEL_FILTER = "kns=modi_ext"  # mangled names of our kernels hold the namespace; a cuBLAS report is not ours


def sanitizer_dirs(env: dict | None = None, site_dirs: list[Path] | None = None) -> list[Path]:
    """Where compute-sanitizer may live: PATH, ``$CUDA_HOME/bin`` (and CUDA_PATH), /usr/local/cuda/bin, and the
    ``nvidia/*/bin`` folders of pip's CUDA packages beside torch (``nvidia-cuda-sanitizer-api`` ships it there)."""
    env = os.environ if env is None else env
    dirs = [Path(d) for d in env.get("PATH", "").split(os.pathsep) if d]
    for var in ("CUDA_HOME", "CUDA_PATH"):
        if env.get(var):
            dirs += [Path(env[var]) / "bin", Path(env[var]) / "compute-sanitizer"]
    dirs.append(Path("/usr/local/cuda/bin"))
    if site_dirs is None:
        site_dirs = [Path(p) for p in site.getsitepackages() + [site.getusersitepackages()]]
    for sp in site_dirs:
        nv = sp / "nvidia"
        if nv.is_dir():
            for pkg in sorted(nv.iterdir()):
                dirs += [pkg / "bin", pkg / "compute-sanitizer"]
    return dirs


def find_sanitizer(env: dict | None = None, site_dirs: list[Path] | None = None) -> str | None:
    """The first executable ``compute-sanitizer`` in ``sanitizer_dirs``, or None."""
    for d in sanitizer_dirs(env, site_dirs):
        exe = d / SANITIZER
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    return None


def plan(work: Path, emulated: bool = False) -> list[Step]:
    """The steps in order, with their timeouts (seconds) -- together within the default budget."""
    py = sys.executable
    tests = ROOT / "tests" / "modi_ext" / "runtime" / "test_cuda_ops.py"
    bench = ROOT / "benchmarks"
    steps = [
        Step("dispatch", [py, "-m", "modi_ext.validate", "--payload", "dispatch", "--out", str(work / "dispatch.json")],
             30, result_json=work / "dispatch.json"),
        # -v: each test's name is in the log before it runs, so a crash (a fatal error kills pytest) names its test
        Step("cuda_tests", [py, "-m", "pytest", "-v", "-p", "no:cacheprovider", str(tests)], 150, needs=[tests]),
    ]
    if emulated:  # the AddressSanitizer rebuild of the emulated module is CPU CI's (minutes of compiling)
        ext_tests = ROOT / "tests" / "modi_ext"
        steps.append(Step("emulated_tests", [py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m",
                                             "cuda_emulated", "--ignore", str(ext_tests / "runtime" / "test_cuda_emulated_asan.py"),
                                             str(ext_tests)], 120, needs=[ext_tests]))
    for tool in SANITIZER_TOOLS:
        # No --leak-check: torch owns every device allocation, and the tensors still alive when the interpreter
        # exits (module caches of CSR maps, say) are never freed, so a leak report is about Python object
        # lifetimes, not about a kernel's memory safety.
        # initcheck watches every kernel: a write by a kernel left out by --kernel-name is not tracked, so torch's own
        # kernels (e.g. the bias gradient's sum) would leave "uninitialized" memory behind them that
        # our kernels then read and a copy to the host then reports: false errors, where the oracle comparisons of
        # the same run pass.
        extra = [] if tool == "initcheck" else ["--kernel-name", KERNEL_FILTER]
        steps.append(Step(f"sanitizer_{tool}", [SANITIZER, "--tool", tool, *extra,
                                                "--error-exitcode", "1", py, "-m", "modi_ext.validate", "--payload",
                                                "kernels"], 40,
                          tool=SANITIZER, env={"PYTORCH_NO_CUDA_MEMORY_CACHING": "1"}))
    for dt, t in (("fp32", 65), ("bf16", 45)):
        out = work / f"compare_{dt}.json"
        steps.append(Step(f"compare_{dt}", [py, str(bench / "compare.py"), "--device", "cuda", "--dtype", dt, "--reps",
                                            "5", "--only", SUBSET, "--json", str(out)], t,
                          needs=[bench / "compare.py", bench / "bench_cuda.py"], result_json=out))
    out = work / "train_step.json"
    steps.append(Step("train_step", [py, str(bench / "train_step.py"), "--device", "cuda", "--preset", "paper",
                                     "--sides", "ref,dense,ext", "--reps", "1", "--gen-reps", "3", "--json", str(out)],
                      85, needs=[bench / "train_step.py"], result_json=out))
    return steps


def run_step(step: Step, timeout_s: float, env: dict | None = None, cwd: Path = ROOT) -> dict:
    """Run one step; ``status`` is pass / fail / timeout / skipped, with the output's tail."""
    missing = [str(p) for p in step.needs if not p.exists()]
    if missing:
        return {"status": "skipped", "reason": f"not found: {', '.join(missing)} (run from a source checkout)"}
    cmd = list(step.cmd)
    if step.tool:
        exe = find_sanitizer(env) if step.tool == SANITIZER else shutil.which(step.tool)
        if exe is None:
            return {"status": "skipped", "reason": f"{step.tool} not on PATH, $CUDA_HOME/bin or pip's nvidia "
                                                   "folders (pip install nvidia-cuda-sanitizer-api, or a CUDA toolkit)"}
        cmd[0] = exe
    if timeout_s < 5:
        return {"status": "skipped", "reason": "time budget spent"}
    env = dict(os.environ if env is None else env, **step.env)
    t0 = time.perf_counter()
    rc, out, timed_out = run_group(cmd, timeout_s, env, cwd)
    res = {"status": "timeout" if timed_out else ("pass" if rc == 0 else "fail"), "rc": rc,
           "seconds": round(time.perf_counter() - t0, 2), "timeout_s": round(timeout_s, 1), "tail": out[-3000:],
           "output": out}
    if step.result_json is not None and step.result_json.is_file():
        try:
            res["result"] = json.loads(step.result_json.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            res["result_error"] = str(exc)
    return res


def run_group(cmd: list[str], timeout_s: float, env: dict | None = None,
              cwd: Path = ROOT) -> tuple[int | None, str, bool]:
    """Run ``cmd`` in a new session (its own process group) and kill the whole group on timeout: under the
    sanitizer the traced python is a grandchild, which ``subprocess.run(timeout=)`` would leave on the GPU."""
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
        return proc.returncode, out or "", False
    except subprocess.TimeoutExpired:
        _kill_group(proc.pid)
        out, _ = proc.communicate()
        return None, out or "", True
    finally:
        if proc.poll() is None:
            _kill_group(proc.pid)
            proc.wait()
        _kill_group(proc.pid)  # a grandchild that outlived a finished child


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


# ---------------------------------------------------------------------------------------------------------- payloads
def _payload_kernels(device: str) -> dict:
    """The shared payload (``modi_ext.runtime.payload``): every kernel instantiation, forward and backward with every
    gradient, in every dtype the device's kernels take, against the float64 oracle -- what compute-sanitizer
    watches.  ``errors`` names any case that disagreed with the oracle (the step then fails)."""
    cuda = device.startswith("cuda")
    res = payload.run(kernels.KERNELS, device, payload.DTYPES if cuda else (torch.float32, torch.float64))
    if cuda:
        torch.cuda.synchronize()
    return res


def _payload_dispatch(device: str) -> dict:
    """Self-check per dtype and auto's choice on MoDi's finest level (batch 16, 32 channels, 64 frames)."""


    os.environ["MODI_EXT_IMPL"] = "auto"
    nb = [[m for m in (j - 1, j, j + 1) if 0 <= m < 25] for j in range(25)]
    cuda = device.startswith("cuda")
    for dtype in (torch.float32, torch.bfloat16, torch.float16) if cuda else (torch.float32,):
        dispatch.kernels_trusted(str(torch.device(device)), str(dtype))
    torch.manual_seed(0)
    for module in (SkeletalConv(32, 32, nb), ModulatedSkeletalConv(32, 32, 512, nb, demodulate=True)):
        module = module.to(device)
        x = torch.randn(16, 32, 25, 64, device=device, requires_grad=True)
        args = (x,) if isinstance(module, SkeletalConv) else (x, torch.randn(16, 512, device=device))
        for _ in range(2):
            module(*args).sum().backward()
            with torch.no_grad():
                module(*args)
    return {"report": modi_ext.dispatch_report()}


def _run_payload(name: str, out: Path | None, device: str) -> int:
    res = (_payload_kernels if name == "kernels" else _payload_dispatch)(device)
    text = json.dumps(res, indent=2, default=str)
    if out is None:
        print(text)
    else:
        _write_atomic(out, text + "\n")
    return 1 if res.get("errors") else 0


# ---------------------------------------------------------------------------------------------------------- main
def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def no_gpu_message() -> str | None:
    """Why no GPU can be validated here, or None when torch sees one."""
    if torch.cuda.is_available():
        return None
    build = f"a CUDA {torch.version.cuda} build" if torch.version.cuda else "a CPU-only build"
    return (f"validate: no GPU is visible (torch.cuda.is_available() is False; torch {torch.__version__} is {build}); "
            "nothing was validated -- run this on a machine with an NVIDIA GPU")


def nvcc_version(nvcc: str | None = None) -> str | None:
    """'12.4' from ``nvcc --version`` ($CUDA_HOME/bin/nvcc, else PATH), or None when there is no nvcc."""
    if nvcc is None:
        home = os.environ.get("CUDA_HOME") or os.environ.get("CUDA_PATH")
        cand = Path(home) / "bin" / "nvcc" if home else None
        nvcc = str(cand) if cand is not None and cand.is_file() else shutil.which("nvcc")
    if nvcc is None:
        return None
    try:
        out = subprocess.run([nvcc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    m = re.search(r"release (\d+\.\d+)", out)
    return m.group(1) if m else None


def preflight_message(gpu_visible: bool, torch_cuda: str | None, torch_version: str, cuda_kernels: bool,
                      nvcc: str | None) -> str | None:
    """The one line that says why nothing can be validated, or None when the run can start.  Pure (the facts come
    in as arguments) so every message is tested on a CPU machine."""
    if torch_cuda is None:
        return (f"validate: torch {torch_version} is a CPU-only build, so no GPU can be used -- install a CUDA build "
                "of torch (https://pytorch.org/get-started/locally/) on a machine with an NVIDIA GPU")
    if not gpu_visible:
        return (f"validate: no GPU is visible (torch.cuda.is_available() is False; torch {torch_version} is a CUDA "
                f"{torch_cuda} build) -- check nvidia-smi and CUDA_VISIBLE_DEVICES")
    if nvcc is not None and nvcc.split(".")[0] != torch_cuda.split(".")[0]:
        return (f"validate: nvcc is CUDA {nvcc} but torch was built with CUDA {torch_cuda}; the extension must be "
                f"compiled by the same major version -- install CUDA toolkit {torch_cuda.split('.')[0]}.x and point "
                "CUDA_HOME at it")
    if not cuda_kernels:
        how = ("rebuild with `pip install -e .` (nvcc and CUDA_HOME present)" if nvcc else
               f"no nvcc found to build them: install CUDA toolkit {torch_cuda.split('.')[0]}.x and set CUDA_HOME, "
               "then `pip install -e .`")
        return f"validate: the built modi_ext extension has no CUDA kernels for this GPU -- {how}"
    return None


def _cuda_kernels_run() -> bool:
    """Whether the built extension registered CUDA kernels and one of them runs on this GPU's arch (a build for
    another arch fails with 'no kernel image is available')."""
    if not (dispatch.kernels_built("cuda") and dispatch.kernels_built("cuda", "fk")):
        return False
    saved = os.environ.get("MODI_EXT_IMPL")
    try:
        _payload_kernels("cuda")
    except RuntimeError as exc:
        if "kernel image" in str(exc):
            return False
        raise
    finally:  # the payload forces 'ext'; the steps inherit this process's environment
        if saved is None:
            os.environ.pop("MODI_EXT_IMPL", None)
        else:
            os.environ["MODI_EXT_IMPL"] = saved
    torch.cuda.synchronize()
    return True


BUILD_TIMEOUT_S = 300.0  # nvcc for this GPU's arch only (torch derives it from the visible GPU)


def build_extension(work: Path, timeout_s: float, env: dict | None = None,
                    emulated: bool = False) -> tuple[Path | None, dict]:
    """``--build``: build modi and modi_ext with the CUDA kernels (the emulated module only for ``--emulated``, whose
    tests import it) into ``work`` -- a temporary folder, never the checkout -- within ``timeout_s``.  Returns the
    folder holding the built packages (the steps import them instead of the checkout's) or None, and the build's
    step result (status, seconds, output tail)."""
    missing = [str(p) for p in (ROOT / "setup.py", ROOT / "csrc") if not p.exists()]
    if missing:
        return None, {"status": "skipped", "reason": f"not found: {', '.join(missing)} (run from a source checkout)"}
    base = work / "build"
    cmd = [sys.executable, "setup.py", "-q", "build", "--build-base", str(base)]
    env = dict(os.environ if env is None else env, MODI_EXT_CUDA="1", MODI_EXT_EMU="1" if emulated else "0")
    t0 = time.perf_counter()
    rc, out, timed_out = run_group(cmd, timeout_s, env)
    res = {"status": "timeout" if timed_out else ("pass" if rc == 0 else "fail"), "rc": rc,
           "seconds": round(time.perf_counter() - t0, 2), "timeout_s": round(timeout_s, 1), "tail": out[-3000:],
           "build_base": str(base)}
    libs = sorted(p for p in base.glob("lib*") if (p / "modi_ext" / "__init__.py").is_file())
    if res["status"] != "pass" or not libs:
        if res["status"] == "pass":
            res.update(status="fail", reason="the build produced no package folder")
        return None, res
    return libs[0], res


def step_env(lib: Path | None, work: Path, env: dict | None = None) -> tuple[dict, Path]:
    """The environment and working folder of the steps: the checkout on PYTHONPATH, or with ``--build`` the built
    packages in ``lib`` -- and then a working folder outside the checkout, so that ``python -m`` (which puts the
    working folder first on sys.path) cannot pick up the checkout's modi_ext instead."""
    env = dict(os.environ if env is None else env)
    first = str(lib) if lib is not None else str(ROOT)
    env["PYTHONPATH"] = os.pathsep.join([first] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return env, (work if lib is not None else ROOT)


def _kernels_run_in(lib: Path, work: Path, timeout_s: float) -> bool:
    """Whether the CUDA kernels of the build in ``lib`` run on this GPU (a fresh process: this one already imported
    the checkout's modi_ext)."""
    env, cwd = step_env(lib, work)
    code = "import sys, modi_ext.validate as v; sys.exit(0 if v._cuda_kernels_run() else 3)"
    rc, _, _ = run_group([sys.executable, "-c", code], timeout_s, env, cwd)
    return rc == 0


def preflight_facts() -> dict:
    """What the preflight decides on: a visible GPU, torch's CUDA version, runnable CUDA kernels, nvcc's version."""
    gpu = torch.cuda.is_available()
    cuda_kernels = gpu and torch.version.cuda is not None and _cuda_kernels_run()
    return dict(gpu_visible=gpu, torch_cuda=torch.version.cuda, torch_version=torch.__version__,
                cuda_kernels=cuda_kernels, nvcc=nvcc_version() if torch.version.cuda else None)


def preflight() -> str | None:
    """Gather the facts on this machine and return ``preflight_message`` for them."""
    return preflight_message(**preflight_facts())


def verdict(steps: dict, allow_skip: bool = False) -> tuple[str, list[str]]:
    """'ok' only when every step ran and passed; 'fail' when one failed or timed out; else 'incomplete' (a skipped
    step checked nothing).  Returns the verdict and the reasons."""
    failed = [f"{n}: {r['status']}" for n, r in steps.items() if r["status"] in ("fail", "timeout")]
    if failed:
        return "fail", failed
    skipped = [f"{n}: skipped ({r.get('reason', '')})" for n, r in steps.items() if r["status"] != "pass"]
    if skipped and not allow_skip:
        return "incomplete", skipped
    if not steps:
        return "incomplete", ["no step ran"]
    return "ok", skipped


def measure_plan(tf32: str = "both") -> list[tuple[str, str, float]]:
    """(stage, TF32 mode, timeout) in order: every stage at torch's defaults, then (``both``) the timed stages again
    with TF32 off on both sides."""
    plan_ = [(s, "default", float(MEASURE_TIMEOUTS[s])) for s in MEASURE_STAGES] if tf32 != "off" else []
    if tf32 != "default":
        first = MEASURE_STAGES if tf32 == "off" else ()
        plan_ += [(s, "off", float(MEASURE_TIMEOUTS[s] if s in first else MEASURE_TIMEOUTS_TF32OFF.get(s, 0)))
                  for s in (MEASURE_STAGES if tf32 == "off" else MEASURE_TIMED)]
    return plan_


def measure_file(out: Path, stage: str, tf32: str = "default") -> Path:
    """Where a stage writes its JSON: ``<stage>.json``, or ``<stage>_tf32off.json`` for the TF32-off pass."""
    return Path(out) / (f"{stage}.json" if tf32 == "default" else f"{stage}_tf32{tf32}.json")


def _precision_for(tf32: str) -> dict:
    """The precision settings a stage runs under (``benchmarks/gpu_measure.py`` records its own; this is what the
    orchestrator writes for a stage that died before it could)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = {"matmul_allow_tf32": bool(torch.backends.cuda.matmul.allow_tf32),
               "cudnn_allow_tf32": bool(torch.backends.cudnn.allow_tf32),
               "cudnn_benchmark": bool(torch.backends.cudnn.benchmark),
               "float32_matmul_precision": torch.get_float32_matmul_precision()}
    if tf32 == "off":
        res.update(matmul_allow_tf32=False, cudnn_allow_tf32=False)
    return res


def _stage_result(out: Path, stage: str, tf32: str, rc: int | None, text: str, timed_out: bool, seconds: float,
                  device: str) -> dict:
    """The stage's own JSON, or -- when it was killed or crashed before writing a final one -- a JSON saying so,
    with whatever partial figures it had written (``status: running``) kept under ``partial``."""
    path = measure_file(out, stage, tf32)
    rec = None
    if path.is_file():
        try:
            rec = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            rec = None
    if rec is not None and rec.get("status") != "running":
        return rec
    why = "timeout" if timed_out else "fail"
    new = {"stage": stage, "device": device, "tf32": tf32, "status": why, "rc": rc, "seconds": round(seconds, 2),
           "precision": (rec or {}).get("precision", _precision_for(tf32)), "tail": text[-3000:],
           "reason": ("killed at its time limit" if timed_out else f"the stage's process ended with {rc} before "
                      "writing its result")}
    if rec is not None:
        new["partial"] = {k: v for k, v in rec.items() if k not in new}
    _write_atomic(path, json.dumps(new, indent=1, default=str) + "\n")
    return new


def measure(out: Path, budget: float = MEASURE_BUDGET_S, dry_run: bool = False, tf32: str = "both") -> int:
    """Issue 51's measurements into ``out``: one JSON per stage (written as the stage ends, so a run stopped early
    keeps what it did) and ``summary.json`` (rewritten after every stage), inside ``budget`` seconds.

    On a GPU every stage is a process of its own (``benchmarks/gpu_measure.py STAGE``) with its own timeout.
    ``dry_run``: every stage in one process on the CPU at tiny sizes -- the plumbing, for CI."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    deadline = t0 + budget
    device = "cpu" if dry_run else "cuda"
    summary: dict = {"command": "python -m modi_ext.validate --out " + str(out) + f" --budget {budget:g}"
                     + (" --dry-run" if dry_run else "") + ("" if tf32 == "both" else f" --tf32 {tf32}"),
                     "device": device, "budget_s": budget, "tf32": tf32, "torch": torch.__version__,
                     "cuda": torch.version.cuda, "date": datetime.date.today().isoformat(),
                     "precision_defaults": _precision_for("default"), "stages": {}}
    spath = out / "summary.json"
    if not MEASURE_SCRIPT.is_file():
        print(f"validate: {MEASURE_SCRIPT} not found (run from a source checkout)", file=sys.stderr)
        return 2
    if not dry_run:
        why = no_gpu_message()
        if why is not None:
            summary["error"] = why
            _write_atomic(spath, json.dumps(summary, indent=1) + "\n")
            print(why + " (--dry-run runs the stages on the CPU)", file=sys.stderr)
            return 2
        p = torch.cuda.get_device_properties(0)
        summary.update(gpu=p.name, sms=p.multi_processor_count)
    log = out / "stages.log"
    log.write_text("", encoding="utf-8")
    py = sys.executable
    env, cwd = step_env(None, ROOT)
    with tempfile.TemporaryDirectory(prefix="modi_measure_") as tmp:
        if dry_run:
            runs = [("all", "default", budget)]
        else:
            runs = measure_plan(tf32)
        for stage, mode, timeout in runs:
            left = deadline - time.perf_counter()
            names = MEASURE_STAGES if stage == "all" else (stage,)
            if left < 5 or timeout <= 0:
                for n in names:
                    rec = {"stage": n, "device": device, "tf32": mode, "status": "skipped",
                           "reason": "time budget spent", "precision": _precision_for(mode)}
                    _write_atomic(measure_file(out, n, mode), json.dumps(rec, indent=1) + "\n")
                    summary["stages"][measure_file(out, n, mode).stem] = {"status": "skipped",
                                                                          "reason": rec["reason"]}
                continue
            limit = min(timeout, left)
            cmd = [py, str(MEASURE_SCRIPT), stage, "--out", str(out), "--work", tmp, "--device", device,
                   "--tf32", mode, "--limit", f"{limit:.0f}"] + (["--tiny"] if dry_run else [])
            t = time.perf_counter()
            rc, text, timed_out = run_group(cmd, limit, env, cwd)
            secs = time.perf_counter() - t
            with log.open("a", encoding="utf-8") as f:
                f.write(f"===== {stage} (tf32 {mode}): rc {rc}{' timeout' if timed_out else ''}\n{text}\n")
            for n in names:
                rec = _stage_result(out, n, mode, rc, text, timed_out, secs, device)
                summary["stages"][measure_file(out, n, mode).stem] = {
                    k: rec.get(k) for k in ("status", "seconds", "reason", "error") if rec.get(k) is not None}
                print(f"{measure_file(out, n, mode).stem:24s} {rec['status']:8s} {rec.get('seconds', 0):7.1f} s  "
                      f"{rec.get('reason', rec.get('error', ''))}"[:200], flush=True)
            summary["total_s"] = round(time.perf_counter() - t0, 1)
            _write_atomic(spath, json.dumps(summary, indent=1, default=str) + "\n")
    bad = [n for n, r in summary["stages"].items() if r["status"] in ("fail", "timeout")]
    summary["verdict"] = "fail" if bad else "ok"
    summary["total_s"] = round(time.perf_counter() - t0, 1)
    _write_atomic(spath, json.dumps(summary, indent=1, default=str) + "\n")
    print(f"wrote {out}/*.json; {summary['verdict']} in {summary['total_s']:.0f} s"
          + (f": {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m modi_ext.validate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, default=None, help="results file (default benchmarks/results/cuda_<gpu>.json)")
    ap.add_argument("--budget", type=float, default=None,
                    help=f"seconds for all steps together (default {DEFAULT_BUDGET_S:.0f}; with --out "
                         f"{MEASURE_BUDGET_S:.0f})")
    ap.add_argument("--emulated", action="store_true", help="also run the cuda_emulated suite (CPU-bound)")
    ap.add_argument("--dry-run", action="store_true", help="list the steps and their timeouts, run nothing")
    ap.add_argument("--allow-skip", action="store_true", help="report ok even when a step could not run")
    ap.add_argument("--build", action="store_true",
                    help="first build the extension with its CUDA kernels into a temporary folder, inside the budget "
                         "(the default when the installed build has no CUDA kernels and nvcc is found)")
    ap.add_argument("--payload", choices=("kernels", "dispatch"), help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=None,
                    help="the GPU step measurements: one JSON per stage in this folder (build, CUDA tests, MoDi step "
                         "vs the authors' train.py, sampling, GANimator, profile); with --dry-run on the CPU at tiny "
                         f"sizes; --budget defaults to {MEASURE_BUDGET_S:.0f} s")
    ap.add_argument("--tf32", choices=("default", "off", "both"), default="both",
                    help="with --out: torch's defaults, TF32 off on both sides, or both (the default; the TF32-off "
                         "pass runs the timed stages again when time is left)")
    ap.add_argument("--device", default="cuda", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.budget is None:
        args.budget = MEASURE_BUDGET_S if args.out is not None and not args.payload else DEFAULT_BUDGET_S
    if args.budget <= 0:
        print(f"validate: --budget must be positive, got {args.budget}", file=sys.stderr)
        return 2
    if args.payload:
        return _run_payload(args.payload, args.out, args.device)
    if args.out is not None:
        return measure(args.out, args.budget, args.dry_run, args.tf32)
    with tempfile.TemporaryDirectory(prefix="modi_validate_") as tmp:
        work = Path(tmp)
        steps = plan(work, args.emulated)
        if args.dry_run:
            total = 0.0
            if args.build:
                total += BUILD_TIMEOUT_S
                print(f"{'build':18s} {BUILD_TIMEOUT_S:5.0f} s  setup.py build --build-base {work / 'build'}")
            for s in steps:
                total += s.timeout_s
                print(f"{s.name:18s} {s.timeout_s:5.0f} s  {' '.join(s.cmd)}")
            print(f"{'total':18s} {total:5.0f} s  (budget {args.budget:.0f} s; each step gets what is left)")
            return 0
        t_start = time.perf_counter()
        facts = preflight_facts()
        kernels_missing = facts["gpu_visible"] and facts["torch_cuda"] is not None and not facts["cuda_kernels"]
        build = args.build or (kernels_missing and facts["nvcc"] is not None)
        why = preflight_message(**dict(facts, cuda_kernels=True)) if build else preflight_message(**facts)
        if why is None and build and facts["nvcc"] is None:
            why = (f"validate: --build needs nvcc: install CUDA toolkit {facts['torch_cuda'].split('.')[0]}.x and "
                   "set CUDA_HOME")
        if why is not None:
            print(why, file=sys.stderr)
            return 2
        lib, built = None, None
        if build:
            lib, built = build_extension(work, min(BUILD_TIMEOUT_S, args.budget), None, args.emulated)
            print(f"{'build':18s} {built['status']:8s} {built.get('seconds', 0):7.1f} s  {built.get('reason', '')}",
                  flush=True)
            if lib is None:
                print(f"validate: the build into {work / 'build'} failed ({built['status']}); its output ends:\n"
                      + built.get("tail", "")[-1500:], file=sys.stderr)
                return 2
            left = args.budget - (time.perf_counter() - t_start)
            if not _kernels_run_in(lib, work, max(5.0, min(60.0, left))):
                print("validate: the extension built with nvcc has no CUDA kernels that run on this GPU (check "
                      "TORCH_CUDA_ARCH_LIST)", file=sys.stderr)
                return 2
        return _validate(steps, args, lib=lib, built=built, t_start=t_start, work=work)


def _validate(steps: list[Step], args: argparse.Namespace, lib: Path | None = None, built: dict | None = None,
              t_start: float | None = None, work: Path | None = None) -> int:
    p = torch.cuda.get_device_properties(0)
    path = args.json or ROOT / "benchmarks" / "results" / f"cuda_{gpu_slug(p.name)}.json"
    report = {"gpu": p.name, "sms": p.multi_processor_count, "memory_gib": round(p.total_memory / 2**30, 1),
              "torch": torch.__version__, "cuda": torch.version.cuda, "date": datetime.date.today().isoformat(),
              "budget_s": args.budget, "steps": {}}
    log = path.with_suffix(".log")  # every step's whole output (the report keeps each one's last 3000 characters)
    report["log"] = str(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("", encoding="utf-8")
    t_start = time.perf_counter() if t_start is None else t_start  # with --build, the build is inside the budget
    deadline = t_start + args.budget
    env, cwd = step_env(lib, work or ROOT)
    if built is not None:
        report["steps"]["build"] = built
        report["built_into"] = str(lib)
    for step in steps:
        left = deadline - time.perf_counter()
        res = run_step(step, min(step.timeout_s, left), env, cwd)
        with log.open("a", encoding="utf-8") as f:
            f.write(f"===== {step.name}: {res['status']}\n{res.pop('output', '')}\n")
        report["steps"][step.name] = res
        print(f"{step.name:18s} {res['status']:8s} {res.get('seconds', 0):7.1f} s  {res.get('reason', '')}",
              flush=True)
        _write_atomic(path, json.dumps(report, indent=2, default=str) + "\n")  # partial results survive a kill
    report["verdict"], report["reasons"] = verdict(report["steps"], args.allow_skip)
    report["ok"] = report["verdict"] == "ok"
    report["total_s"] = round(time.perf_counter() - t_start, 1)
    _write_atomic(path, json.dumps(report, indent=2, default=str) + "\n")
    print(f"wrote {path}; {report['verdict']} in {report['total_s']:.0f} s"
          + (f": {'; '.join(report['reasons'])}" if report["reasons"] else ""))
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
