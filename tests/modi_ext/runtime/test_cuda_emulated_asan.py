"""Global memory of the emulated CUDA kernels, checked by AddressSanitizer (part of ``pytest -m cuda_emulated``).

The emulator models shared memory (bounds-checked arrays, poisoned red zones), but a global load or store is a plain
host pointer access.  Here the emulated module (csrc/emu + the unchanged csrc/*/cuda.cu) is compiled a second time
with ``-fsanitize=address`` and the shared payload (``modi_ext.runtime.payload``: every kernel instantiation, forward
and backward, four dtypes) runs on it in a subprocess with libasan preloaded.  Every tensor torch allocates -- inputs,
outputs, workspaces -- is then a malloc block between red zones, so a kernel that reads or writes even one element
past any global buffer aborts with a ``heap-buffer-overflow`` report that names the kernel.

The injected defect ``global_oob`` (split_reduce_kernel reads one split past the end of its workspace; the module's
run-time switch, off unless turned on) shows that the check can fail.  What this does not cover: an access that
lands inside another live allocation (ASan sees only red zones), and anything about real GPU memory semantics.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.cuda_emulated

REPO = Path(__file__).resolve().parents[3]
CSRC = REPO / "csrc"
SOURCES = ("skeletal_emu.cpp", "fk_emu.cpp", "demod_emu.cpp", "cuda_emu.cpp", "emu_module.cpp", "defs_emu.cpp")
NAME, LIB = "_C_emu_asan", "modi_ext_emu_asan"


def _libasan() -> str:
    cxx = os.environ.get("CXX", "c++")
    try:
        path = subprocess.run([cxx, "-print-file-name=libasan.so"], capture_output=True, text=True, check=True,
                              timeout=60).stdout.strip()
    except (OSError, subprocess.SubprocessError) as exc:
        pytest.fail(f"no C++ compiler to build the AddressSanitizer module: {exc}")
    if not os.path.isabs(path) or not os.path.exists(path):  # the compiler echoes the bare name when it has none
        pytest.fail(f"{cxx} has no AddressSanitizer runtime (libasan.so); install it (e.g. apt install libasan8)")
    return os.path.realpath(path)


def _build(build: Path) -> Path:
    """Compile the emulated module with AddressSanitizer (ninja: incremental, one job per CPU); returns the .so."""
    import torch
    from torch.utils import cpp_extension

    build.mkdir(parents=True, exist_ok=True)
    cxx = os.environ.get("CXX", "c++")
    includes = [str(CSRC)] + cpp_extension.include_paths() + [sysconfig.get_paths()["include"]]
    cflags = ["-O1", "-g1", "-fPIC", "-std=c++20", "-fvisibility=hidden", "-Wno-unknown-pragmas",
              "-fsanitize=address", "-fno-omit-frame-pointer", "-DMODI_EXT_EMULATE_CUDA=1",
              f"-DMODI_EMU_LIB={LIB}", f"-DTORCH_EXTENSION_NAME={NAME}", "-DTORCH_API_INCLUDE_EXTENSION_H",
              f"-D_GLIBCXX_USE_CXX11_ABI={int(torch.compiled_with_cxx11_abi())}"]
    cflags += [f"-I{i}" for i in includes]
    libdirs = cpp_extension.library_paths()
    ldflags = ["-shared", "-fsanitize=address"] + [f"-L{d}" for d in libdirs] + [f"-Wl,-rpath,{d}" for d in libdirs]
    ldflags += ["-lc10", "-ltorch", "-ltorch_cpu", "-ltorch_python"]
    out = build / f"{NAME}.so"
    lines = [f"cxx = {cxx}", f"cflags = {' '.join(cflags)}", f"ldflags = {' '.join(ldflags)}",
             "rule cc", "  command = $cxx -MMD -MF $out.d $cflags -c $in -o $out", "  depfile = $out.d", "  deps = gcc",
             "rule link", "  command = $cxx $in -o $out $ldflags"]
    objs = []
    for src in SOURCES:
        obj = f"{Path(src).stem}.o"
        objs.append(obj)
        lines.append(f"build {obj}: cc {CSRC / 'emu' / src}")
    lines.append(f"build {out.name}: link {' '.join(objs)}")
    (build / "build.ninja").write_text("\n".join(lines) + "\n")
    jobs = str(max(2, os.cpu_count() or 2))
    r = subprocess.run(["ninja", "-C", str(build), "-j", jobs], capture_output=True, text=True)
    assert r.returncode == 0, f"the AddressSanitizer build failed:\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}"
    return out


RUNNER = textwrap.dedent("""
    import importlib.util, json, sys
    import torch
    torch.set_num_threads(1)
    path, defect, dtypes, only = sys.argv[1], sys.argv[2], sys.argv[3].split(","), sys.argv[4]
    spec = importlib.util.spec_from_file_location("{name}", path)
    emu = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(emu)
    from modi_ext.runtime import kernels, payload
    emu.set_injected_defect(defect)
    table = kernels.kernel_table(emu.LIBRARY)
    ran, errors = [], {{}}
    for dt in (getattr(torch, d) for d in dtypes):
        for case in payload.cases(dt):
            if only and case.name != only:
                continue
            fwd, bwd = payload.run_case(table, case, "cpu", dt)
            ran.append(case.name + "." + str(dt))
            if fwd > payload.TOL[dt] or bwd > payload.GRAD_FACTOR * payload.TOL[dt]:
                errors[ran[-1]] = [fwd, bwd]
    if "bfloat16" in dtypes and "float32" in dtypes and not only:
        # the opt-in tensor-core GEMMs under their switch: bf16, and float32 on TF32 (torch's switch on)
        import os
        from modi_ext.runtime import selfcheck
        os.environ["MODI_EXT_CUDA_MMA"] = "1"
        torch.backends.cudnn.allow_tf32 = True
        for dt in (torch.bfloat16, torch.float32):
            tol = selfcheck.tolerance("cpu", dt, emu.LIBRARY)
            for case in payload.cases(dt, ("skeletal",)):
                fwd, bwd = payload.run_case(table, case, "cpu", dt)
                ran.append(case.name + ".mma." + str(dt))
                if fwd > tol or bwd > payload.GRAD_FACTOR * tol:
                    errors[ran[-1]] = [fwd, bwd]
        del os.environ["MODI_EXT_CUDA_MMA"]
    print("RESULT " + json.dumps(dict(ran=ran, errors=errors, launched=sorted(emu.launch_counts()),
                                      registered=emu.registered_kernels())))
