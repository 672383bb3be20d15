"""Find the compiled extension, read the path the user asked for, explain once why a fallback is used.

A build writes ``modi_ext/_build_info.json`` beside ``_C`` (setup.py): the torch it compiled against.  ``_C`` is
loaded only under that torch release: under another one, loading it could fail with an undefined symbol or, worse,
succeed against a changed C++ ABI and crash later; so a mismatch is one warning at import naming both versions, and
the dense path.
"""
from __future__ import annotations

import json
import os
import sys
import warnings
from importlib.machinery import EXTENSION_SUFFIXES

import torch  # before _C: the extension's symbols resolve against libtorch

BUILD_INFO = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "_build_info.json")


def read_build_info(path: str = BUILD_INFO) -> dict | None:
    """The build record of the compiled extension, or None (an in-place build before the record existed, CMake)."""
    try:
        with open(path, encoding="utf-8") as f:
            info = json.load(f)
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def _release(version: str) -> str:
    return str(version).split("+")[0]


def torch_mismatch(info: dict | None, version: str | None = None, cuda: str | None = "<runtime>") -> str | None:
    """Why the extension recorded in ``info`` must not be loaded under this torch (``version``/``cuda``: the running
    torch's by default), or None.

    The release must match (``2.13.0+cpu`` and ``2.13.0+cu130`` share the CPU ABI: a CPU-only build loads under
    both); a build with CUDA kernels also needs the CUDA version it was compiled for."""
    if not info or not info.get("torch"):
        return None
    version = str(torch.__version__) if version is None else version
    cuda = torch.version.cuda if cuda == "<runtime>" else cuda
    built = str(info["torch"])
    if _release(built) != _release(version):
        return f"built for torch {built}, but torch {version} is installed"
    if info.get("cuda") and info["cuda"] != cuda:
        return (f"built for torch {built} with CUDA {info['cuda']}, but torch {version} has "
                f"{'CUDA ' + cuda if cuda else 'no CUDA'}")
    return None


def _caller_stacklevel() -> int:
    """The ``stacklevel`` of the first frame outside modi, modi_ext and torch (an ``nn.Module`` call): the user's
    import or call.  Frames of the import machinery are skipped as ``warnings.warn`` skips them (they do not count)."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    ours = tuple(os.path.join(root, pkg) + os.sep for pkg in ("modi", "modi_ext"))
    ours += (os.path.dirname(os.path.abspath(torch.__file__)) + os.sep,)

    def machinery(f) -> bool:
        return "importlib" in f.f_code.co_filename and "_bootstrap" in f.f_code.co_filename

    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(ours):
        frame = frame.f_back
        while frame is not None and machinery(frame):
            frame = frame.f_back
        level += 1
    return level


HAS_EXT = False
LOAD_ERROR: str | None = None
MISMATCH = torch_mismatch(read_build_info())
_warned = False

if MISMATCH is not None:
    LOAD_ERROR = f"the compiled kernels were {MISMATCH}"
    _warned = True  # this is the one warning: the first dense call does not add another
    warnings.warn(
        f"modi_ext: the compiled kernels were {MISMATCH}; using the dense pure-torch path (slower, same results). "
        f"Install the modi build for torch {_release(str(torch.__version__))}, or build modi from source against it.",
        RuntimeWarning,
        stacklevel=_caller_stacklevel(),
    )
else:
    try:
        from modi_ext import _C  # noqa: F401  registers torch.ops.modi_ext.*

        HAS_EXT = True
    except ImportError as exc:  # not built (no compiler at install time), or a build with no record
        here = os.path.dirname(BUILD_INFO)
        built = any(os.path.exists(os.path.join(here, "_C" + suffix)) for suffix in EXTENSION_SUFFIXES)
        # Python's message for a missing module inside a package being imported blames a circular import
        LOAD_ERROR = str(exc) if built else f"no compiled _C in {here}: installed without a C++ compiler or torch"

IMPLS = ("auto", "ext", "dense", "ref")


def requested_impl() -> str:
    """``MODI_EXT_IMPL`` (auto|ext|dense|ref, default auto), validated; read on every call so it can be switched."""
    want = os.environ.get("MODI_EXT_IMPL", "auto").strip().lower()
    if want not in IMPLS:
        raise ValueError(f"MODI_EXT_IMPL must be 'auto', 'ext', 'dense' or 'ref', not {want!r}")
    if want == "ext" and not HAS_EXT:
        raise RuntimeError(f"MODI_EXT_IMPL=ext but the modi_ext C++ extension is not loaded: {LOAD_ERROR}")
    return want


def warn_not_built() -> None:
    """One warning per process that the dense pure-torch path stands in for the missing extension."""
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(
            "modi_ext: the C++ extension is not built "
            f"({LOAD_ERROR}); using the dense pure-torch path (slower, same results). "
            "Install the modi wheel, or build from source with a C++ compiler (docs/install.md).",
            RuntimeWarning,
            stacklevel=_caller_stacklevel(),
        )


def impl_choice() -> str:
    """The path asked for, device aside: 'ref', 'dense' or 'ext' ('auto' resolves to 'ext' when built, else
    'dense').  Per-call routing (device kernels, self-check, auto timing) is ``modi_ext.runtime.dispatch.route``."""
    want = requested_impl()
    if want in ("ref", "dense", "ext"):
        return want
    if HAS_EXT:
        return "ext"
    warn_not_built()
    return "dense"
