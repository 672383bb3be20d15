"""Build and install modi + the modi_ext C++/CUDA extension.

Install with ``pip install --no-build-isolation -e .`` after ``pip install torch==2.13.0``
(build isolation would fetch a different, multi-GB torch to build against).

Environment switches:
  MODI_EXT_BUILD=0      build no extension (the package runs on the dense reference)
  MODI_EXT_CUDA=1|0     force the CUDA sources on or off (default: on when torch has CUDA and nvcc is found)
  MODI_EXT_DEBUG=1      -O0 -g
  MODI_EXT_EMU=0        skip the test-only emulated-CUDA module modi_ext._C_emu (tests/test_cuda_emulated.py)
  TORCH_CUDA_ARCH_LIST  GPU architectures of the CUDA build; default: the visible GPUs, else 8.0;9.0+PTX

A wheel (``make wheel``: ``python -m build --no-isolation``, then ``auditwheel repair``) carries modi_ext._C compiled
against the torch of the build, records that torch in modi_ext/_build_info.json (the loader checks it before loading
_C) and requires exactly that torch release (docs/install.md says why).
"""
from __future__ import annotations

import glob
import json
import os
import re
import shutil
import sys

from setuptools import find_packages, setup

ROOT = os.path.dirname(os.path.abspath(__file__))


def _version() -> str:
    """The one version string, from modi/_version.py (read as text: setup.py must not import the package)."""
    with open(os.path.join(ROOT, "modi", "_version.py"), encoding="utf-8") as f:
        return re.search(r'__version__ = "([^"]+)"', f.read()).group(1)


def _flag(name: str) -> str | None:
    value = os.environ.get(name)
    return None if value is None else value.strip().lower()


DEFAULT_CUDA_ARCH_LIST = "8.0;9.0+PTX"  # A100, H100/H200 (+ PTX for newer GPUs)


def _default_cuda_arch_list(current: str | None, gpu_visible: bool) -> str | None:
    """The TORCH_CUDA_ARCH_LIST to set for a CUDA build, or None to keep what is there.

    Unset, torch derives the list from the visible GPUs, and with none visible (a build machine, a container build)
    ``_get_cuda_arch_flags`` raises IndexError; so default to the data-centre GPUs MoDi trains on."""
    if current is not None and current.strip():
        return None
    return None if gpu_visible else DEFAULT_CUDA_ARCH_LIST


def _nvcc_flags(opt: list[str]) -> list[str]:
    """Our nvcc flags (torch adds its COMMON_NVCC_FLAGS and the arch flags); .ci/cuda_compile_check reads these."""
    return opt + ["--use_fast_math"]


# csrc/ holds one folder per op (schema.cpp, check.h, cpu.cpp, cuda.cu, ...), shared headers in common/, the module
# shell (module.cpp, registration.cpp) at the top; emu/ (the test-only CUDA emulator) and tools/ are built apart.
CSRC_APART = ("emu", "tools")


def _sources() -> tuple[list[str], list[str]]:
    """(C++ sources, CUDA sources) of modi_ext._C, relative to the repository root."""
    def pick(pattern: str) -> list[str]:
        found = glob.glob(os.path.join("csrc", "**", pattern), recursive=True)
        return sorted(p for p in found if p.split(os.sep)[1] not in CSRC_APART)
    return pick("*.cpp"), pick("*.cu")


def _emu_module(cpp_extension, cxx_flags: list[str]):
    """Test-only: the csrc/<op>/cuda.cu kernels compiled as host C++ on the CUDA emulator (csrc/emu), CPU key only."""
    if _flag("MODI_EXT_EMU") in ("0", "false", "no", "off"):
        return None
    # -O1: the emulator's cost is the fibers, not the kernels' code; this keeps the build short (2-core CI).
    # Hidden symbols: its c10::cuda shims must never bind to a CUDA torch's real libc10_cuda.
    flags = ["-O1", "-g0", "-fvisibility=hidden", "-Wno-unknown-pragmas"]
    flags += [f for f in cxx_flags if f.startswith("-march")]
    return cpp_extension.CppExtension(
        name="modi_ext._C_emu",
        sources=sorted(glob.glob("csrc/emu/*.cpp")),  # defs_emu.cpp includes the schemas of csrc/<op>/schema.cpp
        include_dirs=[os.path.join(ROOT, "csrc")],
        define_macros=[("MODI_EXT_EMULATE_CUDA", "1")],
        extra_compile_args={"cxx": flags},
        extra_link_args=SHARED_LIBSTDCXX,
    )


