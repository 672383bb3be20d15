"""Find the compiled extension, read the path the user asked for, explain once why a fallback is used."""
from __future__ import annotations

import os
import warnings

import torch  # noqa: F401  (the extension's symbols resolve against libtorch)

HAS_EXT = False
LOAD_ERROR: str | None = None

try:
    from modi_ext import _C  # noqa: F401  registers torch.ops.modi_ext.*

    HAS_EXT = True
except ImportError as exc:  # not built (no compiler at install time) or built for another torch
    LOAD_ERROR = str(exc)

IMPLS = ("auto", "ext", "dense", "ref")
_warned = False


def requested_impl() -> str:
    """``MODI_EXT_IMPL`` (auto|ext|dense|ref, default auto), validated; read on every call so it can be switched."""
    want = os.environ.get("MODI_EXT_IMPL", "auto").strip().lower()
    if want not in IMPLS:
        raise ValueError(f"MODI_EXT_IMPL must be 'auto', 'ext', 'dense' or 'ref', not {want!r}")
    if want == "ext" and not HAS_EXT:
        raise RuntimeError(f"MODI_EXT_IMPL=ext but the modi_ext C++ extension is not built: {LOAD_ERROR}")
    return want


def warn_not_built() -> None:
    """One warning per process that the dense pure-torch path stands in for the missing extension."""
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(
            "modi_ext: the C++ extension is not built "
            f"({LOAD_ERROR}); using the dense pure-torch path (slower, same results). "
            "Reinstall with a C++ compiler present to build it.",
            RuntimeWarning,
            stacklevel=4,
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
