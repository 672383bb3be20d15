"""The extension must actually be built where CI runs: a silent fallback to the reference would hide kernel bugs."""
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import modi_ext
from modi_ext.runtime.loader import read_build_info


@pytest.mark.skipif(os.environ.get("CI", "").lower() != "true", reason="only enforced in CI (CI=true)")
def test_extension_is_built_in_ci():
    assert modi_ext.HAS_EXT, f"modi_ext._C failed to load: {modi_ext.LOAD_ERROR}"


@pytest.mark.skipif(os.environ.get("CI", "").lower() != "true", reason="only enforced in CI (CI=true)")
def test_the_build_records_its_torch():
    """setup.py's build_ext writes the record the loader checks before loading _C (a wheel carries it)."""
    info = read_build_info()
    assert info is not None, "modi_ext/_build_info.json is missing: setup.py's build_ext did not write it"
    assert info["torch"] == str(torch.__version__) and info["cuda"] == (torch.version.cuda if info["cuda"] else None)


def _needed(lib: Path) -> list[str]:
    """The shared libraries an ELF file names as NEEDED (readelf, from binutils, which every compiler brings)."""
    out = subprocess.run(["readelf", "-d", str(lib)], capture_output=True, text=True, check=True).stdout
    return re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", out)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ELF shared libraries: Linux only")
@pytest.mark.skipif(shutil.which("readelf") is None, reason="readelf not found (Debian package binutils)")
@pytest.mark.parametrize("name", ["_C", "_C_emu"])
def test_compiled_modules_share_the_process_libstdcxx(name):
    """_C and _C_emu must use libstdc++.so.6, the one libtorch uses: a private static copy has its own locale facet
    ids, and formatting an integer in a TORCH_CHECK message then segfaults (the first GPU image linked one in; see
    SHARED_LIBSTDCXX in setup.py)."""
    libs = sorted(Path(modi_ext.__file__).parent.glob(f"{name}.*.so"))
    if not libs:
        pytest.skip(f"modi_ext.{name} is not built here")
    needed = _needed(libs[0])
    assert "libstdc++.so.6" in needed, f"{libs[0].name} does not link libstdc++.so.6 dynamically: NEEDED {needed}"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ELF shared libraries: Linux only")
@pytest.mark.skipif(shutil.which("readelf") is None or shutil.which("c++") is None,
                    reason="readelf / c++ not found (Debian packages binutils, g++)")
def test_the_libstdcxx_check_sees_a_static_copy(tmp_path):
    """The check above can fail: a library linked with a static libstdc++ does not name libstdc++.so.6."""
    src = tmp_path / "t.cc"
    src.write_text("#include <sstream>\n#include <string>\n"
                   "std::string f(long v) { std::ostringstream o; o << v; return o.str(); }\n")
    for flag, expect in (("-static-libstdc++", False), ("-l:libstdc++.so.6", True)):
        lib = tmp_path / f"t{int(expect)}.so"
        subprocess.run(["c++", "-shared", "-fPIC", str(src), "-o", str(lib), flag], check=True, capture_output=True)
        assert ("libstdc++.so.6" in _needed(lib)) is expect, flag