BUILD_INFO = "_build_info.json"  # in the modi_ext package; read by modi_ext/runtime/loader.py


def build_info(torch, use_cuda: bool) -> dict:
    """What the compiled _C depends on, for the loader to compare with the torch it meets at import time."""
    return {"torch": str(torch.__version__), "cuda": torch.version.cuda if use_cuda else None,
            "python": f"{sys.version_info[0]}.{sys.version_info[1]}", "modi": _version()}


def _build_ext_class(cpp_extension, info: dict):
    """torch's BuildExtension (ninja) that also writes modi_ext/_build_info.json beside the compiled modules:
    into the build tree (so it lands in the wheel) or, with ``--inplace``, into the source tree."""
    base = cpp_extension.BuildExtension.with_options(use_ninja=True)

    class BuildExtWithInfo(base):
        def run(self):
            super().run()
            pkg = os.path.join(ROOT, "modi_ext") if self.inplace else os.path.join(self.build_lib, "modi_ext")
            os.makedirs(pkg, exist_ok=True)
            with open(os.path.join(pkg, BUILD_INFO), "w", encoding="utf-8") as f:
                json.dump(info, f)
                f.write("\n")

    return BuildExtWithInfo


def torch_requirement(ext_built: bool, argv: list[str]) -> str:
    """The torch requirement of the metadata being written.

    A wheel (or an install) that carries the compiled _C requires exactly the torch release it was compiled against:
    torch's C++ ABI changes between releases, as torch-scatter and xformers pin it too.  The local label is left out
    (``torch==2.13.0`` admits 2.13.0+cpu and 2.13.0+cu130: a CPU-only _C loads under both).  The sdist (the wheel
    built from it where it is installed decides again) and a build without the extension: any torch >= 2.4."""
    if ext_built and "sdist" not in argv:
        import torch
        return "torch==" + str(torch.__version__).split("+")[0]
    return "torch>=2.4"


def extension_modules():
    if _flag("MODI_EXT_BUILD") in ("0", "false", "no", "off"):
        print("modi_ext: MODI_EXT_BUILD=0, not building the extension", file=sys.stderr)
        return [], {}
    try:
        import torch
        from torch.utils import cpp_extension
    except ImportError:
        print("modi_ext: torch is not installed at build time; the extension is skipped "
              "(install torch first and use --no-build-isolation)", file=sys.stderr)
        return [], {}
    # One host compiler for every object of _C: nvcc compiles the .cu files' host code with it too (-ccbin; torch
    # would otherwise pass $CC).
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        print(f"modi_ext: no C++ compiler ({cxx}) found; the extension is skipped, "
              "modi runs on the dense reference", file=sys.stderr)
        return [], {}

    cpp_sources, cuda_sources = _sources()
    want_cuda = _flag("MODI_EXT_CUDA")
    has_nvcc = cpp_extension.CUDA_HOME is not None and shutil.which(
        os.path.join(cpp_extension.CUDA_HOME, "bin", "nvcc")) is not None
    if want_cuda in ("1", "true", "yes", "on"):
        use_cuda = True
    elif want_cuda in ("0", "false", "no", "off"):
        use_cuda = False
    else:
        use_cuda = torch.cuda.is_available() or (torch.version.cuda is not None and has_nvcc)
        use_cuda = use_cuda and torch.version.cuda is not None and has_nvcc

    debug = _flag("MODI_EXT_DEBUG") in ("1", "true", "yes", "on")
    opt = ["-O0", "-g"] if debug else ["-O3"]
    # The language standard is torch's choice (C++20 for torch 2.13 headers); our sources stay C++17-clean.
    cxx_flags = opt + ["-fopenmp", "-DAT_PARALLEL_OPENMP=1"]
    if not debug:
        # MODI_EXT_MARCH: the x86 instruction set the kernels may use. The default (x86-64-v2, SSE4.2) runs on any
        # x86-64 machine of the last decade; "native" (AVX2/FMA where present) suits builds used where they are made.
        march = os.environ.get("MODI_EXT_MARCH", "x86-64-v2").strip()
        cxx_flags += [f"-march={march}", "-ffp-contract=fast"] if os.uname().machine == "x86_64" and march else []
    define_macros = [("MODI_EXT_WITH_CUDA", "1")] if use_cuda else []
    kwargs = dict(
        name="modi_ext._C",
        sources=cpp_sources + (cuda_sources if use_cuda else []),
        include_dirs=[os.path.join(ROOT, "csrc")],
        define_macros=define_macros,
        extra_compile_args={"cxx": cxx_flags, "nvcc": _nvcc_flags(opt) + ["-ccbin", shutil.which(cxx)]},
        extra_link_args=["-fopenmp"] + SHARED_LIBSTDCXX,
    )
    if use_cuda:
        arch = _default_cuda_arch_list(os.environ.get("TORCH_CUDA_ARCH_LIST"), torch.cuda.device_count() > 0)
        if arch is not None:
            os.environ["TORCH_CUDA_ARCH_LIST"] = arch
            print(f"modi_ext: no GPU visible, TORCH_CUDA_ARCH_LIST={arch}", file=sys.stderr)
    ext = cpp_extension.CUDAExtension(**kwargs) if use_cuda else cpp_extension.CppExtension(**kwargs)
    print(f"modi_ext: building the {'CPU+CUDA' if use_cuda else 'CPU'} extension", file=sys.stderr)
    emu = _emu_module(cpp_extension, cxx_flags)
    build_ext = _build_ext_class(cpp_extension, build_info(torch, use_cuda))
    return [ext] + ([emu] if emu is not None else []), {"build_ext": build_ext}


