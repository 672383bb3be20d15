"""Build and run ``benchmarks/nn_kernel_rate.cpp``: the skeletal conv's NN micro-kernel alone, one thread, as a
fraction of torch's sgemm on one thread (the bound that the conv's other parts leave to it; docs/results.md).

    python benchmarks/nn_kernel_rate.py [M K N]        # default: MoDi's finest conv, 32 x 288 x 528

It compiles with the installed torch's headers and libraries (``torch.utils.cpp_extension``'s paths) and the
extension's flags (``-O3``, generic x86-64-v2 code, the kernels' ISA chosen at run time as in the extension), and
prints one JSON line.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

from torch.utils import cpp_extension

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str]) -> int:
    with tempfile.TemporaryDirectory(prefix="nn_kernel_rate_") as tmp:
        exe = Path(tmp) / "nn_kernel_rate"
        libs = cpp_extension.library_paths()
        cmd = (["g++", "-O3", "-std=c++20", "-march=x86-64-v2", "-fopenmp", "-I", str(ROOT / "csrc")]
               + [f"-I{p}" for p in cpp_extension.include_paths()]
               + [str(ROOT / "benchmarks" / "nn_kernel_rate.cpp"), "-o", str(exe)]
               + [f"-L{p}" for p in libs] + [f"-Wl,-rpath,{p}" for p in libs] + ["-ltorch_cpu", "-lc10"])
        subprocess.run(cmd, check=True)
        return subprocess.run([str(exe), *argv], check=False).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