""").format(name=NAME)


def _run(so: Path, defect: str = "", dtypes: str = "float32,float64,float16,bfloat16", only: str = ""):
    env = dict(os.environ, LD_PRELOAD=_libasan(), PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get(
        "PYTHONPATH", "")]),
               # torch and python are not instrumented: only our module's accesses are checked; no leak report
               # (python frees little at exit), no container annotations (uninstrumented std::vector users)
               ASAN_OPTIONS="detect_leaks=0:halt_on_error=1:abort_on_error=0:alloc_dealloc_mismatch=0:"
                            "detect_odr_violation=0:detect_container_overflow=0:new_delete_type_mismatch=0")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", RUNNER, str(so), defect, dtypes, only], capture_output=True, text=True,
                       env=env, cwd=REPO, timeout=900)
    return r, time.perf_counter() - t0


@pytest.fixture(scope="module")
def asan_module(tmp_path_factory):
    build = Path(os.environ.get("MODI_EMU_ASAN_BUILD", "")) if os.environ.get("MODI_EMU_ASAN_BUILD") else (
        Path(tmp_path_factory.getbasetemp()).parent / f"modi_emu_asan_{os.getuid()}")
    t0 = time.perf_counter()
    so = _build(build)
    print(f"\nAddressSanitizer build of the emulated module: {time.perf_counter() - t0:.1f} s ({build})")
    return so


def _result(r: subprocess.CompletedProcess) -> dict:
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    assert r.returncode == 0 and lines, f"rc {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-6000:]}"
    return json.loads(lines[-1][len("RESULT "):])


def test_payload_under_address_sanitizer_is_clean_and_complete(asan_module):
    """Every kernel instantiation (the whole payload, four dtypes, then its bf16 and float32 skeletal cases again with
    the opt-in tensor-core GEMMs, float32 on TF32) runs under AddressSanitizer without one global out-of-bounds
    access, and matches the float64 oracle."""
    r, seconds = _run(asan_module)
    res = _result(r)
    print(f"\npayload under AddressSanitizer: {seconds:.1f} s, {len(res['ran'])} cases")
    assert not res["errors"], res["errors"]
    assert "ERROR: AddressSanitizer" not in r.stderr, r.stderr[-6000:]
    # this build has the csrc/<op>/cuda.cu kernels only (no emu_selftest.cpp): launched must be all it registered,
    # the 97 of the default paths and the opt-in tensor-core GEMMs' 12 (the bf16 and TF32 passes above)
    assert set(res["launched"]) == set(res["registered"]), sorted(set(res["registered"]) - set(res["launched"]))
    assert len(res["launched"]) == 109


def test_injected_global_out_of_bounds_read_is_caught(asan_module):
    """global_oob: split_reduce_kernel sums one split past its workspace.  AddressSanitizer stops the run at the
    first such read and names the kernel; the clean run of the same case passes."""
    case = "conv.wide"  # B x T = 260 > 256: the split-K weight gradient, so split_reduce_kernel runs
    clean = _result(_run(asan_module, "", "float32", case)[0])
    assert clean["ran"] == [f"{case}.torch.float32"] and not clean["errors"]
    r, _ = _run(asan_module, "global_oob", "float32", case)
    assert r.returncode != 0 and "RESULT " not in r.stdout, r.stdout[-2000:]
    assert "ERROR: AddressSanitizer: heap-buffer-overflow" in r.stderr, r.stderr[-6000:]
    assert "READ of size 4" in r.stderr and "split_reduce_kernel" in r.stderr, r.stderr[-6000:]