# libstdc++ as a shared library, whatever the compiler's search path finds first: _C shares C++ objects (streams,
# locales, exceptions) with libtorch, which uses the process's one libstdc++.so.6.  A GPU image we build on wraps
# GCC 13 in /opt/gcc/bin/g++ with -B/opt/gcc/lib/gcc/x86_64-linux-gnu/13/, where libstdc++.so is a dangling link and
# libstdc++.a is not, so a plain -lstdc++ linked a private static copy into _C.  Its locale facet ids are not
# libtorch's, and the first TORCH_CHECK message that formatted an integer segfaulted in ostream::_M_insert<long>.
# "-l:libstdc++.so.6" names the shared library's file, which the linker finds in the system's library folders
# (checked there: the library then needs libstdc++.so.6; the same sources built by the system g++ passed all 326 CUDA
# tests).  tests/modi_ext/runtime/test_build.py checks the built module for it.
SHARED_LIBSTDCXX = ["-l:libstdc++.so.6"] if sys.platform.startswith("linux") else []

ext_modules, cmdclass = extension_modules()

setup(
    name="modi",
    version=_version(),
    description="MoDi and GANimator motion synthesis with fast skeleton-aware operators (modi_ext)",
    long_description=open(os.path.join(ROOT, "README.md"), encoding="utf-8").read(),
    long_description_content_type="text/markdown",
    python_requires=">=3.10",
    packages=find_packages(include=["modi", "modi.*", "modi_ext", "modi_ext.*"]),
    package_data={"modi": ["py.typed"], "modi.viz": ["*.js"], "modi.blender": ["*.toml"]},
    install_requires=[
        torch_requirement(bool(ext_modules), sys.argv),
        "numpy>=1.24",
        "scipy>=1.10",
        "tqdm>=4.60",
        "matplotlib>=3.7",
        "pillow>=9.0",
        "tensorboard>=2.12",
        "scikit-learn>=1.3",
    ],
    extras_require={"test": ["pytest>=7", "hypothesis>=6.80", "pytest-benchmark>=4", "expecttest"],
                    # what the authors' released sources (../shared/peers) import when the tests and
                    # benchmarks/peers run them, beyond install_requires (tqdm, matplotlib, scipy, scikit-learn,
                    # tensorboard); without it those tests skip, naming the package
                    "peers": ["pyyaml>=5.4", "networkx>=2.6"],
                    "docs": ["mkdocs==1.6.1", "mkdocstrings==1.0.8", "mkdocstrings-python==2.0.11"],
                    # modi export onnx (onnx, onnxscript: torch.onnx.export(dynamo=True)) and running the models
                    # (onnxruntime: modi.export.onnx_runner, the tests)
                    "onnx": ["onnx>=1.17", "onnxscript>=0.5", "onnxruntime>=1.20"]},
    entry_points={"console_scripts": ["modi=modi.cli:main"]},
    ext_modules=ext_modules,
    cmdclass=cmdclass,
    zip_safe=False,
)
