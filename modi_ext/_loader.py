"""Find the compiled extension, or explain once why the dense reference is used instead."""
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

_warned = False


def impl_choice() -> str:
    """'ext' or 'ref': the path ops take, from MODI_EXT_IMPL (ref|ext|auto) and whether _C loaded."""
    global _warned
    want = os.environ.get("MODI_EXT_IMPL", "auto").strip().lower()
    if want not in ("auto", "ref", "ext"):
        raise ValueError(f"MODI_EXT_IMPL must be 'ref', 'ext' or 'auto', not {want!r}")
    if want == "ref":
        return "ref"
    if HAS_EXT:
        return "ext"
    if want == "ext":
        raise RuntimeError(f"MODI_EXT_IMPL=ext but the modi_ext C++ extension is not built: {LOAD_ERROR}")
    if not _warned:
        _warned = True
        warnings.warn(
            "modi_ext: the C++ extension is not built "
            f"({LOAD_ERROR}); using the dense pure-torch reference (slower, same results). "
            "Reinstall with a C++ compiler present to build it.",
            RuntimeWarning,
            stacklevel=3,
        )
    return "ref"
