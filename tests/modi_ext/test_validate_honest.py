"""`python -m modi_ext.validate` earns every "ok" (issue 33): the parts that do not need a GPU, proven on the CPU.

The preflight's messages, a skipped step never counting as a pass, the sanitizer found outside PATH, the sanitizer
steps' memcheck / kernel filter / caching-allocator setting, and a timeout that kills a grandchild too.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from modi_ext import validate


# ------------------------------------------------------------------------------------------------ preflight
def _pre(**kw):
    facts = dict(gpu_visible=True, torch_cuda="12.4", torch_version="2.5.0", cuda_kernels=True, nvcc="12.4")
    facts.update(kw)
    return validate.preflight_message(**facts)


def test_preflight_passes_only_when_everything_is_in_place():
    assert _pre() is None
    assert _pre(nvcc=None) is None  # kernels already built: no compiler needed
    assert _pre(nvcc="12.1") is None  # same major version is compatible


@pytest.mark.parametrize("facts, words", [
    (dict(torch_cuda=None, gpu_visible=False), ["CPU-only build", "install a CUDA build of torch"]),
    (dict(gpu_visible=False), ["no GPU is visible", "CUDA 12.4 build", "CUDA_VISIBLE_DEVICES"]),
    (dict(nvcc="13.0"), ["nvcc is CUDA 13.0", "torch was built with CUDA 12.4", "install CUDA toolkit 12.x"]),
    (dict(cuda_kernels=False), ["no CUDA kernels", "pip install -e ."]),
    (dict(cuda_kernels=False, nvcc=None), ["no CUDA kernels", "no nvcc", "install CUDA toolkit 12.x"]),
])
def test_preflight_fails_in_one_line_naming_the_problem(facts, words):
    msg = _pre(**facts)
    assert msg is not None and "\n" not in msg and msg.startswith("validate: ")
    for w in words:
        assert w in msg, (w, msg)


@pytest.mark.parametrize("extra", [[], ["--build"]], ids=["plain", "build"])
def test_validate_here_exits_nonzero_in_one_line(tmp_path, extra):
    """No GPU: one line and exit 2 -- with --build too, before anything is compiled."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is visible here")
    out = tmp_path / "r.json"
    r = subprocess.run([sys.executable, "-m", "modi_ext.validate", "--json", str(out), *extra], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("validate: "), r.stderr
    assert "Traceback" not in r.stderr and not out.exists()


def test_nvcc_version_reads_the_release_line(tmp_path):
    fake = tmp_path / "nvcc"
    fake.write_text("#!/bin/sh\necho 'Cuda compilation tools, release 12.6, V12.6.77'\n")
    fake.chmod(0o755)
    assert validate.nvcc_version(str(fake)) == "12.6"
    assert validate.nvcc_version(str(tmp_path / "absent")) is None


# ------------------------------------------------------------------------------------------------ skip is not pass
def test_a_skipped_step_is_not_a_pass():
    passed = {"status": "pass"}
    skipped = {"status": "skipped", "reason": "compute-sanitizer not found"}
    assert validate.verdict({"a": passed, "b": passed}) == ("ok", [])
    v, why = validate.verdict({"a": passed, "s": skipped})
    assert v == "incomplete" and "compute-sanitizer not found" in why[0]
    assert validate.verdict({"a": passed, "s": skipped}, allow_skip=True)[0] == "ok"
    assert validate.verdict({"a": {"status": "timeout"}, "s": skipped}, allow_skip=True)[0] == "fail"
    assert validate.verdict({"a": {"status": "fail"}})[0] == "fail"
    assert validate.verdict({})[0] == "incomplete"  # nothing checked is not ok


# ------------------------------------------------------------------------------------------------ sanitizer
def _fake_exe(folder: Path) -> Path:
    folder.mkdir(parents=True)
    exe = folder / "compute-sanitizer"
    exe.write_text("#!/bin/sh\nexit 0\n")
    exe.chmod(0o755)
    return exe


def test_sanitizer_found_in_cuda_home_and_pip_nvidia_folders(tmp_path):
    empty = {"PATH": str(tmp_path / "nothing")}
    assert validate.find_sanitizer(empty, site_dirs=[]) in (None, "/usr/local/cuda/bin/compute-sanitizer")
    home = _fake_exe(tmp_path / "cuda" / "bin")
    assert validate.find_sanitizer({"PATH": "", "CUDA_HOME": str(tmp_path / "cuda")}, site_dirs=[]) == str(home)
    pip = _fake_exe(tmp_path / "site" / "nvidia" / "cuda_sanitizer_api" / "compute-sanitizer")
    assert validate.find_sanitizer({"PATH": ""}, site_dirs=[tmp_path / "site"]) == str(pip)
    on_path = _fake_exe(tmp_path / "p")
    assert validate.find_sanitizer({"PATH": str(tmp_path / "p")}, site_dirs=[tmp_path / "site"]) == str(on_path)
    (tmp_path / "p" / "compute-sanitizer").chmod(0o644)  # not executable: not the tool
    assert validate.find_sanitizer({"PATH": str(tmp_path / "p")}, site_dirs=[tmp_path / "site"]) == str(pip)


def test_sanitizer_steps_memcheck_filtered_without_the_caching_allocator(tmp_path):
    """memcheck, racecheck and synccheck watch our kernels only; initcheck watches every kernel, because a write by
    an unwatched kernel is not tracked and would look uninitialized to it."""
    steps = {s.name: s for s in validate.plan(tmp_path)}
    for tool in ("memcheck", "racecheck", "synccheck", "initcheck"):
        s = steps[f"sanitizer_{tool}"]
        assert s.cmd[s.cmd.index("--tool") + 1] == tool
        if tool == "initcheck":
            assert "--kernel-name" not in s.cmd
        else:
            assert s.cmd[s.cmd.index("--kernel-name") + 1] == "kns=modi_ext"
        assert s.env["PYTORCH_NO_CUDA_MEMORY_CACHING"] == "1"


def test_sanitizer_step_runs_the_tool_found_off_path_with_its_env(tmp_path):
    folder = tmp_path / "cuda" / "bin"
    folder.mkdir(parents=True)
    exe = folder / "compute-sanitizer"
    seen = tmp_path / "seen"
    exe.write_text(f"#!/bin/sh\necho \"$PYTORCH_NO_CUDA_MEMORY_CACHING $*\" > {seen}\n")
    exe.chmod(0o755)
    step = validate.Step("s", ["compute-sanitizer", "--tool", "memcheck"], 30, tool="compute-sanitizer",
                         env={"PYTORCH_NO_CUDA_MEMORY_CACHING": "1"})
    env = dict(os.environ, PATH="/usr/bin:/bin", CUDA_HOME=str(tmp_path / "cuda"))
    assert validate.run_step(step, 30, env)["status"] == "pass"
    assert seen.read_text().strip() == "1 --tool memcheck"


# ------------------------------------------------------------------------------------------------ timeouts
def test_timeout_kills_the_grandchild_too(tmp_path):
    pidfile = tmp_path / "grandchild.pid"
    inner = "import time; time.sleep(120)"
    outer = (f"import subprocess, sys, time; p = subprocess.Popen([sys.executable, '-c', {inner!r}]); "
             f"open({str(pidfile)!r}, 'w').write(str(p.pid)); print('started', flush=True); p.wait()")
    t0 = time.perf_counter()
    rc, out, timed_out = validate.run_group([sys.executable, "-c", outer], 3)
    assert timed_out and rc is None and "started" in out
    assert time.perf_counter() - t0 < 30
    pid = int(pidfile.read_text())
    for _ in range(50):  # the kill is delivered; the init process reaps it
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        if Path(f"/proc/{pid}/stat").is_file() and Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z":
            break  # a zombie awaiting its reaper is dead
        time.sleep(0.1)
    else:
        os.kill(pid, 9)
        pytest.fail("the grandchild outlived the step's timeout")


# ------------------------------------------------------------------------------------------------ fk under ext
def test_fk_under_ext_raises_on_a_device_without_fk_kernels(monkeypatch):
    import torch

    from modi_ext.fk import fk
    from modi_ext.runtime import dispatch

    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    monkeypatch.setattr(dispatch, "kernels_built", lambda dev, family="skeletal": False)
    q = torch.tensor([[[1.0, 0.0, 0.0, 0.0]] * 2])
    with pytest.raises(RuntimeError, match="no CPU FK kernels"):
        fk(q, torch.ones(2, 3), [-1, 0], torch.zeros(1, 3))


# ------------------------------------------------------------------------------------------------ --build
def test_build_goes_into_a_temporary_folder_not_the_checkout(tmp_path, monkeypatch):
    seen = {}

    def fake_group(cmd, timeout_s, env=None, cwd=validate.ROOT):
        seen.update(cmd=cmd, env=env, cwd=cwd, timeout_s=timeout_s)
        pkg = Path(cmd[cmd.index("--build-base") + 1]) / "lib.linux-x86_64-cpython-311" / "modi_ext"
        pkg.mkdir(parents=True)
        (pkg / "__init__.py").write_text("")
        return 0, "built", False

    monkeypatch.setattr(validate, "run_group", fake_group)
    lib, res = validate.build_extension(tmp_path, 42.0)
    assert res["status"] == "pass" and lib == tmp_path / "build" / "lib.linux-x86_64-cpython-311"
    assert seen["cmd"][1:5] == ["setup.py", "-q", "build", "--build-base"] and "--inplace" not in seen["cmd"]
    assert Path(seen["cmd"][5]).is_relative_to(tmp_path) and seen["timeout_s"] == 42.0
    assert seen["env"]["MODI_EXT_CUDA"] == "1" and seen["env"]["MODI_EXT_EMU"] == "0"
    validate.build_extension(tmp_path / "e", 42.0, emulated=True)  # --emulated: its tests import the emulated module
    assert seen["env"]["MODI_EXT_EMU"] == "1"


def test_a_failed_build_is_reported_not_used(tmp_path, monkeypatch):
    monkeypatch.setattr(validate, "run_group", lambda cmd, t, env=None, cwd=None: (1, "nvcc fatal: boom", False))
    lib, res = validate.build_extension(tmp_path, 10.0)
    assert lib is None and res["status"] == "fail" and "nvcc fatal" in res["tail"]
    monkeypatch.setattr(validate, "run_group", lambda cmd, t, env=None, cwd=None: (None, "", True))
    assert validate.build_extension(tmp_path, 10.0)[1]["status"] == "timeout"


def test_the_steps_import_the_build_not_the_checkout(tmp_path):
    """With --build every step runs with the built packages first on PYTHONPATH and outside the checkout, so even
    ``python -m`` (which puts the working folder first on sys.path) imports the build."""
    lib = tmp_path / "lib"
    (lib / "modi_ext").mkdir(parents=True)
    (lib / "modi_ext" / "__init__.py").write_text("")
    (lib / "modi_ext" / "where.py").write_text("print('BUILT', __file__)\n")
    env, cwd = validate.step_env(lib, tmp_path)
    assert env["PYTHONPATH"].split(os.pathsep)[0] == str(lib) and cwd == tmp_path
    rc, out, _ = validate.run_group([sys.executable, "-m", "modi_ext.where"], 60, env, cwd)
    assert rc == 0 and out.startswith("BUILT") and str(lib) in out, out
    env, cwd = validate.step_env(None, tmp_path)  # no build: the checkout
    assert env["PYTHONPATH"].split(os.pathsep)[0] == str(validate.ROOT) and cwd == validate.ROOT


def test_dry_run_lists_the_build_inside_the_budget(capsys):
    assert validate.main(["--dry-run", "--build"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("build") and "--build-base" in out and "budget 600 s" in out


@pytest.mark.parametrize("script", ["compare.py", "train_step.py"])
def test_the_benchmarks_import_the_build_on_pythonpath(tmp_path, script):
    """validate's compare/train_step steps put a fresh build first on PYTHONPATH; the benchmark scripts add the
    checkout to sys.path too, and must add it after PYTHONPATH (the first GPU run found them importing the
    checkout's unbuilt modi_ext: "the modi_ext C++ extension is not built")."""
    lib = tmp_path / "lib"
    (lib / "modi_ext").mkdir(parents=True)
    (lib / "modi_ext" / "__init__.py").write_text("import sys\nprint('BUILT')\nsys.exit(7)\n")
    env = dict(os.environ, PYTHONPATH=str(lib))
    rc, out, _ = validate.run_group([sys.executable, str(validate.ROOT / "benchmarks" / script), "--help"], 120, env,
                                    tmp_path)
    assert rc == 7 and "BUILT" in out, (rc, out[-2000:])
